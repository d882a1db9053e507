"""Readers, writer and manifest; sessions beside a user's file; points edited by hand; errors
shown as notifications; the headless demo."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from napari_fdlc._napari._io import write_neuron_csv
from napari_fdlc.errors import FdlcError
from napari_fdlc.review import SESSION_SUFFIX
from napari_fdlc.table import NeuronTable, read_table, write_neuropal_id, write_table


def test_manifest_is_valid():
    from npe2 import PluginManifest

    manifest = PluginManifest.from_distribution("napari-fdlc")
    manifest.validate_imports()
    c = manifest.contributions
    assert {w.display_name for w in c.widgets} == {"Auto-label", "Track neurons"}
    assert [s.key for s in c.sample_data] == ["neuropal"]
    assert len(c.readers) == 2 and c.writers[0].layer_types == ["points"]


def test_writer_does_not_merge_time_points(tmp_path):
    """Points over time (t, z, y, x) are written with a 't' column (or refused in one line),
    not merged into one worm."""
    data = np.array([[0, 1, 2, 3], [1, 1, 2, 3], [1, 4, 5, 6]], dtype=float)
    path = tmp_path / "points.csv"
    try:
        written = write_neuron_csv(str(path), data, {"scale": (1, 1, 1, 1)})
    except FdlcError as exc:
        assert "\n" not in str(exc)
        assert not path.exists()
        return

    df = pd.read_csv(written[0])
    assert "t" in df.columns and list(df["t"]) == [0, 1, 1]


def test_writer_refuses_an_empty_layer(tmp_path):
    """An empty Points layer is refused in one line: a header-only CSV could not be opened again."""
    path = tmp_path / "empty.csv"
    with pytest.raises(FdlcError) as exc:
        write_neuron_csv(str(path), np.zeros((0, 3)), {})
    assert "\n" not in str(exc.value)
    assert not path.exists()


def test_writer_unwritable_path_is_an_fdlc_error(tmp_path):
    """A path that cannot be written is one FdlcError line, not a bare OSError."""
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    with pytest.raises(FdlcError) as exc:
        write_neuron_csv(str(blocker / "points.csv"), np.zeros((2, 3)), {})
    assert "\n" not in str(exc.value)


def test_open_a_file_label_export_reopen(make_napari_viewer, sample_files, identifier, templates, tmp_path, monkeypatch):
    from napari_fdlc.table import write_neuropal_id, read_table

    stack_path = tmp_path / "worm 1.ome.tif"  # a user's file in a writable folder
    shutil.copy(sample_files[0], stack_path)
    viewer = make_napari_viewer()
    layers = viewer.open(stack_path, plugin="napari-fdlc")
    assert [layer.colormap.name for layer in layers] == ["red", "green", "blue", "gray"]
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    layer = widget.auto_label()
    assert layer.name == "worm 1 neuron IDs"
    session_file = tmp_path / ("worm 1.ome.tif" + SESSION_SUFFIX)
    assert widget.session.path == session_file and session_file.is_file()
    widget.set_threshold(0.0)
    first = int(np.flatnonzero(layer.features["auto_id"] != "")[0])
    widget.accept(first)

    # --- points edited by hand: the session follows, undoably -------------------------------------
    n = len(layer.data)
    layer.add(layer.data[first] + [0, 20, 20])
    assert len(widget.session) == n + 1 and layer.features["status"][n] == "auto"
    assert np.isfinite(widget.session.table.colours["R"][n])
    gone = n - 1 if first != n - 1 else n - 2
    layer.selected_data = {gone}
    layer.remove_selected()
    assert len(widget.session) == n and layer.features["status"][first] == "accepted"
    assert widget.session.history()[-2:] == ["add 1 neuron(s)", "remove 1 neuron(s)"]
    widget.undo()
    widget.undo()
    assert len(layer.data) == n and len(widget.session) == n
    assert layer.features["status"][first] == "accepted"

    # --- export, and the table reader puts the points back on the same voxels ---------------------
    out = widget.export(tmp_path / "ids.csv")
    (table_layer,) = viewer.open(out, plugin="napari-fdlc")
    assert np.allclose(table_layer.scale, layer.scale)
    assert np.allclose(table_layer.data, layer.data, atol=1e-3)
    assert table_layer.features["label"][first] == layer.features["label"][first]
    # a NeuroPAL_ID CSV opens as points too
    npid = tmp_path / "npid.csv"
    write_neuropal_id(read_table(out), npid)
    (np_layer,) = viewer.open(npid, plugin="napari-fdlc")
    assert np.allclose(np_layer.data[:, ::-1], read_table(out).xyz, atol=1e-3)
    # the writer: a Points layer saved as a neuron-ID CSV

    data, meta, _ = layer.as_layer_data_tuple()
    (written,) = write_neuron_csv(str(tmp_path / "saved.csv"), data, meta)
    back = read_table(written)
    assert np.allclose(back.xyz, widget.session.table.xyz, atol=1e-4)
    assert list(pd.read_csv(written, keep_default_na=False)["status"]) == list(layer.features["status"])

    # --- the export buttons ask before replacing a file ----------------------------------------------
    from napari_fdlc._napari import _widget

    asked = []
    monkeypatch.setattr(_widget.QFileDialog, "getSaveFileName", lambda *a, **k: (str(out), "CSV (*.csv)"))
    monkeypatch.setattr(_widget.QMessageBox, "question", lambda *a, **k: asked.append(a[2]) or _widget.QMessageBox.StandardButton.No)
    stamp = out.stat().st_mtime_ns
    widget.export_button.click()
    assert asked and str(out) in asked[0] and out.stat().st_mtime_ns == stamp
    monkeypatch.setattr(_widget.QMessageBox, "question", lambda *a, **k: _widget.QMessageBox.StandardButton.Yes)
    widget.export_npid_button.click()
    assert out.read_text().startswith("Version,")  # replaced, in NeuroPAL_ID layout
    # a labelled table file as the template
    monkeypatch.setattr(_widget.QFileDialog, "getOpenFileName", lambda *a, **k: (str(written), "CSV (*.csv)"))
    widget.template_combo.setCurrentText(_widget.FROM_FILE)
    widget.template_combo.activated.emit(widget.template_combo.currentIndex())
    assert widget.template_combo.currentText() == "file: saved.csv"

    # --- reopen the file in a new viewer: the session comes back beside it --------------------------
    viewer.close()
    viewer2 = make_napari_viewer()
    layers2 = viewer2.open(stack_path, plugin="napari-fdlc")
    assert layers2[-1].name == "worm 1 neuron IDs"
    assert layers2[-1].features["status"][first] == "accepted"


def test_errors_become_notifications(make_napari_viewer, sample_files, identifier, templates):
    from napari.utils.notifications import notification_manager

    from napari_fdlc.identify import Identifier

    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    before = len(notification_manager.records)
    # a core error in the worker thread: one line, no exception in the GUI
    widget.identifier = Identifier(model=None, device="cpu")
    widget.set_templates(templates)
    assert widget.auto_label() is None
    assert widget.last_error == "no model loaded"
    assert widget.layer is None
    # buttons and keys with nothing to act on
    viewer.layers.selection.active = viewer.layers["NeuroPAL sample [W]"]
    viewer.window._qt_viewer._key_map_handler.press_key("A")  # bound on the viewer too
    assert "Auto-label first" in widget.last_error
    widget.identifier = identifier
    assert widget.auto_label() is not None and widget.last_error is None
    # deleting the neuron-ID layer and running again loses no decision
    r = int(np.flatnonzero(widget.layer.features["auto_id"] != "")[0])
    widget.accept(r)
    viewer.layers.remove(widget.layer)
    assert widget.session is None and widget.layer is None
    layer = widget.auto_label()
    assert layer.features["status"][r] == "accepted" and widget.session.user_id[r] == layer.features["auto_id"][r]
    widget.layer.selected_data = set()
    widget.session.select(None)
    viewer.window._qt_viewer._key_map_handler.press_key("A")
    assert "no neuron selected" in widget.last_error
    widget.set_neurons("sample neurons (truth)")
    widget.set_template("sample neurons (truth)")  # a labelled layer as the template
    assert widget.auto_label() is not None and widget.last_error is None
    assert not viewer.layers["sample neurons (truth)"].visible
    messages = [str(r.message) for r in notification_manager.records[before:]]
    assert "no model loaded" in messages
    assert not any("Traceback" in m for m in messages)


def test_headless_demo(sample_files, identifier, templates, tmp_path, qtbot):
    from napari_fdlc._napari.demo_flow import run_demo

    labels, shot = run_demo(tmp_path / "demo", headless=True, identifier=identifier, templates=templates, threshold=0.1)
    df = pd.read_csv(labels, keep_default_na=False)
    assert len(df) > 100 and (df["label"] != "").any()
    from imageio.v3 import imread

    image = imread(shot)
    assert image.shape[0] > 400 and image.shape[1] > 800
    assert not list(shot.parent.glob(".*.tmp"))  # written through a temporary file, renamed


def test_headless_demo_screenshot_not_writable_is_one_line(sample_files, identifier, templates, tmp_path,
                                                           monkeypatch, capsys, qtbot):
    """`make demo` without a display where demo_output/screenshot.png cannot be written (here a
    folder of that name; likewise a full disk or a read-only file): one line 'fdlc: error: ...'
    and exit 2, no labels.csv beside it. save_screenshot's OSError (IsADirectoryError) escaped
    demo.main as a traceback, after labels.csv was written."""
    import functools

    from napari_fdlc import demo
    from napari_fdlc._napari import demo_flow

    monkeypatch.setattr(demo_flow, "run_demo", functools.partial(demo_flow.run_demo, identifier=identifier,
                                                                 templates=templates))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("FDLC_NO_GUI", raising=False)
    (tmp_path / "demo_output" / "screenshot.png").mkdir(parents=True)
    rc = demo.main(["--headless"])
    err = capsys.readouterr().err
    assert rc == 2 and "screenshot.png" in err and err.strip().count("\n") == 0, (rc, err)
    assert not (tmp_path / "demo_output" / "labels.csv").exists()


def test_closing_the_widget_unbinds_its_keys(make_napari_viewer, sample_files, qtbot):
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    dock, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    handler = viewer.window._qt_viewer._key_map_handler
    viewer.layers.selection.active = viewer.layers["NeuroPAL sample [W]"]
    assert handler.press_key("N")  # bound on the viewer
    viewer.window.remove_dock_widget(dock)
    assert not handler.press_key("N")


def test_nwb_opens_with_its_neurons(sample_files, tmp_path):
    from napari_fdlc._napari._io import get_stack_reader, get_table_reader
    from napari_fdlc.io.nwb import write_nwb
    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, truth)
    assert get_table_reader(str(path)) is None and get_stack_reader(str(tmp_path / "x.png")) is None
    layers = get_stack_reader(str(path))(str(path))
    assert [t for _, _, t in layers] == ["image"] * 4 + ["points"]
    data, kwargs, _ = layers[-1]
    world_xyz = (data * np.asarray(kwargs["scale"]))[:, ::-1]
    assert np.abs(world_xyz - truth.xyz).max() <= 0.5 * max(stack.voxel_size_zyx) + 1e-6  # voxel-mask rounding
    assert list(kwargs["features"]["label"]) == list(truth.label_strings())


def test_gui_stays_responsive_while_labelling(labelled_viewer, identifier):
    import time

    from qtpy.QtCore import QTimer


    viewer, widget = labelled_viewer

    class SlowIdentifier:  # the real model, made slow
        def label(self, *args, **kwargs):
            time.sleep(0.8)
            return identifier.label(*args, **kwargs)

    widget.identifier = SlowIdentifier()
    ticks = []
    timer = QTimer()
    timer.timeout.connect(lambda: ticks.append(time.perf_counter()))
    timer.start(20)
    start = time.perf_counter()
    worker = widget.auto_label(wait=False)  # the button's path
    assert time.perf_counter() - start < 0.5 and widget.busy and worker is not None
    assert not widget.run_button.isEnabled()
    try:
        widget.auto_label()
        raise AssertionError("a second run must be refused while one is running")
    except FdlcError as exc:
        assert "still running" in str(exc)
    assert widget.wait(timeout=30)
    timer.stop()
    assert widget.layer is not None and widget.run_button.isEnabled()
    gaps = np.diff([start] + ticks)
    assert len(ticks) > 20 and gaps.max() < 1.0  # the event loop kept running
    assert widget.progress_bar.value() == 100


def test_wait_returns_when_the_job_failed_before_it_was_called(labelled_viewer):
    # A job that fails at once ends in the worker before wait() listens: wait() must still
    # return at once (it used to wait for its whole timeout, or forever without one).
    import threading
    import time


    viewer, widget = labelled_viewer
    reached = threading.Event()

    class RefusingIdentifier:
        def label(self, *args, **kwargs):
            reached.set()
            raise FdlcError("refused at once")

    widget.identifier = RefusingIdentifier()
    widget.auto_label(wait=False)
    assert reached.wait(timeout=60)
    time.sleep(0.5)  # the worker has returned and emitted "finished" by now
    start = time.perf_counter()
    assert widget.wait(timeout=30)
    assert time.perf_counter() - start < 10
    assert widget.last_error is not None and "refused at once" in widget.last_error


def test_handedness_choice_reaches_the_model(labelled_viewer, monkeypatch):
    """The Handedness box: Auto-label and Re-label name the worm with the chosen chirality."""
    import napari_fdlc.identify as identify

    viewer, widget = labelled_viewer
    seen = []
    original = identify.label_neurons

    def spy(*args, **kwargs):
        if args[0].source != "warm-up":  # the widget's warm-up thread may name its worm meanwhile
            seen.append(kwargs["identifier"].settings.chirality)
        return original(*args, **kwargs)

    monkeypatch.setattr(identify, "label_neurons", spy)
    widget.auto_label()
    widget.chirality_combo.setCurrentIndex(widget.chirality_combo.findData("mirrored"))
    widget.relabel()
    assert seen == ["auto", "mirrored"] and widget.last_error is None


def test_handedness_diameter_and_colour_are_kept_for_the_next_napari_session(make_napari_viewer, tmp_path):
    from napari_fdlc._napari._widget import AutoLabelWidget
    from napari_fdlc.review import preferences_path

    widget = AutoLabelWidget(make_napari_viewer())
    assert widget.chirality_combo.currentData() == "auto" and widget.colour_check.isChecked()
    widget.chirality_combo.setCurrentIndex(widget.chirality_combo.findData("mirrored"))
    widget.diameter_spin.setValue(3.5)
    widget.colour_check.setChecked(False)
    assert tmp_path in preferences_path().parents  # the test's own user folder (conftest)
    again = AutoLabelWidget(make_napari_viewer())
    assert again.chirality_combo.currentData() == "mirrored"
    assert again.diameter_spin.value() == 3.5 and not again.colour_check.isChecked()
    preferences_path().write_text("{not json")  # a damaged file: the defaults, no error
    fresh = AutoLabelWidget(make_napari_viewer())
    assert fresh.chirality_combo.currentData() == "auto" and fresh.diameter_spin.value() == 3.0


def test_left_right_names_that_mirror_the_worm_suggest_setting_the_handedness(make_napari_viewer):
    from types import SimpleNamespace

    from napari_fdlc._napari._widget import BUILTIN, AutoLabelWidget

    widget = AutoLabelWidget(make_napari_viewer())
    mirrored, proper = SimpleNamespace(info={"mirrored": True}), SimpleNamespace(info={"mirrored": False})
    hint = widget._handedness_hint(mirrored, {3: "AVAL", 5: "AVG"}, BUILTIN, "auto")
    assert "AVAL" in hint and "AVG" not in hint and "'mirrored'" in hint
    assert widget._handedness_hint(proper, {3: "AVAL"}, BUILTIN, "auto") is None
    assert widget._handedness_hint(mirrored, {5: "AVG"}, BUILTIN, "auto") is None  # no left/right name
    assert widget._handedness_hint(mirrored, {3: "AVAL"}, BUILTIN, "mirrored") is None  # already set
    assert widget._handedness_hint(mirrored, {3: "AVAL"}, "my_template", "auto") is None  # not the atlas


def test_auto_label_says_what_the_panel_did_with_the_neurons():
    from types import SimpleNamespace

    from napari_fdlc._napari._widget import AutoLabelWidget

    message = AutoLabelWidget._done_message
    assert message(150, SimpleNamespace(info={})) == "done: 150 neurons"
    assert message(150, SimpleNamespace(info={"head_window": 140})) == "done: 150 neurons; 10 beyond the head get no name"
    assert "smaller worm" in message(150, SimpleNamespace(info={"smaller_worm": 1.31}))
    assert "×1.31" in message(150, SimpleNamespace(info={"smaller_worm": 1.31}))


def test_templates_of_another_handedness_are_mirrored_back_with_a_warning(make_napari_viewer, templates, monkeypatch):
    from napari_fdlc.table import NeuronTable

    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    shown = []
    monkeypatch.setattr(widget, "_notify_warning", shown.append)
    first = templates[0]
    mirrored = NeuronTable(first.xyz * [1, 1, -1], first.colours, first.labels, source="mirrored.csv")
    widget.set_templates([first, mirrored])
    assert len(shown) == 1 and shown[0].startswith("mirrored.csv: mirrored relative to")
    assert np.allclose(widget._templates()[0][1].xyz, first.xyz)
    widget.set_templates([first, first])
    assert len(shown) == 1


def test_a_template_file_not_in_micrometres_gets_a_warning(make_napari_viewer, templates, tmp_path, monkeypatch):
    from napari_fdlc.table import NeuronTable, write_table

    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    shown = []
    monkeypatch.setattr(widget, "_notify_warning", shown.append)
    first = templates[0]
    write_table(first, tmp_path / "um.csv")
    write_table(NeuronTable(first.xyz * 1000, first.colours, first.labels), tmp_path / "nm.csv")
    assert widget.add_template_file(tmp_path / "um.csv") == "file: um.csv" and shown == []
    assert widget.add_template_file(tmp_path / "nm.csv") == "file: nm.csv"
    assert len(shown) == 1 and "must be micrometres" in shown[0]


def test_neurons_not_in_micrometres_get_a_warning(make_napari_viewer, identifier, templates, monkeypatch):
    """Auto-label on a points layer in pixels (0.25 µm in x and y) says why its names are poor."""
    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    shown = []
    monkeypatch.setattr(widget, "_notify_warning", shown.append)
    widget.set_templates(templates)
    zyx = templates[0].xyz[:, ::-1]
    viewer.add_points(zyx, name="um")
    viewer.add_points(zyx * [1, 4, 4], name="pixels")
    widget.set_neurons("um")
    assert widget.auto_label() is not None and shown == []
    widget.set_neurons("pixels")
    assert widget.auto_label() is not None
    assert len(shown) == 1 and "its neurons lie" in shown[0] and "must be micrometres" in shown[0]


def test_a_table_opened_in_napari_shows_what_its_reader_warns_about(tmp_path, worm):
    """A name that occurs twice is read as unnamed on both rows; opening the file in napari
    says so in a notification, not only on stderr."""
    from napari.utils.notifications import notification_manager

    from napari_fdlc._napari._io import read_table_layer
    from napari_fdlc.table import NeuronTable, write_table

    labels = np.array(worm.labels, dtype=object)
    named = np.flatnonzero(labels != "")
    labels[named[1]] = labels[named[0]]
    path = tmp_path / "repeated.csv"
    write_table(NeuronTable(worm.xyz, worm.colours, labels), path)
    before = len(notification_manager.records)
    read_table_layer(str(path))
    messages = [str(r.message) for r in notification_manager.records[before:]]
    assert any(labels[named[0]] in m and "more than once" in m for m in messages), messages


# ----- session 30's review of the readers, the writer and the sample -----------------------------


def _small_named_worm(n=12, seed=0, offset=0.0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 6] + [60, 30, 15] + offset
    labels = np.array([f"N{i}" for i in range(n)], dtype=object)
    return NeuronTable(xyz, {c: rng.gamma(2.0, 100.0, n) for c in "RGB"}, labels)


def test_a_table_of_several_time_points_opens_over_time_with_its_names(tmp_path):
    """A table with a 't' column (fdlc segment of a recording, fdlc track, this plugin's writer)
    opens as (t, z, y, x) points, each time point's names its own; it opened as one volume of
    every time point, its names dropped as repeats."""
    from napari_fdlc._napari._io import get_table_reader, write_neuron_csv
    from napari_fdlc.track import join_by_time

    worm = _small_named_worm()
    moved = NeuronTable(worm.xyz + 1.0, worm.colours, worm.labels)
    path = tmp_path / "segmented.csv"
    write_table(join_by_time([worm, moved], [0, 1]), path)
    reader = get_table_reader(str(path))
    assert reader is not None
    data, kwargs, kind = reader(str(path))[0]
    assert kind == "points"
    assert data.shape == (2 * len(worm), 4), f"opened as {data.shape}: the time points are merged into one volume"
    assert sorted(set(data[:, 0])) == [0, 1]
    labels = list(kwargs["features"]["label"])
    assert labels == list(worm.labels) * 2, "the names (one per time point) were dropped as repeats"

    # the plugin's own round trip: points over time saved with its writer, opened again
    points = np.column_stack([np.repeat([0.0, 1.0], len(worm)), np.vstack([worm.xyz, moved.xyz])[:, ::-1]])
    saved = write_neuron_csv(str(tmp_path / "saved.csv"), points, {"scale": (1, 1, 1, 1)})[0]
    data, _, _ = get_table_reader(saved)(saved)[0]
    assert data.shape[1] == 4, "napari-fdlc cannot open over time the file its writer wrote over time"


def test_a_neuron_table_with_a_quoted_header_is_read(tmp_path):
    """A quoted header ("x_um","y_um", R's write.csv) is a neuron table to the napari reader too;
    it declined one that read_table reads."""
    import csv

    worm = _small_named_worm()
    path = tmp_path / "from_r.csv"
    worm.to_dataframe().to_csv(path, index=False, quoting=csv.QUOTE_NONNUMERIC)
    assert path.read_text().startswith('"x_um","y_um","z_um"')
    assert len(read_table(path)) == len(worm)  # the core reads it

    from napari_fdlc._napari._io import get_table_reader

    assert get_table_reader(str(path)) is not None, "the napari reader declines a neuron table the core reads"


def test_a_point_added_to_an_opened_table_gets_no_name_and_loses_none(make_napari_viewer, tmp_path):
    """A point added by hand to an opened table has no name and no colour; napari gave it the last
    row's, and saved and reopened, that name was on two rows and dropped from both."""
    worm = _small_named_worm()
    path = tmp_path / "worm.csv"
    write_table(worm, path)
    viewer = make_napari_viewer()
    layer = viewer.open(str(path), plugin="napari-fdlc")[0]
    layer.add(np.array([[10.0, 20.0, 30.0]]))
    added = layer.features.iloc[-1]
    assert added["label"] == "", f"a point added by hand shows the name {added['label']!r}"
    assert not np.isclose(float(added["R"]), worm.colours["R"][-1]), "a point added by hand carries the last neuron's colour"

    out = tmp_path / "edited.csv"
    viewer.layers.selection = {layer}
    viewer.layers.save(str(out), selected=True, plugin="napari-fdlc")
    again = read_table(out)
    assert again.labels[len(worm) - 1] == worm.labels[-1], "the last neuron's name was lost"


def test_opening_a_lazy_stack_does_not_read_it_whole(monkeypatch):
    """Opening a lazy stack reads a few planes for the contrast, not every plane of a stack of
    fewer than 32 (all of it)."""
    import dask
    import dask.array as da

    from napari_fdlc._napari._layers import stack_layers
    from napari_fdlc.io.images import Stack

    nz, shape = 24, (32, 32)
    reads = []

    def plane(c, z):
        reads.append((c, z))
        return np.full(shape, c * 100 + z, dtype=np.uint16)

    channels = [da.stack([da.from_delayed(dask.delayed(plane)(c, z), shape=shape, dtype=np.uint16) for z in range(nz)])
                for c in range(4)]
    stack = Stack(da.stack(channels), (1.5, 0.3, 0.3), ["R", "G", "B", "W"], "big.ome.tif")
    layers = stack_layers(stack)
    assert all(not isinstance(data, np.ndarray) for data, _, _ in layers)  # the layers stay lazy
    assert len(reads) <= 4 * nz // 2, f"opening read {len(reads)} of {4 * nz} planes"


def test_the_sample_restores_a_renamed_neuron_id_layer_under_its_new_name(make_napari_viewer, sample_files):
    """The sample's restored neuron-ID layer keeps the name it was saved under (gui.md §5); it was
    always renamed 'NeuroPAL sample neuron IDs'."""
    from napari_fdlc._napari._io import make_sample_data
    from napari_fdlc.review import ReviewSession, session_file_for
    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    session = ReviewSession(truth, voxel_size_zyx=stack.voxel_size_zyx, image=stack.source)
    session.settings["image_shape"] = list(stack.shape_zyx)
    session.settings["layer_name"] = "worm 7 reviewed"
    session.save(session_file_for(stack.source))
    layers = make_sample_data()
    assert layers[-1][1]["metadata"]["fdlc"].get("session"), "the session was not restored at all"
    assert layers[-1][1]["name"] == "worm 7 reviewed"


# Session 32 (a helper review of the napari readers and writer); each says what used to happen.

NEUROPAL_NAMES = ["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"]


def _worm(n=6, seed=0, offset=0.0, decimals=None):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 6] + [60, 30, 15] + offset
    if decimals is not None:
        xyz = np.round(xyz, decimals)
    labels = np.array([f"N{i}" for i in range(n)], dtype=object)
    return NeuronTable(xyz, {c: rng.gamma(2.0, 100.0, n) for c in "RGB"}, labels)


def _stack(roles, names, voxel=(1.5, 0.25, 0.25), shape=(6, 40, 50), seed=0):
    from napari_fdlc.io.images import Stack

    data = np.random.default_rng(seed).integers(0, 1000, (len(roles), *shape)).astype(np.uint16)
    return Stack(data, voxel, roles, "memory", names)


def _save_selected(viewer, layer, path):
    viewer.layers.selection = {layer}
    return viewer.layers.save(str(path), selected=True, plugin="napari-fdlc")


# ----- the writer and the time axis ------------------------------------------------------------


def test_a_point_added_to_an_opened_sequence_table_is_saved_at_its_frame(make_napari_viewer, tmp_path):
    """A point added at frame 1 of an opened sequence table was saved with an empty t (its t feature
    NaN, trusted over its frame), and the file did not reopen."""
    from napari_fdlc.track import join_by_time

    worm = _worm()
    moved = NeuronTable(worm.xyz + 1.0, worm.colours, worm.labels)
    path = tmp_path / "sequence.csv"
    write_table(join_by_time([worm, moved], [0, 1]), path)
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(path), plugin="napari-fdlc")
    assert layer.data.shape == (2 * len(worm), 4)
    layer.add(np.array([[1.0, 20.0, 30.0, 40.0]]))

    out = tmp_path / "edited.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, keep_default_na=False)
    assert str(saved["t"].iloc[-1]).strip() not in ("", "nan"), "the added point was saved without its time"
    assert float(saved["t"].iloc[-1]) == 1.0
    (again,) = viewer.open(str(out), plugin="napari-fdlc")
    assert again.data.shape == (2 * len(worm) + 1, 4)
    assert np.allclose(again.data[np.isclose(again.data[:, 1:], [20, 30, 40]).all(axis=1)][:, 0], 1.0)


