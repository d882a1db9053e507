"""The Track widget: a table sequence in, a Tracks layer and labelled Points at the current time out."""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
import pytest

from napari.utils.notifications import notification_manager

from napari_fdlc.table import NeuronTable, write_table


@pytest.fixture
def sequence_csv(tmp_path):
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import SequenceParams, join_by_time, simulate_sequence

    worm = generate_worm(seed=4)
    params = SequenceParams(frames=5, bend_curvature=0.002, roll=0.05, xy_rotation=0.2, drift_um=3.0,
                            drop_fraction=(0.0, 0.05), max_spurious=2, jitter_um=0.2)
    volumes, origins = simulate_sequence(worm, 0, params)
    path = tmp_path / "recording.csv"
    # time values need not be 0..T-1
    write_table(join_by_time(volumes, [10 * t for t in range(len(volumes))]).drop(columns=["label"]), path)
    # a labelled reference: the first volume with the names of its source neurons
    first = volumes[0]
    labels = np.array([worm.labels[o] if o >= 0 else "" for o in origins[0]], dtype=object)
    ref = tmp_path / "reference.csv"
    write_table(type(first)(first.xyz, first.colours, labels), ref)
    return path, ref, volumes


@pytest.fixture
def track_widget(make_napari_viewer, identifier):
    from napari_fdlc._napari.tracks import TrackWidget

    viewer = make_napari_viewer()
    widget = TrackWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Track")
    widget.identifier = identifier
    return viewer, widget


def test_tracks_and_labelled_points_at_the_current_time(track_widget, sequence_csv):
    viewer, widget = track_widget
    path, ref, volumes = sequence_csv
    widget.set_sequence(path)
    widget.set_reference(ref)
    layers = widget.run()
    assert widget.last_error is None, widget.last_error
    tracks, points = layers
    assert type(tracks).__name__ == "Tracks" and type(points).__name__ == "Points"
    assert tracks in viewer.layers and points in viewer.layers
    # Tracks: [track_id, t, z, y, x]; one row per tracked neuron per time point
    assert tracks.data.shape[1] == 5
    # whole-number t are frame numbers: each volume is shown at its own t
    assert set(np.unique(tracks.data[:, 1]).astype(int)) == {10 * t for t in range(len(volumes))}
    # every neuron of every time point is a point; positions are the input's, z y x
    assert len(points.data) == sum(len(v) for v in volumes)
    assert np.allclose(points.data[: len(volumes[0]), 1:], volumes[0].xyz[:, ::-1])
    feats = points.features
    assert {"t", "track_id", "track_conf", "name"} <= set(feats.columns)
    assert sorted(feats["t"].unique()) == [0, 10, 20, 30, 40]
    # the labelled reference names the tracks; the reference volume is itself named right
    first = feats[feats["t"] == 0]
    ref_labels = pd.read_csv(ref, keep_default_na=False)["label"].to_numpy()
    assert (first["name"].to_numpy() == ref_labels).mean() >= 0.95
    assert (first["name"] != "").sum() > 50
    # only the current time point is shown (the whole volume: 3D display), and moving the time
    # slider changes it
    assert viewer.dims.ndisplay == 3
    viewer.dims.set_current_step(0, 0)
    shown = np.asarray(points._view_indices, dtype=int)
    assert len(shown) == len(volumes[0])
    viewer.dims.set_current_step(0, 30)
    shown = np.asarray(points._view_indices, dtype=int)
    assert len(shown) == len(volumes[3]) and (points.data[shown, 0] == 30).all()
    assert widget.progress_bar.value() == 100
    assert "5 time points" in widget.status.text()


def test_running_again_replaces_the_layers(track_widget, sequence_csv):
    viewer, widget = track_widget
    path, _, _ = sequence_csv
    widget.set_sequence(path)
    widget.run()
    widget.run()
    assert widget.last_error is None
    assert [layer.name for layer in viewer.layers] == ["recording tracks", "recording neurons"]
    assert "name" in widget.layers[1].features  # unnamed reference: empty names, ID as text
    assert (widget.layers[1].features["name"] == "").all()


