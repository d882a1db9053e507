"""napari flows with recordings (t, z, y, x layers): which time point Auto-label's neurons belong
to, where they are shown, and where their colours are read."""

from __future__ import annotations

import numpy as np
import pytest


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


def test_neuron_ids_of_a_recording_are_not_shown_over_another_time_point(make_napari_viewer, moving_recording,
                                                                          identifier, templates):
    """gui.md: "Auto-label on a recording's layers names its first time point". Expected: its
    neuron-ID layer is shown at that time point (moving the time slider to frame 2, where the
    worm has moved 10 µm, does not show frame 0's names over frame 2's image, or shows them on
    frame 2's nuclei). Actual: the layer is a z, y, x layer (review_points: axis_labels z, y, x,
    no t), which napari broadcasts over every time point: at frame 2 all of frame 0's names are
    drawn, off their nuclei, over the moved worm."""
    viewer, widget = _labelled(make_napari_viewer, moving_recording, identifier, templates)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    on_first = _on_nuclei(viewer, np.asarray(layer.data, float) * layer.scale[-3:], 0)
    assert on_first.mean() > 0.8  # the neurons are frame 0's
    viewer.dims.ndisplay = 3
    viewer.dims.set_point(0, 2)
    shown = np.asarray(layer._view_indices, dtype=int)
    world = np.asarray(layer.data, float)[shown][:, -3:] * np.asarray(layer.scale[-3:])
    off = int((~_on_nuclei(viewer, world, 2)).sum()) if len(shown) else 0
    assert off <= 0.2 * max(len(shown), 1), (
        f"at frame 2, {len(shown)} of frame 0's neuron IDs are shown, {off} of them off frame 2's nuclei")


def test_next_neuron_on_a_recording_goes_to_the_time_point_that_was_named(make_napari_viewer, moving_recording,
                                                                          identifier, templates):
    """gui.md: Next / Prev "centre the view on the neuron, on its z plane"; a recording's neurons
    are those of its first time point. Expected: with the time slider on frame 2, N shows the
    neuron where it is, on frame 0. Actual: _centre_on sets only z, y, x (the layer has no t):
    the view stays on frame 2, centred where the neuron is not (the worm moved 10 µm)."""
    viewer, widget = _labelled(make_napari_viewer, moving_recording, identifier, templates)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    viewer.dims.set_point(0, 2)
    i = widget.next_neuron()
    assert i is not None
    world = np.asarray(layer.data[i], float)[-3:] * np.asarray(layer.scale[-3:])
    assert _on_nuclei(viewer, world[None], 0)[0]  # the neuron lies on a nucleus of frame 0
    t = int(round(viewer.dims.point[0]))
    assert _on_nuclei(viewer, world[None], t)[0], (
        f"N centred on neuron {i} at frame {t}, where it does not lie (it was found in frame 0)")


def test_points_of_another_time_point_get_their_colours_from_that_time_point(make_napari_viewer, moving_recording,
                                                                            identifier, templates):
    """Auto-label with a Points layer of one time point of a recording (points clicked on frame 2:
    t, z, y, x, every t = 2) as Neurons. Expected: the colours are read in frame 2, where the
    points are (or the layer is refused, since Auto-label names the first time point). Actual:
    table_from_layer drops the t coordinate and stack_from_layers gives the recording's first
    volume: every colour is read in frame 0, where the worm is 10 µm away, silently (the names
    then rest on the wrong colours)."""
    from napari_fdlc.io.images import read_series
    from napari_fdlc.segment import measure_colours, segment_stack

    series = read_series(str(moving_recording))
    frame2 = series.volume(2)
    found = segment_stack(frame2, diameter_um=3.0)
    truth = measure_colours(frame2, found.xyz)
    viewer, widget = _labelled(make_napari_viewer, moving_recording, identifier, templates)
    zyx = found.xyz[:, ::-1] / np.asarray(series.voxel_size_zyx)
    viewer.add_points(np.column_stack([np.full(len(zyx), 2.0), zyx]), scale=viewer.layers[0].scale,
                      name="clicked at t=2")
    widget.set_neurons("clicked at t=2")
    layer = widget.auto_label()
    if layer is None:  # refused: fine, if it says why
        assert widget.last_error and "time" in widget.last_error
        return
    read = widget.session.table.colours
    for c in ("R", "W"):
        r = np.corrcoef(read[c], truth[c])[0, 1]
        assert r > 0.9, f"colour {c} of the points at t=2 read elsewhere (correlation with frame 2's: {r:.2f})"