def _track_neurons_layer(viewer, times, frames=None):
    """The Track widget's neurons layer of a 5-neuron, two-volume result at ``times``."""
    from napari_fdlc._napari.tracks import track_layers
    from napari_fdlc.track import Sequence, TrackResult

    n = 5
    worm = _worm(n)
    volumes = [NeuronTable(worm.xyz), NeuronTable(worm.xyz + 1.0)]
    result = TrackResult([np.arange(n), np.arange(n)], [np.ones(n), np.full(n, 0.9)],
                         [f"N{i}" for i in range(n)], [{}, {}])
    for data, kwargs, kind in track_layers(result, Sequence(volumes, times), "rec", frames=frames):
        layer = getattr(viewer, f"add_{kind}")(data, **kwargs)
    assert layer.name == "rec neurons"
    return layer


def test_a_point_added_to_the_track_neurons_layer_is_saved_at_its_frame_without_a_copied_name(make_napari_viewer, tmp_path):
    """A point added to the Track widget's neurons layer took napari's copy of the last point's
    features: saved at that point's time with its name (twice at t=1)."""
    viewer = make_napari_viewer()
    layer = _track_neurons_layer(viewer, [0, 1])
    layer.add(np.array([[0.0, 10.0, 20.0, 30.0]]))

    out = tmp_path / "tracked.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, keep_default_na=False)
    added = saved.iloc[-1]
    assert float(added["t"]) == 0.0, f"the point added at frame 0 was saved at t={added['t']}"
    assert added["label"] == "", f"the point added by hand was saved with the name {added['label']!r}"