def test_bad_sequence_is_one_line_and_adds_nothing(track_widget, tmp_path, worm):
    viewer, widget = track_widget
    path = tmp_path / "no_time.csv"
    write_table(worm, path)
    widget.set_sequence(path)
    assert widget.run() is None
    assert "no 't' column" in widget.last_error and "\n" not in widget.last_error
    assert len(viewer.layers) == 0
    assert widget.run_button.isEnabled()


def test_the_models_warm_up_while_the_user_picks_the_files(make_napari_viewer, identifier):
    from qtpy.QtWidgets import QApplication

    from napari_fdlc._napari.tracks import TrackWidget
    from napari_fdlc.identify import default_tracker

    widget = TrackWidget(make_napari_viewer())
    widget.identifier = identifier
    assert widget._warming is None  # it starts once the event loop runs
    QApplication.processEvents()
    widget._warming.join(timeout=60)
    assert not widget._warming.is_alive()
    assert identifier._traced and default_tracker()._traced  # both models ran before the first job


def test_a_recording_in_the_viewer_is_segmented_then_tracked(track_widget, recording):
    """A stack file with a time axis opens as t, z, y, x layers; the widget segments every time
    point in its worker and tracks the detections, and the layers overlay the image."""
    from scipy.spatial import cKDTree

    from napari_fdlc._napari._io import read_stack_layers

    viewer, widget = track_widget
    path, truths, origins = recording
    for data, kwargs, kind in read_stack_layers(str(path)):
        getattr(viewer, f"add_{kind}")(data, **kwargs)
    image = viewer.layers[0]
    assert image.data.ndim == 4 and image.scale[0] == 1 and len(viewer.layers) == 4
    assert widget.source_combo.currentText() == "recording: recording"  # offered first
    widget.set_recording(str(path))  # by its file (or its name)
    tracks, points = widget.run()
    assert widget.last_error is None, widget.last_error
    assert "3 time points" in widget.status.text()
    # one time point of the image per volume; points in µm overlay the image's µm
    t = points.data[:, 0]
    assert set(np.unique(t)) == {0, 1, 2}
    for k, truth in enumerate(truths):
        zyx = points.data[t == k, 1:]
        distance, _ = cKDTree(truth.xyz[:, ::-1]).query(zyx)
        assert np.median(distance) < 0.5
    assert (points.features["track_id"] >= 0).mean() >= 0.9
    # a table sequence file is still a choice, and choosing one switches to it
    assert widget.source_combo.findText("the sequence file below") >= 0


def test_no_recording_and_no_sequence_is_one_line(track_widget):
    viewer, widget = track_widget
    assert widget.source_combo.currentText() == "the sequence file below"
    assert widget.run() is None
    assert "choose a recording or a sequence" in widget.last_error and "\n" not in widget.last_error
    with pytest.raises(Exception, match="no recording"):
        widget.set_recording("nothing.tif")


def test_wait_returns_when_the_job_ended_before_it_was_called(track_widget):
    # A job refused on its first line ends in the worker before wait() can listen for the
    # worker's own "finished" (it used to wait forever, hanging the GUI suite about one run in five).
    import time

    viewer, widget = track_widget
    widget.run(wait=False)
    time.sleep(0.5)  # the worker has failed and emitted "finished" by now
    start = time.perf_counter()
    assert widget.wait(timeout=30)
    assert time.perf_counter() - start < 10
    assert "choose a recording or a sequence" in widget.last_error


def test_track_widget_follows_a_renamed_recording(make_napari_viewer):
    """A recording opened by another reader (one t, z, y, x layer), renamed in the layer list:
    'Neurons from' offers it under its new name (it used to keep the old one, and Track said
    the recording was gone)."""
    viewer = make_napari_viewer()
    viewer.add_image(np.zeros((2, 4, 16, 16), dtype=np.float32), name="rec")
    _, track = viewer.window.add_plugin_dock_widget("napari-fdlc", "Track neurons")
    assert track.source_combo.currentText() == "recording: rec"
    viewer.layers["rec"].name = "worm 7"
    items = [track.source_combo.itemText(i) for i in range(track.source_combo.count())]
    assert "recording: worm 7" in items, items


