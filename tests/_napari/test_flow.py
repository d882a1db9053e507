"""The whole Auto-label flow on the bundled sample, through the widget's public methods, its
keys and its controls: open, auto-label, threshold, review, undo, re-label, export, reopen."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.review import find_session, session_file_for, user_session_dir
from napari_fdlc.table import read_table
import shutil

REVIEW_FEATURES = [
    "auto_id", "auto_conf", "cand_1", "cand_2", "cand_3", "prob_1", "prob_2", "prob_3",
    "user_id", "user_conf", "status",
]


def _press(viewer, key):
    """A key press as the canvas delivers it (active layer keymap first, then the viewer's)."""
    assert viewer.window._qt_viewer._key_map_handler.press_key(key), f"key {key} not bound"


def _named_rows(layer, n):
    f = layer.features
    named = np.flatnonzero(f["auto_id"].to_numpy(object) != "")
    return [int(i) for i in named[np.argsort(-f["auto_conf"].to_numpy()[named])][:n]]


def test_display_of_the_sample(labelled_viewer):
    viewer, widget = labelled_viewer
    images = [layer for layer in viewer.layers if type(layer).__name__ == "Image"]
    assert [layer.colormap.name for layer in images] == ["red", "green", "blue", "gray"]
    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    for layer in images:
        assert layer.blending == "additive" and layer.gamma == pytest.approx(0.7)
        assert np.allclose(layer.scale, stack.voxel_size_zyx)
        lo, hi = layer.contrast_limits
        assert np.median(layer.data) <= lo + 1 and hi > lo
    # the neuron table sits on the nuclei: W is bright at every truth centre
    points = viewer.layers["sample neurons (truth)"]
    assert np.allclose(points.scale, stack.voxel_size_zyx)
    w = np.asarray(viewer.layers["NeuroPAL sample [W]"].data, dtype=float)
    idx = np.rint(points.data).astype(int)
    at_centres = w[idx[:, 0], idx[:, 1], idx[:, 2]]
    assert np.median(at_centres) > np.median(w) + 5 * w.std() / 2
    world = points.data * np.asarray(points.scale)
    assert np.allclose(world[:, ::-1], truth.xyz, atol=1e-6)  # µm are right
    # the widget found the channels by role
    assert {r: c.currentText() for r, c in widget.role_combos.items()} == {
        r: f"NeuroPAL sample [{r}]" for r in "RGBW"
    }


def test_whole_flow(labelled_viewer, make_napari_viewer):
    viewer, widget = labelled_viewer
    n_layers = len(viewer.layers)

    # --- auto-label: one Points layer with the review features --------------------------------
    layer = widget.auto_label()
    assert widget.last_error is None and layer is not None
    assert len(viewer.layers) == n_layers + 1 and layer in viewer.layers
    f = layer.features
    for c in REVIEW_FEATURES:
        assert c in f.columns
    n = len(layer.data)
    assert 100 < n < 200 and set(f["status"]) == {"auto"}
    assert viewer.layers.selection.active is layer
    # detections sit on the truth nuclei
    from scipy.spatial import cKDTree

    from napari_fdlc.sample import load_sample

    _, truth = load_sample()
    found = layer.data * np.asarray(layer.scale)
    d, _ = cKDTree(truth.xyz[:, ::-1]).query(found)
    assert np.median(d) < 1.0
    # text shows the current ID
    assert list(layer.text.values) == list(f["label"])

    # --- threshold: hides automatic names below it, coverage live -------------------------------
    widget.set_threshold(0.0)
    named = int((f["auto_id"] != "").sum())
    assert int((layer.features["label"] != "").sum()) == named
    assert f"{named / n:.0%}" in widget.coverage_label.text()
    widget.set_threshold(1.0)
    assert (layer.features["label"] == "").all() and widget.coverage_label.text().startswith("0%")
    widget.threshold_slider.setValue(10)  # the slider drives the same thing
    assert widget.session.threshold == pytest.approx(0.10)
    shown = layer.features["auto_conf"].to_numpy() >= 0.10
    assert ((layer.features["label"] != "").to_numpy() == (shown & (layer.features["auto_id"] != "").to_numpy())).all()

    # --- review ---------------------------------------------------------------------------------
    a, b, c, d_ = _named_rows(layer, 4)
    widget.set_threshold(0.99)
    widget.accept(a)
    auto_a = layer.features["auto_id"][a]
    assert (layer.features["status"][a], layer.features["user_conf"][a], layer.features["label"][a]) == ("accepted", 1.0, auto_a)
    assert np.allclose(layer.border_color[a], [0.2, 1.0, 0.2, 1.0])  # green ring
    other = next(x for x in layer.features["cand_2"] if x and x not in set(layer.features["auto_id"]) | {auto_a})
    widget.assign(b, other)
    assert layer.features["status"][b] == "corrected" and layer.features["label"][b] == other
    cand2 = layer.features["cand_2"][c]
    if cand2 in set(layer.features["user_id"]):
        cand2 = None
    if cand2:
        widget.pick_candidate(c, 2)
        assert layer.features["user_id"][c] == cand2
    widget.mark_unsure(d_)
    assert layer.features["label"][d_].endswith("?") and layer.features["user_conf"][d_] == 0.5
    assert layer.features["status"][d_] == "unsure"
    widget.clear(d_)
    assert layer.features["status"][d_] == "auto" and np.isnan(layer.features["user_conf"][d_])
    taken = set(layer.features["user_id"]) - {""}
    e = next(
        int(j) for j in widget.session.review_order()[::-1]
        if layer.features["status"][j] == "auto" and layer.features["auto_id"][j]
        and not {layer.features["auto_id"][j], layer.features["cand_1"][j]} & taken
    )
    with pytest.raises(FdlcError, match="already the name"):  # scripts get the error, the GUI a notification
        widget.assign(e, auto_a)

    # selecting a point shows its candidates with probabilities
    layer.selected_data = {e}
    assert widget.current == e
    items = [widget.candidate_combo.itemText(k) for k in range(widget.candidate_combo.count())]
    assert len(items) == 3 and items[0].startswith(f"1. {layer.features['cand_1'][e]}")
    assert f"({np.floor(layer.features['prob_1'][e] * 100 + 1e-9) / 100:.2f})" in items[0]  # rounded down
    assert widget._completer.model().rowCount() > 50  # completion over known neuron names
    widget.candidate_combo.activated.emit(0)  # choosing in the dropdown gives the candidate
    assert layer.features["user_id"][e] == layer.features["cand_1"][e] and widget.last_error is None

    # --- keys (bound on the layer: they win over the Points layer's own 1/2/3/A) -----------------
    widget.undo()
    assert layer.features["status"][e] == "auto"
    layer.selected_data = {e}
    _press(viewer, "A")
    assert layer.features["status"][e] == "accepted"
    _press(viewer, "Control-Z")
    assert layer.features["status"][e] == "auto"
    _press(viewer, "U")
    assert layer.features["status"][e] == "unsure"
    _press(viewer, "1")
    assert len(layer.data) == n  # '1' no longer deletes the point
    _press(viewer, "Control-Z")
    _press(viewer, "Control-Z")
    _press(viewer, "Control-Shift-Z")
    assert layer.features["status"][e] == "unsure"
    _press(viewer, "C")
    assert layer.features["status"][e] == "auto"

    # --- undo / redo of every edit --------------------------------------------------------------
    before = widget.session.history()
    statuses = list(layer.features["status"])
    widget.mark_unsure(e)
    assert widget.undo() == f"mark neuron {e} unsure ({widget.session.auto_id[e]}?)"
    assert list(layer.features["status"]) == statuses
    widget.redo()
    assert layer.features["status"][e] == "unsure"
    widget.undo()
    assert widget.session.history() == before

    # --- navigation: lowest confidence first, view centred -----------------------------------------
    order = widget.session.review_order()
    assert widget.next_neuron() == order[(order.index(e) + 1) % len(order)]
    i = widget.current
    world = layer.data[i] * np.asarray(layer.scale)
    assert viewer.dims.point[0] == pytest.approx(world[0], abs=layer.scale[0])
    from napari_fdlc._napari._widget import camera

    assert np.allclose(camera(viewer).center[-2:], world[-2:])
    assert layer.selected_data == {i}
    assert widget.previous_neuron() == e
    _press(viewer, "N")
    assert widget.current == i
    _press(viewer, "Shift-N")
    assert widget.current == e
    widget._on_table_clicked(0, 0)  # the list, lowest confidence first
    assert widget.current == order[0]

    # --- re-label: user decisions fixed, never overwritten ----------------------------------------
    user_before = layer.features[["user_id", "user_conf", "status"]].copy()
    assert widget.relabel() is layer and widget.last_error is None
    assert widget.session.history()[-1] == "re-label"
    pd.testing.assert_frame_equal(layer.features[["user_id", "user_conf", "status"]], user_before)
    users = set(user_before["user_id"]) - {""}
    autos = layer.features.loc[layer.features["status"] == "auto", "auto_id"]
    assert not users & set(autos)

    # --- autosave: every edit is already on disk ------------------------------------------------------
    path = widget.session.path
    assert path == session_file_for(widget.session.image) and path.is_file()
    from napari_fdlc.sample import sample_paths

    if "napari_fdlc" in str(sample_paths()[0]):  # the bundled sample: the user's data folder
        assert path.parent == user_session_dir()
    saved = json.loads(path.read_text())
    assert saved["neurons"]["status"] == list(layer.features["status"])

    # --- export -----------------------------------------------------------------------------------------
    out = widget.export(path.parent.parent / "ids.csv")
    df = pd.read_csv(out, keep_default_na=False)
    feats = layer.features
    for c in ["x_um", "y_um", "z_um", "label", "x_px", "y_px", "z_px", "R", "G", "B", "W"] + REVIEW_FEATURES:
        assert c in df.columns
    final = [
        u + ("?" if s == "unsure" else "") if s != "auto" else (aid if (aid and conf >= 0.99 and aid not in users) else "")
        for u, s, aid, conf in zip(feats["user_id"], feats["status"], feats["auto_id"], feats["auto_conf"])
    ]
    assert list(df["label"]) == final
    assert np.allclose(df[["z_px", "y_px", "x_px"]].to_numpy(float), layer.data, atol=1e-3)
    assert list(df["status"]) == list(feats["status"])
    with pytest.raises(FdlcError, match="already exists"):
        widget.export(out)
    widget.export(out, overwrite=True)
    npid = widget.export(path.parent.parent / "ids_npid.csv", format="neuropal_id")
    nd = pd.read_csv(npid, skiprows=6, keep_default_na=False)
    assert np.allclose(nd["Internal X (px)"].astype(float), layer.data[:, 2] + 1, atol=1e-2)
    assert list(nd["User ID"]) == list(feats["user_id"])
    assert len(read_table(npid)) == n

    # --- reopen: the session comes back (napari killed now would lose nothing) ----------------------
    expected = layer.features[["user_id", "status", "auto_id"]].copy()
    viewer.close()
    viewer2 = make_napari_viewer()
    viewer2.open_sample("napari-fdlc", "neuropal")
    restored = [lyr for lyr in viewer2.layers if lyr.name.endswith("neuron IDs")]
    assert len(restored) == 1
    pd.testing.assert_frame_equal(restored[0].features[["user_id", "status", "auto_id"]], expected)
    _, widget2 = viewer2.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    assert widget2.layer is restored[0] and widget2.session.path == path
    assert widget2.threshold == pytest.approx(0.99)
    widget2.accept(a)  # already accepted: nothing changes
    widget2.clear(a)
    assert json.loads(path.read_text())["neurons"]["status"][a] == "auto"
    assert find_session(widget2.session.image) == path


def test_the_model_warms_up_while_the_user_picks_channels(make_napari_viewer, sample_files, templates):
    # The first Auto-label would otherwise pay torch's import, the weights' load and the model's
    # traces (~1.5 s on two cores): the widget does that in a thread as soon as it is shown.
    from qtpy.QtWidgets import QApplication

    from napari_fdlc._napari._widget import AutoLabelWidget
    from napari_fdlc.identify import Identifier
    from napari_fdlc.model import CorrespondenceModel

    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    widget = AutoLabelWidget(viewer)
    identifier = Identifier(CorrespondenceModel({"layers": 1, "dim": 32}), device="cpu")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget._warming is None  # it starts once the event loop runs
    QApplication.processEvents()
    assert widget._warming is not None
    widget._warming.join(timeout=60)
    assert not widget._warming.is_alive()
    warmed = set(identifier._traced)
    assert warmed, "the warm-up ran no model pass"
    assert widget.auto_label() is not None
    assert set(identifier._traced) == warmed, "the first Auto-label traced the model again"




VOX = (1.0, 0.4, 0.4)


def _blobs(seed=0, shape=(12, 48, 64), n=8, extra=()):
    """Four channels of ``n`` Gaussian nuclei (sigma 0.9 µm) on noise; centres z, y, x in µm."""
    rng = np.random.default_rng(seed)
    z, y, x = (a * v for a, v in zip(np.indices(shape).astype(float), VOX))
    ext = np.array(shape) * VOX
    centres = [np.asarray(c, float) for c in extra]
    while len(centres) < n + len(extra):
        c = rng.uniform([3, 3, 3], ext - 3)
        if all(np.linalg.norm(c - d) > 5 for d in centres):
            centres.append(c)
    centres = np.array(centres)
    chans = []
    for _ in range(4):
        img = rng.normal(100, 3, shape)
        for c in centres:
            img += rng.uniform(300, 900) * np.exp(-((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2) / (2 * 0.9 ** 2))
        chans.append(img.astype(np.float32))
    return chans, centres


def _tiny_viewer(make_napari_viewer, identifier, templates, chans=None, **layer_kwargs):
    """napari with a tiny 4-channel stack added by a script (R/G/B/W named) and the widget docked."""
    chans = chans if chans is not None else _blobs()[0]
    viewer = make_napari_viewer()
    for role, data in zip("RGBW", chans):
        viewer.add_image(data, name=f"tiny [{role}]", scale=VOX, **layer_kwargs)
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return viewer, widget


def _notifications_since(before):
    from napari.utils.notifications import notification_manager

    return [str(r.message) for r in notification_manager.records[before:]]


def _n_records():
    from napari.utils.notifications import notification_manager

    return len(notification_manager.records)


@pytest.mark.parametrize("how", ["rotate", "affine"])
def test_an_image_rotated_in_the_viewer_does_not_get_neurons_off_its_nuclei(make_napari_viewer, identifier, templates, how):
    """docs/gui.md: the channels must 'sit where the file put them', as neurons are placed and their
    colours read in the image's own voxels; a translated image is refused with a message. A user
    who rotates the image layers to see the worm straight (layer.rotate, or an affine) should get
    the same: either a message, or neuron-ID points that land on the nuclei shown. Instead
    Auto-label runs, and the neuron-ID layer (no transform) sits away from the rotated image."""
    chans, centres = _blobs()
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates, chans)
    for layer in list(viewer.layers):
        if how == "rotate":
            layer.rotate = 90
        else:
            layer.affine = [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
    result = widget.auto_label()
    if result is None:  # refused: it must say why
        assert widget.last_error and "unexpected" not in widget.last_error, widget.last_error
        return
    image = viewer.layers["tiny [W]"]
    nuclei_world = np.array([image.data_to_world(c / np.asarray(VOX)) for c in centres])
    points_world = np.array([result.data_to_world(p) for p in np.asarray(result.data)])
    gap = np.linalg.norm(points_world[:, None] - nuclei_world[None], axis=2).min(axis=1)
    assert np.median(gap) < 1.5, f"neuron-ID points lie a median {np.median(gap):.1f} µm off the nuclei shown"


def test_a_multiscale_image_layer_gets_a_message_not_an_unexpected_error(make_napari_viewer, identifier, templates):
    """An image layer added by a script (or another plugin's reader) as a pyramid
    (``add_image([full, half], multiscale=True)``, common for big stacks) chosen as W: expected
    Auto-label to detect on its full-resolution level, or to refuse it in one message. Instead
    the worker crashes: 'unexpected error (TypeError: list indices must be integers or slices,
    not tuple)' (stack_from_layers indexes ``layer.data``, a list of levels)."""
    chans, _ = _blobs()
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates, chans)
    viewer.add_image([chans[3], chans[3][:, ::2, ::2]], multiscale=True, name="pyramid", scale=VOX)
    widget.set_channels(R=None, G=None, B=None, W="pyramid")
    widget.auto_label()
    assert widget.last_error is None or "unexpected error" not in widget.last_error, widget.last_error


def test_detecting_without_a_w_channel_says_so_in_napari(make_napari_viewer, identifier, templates):
    """W set to (none), the colour channels chosen: detection runs on the sum of the channels and
    the core warns 'no W (TagRFP-T) channel marked; detecting on the sum of channels' (fdlc
    segment shows it). In napari that line goes to stderr only (the worker has no
    ``warnings_to``): the user, who does not see stderr, is never told what nuclei were found on."""
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates)
    widget.set_channels(W=None)
    before = _n_records()
    assert widget.auto_label() is not None, widget.last_error
    messages = _notifications_since(before)
    assert any("W" in m and "sum of" in m for m in messages), messages