# ----- the writer: world positions ------------------------------------------------------------


@pytest.mark.parametrize("how", ["affine", "rotate"])
def test_the_writer_writes_world_positions_of_a_transformed_layer(make_napari_viewer, tmp_path, how):
    """A Points layer rotated or moved by an affine in the viewer was written as if it had not moved.
    Now refused (napari-fdlc reads scale and translate only)."""
    from napari.utils.transforms import Affine

    from napari_fdlc.errors import FdlcError

    pts = np.array([[2.0, 10, 20], [3, 15, 25], [4, 12, 30]])
    viewer = make_napari_viewer()
    if how == "affine":
        layer = viewer.add_points(pts, name="moved", scale=(1.5, 0.25, 0.3))
        layer.affine = Affine(translate=(0.0, 5.0, 7.0))
    else:
        layer = viewer.add_points(pts, name="turned", scale=(1.5, 0.25, 0.3), rotate=90)
    world = np.array([layer.data_to_world(p) for p in layer.data])
    out = tmp_path / "points.csv"
    try:
        _save_selected(viewer, layer, out)
    except Exception as exc:  # a one-line refusal is fine too
        cause = exc.__cause__ or exc
        assert isinstance(cause, FdlcError) and "\n" not in str(cause)
        assert not out.exists()
        return
    saved = pd.read_csv(out)
    assert np.allclose(saved[["z_um", "y_um", "x_um"]].to_numpy(), world, atol=1e-6), (
        f"written {saved[['z_um', 'y_um', 'x_um']].to_numpy().tolist()}, napari shows {world.tolist()}")