def test_a_reference_of_several_time_points_is_refused(track_widget, sequence_csv):
    """A table of several time points given as the reference: one line, as `fdlc track
    --reference` gives (the widget used to take the whole recording as one reference volume)."""
    viewer, widget = track_widget
    path, _, _ = sequence_csv
    widget.set_sequence(path)
    widget.set_reference(path)
    assert widget.run() is None
    assert "time points" in widget.last_error and "\n" not in widget.last_error
    assert not any(type(layer).__name__ in ("Tracks", "Points") for layer in viewer.layers)


def test_table_volumes_lie_on_their_frames_and_other_times_in_order():
    """A CSV from fdlc segment leaves out time points without nuclei: its volumes are shown at
    their t, so they stay on the recording's frames; t in seconds is shown in order."""
    from napari_fdlc._napari.tracks import frames_of, track_layers
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import Sequence, TrackResult

    assert frames_of([0, 1, 3, 4]) == [0, 1, 3, 4]
    assert frames_of([0.0, 0.5, 1.0]) is None
    assert frames_of([1_700_000_000_000_000_000, 1_700_000_000_100_000_000]) is None  # ns timestamps
    assert frames_of([-2, -1]) is None
    worm = generate_worm(seed=1)
    sequence = Sequence([worm, worm], [0, 3], ["", ""])
    ids = np.arange(len(worm))
    result = TrackResult([ids, ids], [np.ones(len(worm))] * 2, [""] * len(worm), [{}, {}])
    tracks, points = track_layers(result, sequence, "s", frames_of(sequence.times))
    assert set(tracks[0][:, 1]) == {0, 3} and set(points[0][:, 0]) == {0, 3}


def test_a_track_reference_with_a_repeated_name_says_so_in_napari(track_widget, tmp_path):
    """A labelled reference whose name occurs twice: the worker's reader warning is shown in
    napari when the job ends."""
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import join_by_time

    viewer, widget = track_widget
    worm = generate_worm(seed=4)
    seq = tmp_path / "seq.csv"
    write_table(join_by_time([worm, worm]).drop(columns=["label"]), seq)
    labels = np.array(worm.labels, dtype=object).copy()
    named = np.flatnonzero(labels != "")
    labels[named[1]] = labels[named[0]]
    ref = tmp_path / "ref.csv"
    write_table(NeuronTable(worm.xyz, worm.colours, labels), ref)
    widget.set_sequence(seq)
    widget.set_reference(ref)
    before = len(notification_manager.records)
    assert widget.run() is not None, widget.last_error
    messages = _messages_since(before, 5.0, until=labels[named[0]])
    assert any(labels[named[0]] in m for m in messages), messages


def test_a_sequence_in_pixels_says_so_in_napari(track_widget, tmp_path):
    """Positions in pixels of 0.25 µm (four times too far apart): `fdlc track` warns that they
    cannot be µm; the Track widget tracked them without a word."""
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import join_by_time

    viewer, widget = track_widget
    worm = generate_worm(seed=4)
    pixels = NeuronTable(worm.xyz * 4.0, worm.colours, worm.labels)
    seq = tmp_path / "pixels.csv"
    write_table(join_by_time([pixels, pixels]).drop(columns=["label"]), seq)
    widget.set_sequence(seq)
    before = len(notification_manager.records)
    assert widget.run() is not None, widget.last_error
    messages = _messages_since(before, 5.0, until="must be micrometres")
    assert any("must be micrometres" in m for m in messages), messages


