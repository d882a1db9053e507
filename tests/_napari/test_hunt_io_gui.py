"""Defect hunt on the napari I/O side (readers, writer, sample): each test fails on the current
code because of a defect its docstring describes (steps, what happens now, what should)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.table import NeuronTable, read_table, write_table

NEUROPAL_NAMES = ["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"]


def _worm(n=6, seed=0, offset=0.0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 6] + [60, 30, 15] + offset
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
    """Steps: write a sequence table (t = 0, 1) with write_table; viewer.open it with napari-fdlc
    (t, z, y, x points); add a point at frame 1 (layer.add([[1, z, y, x]])); File > Save Selected
    Layers with napari-fdlc; open the saved file again.

    Now: the added point's 't' feature is NaN (feature_defaults), the writer takes a 't' feature
    over the point's own frame, so the row is written with an empty t, and the file napari-fdlc
    just wrote cannot be opened: "TableError: ...: line 14, column 't': an empty cell is not a
    finite number".

    Should: the point is saved at its frame (t = 1) and the file opens again with it."""
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


def test_a_point_added_to_the_track_neurons_layer_is_saved_at_its_frame_without_a_copied_name(make_napari_viewer, tmp_path):
    """Steps: the Track widget's neurons layer (tracks.track_layers of a 2-volume result, named
    N0..N4 at t = 0 and t = 1); at frame 0 add a point by hand; save the layer with the
    napari-fdlc writer (gui.md: a sequence table that fdlc track reads).

    Now: the layer has no feature_defaults, so napari gives the new point the last row's
    features {'t': 1, 'track_id': 4, 'name': 'N4'}; the writer prefers the 't' feature to the
    point's frame, so the row is written as 't=1, label N4, track_id 4': the point is at the wrong
    time point and N4 appears twice at t=1 (read back, N4 is dropped from both rows).

    Should: the added point has no name / track (like a point added to an opened table) and is
    written at the frame it was added in (t = 0)."""
    from napari_fdlc._napari.tracks import track_layers
    from napari_fdlc.track import Sequence, TrackResult

    n = 5
    worm = _worm(n)
    volumes = [NeuronTable(worm.xyz), NeuronTable(worm.xyz + 1.0)]
    result = TrackResult([np.arange(n), np.arange(n)], [np.ones(n), np.full(n, 0.9)],
                         [f"N{i}" for i in range(n)], [{}, {}])
    viewer = make_napari_viewer()
    for data, kwargs, kind in track_layers(result, Sequence(volumes, [0, 1]), "rec"):
        layer = getattr(viewer, f"add_{kind}")(data, **kwargs)
    assert layer.name == "rec neurons"
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
    """Steps: a Points layer with scale (1.5, 0.25, 0.3) whose world placement also has an
    affine translation (as napari's transform mode sets it) or a rotation; save it with the
    napari-fdlc writer.

    Now: write_neuron_csv computes world = data * scale + translate and ignores rotate / shear /
    affine, so x_um, y_um, z_um are written at the unmoved positions (the first point's x_um is
    6.0 where napari shows it at 13.0 µm), silently.

    Should: x_um, y_um, z_um are the world positions napari shows (layer.data_to_world), as the
    writer's docstring says ("x_um, y_um, z_um in the world frame"), or the layer is refused in
    one line."""
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
    """Steps: a neuron table saved with Excel's 'sep=,' first line (read_table skips it: table.py
    _read_csv); viewer.open(path, plugin='napari-fdlc').

    Now: get_table_reader looks only at the first line ('sep=,') for x_um, y_um, z_um and
    declines the file: "ValueError: Reader 'napari-fdlc' was selected to open [...], but refused
    the file.", though the core reads it (6 neurons).

    Should: it opens as the same Points layer as the file without that line."""
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
    """Steps: an OME-TIFF with channels mNeptune2.5, DIC, mTagBFP2, TagRFP-T, GCaMP6s (roles R,
    None, B, W, GFP; no CyOFP); viewer.open it with napari-fdlc; dock Auto-label.

    Now: the reader's metadata says DIC has no role and GCaMP is GFP, but layer_role
    (_layers.py layer_role) falls back to the colormap: DIC is grey -> 'W', GCaMP green -> 'G'.
    The widget picks {'W': 'worm [DIC]', 'G': 'worm [GFP]'}: nuclei are detected on the DIC
    channel and the GCaMP signal is read as CyOFP, silently.

    Should: W is 'worm [W]' (the TagRFP-T layer) and G is none (no CyOFP channel), as the file
    says."""
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
    """Steps: a review session of worm.ome.tif saved with voxel size (1.5, 0.25, 0.25) µm, its
    neurons on voxels (3, 20, 25) and (2, 10, 30); the user fixes the file's calibration to
    (1.5, 0.5, 0.5) µm (same shape); viewer.open the file with napari-fdlc.

    Now: restored_session_layer (_io.py) checks the image shape but not the voxel size: the
    neuron-ID layer comes back with the old scale, so in the viewer its neurons lie over image
    voxels (3, 10, 12.5) and (2, 5, 15), half way to the origin, off their nuclei, and nothing is
    said.

    Should: the restored neurons stay on the voxels they were placed on (µm updated to the new
    voxel size), or the session is not restored and napari says why (as for a shape that does
    not fit)."""
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
    """Steps: a sequence table whose t are timestamps in ns, 100 ns apart
    (1700000000123456789, 1700000000123456889: split_by_time compares such whole numbers
    exactly); viewer.open it with napari-fdlc (two volumes: fine); save the layer with the
    napari-fdlc writer; open the saved file again.

    Now: the reader's features go through _plain_features (_layers.py), which turns every numeric
    column, t too, into float64: both times become 1.7000000001234568e+18, the writer writes
    that for every row, and the saved file holds ONE time point of 8 neurons (N0..N3 twice,
    dropped as repeated names); it reopens as a 3D layer.

    Should: the t values are written as they were read (exactly), and the saved file opens again
    as the same two time points with their names."""
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