# ----- the table reader -----------------------------------------------------------------------


def test_a_neuron_table_with_excels_sep_line_opens_in_napari(make_napari_viewer, tmp_path):
    """A table with Excel's `sep=,` first line was refused by the napari reader (read_table reads it)."""
    worm = _worm()
    plain = tmp_path / "plain.csv"
    write_table(worm, plain)
    path = tmp_path / "from excel.csv"
    path.write_text("sep=,\n" + plain.read_text())
    assert len(read_table(path)) == len(worm)  # the core reads it

    from napari_fdlc._napari._io import get_table_reader

    assert get_table_reader(str(path)) is not None, "the napari reader declines a neuron table the core reads"
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(path), plugin="napari-fdlc")
    assert np.allclose(layer.data[:, ::-1], worm.xyz)


# ----- the stack reader: channel roles ----------------------------------------------------------


def test_channels_without_a_neuropal_role_are_not_chosen_as_w_or_g(make_napari_viewer, tmp_path):
    """Channels napari-fdlc read with no role (DIC) or GFP were chosen as W and G by their colormap."""
    from napari_fdlc.io.images import write_tiff

    path = tmp_path / "worm.ome.tif"
    write_tiff(path, _stack(["R", None, "B", "W", "GFP"], ["mNeptune2.5", "DIC", "mTagBFP2", "TagRFP-T", "GCaMP6s"]))
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-fdlc")
    assert [layer.name for layer in layers] == ["worm [R]", "worm [DIC]", "worm [B]", "worm [W]", "worm [GFP]"]
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    chosen = {role: combo.currentText() for role, combo in widget.role_combos.items()}
    assert chosen["W"] == "worm [W]", f"the W channel chosen is {chosen['W']!r}"
    assert chosen["G"] != "worm [GFP]", "the GCaMP channel is chosen as CyOFP (G)"


# ----- the stack reader: restored sessions ---------------------------------------------------------


def test_reopening_an_image_whose_voxel_size_changed_does_not_misplace_its_neurons(make_napari_viewer, tmp_path):
    """A session restored onto an image rewritten with another voxel size put its neurons on other
    voxels, silently. Now not restored, and said."""
    from napari.utils.notifications import notification_manager

    from napari_fdlc.io.images import write_tiff
    from napari_fdlc.review import ReviewSession, session_file_for

    path = tmp_path / "worm.ome.tif"
    write_tiff(path, _stack(["R", "G", "B", "W"], NEUROPAL_NAMES, voxel=(1.5, 0.25, 0.25)))
    voxels = np.array([[3.0, 20.0, 25.0], [2.0, 10.0, 30.0]])
    xyz = (voxels * [1.5, 0.25, 0.25])[:, ::-1]
    session = ReviewSession(NeuronTable(xyz, {}, np.array(["AVAL", "AVAR"], dtype=object)),
                            voxel_size_zyx=(1.5, 0.25, 0.25), image=str(path))
    session.settings["image_shape"] = [6, 40, 50]
    session.save(session_file_for(path))
    write_tiff(path, _stack(["R", "G", "B", "W"], NEUROPAL_NAMES, voxel=(1.5, 0.5, 0.5)))  # recalibrated

    viewer = make_napari_viewer()
    before = len(notification_manager.records)
    layers = viewer.open(str(path), plugin="napari-fdlc")
    messages = [str(r.message) for r in notification_manager.records[before:]]
    restored = [layer for layer in layers if layer.name == "worm neuron IDs"]
    if not restored:
        assert any("voxel" in m for m in messages), f"the session was dropped without a word: {messages}"
        return
    image = layers[0]
    on_image = np.array([image.world_to_data(restored[0].data_to_world(p)) for p in restored[0].data])
    assert np.allclose(on_image, voxels, atol=1e-6), (
        f"the restored neurons lie on image voxels {on_image.tolist()}, placed on {voxels.tolist()}; said: {messages}")


# ----- round trips over time ---------------------------------------------------------------------


def test_a_sequence_with_timestamps_in_ns_keeps_its_times_through_napari(make_napari_viewer, tmp_path):
    """Timestamps in ns became float64 features and were written back merged into one time point."""
    from napari_fdlc.track import join_by_time

    worm = _worm(4)
    times = [1700000000123456789, 1700000000123456889]
    path = tmp_path / "timestamps.csv"
    write_table(join_by_time([worm, NeuronTable(worm.xyz + 1.0, worm.colours, worm.labels)], times), path)
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(path), plugin="napari-fdlc")
    assert layer.data.shape == (8, 4) and sorted(set(layer.data[:, 0])) == [0, 1]

    out = tmp_path / "saved.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, dtype=str, keep_default_na=False)
    assert sorted(set(saved["t"])) == [str(t) for t in times], f"times written: {sorted(set(saved['t']))}"
    (again,) = viewer.open(str(out), plugin="napari-fdlc")
    assert again.data.shape == (8, 4), f"the saved file reopens as {again.data.shape}: its time points merged"