def test_tracking_another_sequence_keeps_the_first_ones_layers(make_napari_viewer, identifier, tmp_path):
    """Tracking worm B after worm A keeps A's layers (a run on the same input replaces its own);
    A's result used to be deleted."""
    from napari_fdlc._napari.tracks import TrackWidget
    from napari_fdlc.track import join_by_time

    viewer = make_napari_viewer()
    widget = TrackWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Track")
    widget.identifier = identifier
    for name, seed in (("wormA", 1), ("wormB", 2)):
        worm = _random_named_worm(40, seed)
        path = tmp_path / f"{name}.csv"
        write_table(join_by_time([worm, NeuronTable(worm.xyz + 0.2, worm.colours)]).drop(columns=["label"]), path)
        widget.set_sequence(path)
        assert widget.run() is not None, widget.last_error
    names = [layer.name for layer in viewer.layers]
    assert {"wormB tracks", "wormB neurons"} <= set(names)
    assert {"wormA tracks", "wormA neurons"} <= set(names), f"worm A's tracking result was deleted: {names}"



def _random_named_worm(n: int, seed: int) -> NeuronTable:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 6] + [60, 30, 15]
    return NeuronTable(xyz, {c: rng.gamma(2.0, 100.0, n) for c in "RGB"}, np.array([f"N{i}" for i in range(n)], dtype=object))


# Session 32 (a helper review of the Track widget); each says what used to happen.


def _moving_csv(path, worm, frames=3):
    from napari_fdlc.track import join_by_time

    volumes = [NeuronTable(worm.xyz + 0.2 * k, worm.colours) for k in range(frames)]
    write_table(join_by_time(volumes).drop(columns=["label"]), path)
    return path


def _open_recording(viewer, path, change=None):
    from napari_fdlc._napari._io import read_stack_layers

    for data, kwargs, kind in read_stack_layers(str(path)):
        getattr(viewer, f"add_{kind}")(change(np.array(data)) if change else data, **kwargs)


def _messages_since(before: int, wait: float = 2.0, until: str | None = None) -> list[str]:
    """napari's notifications since record ``before``, after ``wait`` seconds of Qt events (a
    warning reaches napari through the event loop), or as soon as one holds ``until``."""
    from qtpy.QtWidgets import QApplication

    deadline = time.monotonic() + wait
    while time.monotonic() < deadline and not (
            until and any(until in str(r.message) for r in notification_manager.records[before:])):
        QApplication.processEvents()
        time.sleep(0.01)
    return [str(r.message) for r in notification_manager.records[before:]]


def test_points_lie_on_the_image_frame_when_the_recording_has_a_time_scale(track_widget, recording):
    """Image layers with a time scale (4 Hz volumes shown in seconds): the results were at scale 1
    in t, so at the image's third frame the neurons of frames 0 and 1 showed."""
    viewer, widget = track_widget
    _open_recording(viewer, recording[0])
    for layer in list(viewer.layers):
        layer.scale = (0.25, *tuple(layer.scale)[1:])
    _, points = widget.run()
    assert widget.last_error is None, widget.last_error
    viewer.dims.set_point(0, float(viewer.layers[0].data_to_world([2, 0, 0, 0])[0]))
    shown = np.asarray(points._view_indices, dtype=int)
    assert len(shown) and (points.data[shown, 0] == 2).all(), sorted(set(points.data[shown, 0].tolist()))


def test_each_input_keeps_its_own_layers(track_widget, tmp_path):
    """A, then B, then A again: A's first layers stayed beside 'wormA tracks [1]'. And two files of
    one name in two folders: the second deleted the first's layers (inputs were told apart by
    the layer name)."""
    viewer, widget = track_widget
    a = _moving_csv(tmp_path / "wormA.csv", _random_named_worm(30, 1))
    b = _moving_csv(tmp_path / "wormB.csv", _random_named_worm(30, 2))
    for path in (a, b, a):
        widget.set_sequence(path)
        assert widget.run() is not None, widget.last_error
    assert sorted(layer.name for layer in viewer.layers) == ["wormA neurons", "wormA tracks", "wormB neurons", "wormB tracks"]
    (tmp_path / "day2").mkdir()
    widget.set_sequence(_moving_csv(tmp_path / "day2" / "wormA.csv", _random_named_worm(30, 3)))
    assert widget.run() is not None, widget.last_error
    assert len(viewer.layers) == 6, [layer.name for layer in viewer.layers]