def test_neurons_that_lie_outside_the_chosen_image_are_not_coloured_from_its_edge_silently(
        make_napari_viewer, identifier, templates):
    """docs/gui.md: with a Points layer as Neurons, 'colours are read from the image when the
    layer has none'. A Points layer that does not lie on the chosen image at all (another
    worm's table, or the wrong channels chosen: here every point is beyond the stack) should be
    refused or get a warning. Instead measure_colours clips every position to the stack's edge
    (segment._sample) and the neurons are named with colours read from the border voxels, and
    napari says nothing."""
    chans, centres = _blobs()
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates, chans)
    extent = np.array(chans[0].shape) * VOX
    viewer.add_points(centres + [0.0, 0.0, 2 * extent[2]], name="another worm")  # µm, beyond x
    widget.set_neurons("another worm")
    before = _n_records()
    result = widget.auto_label()
    messages = _notifications_since(before)
    assert result is None or messages, "named with colours from the image's edge; no message"


def test_a_template_layer_with_a_repeated_name_says_so_in_napari(make_napari_viewer, identifier, templates):
    """A Points layer with names as the template (docs/gui.md): a name on two rows is read as
    unnamed on both (table_from_layer -> _drop_duplicate_names), which warns on stderr only.
    The same for a template *file* reaches napari (add_template_file wraps warnings_to); the
    layer's does not, so the user loses that name from the template without a word."""
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates)
    t = templates[0]
    labels = np.array(t.labels, dtype=object).copy()
    named = np.flatnonzero(labels != "")
    labels[named[1]] = labels[named[0]]
    viewer.add_points(t.xyz[:, ::-1], name="labelled worm", features={"label": labels})
    widget.set_template("labelled worm")
    before = _n_records()
    assert widget.auto_label() is not None, widget.last_error
    messages = _notifications_since(before)
    assert any(labels[named[0]] in m for m in messages), messages