def test_an_uncalibrated_stack_opens_in_pixels_and_its_voxel_size_is_set_in_the_widget(make_napari_viewer, sample_files,
                                                                                      identifier, templates, tmp_path):
    """A TIFF that does not say its voxel size used to be refused, with advice for the command
    line (--voxel-size) that a napari user cannot follow. It now opens in pixels, said; Auto-label
    refuses it until the voxel size is set in the widget (every channel's scale), then labels it;
    the file opened again takes the voxel size from its saved session."""
    import tifffile
    from napari.utils.notifications import notification_manager

    from napari_fdlc.io.images import read_stack

    sample = read_stack(sample_files[0])
    path = tmp_path / "uncalibrated.tif"
    tifffile.imwrite(path, np.asarray(sample.data)[None].transpose(0, 2, 1, 3, 4), imagej=True,
                     metadata={"axes": "TZCYX", "Labels": list(sample.channel_roles)})
    viewer = make_napari_viewer()
    before = len(notification_manager.records)
    images = viewer.open(str(path), plugin="napari-fdlc")
    said = [str(r.message) for r in notification_manager.records[before:]]
    assert len(images) == 4 and all(tuple(layer.scale) == (1, 1, 1) for layer in images)
    assert any("does not say the voxel size" in m and "Voxel size" in m for m in said), said
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget.voxel_edit.text() == "" and "not in the file" in widget.voxel_edit.placeholderText()
    assert widget.auto_label() is None
    assert "does not say the voxel size" in widget.last_error and "Voxel size" in widget.last_error
    widget.voxel_edit.setText("oops")
    widget._gui(widget._on_voxel_entered)  # said, nothing changed
    assert all(tuple(layer.scale) == (1, 1, 1) for layer in images)
    widget.voxel_edit.setText(" ".join(f"{v:g}" for v in sample.voxel_size_zyx))
    widget._gui(widget._on_voxel_entered)
    assert all(np.allclose(layer.scale, sample.voxel_size_zyx) for layer in images)
    layer = widget.auto_label()
    assert layer is not None and widget.last_error is None, widget.last_error
    assert np.allclose(widget.session.voxel_size_zyx, sample.voxel_size_zyx)
    with pytest.raises(FdlcError, match="move them off their nuclei"):  # its neurons are placed
        widget.set_voxel_size(1, 1, 1)

    again = make_napari_viewer().open(str(path), plugin="napari-fdlc")
    assert all(np.allclose(layer.scale, sample.voxel_size_zyx) for layer in again)
    assert [type(layer).__name__ for layer in again] == ["Image"] * 4 + ["Points"]  # the session restored


# ----- the Voxel size row -------------------------------------------------------------------------


def _sample(sample_files):
    from napari_fdlc.io.images import read_stack

    return read_stack(sample_files[0])


def _auto_label(viewer, identifier, templates):
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return widget


def test_a_voxel_size_set_to_the_readers_stand_in_values_is_still_refused(make_napari_viewer, sample_files,
                                                                          identifier, templates, tmp_path):
    """A voxel size set in the row is known, also when it equals the reader's stand-in (an
    OME-TIFF without z, whose z step is 1 µm): it was told from the stand-in by its values, so
    '1 0.36 0.36' (or '1 1 1') stayed refused whatever the user did."""
    import tifffile

    sample = _sample(sample_files)
    path = tmp_path / "partial.ome.tif"
    tifffile.imwrite(path, np.asarray(sample.data), ome=True,
                     metadata={"axes": "CZYX", "PhysicalSizeX": 0.36, "PhysicalSizeY": 0.36,
                               "Channel": {"Name": list(sample.channel_roles)}})
    viewer = make_napari_viewer()
    images = viewer.open(str(path), plugin="napari-fdlc")
    assert all(np.allclose(layer.scale, (1.0, 0.36, 0.36)) for layer in images)
    widget = _auto_label(viewer, identifier, templates)
    widget.voxel_edit.setText("1 0.36 0.36")
    widget._gui(widget._on_voxel_entered)
    assert widget.last_error is None, widget.last_error
    layer = widget.auto_label()
    assert layer is not None and widget.last_error is None, widget.last_error


def test_set_voxel_size_leaves_the_other_chosen_channels_in_pixels(make_napari_viewer, sample_files, identifier,
                                                                  templates, tmp_path):
    """One uncalibrated file per channel: Set rescales every chosen channel's file (only W's
    was, and Auto-label then refused channels of different voxel sizes)."""
    import tifffile

    sample = _sample(sample_files)
    data = np.asarray(sample.data)
    viewer = make_napari_viewer()
    layers = {}
    for i, role in enumerate(sample.channel_roles):
        path = tmp_path / f"worm_{role}.tif"
        tifffile.imwrite(path, data[i], imagej=True, metadata={"axes": "ZYX"})
        (layers[role],) = viewer.open(str(path), plugin="napari-fdlc")
    widget = _auto_label(viewer, identifier, templates)
    widget.set_channels(**{role: layer.name for role, layer in layers.items()})
    widget.set_voxel_size(*sample.voxel_size_zyx)
    assert all(np.allclose(layer.scale, sample.voxel_size_zyx) for layer in layers.values()), \
        {role: tuple(layer.scale) for role, layer in layers.items()}
    layer = widget.auto_label()
    assert layer is not None and widget.last_error is None, widget.last_error


def test_a_corrected_voxel_size_and_its_session_are_not_restored_on_reopening(make_napari_viewer, sample_files,
                                                                            identifier, templates, tmp_path):
    """A voxel size corrected in the row (the file says 1.2 µm in z) is the one the file opened
    again takes, from its session, with the session (it opened at 1.2 and the session was
    refused as saved for other voxels)."""
    import shutil

    path = tmp_path / "worm.ome.tif"
    shutil.copy(sample_files[0], path)
    viewer = make_napari_viewer()
    viewer.open(str(path), plugin="napari-fdlc")
    widget = _auto_label(viewer, identifier, templates)
    widget.set_voxel_size(1.0, 0.36, 0.36)
    assert widget.auto_label() is not None, widget.last_error
    row = int(np.flatnonzero(np.asarray(widget.session.auto_id) != "")[0])
    widget.accept(row)

    again = make_napari_viewer().open(str(path), plugin="napari-fdlc")
    assert all(np.allclose(layer.scale[-3:], (1.0, 0.36, 0.36)) for layer in again), \
        [tuple(layer.scale) for layer in again]
    assert [type(layer).__name__ for layer in again] == ["Image"] * 4 + ["Points"]


def test_nwb_neurons_stay_at_the_old_voxel_size_when_it_is_corrected(make_napari_viewer, sample_files, identifier,
                                                                   templates, tmp_path):
    """An NWB file's annotated neurons (on its voxels) move with its images when the voxel
    size is corrected; they stayed at the old scale, off their nuclei."""
    from napari_fdlc.io.nwb import write_nwb
    from napari_fdlc.table import NeuronTable

    sample = _sample(sample_files)
    rng = np.random.default_rng(0)
    zyx = rng.integers(2, 30, size=(20, 3)) * np.array([1, 3, 8])
    neurons = NeuronTable(zyx[:, ::-1] * np.asarray(sample.voxel_size_zyx)[::-1], {},
                          np.array([f"N{i}" for i in range(20)], dtype=object))
    path = tmp_path / "worm.nwb"
    write_nwb(path, sample, neurons)
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-fdlc")
    points = [layer for layer in layers if type(layer).__name__ == "Points"]
    assert len(points) == 1
    widget = _auto_label(viewer, identifier, templates)
    try:
        widget.set_voxel_size(1.0, 0.36, 0.36)
    except Exception as exc:  # refused: acceptable
        assert "nuclei" in str(exc)
        return
    image = next(layer for layer in layers if type(layer).__name__ == "Image")
    assert np.allclose(points[0].scale[-3:], image.scale[-3:]), (tuple(points[0].scale), tuple(image.scale))


def test_pressing_set_on_the_shown_voxel_size_changes_it(make_napari_viewer, sample_files, identifier, templates,
                                                        tmp_path):
    """Set on what the row shows leaves a many-digit voxel size as it is (shown to 6 digits,
    it was rewritten 1.5e-6 off: enough for the session then saved to be refused on reopening)."""
    import tifffile

    sample = _sample(sample_files)
    exact = (1.2, 0.2596153846153846, 0.2596153846153846)
    path = tmp_path / "worm.ome.tif"
    tifffile.imwrite(path, np.asarray(sample.data), ome=True,
                     metadata={"axes": "CZYX", "PhysicalSizeZ": exact[0], "PhysicalSizeY": exact[1],
                               "PhysicalSizeX": exact[2], "Channel": {"Name": list(sample.channel_roles)}})
    viewer = make_napari_viewer()
    images = viewer.open(str(path), plugin="napari-fdlc")
    widget = _auto_label(viewer, identifier, templates)
    shown = widget.voxel_edit.text()
    widget._gui(widget._on_voxel_entered)  # Set pressed on what the row shows
    assert widget.last_error is None, widget.last_error
    assert all(np.allclose(layer.scale, exact, rtol=1e-9, atol=0) for layer in images), \
        (shown, [tuple(layer.scale) for layer in images])


