"""Autosave hunt (session 36): sequences of user actions after which an edit made in napari is
not in the autosaved session file, is lost on reopening, or is written wrong. Each test says what
the user does, what is expected (docs/gui.md §4-6: "Every edit is autosaved", "Points you add,
delete or drag in the neuron-ID layer are followed", "A renamed neuron-ID layer comes back under
its new name", Auto-label again keeps decisions and says what it could not carry) and what happens.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pandas as pd

from napari_fdlc.table import read_table


def _dock(viewer, identifier, templates):
    dock, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return dock, widget


def _saved_neurons(path) -> int:
    return len(json.loads(path.read_text())["neurons"]["x_um"])


class _Slow:
    """The real (untrained) model, made slow: a job still running while the user edits."""

    def __init__(self, identifier, seconds=1.5):
        self.identifier, self.seconds = identifier, seconds

    def label(self, *args, **kwargs):
        time.sleep(self.seconds)
        return self.identifier.label(*args, **kwargs)


def _add_worm_b(viewer, tmp_path):
    from napari_fdlc._napari._layers import stack_layers
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    for data, kwargs, _ in stack_layers(stack, name="worm B", source_key=str(tmp_path / "worm B.ome.tif")):
        viewer.add_image(data, **kwargs)


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


def test_a_point_added_to_an_earlier_worms_neuron_id_layer_is_kept_when_it_is_reviewed_again(labelled_viewer, tmp_path):
    """Two worms in one viewer (gui.md §4: a key on an earlier worm's layer reviews that worm):
    Auto-label worm A, then worm B, add a neuron to A's layer, press a review key on A's layer.
    Expected: A's session follows the added point (as it does for the worm under review).
    Actual: only the linked layer's data events are connected, so the point is not followed;
    re-adopting A (_adopt -> _link -> _refresh_layer(structure=True)) writes A's saved table back
    into the layer: the point disappears and was never saved."""
    viewer, widget = labelled_viewer
    layer_a = widget.auto_label()
    session_a = widget.session
    n = len(session_a)
    _add_worm_b(viewer, tmp_path)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    assert widget.auto_label() is not layer_a, widget.last_error
    layer_a.add(np.asarray(layer_a.data)[0] + np.array([0.0, 8.0, 8.0]))
    assert len(layer_a.data) == n + 1
    widget._on_key(layer_a, lambda: None)  # a review key pressed on A's layer
    assert widget.layer is layer_a
    assert len(layer_a.data) == n + 1, "the point added to worm A's layer was removed when A was reviewed again"
    assert len(widget.session) == n + 1 and _saved_neurons(session_a.path) == n + 1


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


def test_a_point_added_while_auto_label_runs_again_is_not_dropped_silently(labelled_viewer):
    """Click Auto-label again (a new detection, in the background) and, while it runs, add a
    neuron by hand where no nucleus is detected. Expected (gui.md §4: a neuron you added that the
    new detection lacks is not in it, and napari says how many, with the earlier session kept
    aside): a message, or the neuron kept. Actual: ``missing`` is computed from the snapshot
    taken when the job started (auto_label's previous_snapshot), and done() only carries the
    *decisions* made while the job ran: the neuron is dropped without a word, the session file
    is overwritten without it (nothing set aside) and the new history cannot undo it."""
    from napari.utils.notifications import notification_manager

    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    path = widget.session.path
    widget.identifier = _Slow(widget.identifier)
    widget.auto_label(wait=False)
    layer.add(np.asarray(layer.data)[0] + np.array([0.0, 8.0, 8.0]))
    added_um = widget.session.table.xyz[-1].copy()
    assert widget.session.by_hand[-1] and _saved_neurons(path) == len(widget.session)  # followed and saved
    before = len(notification_manager.records)
    widget.wait()
    assert widget.last_error is None, widget.last_error
    said = [str(r.message) for r in notification_manager.records[before:]]
    kept = np.linalg.norm(widget.session.table.xyz - added_um, axis=1).min() < 1.5
    aside = [p for p in path.parent.iterdir() if p != path]
    assert kept or (any("added" in m for m in said) and aside), \
        f"the neuron added while Auto-label ran is gone; messages {said}; files kept aside {aside}"


def test_a_decision_made_while_auto_label_runs_is_not_lost_when_the_layer_is_deleted_before_it_ends(labelled_viewer):
    """Click Auto-label again (in the background), accept a neuron while it runs (autosaved),
    then delete the neuron-ID layer before the job ends. Expected (gui.md §4: Auto-label again,
    even after deleting the neuron-ID layer, keeps your decisions; a decision it cannot carry is
    said and its session file kept aside): the accept is in the new session or in a file kept
    aside. Actual: with the layer gone self.session is None, so done() carries only the snapshot
    taken when the job started; the new session's autosave overwrites the file that held the
    accept, nothing is set aside and nothing is said."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    path = widget.session.path
    k = next(i for i in range(len(widget.session)) if widget.session.auto_id[i])
    widget.identifier = _Slow(widget.identifier)
    widget.auto_label(wait=False)
    widget.accept(k)
    assert json.loads(path.read_text())["neurons"]["status"][k] == "accepted"  # autosaved
    viewer.layers.remove(layer)
    widget.wait()
    assert widget.last_error is None, widget.last_error
    files = sorted(path.parent.iterdir())
    assert any("accepted" in json.loads(p.read_text())["neurons"]["status"] for p in files), \
        f"the accept made while Auto-label ran is in no session file ({[p.name for p in files]})"


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