@pytest.mark.parametrize("dialog", ["cancelled", "unreadable file"])
def test_leaving_the_labelled_table_file_dialog_keeps_the_template_chosen_before(make_napari_viewer, templates, tmp_path,
                                                                                 monkeypatch, dialog):
    """The user has a labelled worm chosen as the template, opens *Names from*, picks
    'Labelled table file…' and cancels the file dialog (or picks a file that cannot be read).
    Expected: the template chosen before stays chosen. Instead the choice falls back to the
    built-in panel / script templates on cancel (_refresh_choices' fallback from
    FROM_FILE), or stays on the 'Labelled table file…' entry after the error, which
    _templates() silently runs as the built-in panel: Auto-label then names the worm from
    another template than the one the user had chosen."""
    from napari_fdlc._napari import _widget as widget_module
    from napari_fdlc._napari._widget import FROM_FILE
    from napari_fdlc.table import write_table

    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    write_table(templates[0], tmp_path / "my_worm.csv")
    chosen = widget.add_template_file(tmp_path / "my_worm.csv")
    assert widget.template_combo.currentText() == chosen
    bad = tmp_path / "not_a_table.csv"
    bad.write_text("a,b\n1,2\n")
    answer = "" if dialog == "cancelled" else str(bad)
    monkeypatch.setattr(widget_module.QFileDialog, "getOpenFileName", staticmethod(lambda *a, **k: (answer, "")))
    index = widget.template_combo.findText(FROM_FILE)
    widget.template_combo.setCurrentIndex(index)  # what a click on the entry does before 'activated'
    widget._on_template_activated(index)
    assert widget.template_combo.currentText() == chosen, widget.template_combo.currentText()