def test_a_set_voxel_size_moves_the_track_layers_of_the_recording_off_their_nuclei(make_napari_viewer, sample_files,
                                                                                 identifier, templates, tmp_path):
    """A recording's voxel size may not change under its tracked neurons (in µm at the old
    size): refused, as under a neuron-ID layer; it was changed and they lay off their nuclei."""
    import tifffile

    from napari_fdlc._napari.tracks import TrackWidget

    sample = _sample(sample_files)
    data = np.asarray(sample.data)
    recording = np.stack([data, np.roll(data, 1, axis=-1)])[:, :, 8:24, 20:80, 60:220]  # t, c, z, y, x: small
    path = tmp_path / "recording.ome.tif"
    tifffile.imwrite(path, recording, ome=True,
                     metadata={"axes": "TCZYX", "PhysicalSizeZ": 1.2, "PhysicalSizeY": 0.36, "PhysicalSizeX": 0.36,
                               "Channel": {"Name": list(sample.channel_roles)}})
    viewer = make_napari_viewer()
    images = viewer.open(str(path), plugin="napari-fdlc")
    track = TrackWidget(viewer)
    viewer.window.add_dock_widget(track, name="Track")
    track.identifier = identifier
    out = track.run()
    assert out is not None, track.last_error
    points = out[-1]
    before = points.data[:, 1:] * np.asarray(points.scale[1:])  # world µm
    widget = _auto_label(viewer, identifier, templates)
    try:
        widget.set_voxel_size(1.0, 0.36, 0.36)
    except Exception as exc:
        assert "nuclei" in str(exc)
        return
    # the image moved under the points: a point that lay on voxel v now lies elsewhere
    ratio = np.asarray(images[0].scale[-3:]) / np.asarray((1.2, 0.36, 0.36))
    after = points.data[:, 1:] * np.asarray(points.scale[1:])
    assert np.allclose(after, before * ratio), "the tracked neurons no longer lie on their nuclei"


def test_a_point_added_at_an_empty_frame_of_an_opened_sequence_is_saved_at_that_frame(make_napari_viewer, tmp_path):
    """gui.md: a point added by hand to a layer over time 'takes the time of its frame'; tracking.md:
    a time point left out for want of nuclei leaves its frame empty. Expected: a point added at the
    empty frame 1 of a sequence with t = 0 and 2 is saved with t = 1. Actual: it is saved with
    t = 0 (the reader's feature default for an integer t column is the first t, which the writer
    trusts over the frame), so on reopening it joins the first volume."""
    from napari_fdlc.track import join_by_time

    worm = _worm()
    path = tmp_path / "gap.csv"
    write_table(join_by_time([worm, NeuronTable(worm.xyz + 1.0, worm.colours, worm.labels)], [0, 2]), path)
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(path), plugin="napari-fdlc")
    assert sorted(set(layer.data[:, 0])) == [0, 2]
    layer.add(np.array([[1.0, 20.0, 30.0, 40.0]]))

    out = tmp_path / "edited.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, keep_default_na=False)
    assert float(saved["t"].iloc[-1]) == 1.0, f"the point added at frame 1 was saved at t={saved['t'].iloc[-1]}"


def test_a_point_added_at_an_empty_frame_of_the_track_neurons_layer_is_saved_at_that_frame(make_napari_viewer, tmp_path):
    """The Track widget's neurons layer of a recording whose frame 1 had no nuclei (frames 0 and 2).
    Expected: a point added by hand at frame 1 is saved with t = 1 (gui.md: 'a point added by hand
    takes the time of its frame'). Actual: t = 0, the layer's feature default (the first time),
    which the writer takes over the frame."""
    viewer = make_napari_viewer()
    layer = _track_neurons_layer(viewer, [0, 2], frames=[0, 2])
    layer.add(np.array([[1.0, 10.0, 20.0, 30.0]]))

    out = tmp_path / "tracked.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, keep_default_na=False)
    assert float(saved["t"].iloc[-1]) == 1.0, f"the point added at frame 1 was saved at t={saved['t'].iloc[-1]}"


def test_an_nwb_file_without_a_voxel_size_opens_with_its_annotated_neurons(tmp_path):
    """gui.md: 'An NWB file's annotated neurons come with its image as a Points layer', and a file
    that does not say its voxel size opens in pixels, the Voxel size row then setting 'the scale
    of every layer ... an NWB file's neurons included'. Expected: an NWB file whose grid spacing is
    in pixels opens as its images plus its neurons (in voxels, like the images). Actual: the
    neurons are dropped with the warning 'the NWB file does not say the voxel size'
    (_io._nwb_neurons -> read_nwb_neurons refuses it)."""
    import h5py

    from napari_fdlc._napari._io import get_stack_reader
    from napari_fdlc.io.images import Stack
    from napari_fdlc.io.nwb import write_nwb

    rng = np.random.default_rng(0)
    data = rng.integers(0, 1000, (4, 6, 20, 24)).astype(np.uint16)
    path = tmp_path / "worm.nwb"
    zyx = np.array([[1, 3, 4], [2, 10, 12], [4, 15, 20]])
    voxel = (1.5, 0.4, 0.4)
    neurons = NeuronTable(zyx[:, ::-1] * np.asarray(voxel)[::-1], {}, np.array(["AVAL", "AVAR", "RIAL"], dtype=object))
    write_nwb(path, Stack(data, voxel, ["R", "G", "B", "W"], str(path), None), neurons)
    with h5py.File(path, "r+") as f:
        f["general/optophysiology/NeuroPALImVol/grid_spacing"].attrs["unit"] = "pixels"

    layers = get_stack_reader(str(path))(str(path))
    kinds = [kind for _, _, kind in layers]
    assert kinds[:4] == ["image"] * 4 and layers[0][1]["scale"] == (1.0, 1.0, 1.0)  # opened in pixels
    assert "points" in kinds, f"the NWB file's 3 annotated neurons were not opened (layers: {kinds})"


def test_a_recording_whose_channels_are_not_named_is_offered_by_the_track_widget(make_napari_viewer, identifier, tmp_path):
    """README / gui.md: a recording opened in napari is offered first under the Track widget's
    *Neurons from* (`fdlc track` tracks such a file: without roles it segments the sum of the
    channels). Expected: a two-channel recording whose file does not name its channels is
    offered. Actual: it is not offered at all (TrackWidget._recordings keeps only layers with a
    known role when the file has more than one channel), and set_recording says there is no
    such recording in the viewer."""
    from napari_fdlc._napari.tracks import SEQUENCE_FILE, TrackWidget
    from napari_fdlc.io.images import StackSeries, write_tiff

    data = np.random.default_rng(0).integers(0, 1000, (2, 2, 4, 16, 18)).astype(np.uint16)
    path = tmp_path / "rec.ome.tif"
    write_tiff(path, StackSeries(data, (1.5, 0.4, 0.4), [None, None], str(path), None), channel_names=["", ""])
    viewer = make_napari_viewer()
    layers = viewer.open(str(path), plugin="napari-fdlc")
    assert len(layers) == 2 and all(layer.data.ndim == 4 for layer in layers)
    widget = TrackWidget(viewer)
    widget.identifier = identifier
    offered = [widget.source_combo.itemText(i) for i in range(widget.source_combo.count())]
    assert offered != [SEQUENCE_FILE], f"the recording open in the viewer is not offered: {offered}"


def test_review_layer_features_keep_a_colour_gap(gap_table):
    """The neuron-ID layer's features are what File → Save Selected Layers writes (and what
    table_from_layer reads). A neuron without an R reading should hold NaN there (the table
    layer does, through to_dataframe); review_features copies ``session.table.colours``, the
    median filled in, so a saved result layer writes the median as a reading."""
    from napari_fdlc._napari._layers import review_features
    from napari_fdlc.review import ReviewSession

    feats = review_features(ReviewSession(gap_table))
    assert np.isnan(feats["R"].iloc[3]), feats["R"].iloc[3]


def _open_and_save(path, out):
    """The napari reader's layer data written back by the napari writer (what File > Open then
    File > Save Selected Layers do, without moving a point)."""
    from napari_fdlc._napari._io import get_table_reader, write_neuron_csv

    reader = get_table_reader(str(path))
    assert reader is not None, f"napari-fdlc declines {path}"
    data, kwargs, _ = reader(str(path))[0]
    return write_neuron_csv(str(out), data, {"scale": kwargs["scale"], "features": kwargs["features"]})[0]


def test_a_neuropal_id_export_with_a_quoted_header_opens_in_napari(tmp_path):
    """A NeuroPAL_ID "Save ID Info" CSV whose header is quoted ("User ID","User Confidence",...,
    as R's write.csv or a spreadsheet re-saves it) is read by read_table (its NeuroPAL_ID header is
    recognised quoted or not). Expected: napari-fdlc's table reader opens it too. Actual:
    get_table_reader declines it (it looks for the bare text 'User ID,'), so napari says no
    plugin can read the file."""
    from napari_fdlc._napari._io import get_table_reader

    worm = _worm(8)
    plain = tmp_path / "plain_npid.csv"
    write_neuropal_id(worm, plain, voxel_size_zyx=(1.5, 0.25, 0.25))
    lines = plain.read_text().splitlines()
    header = next(csv.reader([lines[7]]))
    path = tmp_path / "resaved_npid.csv"
    path.write_text("\n".join(lines[:7] + [",".join(f'"{h}"' for h in header)] + lines[8:]) + "\n")
    assert list(read_table(path).labels) == list(worm.labels)  # the core reads it, names and all

    assert get_table_reader(str(path)) is not None, "the napari reader declines a NeuroPAL_ID table the core reads"