def test_two_recordings_of_one_file_name_are_both_offered(track_widget, recording, tmp_path):
    """day1/worm.ome.tif and day2/worm.ome.tif open: one 'recording: worm' was offered (day 2's)."""
    import shutil

    viewer, widget = track_widget
    for day in ("day1", "day2"):
        (tmp_path / day).mkdir()
        shutil.copy(recording[0], tmp_path / day / "worm.ome.tif")
        _open_recording(viewer, tmp_path / day / "worm.ome.tif")
    keys = {widget.source_combo.itemData(i) for i in range(widget.source_combo.count())} - {None}
    assert len(keys) == 2, [widget.source_combo.itemText(i) for i in range(widget.source_combo.count())]


def test_a_sequence_path_typed_in_the_field_is_what_is_tracked(track_widget, recording, tmp_path):
    """With a recording open, a path typed into Sequence was ignored: the recording was tracked."""
    from qtpy.QtTest import QTest

    viewer, widget = track_widget
    _open_recording(viewer, recording[0])
    QTest.keyClicks(widget.sequence_edit, str(_moving_csv(tmp_path / "typed.csv", _random_named_worm(30, 1))))
    assert widget.run() is not None, widget.last_error
    assert "typed tracks" in [layer.name for layer in viewer.layers]


def test_a_reference_that_tracks_nothing_shows_the_neurons_and_says_so(track_widget, tmp_path):
    """A reference of 3 landmark neurons that tracked nothing: napari's add_tracks raised an
    IndexError on the empty tracks (a traceback, no layer, no message)."""
    viewer, widget = track_widget
    worm = _random_named_worm(30, 1)
    widget.set_sequence(_moving_csv(tmp_path / "seq.csv", worm))
    ref = tmp_path / "three.csv"
    write_table(NeuronTable(worm.xyz[:3], {c: v[:3] for c, v in worm.colours.items()},
                            np.array(["AVAL", "AVAR", "RIML"], dtype=object)), ref)
    widget.set_reference(ref)
    before = len(notification_manager.records)
    out = widget.run()
    assert widget.last_error is None, widget.last_error
    assert [type(layer).__name__ for layer in out] == ["Points"]  # nothing tracked with the test model
    assert any("no neuron could be tracked" in m for m in _messages_since(before))


def test_exported_track_points_keep_their_names(track_widget, tmp_path):
    """The Track widget's points saved with the plugin's writer: the names went into a `name`
    column the readers ignore, `label` empty; read back, every neuron was unnamed."""
    from napari_fdlc.track import read_sequence

    viewer, widget = track_widget
    worm = _random_named_worm(30, 1)
    widget.set_sequence(_moving_csv(tmp_path / "seq.csv", worm))
    write_table(worm, tmp_path / "ref.csv")
    widget.set_reference(tmp_path / "ref.csv")
    _, points = widget.run()
    names = list(points.features["name"])
    assert sum(bool(n) for n in names) > 20
    viewer.layers.selection = {points}
    viewer.layers.save(str(tmp_path / "exported.csv"), selected=True, plugin="napari-fdlc")
    again = read_sequence(str(tmp_path / "exported.csv"))
    assert [str(n) for v in again.volumes for n in v.label_strings()] == names


def test_a_time_point_without_nuclei_is_said_in_napari(track_widget, recording):
    """A blank volume in a recording was left out without a word (the CLI warns)."""
    def blank_second(data):
        data[1] = np.median(data[0])
        return data

    viewer, widget = track_widget
    _open_recording(viewer, recording[0], change=blank_second)
    before = len(notification_manager.records)
    _, points = widget.run()
    assert widget.last_error is None, widget.last_error
    assert set(np.unique(points.data[:, 0])) == {0, 2}
    assert any("no nuclei found at 1 time point" in m for m in _messages_since(before))