def test_two_template_files_of_the_same_name_are_both_offered(make_napari_viewer, templates, tmp_path):
    """Labelled worms of two rigs kept as rig1/worm1.csv and rig2/worm1.csv, both added with
    'Labelled table file…'. Expected: two entries, each naming from its own file. Instead the
    entries are keyed by the file name only ('file: worm1.csv'): the second silently replaces
    the first, which is no longer offered, and the session's settings record a template that
    could be either."""
    from napari_fdlc.table import NeuronTable, write_table

    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    t = templates[0]
    (tmp_path / "rig1").mkdir()
    (tmp_path / "rig2").mkdir()
    write_table(t, tmp_path / "rig1" / "worm1.csv")
    write_table(NeuronTable(t.xyz * [1, 1, -1], t.colours, t.labels), tmp_path / "rig2" / "worm1.csv")
    first = widget.add_template_file(tmp_path / "rig1" / "worm1.csv")
    second = widget.add_template_file(tmp_path / "rig2" / "worm1.csv")
    entries = [widget.template_combo.itemText(i) for i in range(widget.template_combo.count())]
    assert first != second and first in entries and second in entries, entries


def test_a_run_refused_at_the_start_does_not_show_a_full_progress_bar(make_napari_viewer, identifier, templates):
    """An error inside the job leaves the progress bar at 0 % with the message (_set_running).
    An Auto-label refused before the job starts (here: every channel set to (none)) after an
    earlier successful run writes its message onto the bar but leaves it at 100 %: a full bar
    reading 'no image chosen to detect nuclei in…', as if something had completed."""
    viewer, widget = _tiny_viewer(make_napari_viewer, identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    widget.set_channels(R=None, G=None, B=None, W=None)
    widget.run_button.click()
    assert widget.last_error and "no image" in widget.last_error, widget.last_error
    assert widget.progress_bar.value() == 0, (widget.progress_bar.value(), widget.progress_bar.format())


@pytest.fixture(scope="module")
def moving_recording(tmp_path_factory):
    """A small 3-frame OME-TIFF recording (T, C, Z, Y, X) whose worm moves 5 µm along x per frame
    (frame t is frame 0 shifted by 10·t voxels of 0.5 µm), with the rendered worm of frame 0."""
    from napari_fdlc.io.images import StackSeries, write_tiff
    from napari_fdlc.render import random_worm, render_recording
    from napari_fdlc.track import SequenceParams, simulate_sequence

    worm = random_worm(30, size_um=(36, 14, 10), min_spacing_um=2.8, seed=5)
    still = SequenceParams(frames=1, bend_curvature=0.0, roll=0.0, xy_rotation=0.0, drift_um=0.0,
                           drop_fraction=(0.0, 0.0), max_spurious=0, jitter_um=0.0)
    volumes, origins = simulate_sequence(worm, 1, still)
    series, _ = render_recording(volumes, origins, voxel_size_zyx=(1.5, 0.5, 0.5), gut=False, seed=2)
    first = np.asarray(series.data[0])
    data = np.stack([np.roll(first, 10 * t, axis=-1) for t in range(3)])
    path = tmp_path_factory.mktemp("rec4d") / "moving.ome.tif"
    write_tiff(path, StackSeries(data, series.voxel_size_zyx, series.channel_roles, source=str(path),
                                 channel_names=series.channel_names))
    return path


def _labelled(make_napari_viewer, path, identifier, templates, neurons=None):
    viewer = make_napari_viewer()
    viewer.open(str(path), plugin="napari-fdlc")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return viewer, widget


def _on_nuclei(viewer, world_zyx: np.ndarray, t: int) -> np.ndarray:
    """Whether each world position (z, y, x µm) lies on a bright nucleus of frame ``t``'s W."""
    w = next(layer for layer in viewer.layers if layer.name.endswith("[W]"))
    volume = np.asarray(w.data[t], dtype=float)
    vox = np.round(world_zyx / np.asarray(w.scale[1:], dtype=float)).astype(int)
    vox = np.clip(vox, 0, np.asarray(volume.shape) - 1)
    return volume[tuple(vox.T)] > np.percentile(volume, 90)


def test_a_recordings_neuron_ids_are_drawn_at_the_time_point_they_name(make_napari_viewer, moving_recording,
                                                                         identifier, templates):
    """Auto-label on a recording names its first time point, and its neuron-ID layer has a time
    axis: napari draws the names at that time point only (they were drawn over every frame, on
    a worm that moved away), N brings the time slider back to it, and a neuron added at
    another time point is refused in one line, the session unchanged."""
    viewer, widget = _labelled(make_napari_viewer, moving_recording, identifier, templates)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    image = next(lay for lay in viewer.layers if lay.name.endswith("[W]"))
    assert layer.ndim == 4 and np.all(np.asarray(layer.data)[:, 0] == 0)
    assert layer.scale[0] == image.scale[0] and layer.translate[0] == image.translate[0]
    np.testing.assert_allclose(widget.session.table.xyz[:, ::-1],
                               np.asarray(layer.data)[:, 1:] * np.asarray(layer.scale[1:]))
    viewer.dims.set_point(0, 2)
    assert len(layer._view_indices) == 0  # none drawn at frame 2
    widget.next_neuron()
    assert viewer.dims.point[0] == 0 and len(layer._view_indices) > 0
    viewer.dims.set_point(0, 2)
    n = len(widget.session)
    layer.add(np.r_[2.0, layer.data[0][1:] + 3])
    assert widget.last_error and "first time point" in widget.last_error, widget.last_error
    assert len(layer.data) == len(widget.session) == n
    layer.add(np.r_[0.0, layer.data[0][1:] + 3])  # at the named time point: a neuron added
    assert len(layer.data) == len(widget.session) == n + 1


def test_points_of_another_time_point_are_refused_by_auto_label(make_napari_viewer, moving_recording,
                                                                            identifier, templates):
    """Auto-label with a Points layer of one time point of a recording (points clicked on frame 2:
    t, z, y, x, every t = 2) as Neurons: refused in one line (Auto-label names the first time
    point). table_from_layer dropped the t coordinate and stack_from_layers gave the
    recording's first volume: every colour was read in frame 0, where the worm is 10 µm away,
    silently, and frame 0's decisions carried onto these neurons by position."""
    from napari_fdlc.errors import FdlcError
    from napari_fdlc.io.images import read_series
    from napari_fdlc.segment import segment_stack

    series = read_series(str(moving_recording))
    frame2 = series.volume(2)
    found = segment_stack(frame2, diameter_um=3.0)
    viewer, widget = _labelled(make_napari_viewer, moving_recording, identifier, templates)
    zyx = found.xyz[:, ::-1] / np.asarray(series.voxel_size_zyx)
    viewer.add_points(np.column_stack([np.full(len(zyx), 2.0), zyx]), scale=viewer.layers[0].scale,
                      name="clicked at t=2")
    widget.set_neurons("clicked at t=2")
    with pytest.raises(FdlcError, match="first time point"):
        widget.auto_label()


def _images(viewer):
    from napari_fdlc._napari._layers import is_image_layer

    return [layer for layer in viewer.layers if is_image_layer(layer)]


def test_auto_label_again_after_the_time_axis_moved_moves_the_reused_layer(make_napari_viewer, moving_recording,
                                                                           identifier, templates, tmp_path):
    """Auto-label on a recording, then the recording's time axis is shifted (its layers'
    translate in t set to 10: the recording starts at t = 10) and Auto-label is run again: the
    session stores time_axis [1, 10] and the reused neuron-ID layer should lie at t = 10, the
    recording's first time point. Instead _refresh_layer updates the layer's scale but never its
    translate: the names stay at t = 0, where there is no frame of the recording."""
    path = tmp_path / "moving.ome.tif"
    shutil.copy(moving_recording, path)
    viewer, widget = _labelled(make_napari_viewer, path, identifier, templates)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    for image in _images(viewer):
        image.translate = (10.0, 0.0, 0.0, 0.0)
    again = widget.auto_label()
    assert again is layer, "the image's neuron-ID layer is reused"
    assert list(widget.session.settings["time_axis"]) == [1.0, 10.0]
    assert float(layer.translate[0]) == 10.0, f"neuron-ID layer left at t = {layer.translate[0]:g}"


def test_reopening_restores_the_names_on_the_recordings_own_first_time_point(make_napari_viewer, moving_recording,
                                                                              identifier, templates, tmp_path):
    """A recording whose layers were shifted in time in napari (translate t = 2) is Auto-labelled
    (the session keeps time_axis [1, 2]); reopening the file gives the recording's own time
    axis (translate 0). The restored neuron-ID layer should lie on the recording's first time
    point, t = 0 (Auto-label named frame 0). Instead restored_session_layer takes the saved
    time_axis: the names are drawn on frame 2, where the worm has moved 10 µm away."""
    path = tmp_path / "moving.ome.tif"
    shutil.copy(moving_recording, path)
    viewer, widget = _labelled(make_napari_viewer, path, identifier, templates)
    for image in _images(viewer):
        image.translate = (2.0, 0.0, 0.0, 0.0)
    assert widget.auto_label() is not None, widget.last_error
    assert list(widget.session.settings["time_axis"]) == [1.0, 2.0]

    again = make_napari_viewer()
    again.open(str(path), plugin="napari-fdlc")
    image = _images(again)[0]
    restored = next(layer for layer in again.layers if layer.name.endswith("neuron IDs"))
    assert restored.ndim == 4
    assert float(restored.translate[0]) == float(image.translate[0]), (
        f"names drawn at t = {restored.translate[0]:g}; the recording's first time point is t = {image.translate[0]:g}")


def test_a_session_saved_before_names_had_a_time_axis_reopens_on_its_time_point(make_napari_viewer, moving_recording,
                                                                                 identifier, templates, tmp_path):
    """docs/gui.md 1: a recording's neuron-ID layer has the recording's time axis, so napari
    draws the names at the named time point only; reopening the image restores it. A session
    of a recording saved before today has no settings['time_axis']: reopened, its layer should
    still have the time axis (the reader knows the file is a recording). Instead it comes back
    3D and the names of frame 0 are drawn over every frame, on a worm that moved away."""
    path = tmp_path / "moving.ome.tif"
    shutil.copy(moving_recording, path)
    viewer, widget = _labelled(make_napari_viewer, path, identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    saved = widget.session.path
    d = json.loads(saved.read_text())
    del d["settings"]["time_axis"]  # as written before the layer had a time axis
    saved.write_text(json.dumps(d))

    again = make_napari_viewer()
    again.open(str(path), plugin="napari-fdlc")
    restored = next(layer for layer in again.layers if layer.name.endswith("neuron IDs"))
    again.dims.set_point(0, 2)
    assert restored.ndim == 4 and len(restored._view_indices) == 0, (
        f"restored {restored.ndim}D: frame 0's names drawn on frame 2 too")


def test_edits_made_with_the_dock_closed_are_kept_beside_a_point_at_another_time(make_napari_viewer, moving_recording,
                                                                                identifier, templates, tmp_path):
    """docs/gui.md 4: edits made while no widget follows the layer are taken up when it is
    reviewed again. With the dock closed, a neuron is deleted at the named time point (t = 0)
    and another point added on frame 2. Docked again, the deletion should be kept and the point
    on frame 2 refused (as when the dock is open: 'names the recording's first time point').
    Instead _catch_up hands the whole layer to layer_xyz_um, which refuses it ('holds points of
    several time points'): the deletion is thrown away with the stray point."""
    path = tmp_path / "moving.ome.tif"
    shutil.copy(moving_recording, path)
    viewer, widget = _labelled(make_napari_viewer, path, identifier, templates)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    n = len(widget.session)
    viewer.window.remove_dock_widget("all")
    layer.selected_data = {0}
    layer.remove_selected()
    assert len(layer.data) == n - 1
    layer.add(np.r_[2.0, np.asarray(layer.data[0])[1:] + 3])
    _, widget2 = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    assert widget2.layer is layer
    assert len(widget2.session) == n - 1, (
        f"the deletion made with the dock closed was lost ({len(widget2.session)} neurons; last error: "
        f"{widget2.last_error})")


def test_a_recordings_neuron_id_layer_as_neurons_without_an_image_keeps_its_time_axis(
        make_napari_viewer, moving_recording, identifier, templates, tmp_path):
    """Two worms in one viewer (docs/gui.md 4): the recording A is Auto-labelled, then worm B.
    A's neuron-ID layer is then chosen as Neurons with no channel chosen (names from positions
    and the colours it holds) and Auto-label is run: A's layer should be reused and keep its
    time axis. Instead the new session has no settings['time_axis'] (no recording among the
    channels), review_coordinates gives 3D points for the reused 4D layer and napari raises
    'Points dimensions must be equal to ndim': an 'unexpected error … please report it', the
    layer left showing the old points while the session (autosaved without its time axis)
    has the new ones."""
    from napari_fdlc._napari._layers import stack_layers
    from napari_fdlc.sample import load_sample

    path = tmp_path / "moving.ome.tif"
    shutil.copy(moving_recording, path)
    viewer, widget = _labelled(make_napari_viewer, path, identifier, templates)
    layer_a = widget.auto_label()
    assert layer_a is not None, widget.last_error
    stack, _ = load_sample()
    for data, kwargs, _ in stack_layers(stack, name="worm B", source_key=str(tmp_path / "worm B.ome.tif")):
        viewer.add_image(data, **kwargs)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    layer_b = widget.auto_label()
    assert layer_b is not None and layer_b is not layer_a, widget.last_error
    widget.set_channels(**{r: None for r in "RGBW"})
    widget.set_neurons(layer_a.name)
    got = widget.auto_label()
    assert got is layer_a and widget.last_error is None, widget.last_error
    assert layer_a.ndim == 4 and "time_axis" in widget.session.settings