def test_a_neuron_table_with_a_blank_line_above_its_header_opens_in_napari(tmp_path):
    """A table with an empty line (or Excel's row of bare commas) above its header is read by
    read_table (blank rows above the header are skipped). Expected: napari-fdlc's table reader
    opens it too. Actual: get_table_reader takes the blank first line for the header and declines
    the file: napari says no plugin can read it."""
    from napari_fdlc._napari._io import get_table_reader

    worm = _worm(8)
    plain = tmp_path / "plain.csv"
    write_table(worm, plain)
    declined = []
    for name, above in (("blank line.csv", "\n"), ("excel commas.csv", ",,,,,,,\n")):
        path = tmp_path / name
        path.write_text(above + plain.read_text())
        assert len(read_table(path)) == len(worm)  # the core reads it
        if get_table_reader(str(path)) is None:
            declined.append(name)
    assert not declined, f"the napari reader declines tables the core reads: {declined}"


def test_a_point_added_to_an_opened_table_of_one_time_point_reopens(make_napari_viewer, tmp_path):
    """A table of one time point with a 't' column (one volume of `fdlc segment`/`fdlc track`
    output, t = 5 on every row) opens as one volume, its t a text feature. Expected: after adding a
    point by hand and saving with the napari-fdlc writer, the file opens again (the added point at
    t = 5, like every other). Actual: the added point gets the feature default '' for t, the file
    is saved with an empty t cell, and opening it again fails: "line 8, column 't': an empty cell
    is not a finite number" (two 't' values, '5' and '', make it a sequence)."""
    worm = _worm(6)
    df = worm.to_dataframe()
    df.insert(0, "t", 5)
    path = tmp_path / "one time point.csv"
    write_table(df, path)
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(path), plugin="napari-fdlc")
    assert layer.data.shape == (6, 3)
    layer.add(np.array([[10.0, 20.0, 30.0]]))

    out = tmp_path / "edited.csv"
    _save_selected(viewer, layer, out)
    saved = pd.read_csv(out, dtype=str, keep_default_na=False)
    assert saved["t"].iloc[-1].strip() != "", "the point added by hand was saved with an empty t"
    (again,) = viewer.open(str(out), plugin="napari-fdlc")
    assert len(again.data) == 7


def test_saving_an_opened_table_keeps_a_column_named_neuron_or_shown(tmp_path):
    """gui.md: a neuron table opens with 'any other columns as features', and the writer saves 'the
    layer's features'. Expected: a user's own columns 'neuron' (their neuron number) and 'shown'
    come back in the saved file, as 'score' does. Actual: write_neuron_csv drops every feature
    called 'neuron' or 'shown' (the names of the review layer's own features), so open -> save
    silently loses those columns of the user's table."""
    worm = _worm(6)
    df = worm.to_dataframe()
    df["neuron"] = np.arange(101, 107)
    df["shown"] = ["yes", "no"] * 3
    df["score"] = np.linspace(0.1, 0.6, 6)
    path = tmp_path / "mine.csv"
    write_table(df, path)

    out = _open_and_save(path, tmp_path / "saved.csv")
    saved = pd.read_csv(out, dtype=str, keep_default_na=False)
    lost = [c for c in ("neuron", "shown", "score") if c not in saved.columns]
    assert not lost, f"columns lost by open -> save: {lost} (saved: {list(saved.columns)})"
    assert list(saved["neuron"]) == [str(v) for v in range(101, 107)]


def test_saving_an_opened_table_keeps_its_pixel_columns_when_they_give_no_voxel_size(tmp_path):
    """A table whose x_px, y_px, z_px do not scale to its µm (here the stage offset of a crop: x_um
    = 10 + 0.25 x_px) opens in µm, its pixel columns kept as features. Expected: open -> save keeps
    the x_px, y_px, z_px columns and their values. Actual: the writer drops the x_px/y_px/z_px
    features and writes pixel columns only for a scaled layer, so the file saved has none: the
    user's pixel coordinates are lost."""
    worm = _worm(6, decimals=2)
    df = worm.to_dataframe()
    df["x_px"] = (worm.xyz[:, 0] - 10.0) / 0.25
    df["y_px"] = (worm.xyz[:, 1] - 5.0) / 0.25
    df["z_px"] = worm.xyz[:, 2] / 1.5
    path = tmp_path / "crop.csv"
    write_table(df, path)

    out = _open_and_save(path, tmp_path / "saved.csv")
    saved = pd.read_csv(out)
    lost = [c for c in ("x_px", "y_px", "z_px") if c not in saved.columns]
    assert not lost, f"columns lost by open -> save: {lost} (saved: {list(saved.columns)})"
    assert np.allclose(saved["x_px"], df["x_px"], atol=1e-3)


def test_saving_the_sample_neuron_table_unchanged_keeps_its_positions(tmp_path):
    """Open -> save must give the same positions (write_table writes µm 'to the last digit': a
    position written back is the one read). Expected: the bundled sample's neuron table
    (sample_neurons.csv, with x_px, y_px, z_px) opened in napari and saved unchanged with the
    napari-fdlc writer has exactly the positions read. Actual: the reader puts the points at µm /
    voxel, with a voxel size inferred from x_px written to 6 digits (1.1999993 for 1.2), and the
    writer multiplies back: about one position in six comes back off in its last bits
    (15.434 -> 15.434000000000001), and every further save moves more of them."""
    from napari_fdlc import sample

    path = sample.sample_paths()[1]
    if not path.exists():
        import pytest

        pytest.skip("the package does not ship the sample neuron table")
    out = _open_and_save(path, tmp_path / "saved.csv")
    before = pd.read_csv(path, dtype=str, keep_default_na=False)
    after = pd.read_csv(out, dtype=str, keep_default_na=False)
    changed = {c: int((before[c].astype(float).to_numpy() != after[c].astype(float).to_numpy()).sum())
               for c in ("x_um", "y_um", "z_um")}
    assert not any(changed.values()), (
        f"positions changed by open -> save (of {len(before)}): {changed}; e.g. "
        f"{before['x_um'][before['x_um'] != after['x_um']].head(2).tolist()} -> "
        f"{after['x_um'][before['x_um'] != after['x_um']].head(2).tolist()}")


def test_a_plain_3d_tiff_is_not_refused_with_advice_only_the_command_line_can_follow(tmp_path):
    """A plain TIFF of one 3D array (tifffile.imwrite(path, zyx), the commonest way a script saves
    a stack) does not record its axes. Expected in napari: it opens (3 axes with several planes:
    Z, Y, X, in pixels until the voxel size is set, as an uncalibrated stack does), or a one-line
    message saying what a napari user can do. Actual: read_stack_layers refuses it with the
    command-line/script advice "give them, e.g. --axes ZYX (axes='ZYX')", which napari's File >
    Open offers no way to give (napari-fdlc's earlier fix for the voxel size, the same case)."""
    import tifffile

    from napari_fdlc._napari._io import read_stack_layers
    from napari_fdlc.errors import FdlcError

    path = tmp_path / "stack.tif"
    tifffile.imwrite(path, np.random.default_rng(0).integers(0, 1000, (6, 30, 40)).astype(np.uint16))
    try:
        layers = read_stack_layers(str(path))
    except FdlcError as exc:
        message = str(exc)
        assert "--axes" not in message and "axes=" not in message, f"napari shows: {message}"
        return
    assert layers and np.shape(layers[0][0]) == (6, 30, 40)


def test_fdlc_track_output_opens_with_the_names_of_its_tracks(tmp_path):
    """`fdlc track` with a labelled reference writes each track's name in a `name` column (the
    input's own names stay `label`); opened in napari its points showed no names at all."""
    from napari_fdlc._napari._io import get_table_reader
    from napari_fdlc.cli import main
    from napari_fdlc.track import join_by_time

    worm = _small_named_worm()
    unnamed = NeuronTable(worm.xyz, worm.colours)
    moved = NeuronTable(worm.xyz + 0.3, worm.colours)
    write_table(join_by_time([unnamed, moved], [0, 1]), tmp_path / "recording.csv")
    write_table(worm, tmp_path / "reference.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(tmp_path / "recording.csv"), "--reference", str(tmp_path / "reference.csv"),
                 "--method", "geometry", "--out", str(out), "--quiet"]) == 0
    data, kwargs, _ = get_table_reader(str(out))(str(out))[0]
    assert kwargs.get("text", {}).get("string") == "{name}", "the tracks' names are not shown"
    assert list(kwargs["features"]["name"][: len(worm)]) == list(worm.labels)


def _dock(viewer, identifier, templates):
    dock, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return dock, widget


def _saved_neurons(path) -> int:
    return len(json.loads(path.read_text())["neurons"]["x_um"])