def test_a_refused_second_run_does_not_outlive_the_job(track_widget, tmp_path):
    """run() while a job runs is refused; the refusal became the running job's last_error."""
    viewer, widget = track_widget
    widget.set_sequence(_moving_csv(tmp_path / "s.csv", _random_named_worm(30, 1)))
    widget.run(wait=False)
    assert widget.run() is None
    assert widget.wait(timeout=120)
    assert len(viewer.layers) == 2 and widget.last_error is None, widget.last_error


def test_cancel_stops_the_job_and_keeps_the_layers(track_widget, recording):
    """Cancel (enabled only while a job runs) stops segmenting/tracking at the next volume: no
    layer added or replaced, no error, and the next run works. There was no way to stop a long
    recording's job."""
    from napari_fdlc._napari._io import read_stack_layers

    viewer, widget = track_widget
    path, _, _ = recording
    for data, kwargs, kind in read_stack_layers(str(path)):
        getattr(viewer, f"add_{kind}")(data, **kwargs)
    before = list(viewer.layers)
    assert not widget.cancel_button.isEnabled()
    widget.run(wait=False)
    assert widget.cancel_button.isEnabled()
    widget.cancel_button.click()  # the worker is still segmenting its first time point
    assert widget.wait(timeout=120)
    assert widget.cancelled and widget.last_error is None
    assert list(viewer.layers) == before
    assert "cancelled" in widget.status.text() and widget.progress_bar.value() < 100
    assert not widget.cancel_button.isEnabled()
    tracks, points = widget.run()  # a cancel does not carry over to the next job
    assert not widget.cancelled and set(np.unique(points.data[:, 0])) == {0, 1, 2}


def test_cancel_racing_the_end_of_the_job_leaves_a_stale_cancelling_status(make_napari_viewer, identifier, tmp_path):
    """Cancel clicked after the result is in (before the job's end is handled) leaves the
    result and says it was done; the status said 'cancelling…' for good."""
    from napari_fdlc._napari.tracks import TrackWidget
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.table import write_table
    from napari_fdlc.track import SequenceParams, join_by_time, simulate_sequence

    worm = generate_worm(seed=4)
    volumes, _ = simulate_sequence(worm, 0, SequenceParams(frames=3, jitter_um=0.2))
    path = tmp_path / "recording.csv"
    write_table(join_by_time(volumes).drop(columns=["label"]), path)
    viewer = make_napari_viewer()
    widget = TrackWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Track")
    widget.identifier = identifier
    widget.set_sequence(path)
    worker = widget.run(wait=False)
    worker.returned.connect(lambda *_: widget.cancel())  # the click lands between 'returned' and 'finished'
    assert widget.wait(timeout=120)
    assert not widget.cancelled and widget.last_error is None and len(widget.layers) >= 1
    assert "cancelling" not in widget.status.text(), widget.status.text()


torch = pytest.importorskip("torch")


torch.set_num_threads(1)


def _press(viewer, key):
    """A key press as the canvas delivers it (active layer keymap first, then the viewer's)."""
    return viewer.window._qt_viewer._key_map_handler.press_key(key)


def test_set_recording_by_its_file_chooses_that_file_when_two_recordings_share_a_name(make_napari_viewer, tmp_path):
    """gui.md, Scripting: "t.set_recording("recording.ome.tif") (a recording open in the viewer,
    by its file or name)". With day1/worm.ome.tif and day2/worm.ome.tif both open (offered as
    'recording: worm' and 'recording: worm [2]'), set_recording(<day2 path>) should choose day 2.
    It chooses day 1 (matched by the short name 'worm' only), so Track silently tracks the other
    recording."""
    from napari_fdlc._napari.tracks import TrackWidget

    viewer = make_napari_viewer()
    keys = {}
    for day in ("day1", "day2"):
        keys[day] = str(tmp_path / day / "worm.ome.tif")
        viewer.add_image(np.zeros((2, 4, 16, 16), np.float32), name=f"worm {day} [W]",
                         metadata={"fdlc": {"image": keys[day], "role": "W", "stack_name": "worm"}})
    widget = TrackWidget(viewer)
    viewer.window.add_dock_widget(widget, name="Track")
    widget.set_recording(keys["day2"])
    assert widget.source_combo.currentData() == keys["day2"], (
        f"set_recording({keys['day2']!r}) chose {widget.source_combo.currentText()!r} = {widget.source_combo.currentData()}")