def test_a_point_added_while_the_auto_label_dock_is_closed_survives_docking_it_again(
        make_napari_viewer, sample_files, identifier, templates):
    """Auto-label, close the Auto-label dock (for room), add a neuron to the neuron-ID layer by
    hand, dock the widget again. Expected: the added neuron is kept (followed, autosaved).
    Actual: while the dock is closed nothing follows the layer (_release_viewer disconnected its
    data events), so the point is never saved; docking again re-adopts the cached session and
    _refresh_layer(structure=True) overwrites layer.data with the session's table: the point the
    user added vanishes from the layer without a word, and it is in no file."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    dock, widget = _dock(viewer, identifier, templates)
    layer = widget.auto_label()
    n = len(widget.session)
    path = widget.session.path
    viewer.window.remove_dock_widget(dock)
    layer.add(np.asarray(layer.data)[0] + np.array([0.0, 8.0, 8.0]))
    assert len(layer.data) == n + 1
    _, again = _dock(viewer, identifier, templates)
    assert again.layer is layer
    assert len(layer.data) == n + 1, "the point added while the dock was closed was removed from the layer"
    assert _saved_neurons(path) == n + 1, "the point added while the dock was closed is not in the session file"


def test_renaming_the_neuron_id_layer_while_the_dock_is_closed_is_kept_on_reopening(
        make_napari_viewer, sample_files, identifier, templates):
    """Auto-label, close the dock, rename the neuron-ID layer, reopen the image. Expected
    (gui.md §5: "A renamed neuron-ID layer comes back under its new name"): the new name.
    Actual: the rename is only recorded by _on_layer_renamed, connected to the linked layer
    alone (disconnected when the dock closes, or when another worm is reviewed; _link does not
    take the name of an adopted layer either), so the session file keeps the old name and the
    layer comes back as 'NeuroPAL sample neuron IDs'."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    dock, widget = _dock(viewer, identifier, templates)
    layer = widget.auto_label()
    viewer.window.remove_dock_widget(dock)
    layer.name = "worm 1 reviewed"
    again = make_napari_viewer()
    again.open_sample("napari-fdlc", "neuropal")
    assert again.layers[-1].name == "worm 1 reviewed", [lay.name for lay in again.layers]


def test_a_point_added_to_a_restored_neuron_id_layer_is_saved_without_another_neurons_name(make_napari_viewer, tmp_path):
    """Reopen a reviewed image (its neuron-ID layer is restored; the Auto-label dock not open),
    add a neuron by hand, File > Save Selected Layers with the napari-fdlc writer. Expected (as
    for an opened table, gui.md §1: a point you add has no name): the added neuron has no name
    and the user's decision stays on its neuron. Actual: review_points sets no feature_defaults,
    so napari copies the last row's features (label, user_id, status) onto the new point: the
    CSV names two neurons AVAL 'corrected', and read back (fdlc commands, this plugin) both rows
    are unnamed: the user's decision is lost from the saved file."""
    from napari_fdlc.review import ReviewSession, session_file_for
    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    session = ReviewSession(truth, voxel_size_zyx=stack.voxel_size_zyx, image=stack.source)
    session.settings["image_shape"] = list(stack.shape_zyx)
    last = len(session) - 1
    session.assign(last, "AVAL")
    session.save(session_file_for(stack.source))
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    layer = viewer.layers[-1]
    assert layer.features["user_id"].iloc[last] == "AVAL"
    layer.add(np.asarray(layer.data)[0] + [0.0, 8.0, 8.0])
    out = tmp_path / "ids.csv"
    viewer.layers.selection = {layer}
    viewer.layers.save(str(out), selected=True, plugin="napari-fdlc")
    df = pd.read_csv(out, keep_default_na=False)
    assert df["user_id"].iloc[-1] == "", f"the added neuron carries the name {df['user_id'].iloc[-1]!r}"
    assert read_table(out).labels[last] == "AVAL", "the user's decision is lost from the saved file"


def test_the_writer_leaves_out_neuropal_id_voxel_coordinates_when_it_writes_its_own(tmp_path):
    """A scaled layer is saved with x_px, y_px, z_px written anew from its points; NeuroPAL_ID's
    'Internal X (px)' features (of the position when read) are left out: a point moved since
    was saved with the old ones beside its new position."""
    data = np.array([[2.0, 10.0, 20.0], [3.0, 12.0, 25.0]])
    feats = pd.DataFrame({"label": ["AVAL", "AVAR"], "Internal X (px)": ["1", "2"], "Internal Z (slice)": ["1", "2"]})
    [out] = write_neuron_csv(str(tmp_path / "saved.csv"), data, {"scale": (1.5, 0.25, 0.25), "features": feats})
    df = pd.read_csv(out, keep_default_na=False)
    assert not {"Internal X (px)", "Internal Z (slice)"} & set(df.columns), list(df.columns)
    assert list(df["x_px"]) == [20.0, 25.0]


def test_a_neuropal_id_table_opens_on_its_voxels_and_a_moved_point_is_saved_with_new_ones(tmp_path):
    """A NeuroPAL_ID table gives its voxel coordinates (1-based 'Internal X (px)') beside µm:
    it opens scaled by that voxel size, like our tables with x_px, so a point moved is saved
    with voxel coordinates of where it is now. It opened unscaled, and a point moved was saved
    with its old 'Internal X (px)' beside its new position."""
    from napari_fdlc._napari._io import get_table_reader

    xyz = np.array([[5.0, 2.5, 3.0], [9.0, 4.0, 6.0], [12.5, 7.25, 10.5]])
    path = tmp_path / "npid.csv"
    write_neuropal_id(NeuronTable(xyz, labels=np.array(["AVAL", "AVAR", "RIAL"], dtype=object)), path,
                      voxel_size_zyx=(1.5, 0.25, 0.25))
    data, kwargs, _ = get_table_reader(str(path))(str(path))[0]
    assert tuple(kwargs["scale"]) == (1.5, 0.25, 0.25)
    np.testing.assert_allclose(data * kwargs["scale"], xyz[:, ::-1])
    data[0, 2] += 8  # moved 2 µm along x
    [out] = write_neuron_csv(str(tmp_path / "saved.csv"), data, kwargs)
    df = pd.read_csv(out, keep_default_na=False)
    assert "Internal X (px)" not in df.columns
    assert df["x_px"][0] == pytest.approx(xyz[0, 0] / 0.25 + 8) and df["x_um"][0] == pytest.approx(7.0)


def test_a_segment_table_opened_and_saved_in_napari_keeps_its_positions(tmp_path):
    """Expected: a neuron table as ``fdlc segment`` writes it (positions to the last digit,
    repr, beside x_px, y_px, z_px) opened in napari and saved unchanged with the napari-fdlc
    writer has exactly the positions read (write_table writes them "to the last digit"; the
    sample's 3-decimal table already round-trips). Actual: every 16-17-digit position comes back
    cut to 15 significant digits (12.345678901234567 -> 12.3456789012346), even with a voxel
    size of 0.25 where µm / voxel * voxel is exact. Cause: _napari/_io.py:write_neuron_csv
    rounds every scaled world coordinate to ``.15g`` to undo the division's last bits, which
    also drops the digits that were read."""
    from napari_fdlc._napari._io import get_table_reader, write_neuron_csv

    xyz = np.array([[12.345678901234567, 3.141592653589793, 7.123456789012345],
                    [40.98765432109876, 1.6389409646301716, 10.791468550226549]])
    vox = np.array([0.25, 0.25, 1.5])  # x, y, z
    extra = pd.DataFrame({"x_px": xyz[:, 0] / vox[0], "y_px": xyz[:, 1] / vox[1], "z_px": xyz[:, 2] / vox[2]})
    path = tmp_path / "neurons.csv"
    write_table(NeuronTable(xyz, extra=extra), path)
    data, kwargs, _ = get_table_reader(str(path))(str(path))[0]
    assert kwargs["scale"] == (1.5, 0.25, 0.25)
    [saved] = write_neuron_csv(str(tmp_path / "saved.csv"), data, {"scale": kwargs["scale"], "features": kwargs["features"]})
    back = read_table(saved).xyz
    # x, y on voxels of 0.25 (µm / voxel * voxel exact) come back whole; z's 1.5 leaves both
    # 7.123456789012345 and the ...344 next to it on the same voxel coordinate: one ulp
    assert back[:, :2].tolist() == xyz[:, :2].tolist(), f"{xyz.tolist()} -> {back.tolist()}"
    np.testing.assert_allclose(back[:, 2], xyz[:, 2], rtol=4e-16, atol=0)


def test_napari_opens_a_table_whose_first_column_name_holds_a_line_break(tmp_path):
    """Expected: a neuron table that read_table reads opens in napari too (its reader claims
    our CSV). A column name with a line break (Excel's Alt+Enter in a header cell, quoted in
    the CSV) in front of x_um: read_table reads it, napari's reader declines the file
    (get_table_reader returns None: "no reader"). Cause: _napari/_io.py:get_table_reader parses
    each physical line on its own (csv.reader([line])), so the quoted header is cut at its line
    break and x_um, y_um, z_um are never seen."""
    from napari_fdlc._napari._io import get_table_reader

    path = tmp_path / "t.csv"
    path.write_text('"cell\nnote",x_um,y_um,z_um\na,1,2,3\nb,4,5,6\n', encoding="utf-8")
    assert read_table(path).xyz.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert get_table_reader(str(path)) is not None, "the napari reader declines a neuron table the core reads"