def test_a_relative_session_dir_is_taken_from_where_napari_started(labelled_viewer, make_napari_viewer, tmp_path,
                                                                    monkeypatch):
    """gui.md, Autosave: "FDLC_SESSION_DIR overrides it (... a relative path is taken from where
    napari starts)". The relative path is resolved against the *current* folder at every look-up
    (review.user_session_dir), so after the working folder changes in the running napari (its
    console's %cd, a script's os.chdir) reopening the image no longer finds its session."""
    start, later = tmp_path / "start", tmp_path / "later"
    start.mkdir()
    later.mkdir()
    monkeypatch.chdir(start)
    monkeypatch.setenv("FDLC_SESSION_DIR", "my-sessions")
    viewer, widget = labelled_viewer
    assert widget.auto_label() is not None, widget.last_error
    saved = widget.session.path
    assert saved.is_file() and start in saved.parents
    monkeypatch.chdir(later)
    viewer2 = make_napari_viewer()
    viewer2.open_sample("napari-fdlc", "neuropal")
    restored = [lyr for lyr in viewer2.layers if lyr.name.endswith("neuron IDs")]
    assert restored, f"the session saved in {saved} was not restored after the working folder changed"


def _blank_recording(viewer):
    """A recording made in napari (a script, the console, another reader): one t, z, y, x layer
    in µm in which no nucleus can be found."""
    viewer.add_image(np.zeros((2, 8, 32, 32), np.float32), name="blank", scale=(1, 1.5, 0.35, 0.35))


def test_closing_the_viewer_while_tracking_runs_raises_no_traceback(track_widget, tmp_path, qtbot):
    """Close napari while a tracking job runs: the job should end quietly (its result dropped).
    Instead, when the worker finishes, TrackWidget._set_busy touches the deleted Track button:
    'RuntimeError: wrapped C/C++ object of type QPushButton has been deleted' in the Qt event
    loop (and the widget's idle signal is never emitted, so wait() hangs until its timeout)."""
    viewer, widget = track_widget
    widget.set_sequence(_moving_csv(tmp_path / "s.csv", _random_named_worm(30, 1), frames=6))
    with qtbot.capture_exceptions() as exceptions:
        widget.run(wait=False)
        viewer.close()
        qtbot.waitUntil(lambda: not widget._busy, timeout=60_000)
        qtbot.wait(100)
    assert not exceptions, [f"{type(e[1]).__name__}: {e[1]}" for e in exceptions]


def test_a_recording_without_nuclei_is_named_as_the_user_knows_it(track_widget):
    """A recording made in napari in which no nucleus is found: the one-line error should name the
    recording ('blank'). It names the internal image key instead: 'layer:05fa2bc5cc:blank: no
    nuclei found; ...' (the key with its data fingerprint, passed as the stack's source)."""
    viewer, widget = track_widget
    _blank_recording(viewer)
    assert widget.run() is None
    assert widget.last_error and "no nuclei found" in widget.last_error
    assert not widget.last_error.startswith("layer:"), widget.last_error


def test_a_failed_run_does_not_show_a_full_progress_bar(track_widget):
    """A job that fails after its segmentation (no nucleus found in any time point) should not
    leave the bar at 100 % beside the error (Auto-label resets it to 0 on an error). The bar stays
    full: _set_busy(False) leaves it at the last progress value, the segmentation's 2/2."""
    viewer, widget = track_widget
    _blank_recording(viewer)
    assert widget.run() is None and widget.last_error
    assert widget.progress_bar.value() < 100, (widget.progress_bar.value(), widget.last_error)


def test_saved_track_points_keep_each_neurons_measured_columns(track_widget, tmp_path):
    """`fdlc track` writes each neuron's other columns (colours, GFP: the activity trace of each
    track; tracking.md's table, 'the input's other columns'); the Track widget's points saved
    with the plugin's writer ('a sequence table that fdlc track reads', gui.md) should too.
    They are lost: track_layers keeps only t, track_id, track_conf and name as features, so the
    saved CSV has no GFP (nor R, G, B: tracked again from it, the colour evidence is gone)."""
    from napari_fdlc.track import join_by_time

    viewer, widget = track_widget
    worm = _random_named_worm(30, 1)
    volumes = [NeuronTable(worm.xyz + 0.2 * k, worm.colours) for k in range(3)]
    df = join_by_time(volumes).drop(columns=["label"])
    df["GFP"] = np.arange(len(df), dtype=float) + 0.5
    write_table(df, tmp_path / "seq.csv")
    widget.set_sequence(tmp_path / "seq.csv")
    _, points = widget.run()
    viewer.layers.selection = {points}
    viewer.layers.save(str(tmp_path / "saved.csv"), selected=True, plugin="napari-fdlc")
    saved = pd.read_csv(tmp_path / "saved.csv")
    assert {"R", "G", "B", "GFP"} <= set(saved.columns), list(saved.columns)
    assert np.allclose(saved["GFP"], df["GFP"])


def test_set_recording_by_the_name_of_one_of_its_layers(track_widget, recording):
    """tracks.py's docstring: `w.set_recording(...)  # or the image layers of a recording (its file
    or layer name)`. A recording opened with napari-fdlc has layers 'recording [R]', … '[W]';
    set_recording('recording [W]') raises "no recording 'recording [W]' in the viewer": only
    the name in the combo box ('recording') or the file is matched."""
    from napari_fdlc._napari._io import read_stack_layers

    viewer, widget = track_widget
    for data, kwargs, kind in read_stack_layers(str(recording[0])):
        getattr(viewer, f"add_{kind}")(data, **kwargs)
    widget.set_recording("recording [W]")
    assert widget.source_combo.currentText() == "recording: recording"


def test_a_point_added_on_a_timed_recordings_empty_frame_is_saved_at_its_frame(track_widget, recording, tmp_path):
    """gui.md: the Track widget's points saved with File > Save are "a sequence table that fdlc
    track reads; a point added by hand takes the time of its frame". A recording's t column is
    its frame number (0, 1, 2 here: frame 1 has no nuclei and is left out). With the recording's
    layers given a time scale/offset (0.25 s per volume from 3 s; the results follow it, as
    tracking.md says), a point added by hand at frame 1 is saved with t = 3.25 (its world time,
    write_neuron_csv/_times_of_frames falling back to ``world[:, -4]``) instead of 1: the saved
    sequence mixes frame numbers with seconds (0, 2, 3.25), so it no longer lies on the
    recording's frames when read again."""
    from napari_fdlc._napari._io import read_stack_layers

    def blank_second(data):
        data[1] = np.median(data[0])
        return data

    viewer, widget = track_widget
    for data, kwargs, kind in read_stack_layers(str(recording[0])):
        getattr(viewer, f"add_{kind}")(blank_second(np.array(data)), **kwargs)
    for layer in list(viewer.layers):
        layer.scale = (0.25, *tuple(layer.scale)[1:])
        layer.translate = (3.0, *tuple(layer.translate)[1:])
    _, points = widget.run()
    assert widget.last_error is None, widget.last_error
    assert set(np.unique(points.data[:, 0])) == {0, 2}
    points.add([[1, 5.0, 5.0, 5.0]])  # on the empty frame 1
    viewer.layers.selection = {points}
    viewer.layers.save(str(tmp_path / "out.csv"), selected=True, plugin="napari-fdlc")
    saved = pd.read_csv(tmp_path / "out.csv")
    assert saved["t"].iloc[-1] == 1, sorted(saved["t"].unique())
