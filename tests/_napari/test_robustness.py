"""The Auto-label widget when layers, sessions and the widget itself change around it: what
a user does to layers while a job runs, to the channel and neuron choices, to the neuron-ID
layer, and what keeps their decisions from ever being lost. Each test says what the user does
and what happens (and what used to happen: these came from a review of the widget).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from napari_fdlc._napari._layers import META_KEY, is_image_layer, layer_xyz_um, stack_layers
from napari_fdlc._napari._widget import NONE
from napari_fdlc.table import NeuronTable, write_table


class _Slow:
    """The real (untrained) model, made slow: a job that is still running when the user acts."""

    def __init__(self, identifier, seconds=1.0):
        self.identifier, self.seconds = identifier, seconds

    def label(self, *args, **kwargs):
        time.sleep(self.seconds)
        return self.identifier.label(*args, **kwargs)


# --- Auto-label widget: the user's choices in the combo boxes -----------------------------------


def test_a_channel_set_to_none_stays_none_after_auto_label(labelled_viewer):
    """The user turns a channel off (B = (none), e.g. a bad BFP channel) and runs Auto-label: B
    stays off (the neuron-ID layer that Auto-label adds, as any layer added, removed or renamed,
    used to put the B layer back, and the next run silently used it)."""
    viewer, widget = labelled_viewer
    widget.set_channels(B=None)
    assert widget.auto_label() is not None
    assert widget.role_combos["B"].currentText() == NONE
    assert "B" not in widget._chosen_images()


def test_renaming_the_chosen_neurons_layer_keeps_it_chosen(labelled_viewer):
    """The user picks a Points layer as Neurons and as the template, then renames it: both
    choices follow the layer (they used to fall back to 'Detect nuclei in the image' and the
    built-in panel)."""
    viewer, widget = labelled_viewer
    truth = viewer.layers["sample neurons (truth)"]
    widget.set_neurons(truth)
    widget.set_template("sample neurons (truth)")
    truth.name = "my neurons"
    chosen = {"neurons": widget.neurons_combo.currentText(), "template": widget.template_combo.currentText()}
    assert chosen == {"neurons": "my neurons", "template": "layer: my neurons"}


# --- Auto-label widget: layers closed while a job runs ------------------------------------------


def test_deleting_the_neuron_id_layer_while_auto_label_runs_on_it(labelled_viewer, identifier, qtbot):
    """Neurons = the neuron-ID layer itself (to keep points edited by hand), click Auto-label,
    delete the layer while it runs: a one-line message, no traceback (it used to raise
    AttributeError in the result handler)."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    widget.set_neurons(layer)
    widget.identifier = _Slow(identifier, 1.0)
    with qtbot.capture_exceptions() as exceptions:
        widget.auto_label(wait=False)
        viewer.layers.remove(layer)
        assert widget.wait(timeout=30)
    assert not exceptions, [str(e[1]) for e in exceptions]
    assert widget.last_error is not None or widget.layer is not None


def test_deleting_a_point_while_auto_label_runs_on_the_neuron_id_layer(labelled_viewer, identifier):
    """Neurons = the neuron-ID layer, click Auto-label, delete a point while it runs: the result
    is refused with a message that says what to do (it used to be an internal one: 'the
    labelling has N neurons but the table has N-1')."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    widget.set_neurons(layer)
    widget.identifier = _Slow(identifier, 1.0)
    widget.auto_label(wait=False)
    layer.selected_data = {0}
    layer.remove_selected()
    assert widget.wait(timeout=30)
    assert widget.last_error is None or "labelling has" not in widget.last_error, widget.last_error


# --- Auto-label widget: work on the GUI thread --------------------------------------------------


def test_the_image_is_copied_off_the_gui_thread(labelled_viewer, monkeypatch):
    """Clicking Auto-label stacks the chosen channel layers (a copy of every channel) in the
    worker, not on the GUI thread."""
    from napari_fdlc._napari import _widget

    viewer, widget = labelled_viewer
    threads = []
    original = _widget.stack_from_layers

    def spy(*args, **kwargs):
        threads.append(threading.current_thread())
        return original(*args, **kwargs)

    monkeypatch.setattr(_widget, "stack_from_layers", spy)
    widget.auto_label(wait=False)
    assert widget.wait(timeout=60)
    assert threads and threading.main_thread() not in threads


# --- annotations lost ------------------------------------------------------------------------------


def _notifications_since(before):
    from napari.utils.notifications import notification_manager

    return [str(r.message) for r in notification_manager.records[before:]]


def _isolated_named_row(widget, min_um=3.0):
    """A named neuron with no other neuron within ``min_um``: its decision cannot be carried."""
    xyz = widget.session.table.xyz
    d, _ = cKDTree(xyz).query(xyz, k=2)
    rows = [i for i in np.flatnonzero(d[:, 1] > min_um) if widget.session.auto_id[i]]
    assert rows
    return int(rows[0])


def _auto_label_again_without(viewer, widget, row):
    """Auto-label again on a new detection that misses neuron ``row`` (e.g. another diameter)."""
    layer = widget.layer
    keep = [i for i in range(len(layer.data)) if i != row]
    viewer.add_points(np.asarray(layer.data)[keep], scale=layer.scale, name="new detection")
    widget.set_neurons("new detection")
    return widget.auto_label()


def test_decisions_not_carried_to_a_new_detection_are_reported_in_the_gui(labelled_viewer):
    """Auto-label again on a new detection (e.g. another nucleus diameter) that misses a
    neuron the user named: napari says the decision was not carried over (it used to say so
    on stderr only)."""
    from napari.utils.notifications import notification_manager

    viewer, widget = labelled_viewer
    widget.auto_label()
    row = _isolated_named_row(widget)
    widget.assign(row, "AVAL")
    before = len(notification_manager.records)
    assert _auto_label_again_without(viewer, widget, row) is not None
    assert "AVAL" not in widget.session.user_id  # the decision is gone ...
    messages = _notifications_since(before)
    assert any("not carried over" in m for m in messages), messages  # ... and napari should say so


def test_a_decision_not_carried_over_is_kept_on_disk(labelled_viewer):
    """... and the decision is not lost: the earlier session file is set aside, not replaced
    (the new session's autosave used to overwrite it), and the message says where it is."""
    from napari.utils.notifications import notification_manager

    viewer, widget = labelled_viewer
    widget.auto_label()
    row = _isolated_named_row(widget)
    widget.assign(row, "AVAL")
    path = widget.session.path
    before = len(notification_manager.records)
    assert _auto_label_again_without(viewer, widget, row) is not None
    assert "AVAL" not in widget.session.user_id and "AVAL" not in _user_ids(path)
    kept = [p for p in path.parent.iterdir() if p != path and "AVAL" in _user_ids(p)]
    assert len(kept) == 1 and kept[0].name.endswith(".json")
    assert any(str(kept[0]) in m for m in _notifications_since(before))


def _user_ids(path):
    try:
        return json.loads(path.read_text())["neurons"]["user_id"]
    except (ValueError, KeyError, TypeError):
        return []


def _dock(viewer, identifier, templates):
    """The Auto-label widget docked in ``viewer`` and set up (not run): (dock, widget)."""
    dock, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return dock, widget


def _auto_label_widget(viewer, stack_path, identifier, templates):
    """``stack_path`` opened in ``viewer``, the Auto-label widget docked and set up (not run)."""
    viewer.open(stack_path, plugin="napari-fdlc")
    return _dock(viewer, identifier, templates)[1]


def _label_a_copy_of_the_sample(viewer, sample_files, identifier, templates, tmp_path):
    stack_path = tmp_path / "worm.ome.tif"
    shutil.copy(sample_files[0], stack_path)
    widget = _auto_label_widget(viewer, stack_path, identifier, templates)
    widget.auto_label()
    row = int(np.flatnonzero(np.asarray(widget.session.auto_id) != "")[0])
    widget.accept(row)
    return stack_path, widget.session.path


def _from_a_newer_version(session_path) -> str:
    """Make the session file unreadable (written by a newer napari-fdlc); returns its text."""
    saved = json.loads(session_path.read_text())
    newer = json.dumps({**saved, "version": saved["version"] + 1})
    session_path.write_text(newer)
    return newer


def test_a_session_that_cannot_be_restored_is_reported_in_the_gui(make_napari_viewer, sample_files, identifier, templates, tmp_path):
    """Reopening an image whose session file cannot be read (here: written by a newer
    napari-fdlc) says so in napari (it used to say so on stderr only)."""
    from napari.utils.notifications import notification_manager

    stack_path, session_path = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    _from_a_newer_version(session_path)
    before = len(notification_manager.records)
    layers = make_napari_viewer().open(stack_path, plugin="napari-fdlc")
    assert [type(layer).__name__ for layer in layers] == ["Image"] * 4  # not restored ...
    messages = _notifications_since(before)
    assert any("not restored" in m or "newer napari-fdlc" in m for m in messages), messages  # ... say so


def test_auto_label_never_overwrites_a_session_file_it_could_not_read(make_napari_viewer, sample_files, identifier, templates, tmp_path):
    """... and Auto-label on that image keeps the unreadable file (set aside) instead of
    writing a new session over it."""
    stack_path, session_path = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    newer = _from_a_newer_version(session_path)
    _auto_label_widget(make_napari_viewer(), stack_path, identifier, templates).auto_label()
    kept = [p for p in tmp_path.iterdir() if p.is_file() and p.read_text(errors="replace") == newer]
    assert kept, "the unreadable session file was overwritten"


def test_a_session_file_that_cannot_be_set_aside_is_left_untouched(make_napari_viewer, sample_files, identifier, templates,
                                                                     tmp_path, monkeypatch):
    """... and when it cannot even be renamed (a read-only folder), Auto-label says so, leaves
    it as it is and keeps the new session in the user's data folder (it used to fail with
    "unexpected error ... please report it", on every run)."""
    import os

    from napari_fdlc._napari import _widget

    stack_path, session_path = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    newer = _from_a_newer_version(session_path)
    real_replace = os.replace

    def refuse_rename(src, dst):
        if os.fspath(src) == os.fspath(session_path):
            raise PermissionError(13, "Permission denied", os.fspath(src))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", refuse_rename)
    widget = _auto_label_widget(make_napari_viewer(), stack_path, identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    assert session_path.read_text() == newer
    assert widget.session.path == _widget.user_session_file(widget.session.image)


def test_an_image_without_a_file_does_not_get_another_images_session(make_napari_viewer, identifier, templates, qtbot):
    """Images made in napari (a script, the console, another plugin) have no file: their
    session is keyed by the layer's name and a fingerprint of its data, so another image with
    the same layer name (here another worm: the sample mirrored) does not get the first one's
    neuron IDs (it used to: the key was the name alone)."""
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    scale = stack.voxel_size_zyx
    viewer = make_napari_viewer()
    viewer.add_image(stack.data[3], name="W", scale=scale, colormap="gray")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget.auto_label() is not None
    for i in np.flatnonzero(np.asarray(widget.session.auto_id) != "")[:20]:
        widget.accept(int(i))

    other = make_napari_viewer()  # another day, another worm
    _, widget2 = other.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    other.add_image(stack.data[3][:, :, ::-1].copy(), name="W", scale=scale, colormap="gray")
    qtbot.wait(100)
    restored = [layer.name for layer in other.layers if type(layer).__name__ == "Points"]
    assert restored == [], restored


def test_duplicating_the_neuron_id_layer_leaves_the_review_on_it(labelled_viewer):
    """Duplicate Layer on the neuron-ID layer (e.g. to keep a copy): the review stays on the
    original, the copy is a plain points layer (the widget used to move to the copy, and points
    then edited in the original were neither followed nor saved)."""
    from napari.layers._layer_actions import _duplicate_layer

    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    n = len(widget.session)
    viewer.layers.selection = {layer}
    _duplicate_layer(viewer.layers)
    assert widget.layer is layer, f"the widget now reviews '{widget.layer.name}'"
    layer.selected_data = {0}
    layer.remove_selected()
    assert len(widget.session) == n - 1


def test_closing_the_widget_while_it_runs_then_docking_it_again(make_napari_viewer, sample_files, identifier, templates, qtbot):
    """Close the Auto-label dock while Auto-label runs, dock it again: the closed widget's result
    is dropped (it used to link the result layer to itself, so that its keys acted on a session
    the docked widget did not show and both wrote one session file); the docked widget's own
    run and its keys work as usual."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    dock, old = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    old.identifier = _Slow(identifier, 1.0)
    old.set_templates(templates)
    old.auto_label(wait=False)
    viewer.window.remove_dock_widget(dock)
    _, new = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    new.identifier = identifier
    new.set_templates(templates)
    assert old.wait(timeout=30)
    qtbot.wait(50)
    from napari_fdlc._napari._layers import META_KEY

    assert old.layer is None and not any("session" in (layer.metadata.get(META_KEY) or {}) for layer in viewer.layers)
    layer = new.auto_label()
    assert layer is not None and new.layer is layer
    row = int(np.flatnonzero(np.asarray(new.session.auto_id) != "")[0])
    layer.selected_data = {row}
    viewer.layers.selection.active = layer
    viewer.window._qt_viewer._key_map_handler.press_key("A")  # accept, by key
    other = int(np.flatnonzero(np.asarray(new.session.auto_id) != "")[1])
    new.accept(other)  # accept another, with the docked widget's button
    saved = json.loads(new.session.path.read_text())["neurons"]["status"]
    assert (saved[row], saved[other]) == ("accepted", "accepted")


def test_reopening_a_recording_restores_its_neuron_ids(make_napari_viewer, recording, identifier, templates, tmp_path):
    """docs/gui.md: Auto-label on a recording's layers names its first time point, and
    reopening the image restores the neuron-ID layer (for a recording the reader used to skip
    the saved session, and a widget docked afterwards did not bring it back)."""
    path = tmp_path / "worm rec.ome.tif"
    shutil.copy(recording[0], path)
    viewer = make_napari_viewer()
    viewer.open(path, plugin="napari-fdlc")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget.auto_label() is not None, widget.last_error
    widget.assign(0, "AVAL")
    assert widget.session.path.is_file()

    again = make_napari_viewer()
    again.open(path, plugin="napari-fdlc")
    _, widget2 = again.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    names = [layer.name for layer in again.layers]
    assert widget2.session is not None and widget2.session.user_id[0] == "AVAL", names
    assert widget2.layer.ndim == 4, "restored without its time axis: drawn over every time point"


def test_review_keys_on_an_earlier_neuron_id_layer_act_on_that_layer(labelled_viewer, tmp_path):
    """Two worms in one viewer: Auto-label worm A, then worm B; select a neuron in A's layer
    and press A: A's neuron is accepted (the keys used to act on B's session)."""
    from napari_fdlc._napari._layers import stack_layers
    from napari_fdlc.sample import load_sample

    viewer, widget = labelled_viewer
    layer_a = widget.auto_label()
    stack, _ = load_sample()
    for data, kwargs, _ in stack_layers(stack, name="worm B", source_key=str(tmp_path / "worm B.ome.tif")):
        viewer.add_image(data, **kwargs)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    widget.set_neurons("segment")
    layer_b = widget.auto_label()
    assert layer_b is not layer_a
    row = int(np.flatnonzero(layer_a.features["auto_id"].to_numpy(object) != "")[0])
    row_b = int(np.flatnonzero(layer_b.features["auto_id"].to_numpy(object) != "")[1])
    widget.select_neuron(row_b)  # B was being reviewed
    viewer.layers.selection.active = layer_a
    layer_a.selected_data = {row}
    viewer.window._qt_viewer._key_map_handler.press_key("A")
    got = (layer_a.features["status"][row], layer_b.features["status"][row_b])
    assert got == ("accepted", "auto"), f"A's neuron: {got[0]}, B's neuron: {got[1]}"


def test_a_2d_image_gets_a_message_that_says_so(make_napari_viewer, identifier, templates):
    """Only a 2D image (e.g. a max projection): Auto-label says a 3D stack is needed (it used
    to ask for the W channel layer, which the user could not pick)."""
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    viewer = make_napari_viewer()
    viewer.add_image(stack.data[3].max(0), name="max projection")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    widget.run_button.click()
    assert widget.last_error is not None and ("2D" in widget.last_error or "3D" in widget.last_error), widget.last_error


def test_points_of_several_time_points_are_refused_as_neurons(labelled_viewer):
    """The Track widget's points (t, z, y, x) chosen as Neurons: refused with a message (they
    used to be pooled into one worm of every time point)."""
    viewer, widget = labelled_viewer
    truth = viewer.layers["sample neurons (truth)"]
    zyx = np.asarray(truth.data)
    tracked = np.vstack([np.column_stack([np.full(len(zyx), t), zyx]) for t in (0, 1)])
    viewer.add_points(tracked, scale=(1,) + tuple(truth.scale), name="tracks at t")
    widget.set_neurons("tracks at t")
    widget.run_button.click()
    assert widget.last_error is not None and "several time points" in widget.last_error


def test_a_renamed_neuron_id_layer_comes_back_under_its_new_name(make_napari_viewer, sample_files, identifier, templates, tmp_path):
    """Rename the neuron-ID layer, reopen the image: it is restored under the new name."""
    stack_path, session_path = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    saved = json.loads(session_path.read_text())
    assert saved["settings"]["layer_name"] != "worm 1 reviewed"
    viewer = make_napari_viewer()
    layers = viewer.open(stack_path, plugin="napari-fdlc")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    assert widget.layer is layers[-1]
    widget.layer.name = "worm 1 reviewed"
    again = make_napari_viewer().open(stack_path, plugin="napari-fdlc")
    assert again[-1].name == "worm 1 reviewed"


def test_a_key_with_several_neurons_selected_names_none_of_them(labelled_viewer):
    """Box-select several neurons and press A: a message asks for one (the key used to act on
    the neuron shown last, which may be none of those selected)."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    widget.select_neuron(5)
    layer.selected_data = {0, 1, 2}
    viewer.layers.selection.active = layer
    viewer.window._qt_viewer._key_map_handler.press_key("A")
    assert set(widget.session.status) == {"auto"}
    assert "3 neurons are selected" in widget.last_error


def test_undoing_a_deletion_keeps_the_current_neuron_on_the_same_cell(labelled_viewer):
    """Delete a point, select a neuron, Ctrl+Z: the current neuron is not left on its row number,
    which the undone deletion gives to another cell (the review box and keys would act on a
    neuron the user did not pick)."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    session = widget.session
    layer.selected_data = {3}
    layer.remove_selected()
    widget.select_neuron(10)  # row 11 before the deletion
    cell = session.table.xyz[10].copy()
    widget.undo()
    current = widget.current
    assert current is None or np.allclose(session.table.xyz[current], cell), (current, cell)
    assert current is None or set(layer.selected_data) == {current}


def test_a_cleared_correction_offers_the_machines_candidates_again(labelled_viewer):
    """Correct a neuron, Re-label, Clear: the Candidates dropdown offers the machine's top 3
    again, not the cleared name at 1.00 (a decided neuron keeps the machine's earlier candidates,
    as it keeps its earlier name)."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    session = widget.session
    i = next(j for j in reversed(session.review_order()) if len(session.candidates(j)) == 3)
    widget.select_neuron(i)
    before = [widget.candidate_combo.itemText(k) for k in range(widget.candidate_combo.count())]
    widget.pick_candidate(i, 2)
    assert widget.relabel() is not None, widget.last_error
    widget.clear(i)
    after = [widget.candidate_combo.itemText(k) for k in range(widget.candidate_combo.count())]
    assert after == before


def test_auto_label_again_after_the_voxel_size_changed_puts_points_on_their_neurons(labelled_viewer):
    """Auto-label again after the image's voxel size (scale) changed: the reused neuron-ID layer
    takes the new scale, so its points sit on their neurons (and positions read back from it are
    right)."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    for layer in viewer.layers:
        if is_image_layer(layer):
            layer.scale = tuple(np.asarray(layer.scale, dtype=float) * 2)
    layer = widget.auto_label()
    assert layer is not None, widget.last_error
    assert np.allclose(layer.scale[-3:], widget.session.voxel_size_zyx)
    assert np.abs(layer_xyz_um(layer) - widget.session.table.xyz).max() < 1e-6


def test_a_template_file_with_a_repeated_name_says_so_in_napari(make_napari_viewer, templates, tmp_path):
    """A template file whose name occurs twice loses it on both rows; napari says so (a reader's
    warning reaches the user, not only stderr)."""
    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    t = templates[0]
    labels = np.array(t.labels, dtype=object).copy()
    named = np.flatnonzero(labels != "")
    labels[named[1]] = labels[named[0]]
    path = tmp_path / "template.csv"
    write_table(NeuronTable(t.xyz, t.colours, labels), path)
    from napari.utils.notifications import notification_manager

    before = len(notification_manager.records)
    widget.add_template_file(path)
    assert any(labels[named[0]] in m for m in _notifications_since(before)), \
        _notifications_since(before)


@pytest.mark.parametrize("moved", ["every channel", "R only"])
def test_an_image_moved_in_the_viewer_is_refused_in_one_message(labelled_viewer, moved):
    """Neurons are found and coloured in the stack's own voxels. With the image layers given a
    translate, the neuron-ID points landed off the nuclei (median 6.3 µm) and the colours under
    a Points layer moved alike were read elsewhere (correlation 0.07 with the true ones); with
    R alone moved, the channels were stacked voxel by voxel: colours from the wrong cells.
    Now: one message, nothing named."""

    viewer, widget = labelled_viewer
    for layer in viewer.layers:
        if is_image_layer(layer) and (moved == "every channel" or layer.name.endswith("[R]")):
            layer.translate = (5.0, 10.0, 15.0)
    assert widget.auto_label() is None
    assert "shifted in the viewer" in widget.last_error


def test_decisions_survive_renaming_an_image_made_in_napari(make_napari_viewer, identifier, templates):
    """An image made in napari (no file) is known by its name and data; renamed after decisions
    were made, Auto-label again started a session without them and said nothing. The key is
    now kept in the layer's metadata at the first run."""
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    viewer = make_napari_viewer()
    for i, role in enumerate(stack.channel_roles):
        viewer.add_image(np.asarray(stack.data[i]), name=f"c [{role}]", scale=tuple(stack.voxel_size_zyx))
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    widget.auto_label()
    widget.assign(0, "AVAL")
    widget.assign(1, "AVAR")
    viewer.layers["c [W]"].name = "worm1 [W]"
    widget.auto_label()
    assert widget.last_error is None, widget.last_error
    assert sorted(n for n in widget.session.user_id if n) == ["AVAL", "AVAR"]

# Session 32 (a helper review of the review workflow); each says what used to happen.


def _press(viewer, key):
    assert viewer.window._qt_viewer._key_map_handler.press_key(key), f"key {key} not bound"


def _add_worm_b(viewer, tmp_path):
    """A second worm in the same viewer (the sample again, as if read from another file)."""
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    for data, kwargs, _ in stack_layers(stack, name="worm B", source_key=str(tmp_path / "worm B.ome.tif")):
        viewer.add_image(data, **kwargs)


def _named_row(layer, k=0):
    return int(np.flatnonzero(layer.features["auto_id"].to_numpy(object) != "")[k])


# --- two worms in one viewer ---------------------------------------------------------------------


def test_undo_history_survives_switching_to_another_worm_and_back(labelled_viewer, tmp_path):
    """Ctrl+Z on worm A after reviewing worm B: "nothing to undo" (going back reloaded A's session from
    its file, without its history; gui.md: the history is kept while napari runs)."""
    viewer, widget = labelled_viewer
    layer_a = widget.auto_label()
    row = _named_row(layer_a)
    widget.accept(row)
    _add_worm_b(viewer, tmp_path)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    assert widget.auto_label() is not None, widget.last_error
    viewer.layers.selection.active = layer_a
    layer_a.selected_data = {row}
    _press(viewer, "Control-Z")
    assert widget.layer is layer_a
    assert layer_a.features["status"][row] == "auto", widget.progress_bar.format()


def test_auto_label_again_on_an_earlier_worm_reuses_its_neuron_id_layer(labelled_viewer, tmp_path):
    """Auto-label A, then B, then A again: a second layer for A's session was added beside the first,
    the two disagreeing after an edit. One neuron-ID layer per image."""
    viewer, widget = labelled_viewer
    layer_a = widget.auto_label()
    row = _named_row(layer_a)
    widget.accept(row)
    path_a = str(widget.session.path)
    _add_worm_b(viewer, tmp_path)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    assert widget.auto_label() is not None, widget.last_error
    widget.set_channels(**{r: f"NeuroPAL sample [{r}]" for r in "RGBW"})
    assert widget.auto_label() is not None, widget.last_error
    widget.clear(row)
    of_a = [layer for layer in viewer.layers
            if ((layer.metadata or {}).get(META_KEY) or {}).get("session") == path_a]
    assert [layer.name for layer in of_a] == ["NeuroPAL sample neuron IDs"], \
        [(layer.name, layer.features["status"][row]) for layer in of_a]


# --- editing points by hand, then Auto-label again -----------------------------------------------


def test_next_after_deleting_a_false_detection_continues_down_the_list(labelled_viewer):
    """N after deleting the current point (a false detection) went back to the top of the list."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    order = widget.session.review_order()
    for _ in range(5):
        widget.next_neuron()
    deleted = widget.current
    follower = order[order.index(deleted) + 1]
    follower_xyz = widget.session.table.xyz[follower].copy()
    layer.selected_data = {deleted}
    layer.remove_selected()
    assert len(widget.session) == len(order) - 1
    got = widget.next_neuron()
    assert np.allclose(widget.session.table.xyz[got], follower_xyz), \
        f"N went to position {widget.session.review_order().index(got)} of the list"


def test_auto_label_again_does_not_silently_drop_a_neuron_added_by_hand(labelled_viewer):
    """A point added by hand, then Auto-label again (a new detection): it was gone without a word and
    could not be undone. Now said, and the earlier session kept aside."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    added = layer.data[0] + np.array([0.0, 8.0, 8.0])
    layer.add(added)
    assert len(widget.session) == len(layer.data)
    added_um = widget.session.table.xyz[-1].copy()
    from napari.utils.notifications import notification_manager

    before = len(notification_manager.records)
    assert widget.auto_label() is not None, widget.last_error
    said = [str(r.message) for r in notification_manager.records[before:]]

    def kept():
        return np.linalg.norm(widget.session.table.xyz - added_um, axis=1).min() < 1.5

    if not kept():
        widget.undo()
    assert kept() or any("added" in m or "dropped" in m for m in said), \
        f"hand-added neuron lost; undo said {widget.progress_bar.format()!r}; messages {said}"


def test_clearing_a_decision_carried_by_auto_label_again_offers_the_machines_candidates(labelled_viewer):
    """Pick candidate 2, Auto-label again, Clear: the dropdown offered only the cleared name at 1.00."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    s = widget.session
    i = next(j for j in reversed(s.review_order()) if len(s.candidates(j)) == 3)
    before = s.candidates(i)
    widget.pick_candidate(i, 2)
    assert widget.auto_label() is not None, widget.last_error
    assert widget.session.status[i] == "corrected"
    widget.clear(i)
    after = widget.session.candidates(i)
    assert [c for c, _ in after] == [c for c, _ in before], (before, after)


# --- threshold line ------------------------------------------------------------------------------


def test_the_coverage_line_counts_no_name_below_a_zero_threshold(labelled_viewer):
    """At threshold 0, an automatic name taken by a decision elsewhere was counted "below threshold"."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    widget.set_threshold(0.0)
    s = widget.session
    named = [int(j) for j in np.flatnonzero(np.asarray(s.auto_id) != "")]
    q = named[0]
    r = next(j for j in named[1:] if s.auto_id[j] != s.auto_id[q])
    widget.assign(r, s.auto_id[q])
    assert layer.features["label"][q] == ""  # taken, as documented
    assert "0 below threshold" in widget.coverage_label.text(), widget.coverage_label.text()


# --- tables opened as Points ---------------------------------------------------------------------


def test_user_ids_of_a_neuropal_id_table_used_as_neurons_are_kept(labelled_viewer, make_napari_viewer, tmp_path):
    """A NeuroPAL_ID export opened as Points and Auto-labelled: every User ID was dropped (decisions
    were read from a `user_id` column only), silently."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    a, b, c = (_named_row(layer, k) for k in range(3))
    widget.accept(a)
    widget.mark_unsure(b)
    widget.assign(c, "FOO1")
    expected = {a: widget.session.user_id[a], b: widget.session.user_id[b], c: "FOO1"}
    out = widget.export(tmp_path / "worm_npid.csv", format="neuropal_id")

    other = make_napari_viewer()
    points = other.open(out, plugin="napari-fdlc")[0]
    _, w2 = other.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    w2.identifier = widget.identifier
    w2.set_templates(widget._script_templates)
    w2.set_neurons(points)
    assert w2.auto_label() is not None, w2.last_error
    got = {i: w2.session.user_id[i] for i in expected}
    assert got == expected
    assert w2.session.status[b] == "unsure"


# --- a damaged autosave --------------------------------------------------------------------------


def test_a_damaged_session_file_does_not_stop_the_image_from_opening(make_napari_viewer, sample_files, identifier,
                                                                     templates, tmp_path):
    """A session file with `"image_shape": 5`: the image did not open (a TypeError out of the reader)."""
    stack_path, path = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    saved = json.loads(path.read_text())
    saved["settings"]["image_shape"] = 5
    path.write_text(json.dumps(saved))
    layers = make_napari_viewer().open(stack_path, plugin="napari-fdlc")
    assert sum(type(lyr).__name__ == "Image" for lyr in layers) == 4


def _saving_fails_in(folder, code=errno.EROFS):
    """ReviewSession.save, failing in ``folder`` as a read-only (or full) disk does."""
    from napari_fdlc.review import ReviewSession

    save = ReviewSession.save

    def failing(self, path=None):
        if path is not None and Path(path).parent == folder:
            raise OSError(code, os.strerror(code))
        return save(self, path)

    return failing


@pytest.mark.parametrize("when", ["at its first save", "after an edit"])
def test_a_session_moved_to_the_user_folder_is_said_in_napari(make_napari_viewer, sample_files, identifier, templates,
                                                             tmp_path, monkeypatch, when):
    """When the image's folder stops taking the session (read-only remount, disk full), the
    session goes on in the user's folder and napari says where (it was said on stderr only, so a
    napari user did not know where the annotations went)."""
    from napari.utils.notifications import notification_manager

    from napari_fdlc.review import ReviewSession

    stack_path, beside = _label_a_copy_of_the_sample(make_napari_viewer(), sample_files, identifier, templates, tmp_path)
    read_only = _saving_fails_in(tmp_path)
    before = len(notification_manager.records)
    widget = _auto_label_widget(make_napari_viewer(), stack_path, identifier, templates)
    if when == "at its first save":
        monkeypatch.setattr(ReviewSession, "save", read_only)
    widget.auto_label()
    monkeypatch.setattr(ReviewSession, "save", read_only)
    widget.accept(int(np.flatnonzero(np.asarray(widget.session.auto_id) != "")[1]))
    moved = widget.session.path
    assert moved != beside and moved.is_file()
    assert any(str(moved) in m for m in _notifications_since(before)), _notifications_since(before)


# ----- session 33's review of the Auto-label widget's review side --------------------------------


def _old_row(xyz_before, xyz_now, r):
    """The row, before an edit, of the neuron now at row ``r``."""
    return int(np.flatnonzero(np.all(np.isclose(xyz_before, xyz_now[r]), axis=1))[0])


# --- Name field ----------------------------------------------------------------------------------


def test_a_known_name_typed_in_lower_case_is_taken_in_its_own_case(labelled_viewer):
    """docs/gui.md: completion over the known neuron names; 'a known name typed in another case,
    `aval`, is taken as `AVAL`'. Expected: a name the completer offers (the atlas's), typed in
    lower case, is stored in its own case. Actual: with a template that lacks it, it is stored as
    typed ('adfl'), a name no template, atlas or tool knows."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    s = widget.session
    completer = widget._completer.model().stringList()
    known = sorted(n for n in completer if n not in s.vocabulary and n.lower() != n)
    assert known, "every completer name is in the session's vocabulary"
    name = known[0]
    i = s.review_order()[0]
    widget.select_neuron(i)
    widget.name_edit.setText(name.lower())
    widget._on_name_entered()
    assert s.user_id[i] == name, (s.user_id[i], widget.last_error)


def test_names_of_a_template_file_are_offered_by_the_completer(make_napari_viewer, templates, tmp_path):
    """Expected: a labelled table added as a template (Labelled table file…) puts its names in
    the Name completer (the widget's known names include file templates). Actual: the list of
    known names is cached when the widget starts and add_template_file never refreshes it, so its
    names (here one the atlas lacks) are not offered until a new session is linked."""
    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    table = templates[0]
    df = table.to_dataframe()
    labels = df["label"].astype(str).to_numpy(object)
    first = int(np.flatnonzero(labels != "")[0])
    labels[first] = "MYNEURONL"
    df["label"] = labels
    path = tmp_path / "my_worm.csv"
    write_table(df, path)
    widget.add_template_file(path)
    widget._refresh_all()
    assert "MYNEURONL" in widget._completer.model().stringList()


# --- threshold -----------------------------------------------------------------------------------


def test_the_threshold_shown_is_the_threshold_applied(labelled_viewer):
    """set_threshold(0.555) (a script, or a session saved with it): expected the widget's
    threshold, its label and the session's threshold to agree. Actual: the slider (and
    w.threshold, and the label) say 0.56 while the session hides names below 0.555, so a name at
    0.557 is shown (and exported) under a threshold that reads 0.56; the next Auto-label on a new
    detection silently takes 0.56."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    widget.set_threshold(0.555)
    assert widget.threshold == widget.session.threshold, (widget.threshold, widget.session.threshold)


# --- points edited by hand -----------------------------------------------------------------------


def test_deleting_the_current_neuron_leaves_the_review_on_a_neuron_of_the_list(labelled_viewer):
    """Walk the list with N, delete the current point (a false detection). Expected: the review
    box and the layer's selection (what A/U/C/1-3 act on) show the session's current neuron (the
    one before the deleted one, so that N goes on). Actual: they show the row number the deleted
    neuron had, which is now another neuron, unrelated in the list; pressing A accepts it."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    s = widget.session
    for _ in range(5):
        widget.next_neuron()
    deleted = widget.current
    layer.selected_data = {deleted}
    layer.remove_selected()
    assert s.current is not None
    assert set(layer.selected_data) == {s.current}, (set(layer.selected_data), s.current)
    assert f"Neuron {s.current}</b>" in widget.current_label.text(), widget.current_label.text()


def test_previous_after_deleting_the_current_neuron_goes_to_the_one_before_it(labelled_viewer):
    """docs/gui.md: after deleting the current neuron, N goes on to the one after it. Expected:
    Shift+N goes to the one before it, symmetrically. Actual: it skips that one and goes two
    back (the deletion made the one before it current already)."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    s = widget.session
    order = s.review_order()
    for _ in range(5):
        widget.next_neuron()
    deleted = widget.current
    before = order[order.index(deleted) - 1]
    xyz = s.table.xyz.copy()
    layer.selected_data = {deleted}
    layer.remove_selected()
    got = widget.previous_neuron()
    assert _old_row(xyz, s.table.xyz, got) == before, (order.index(deleted), order.index(_old_row(xyz, s.table.xyz, got)))


def test_a_point_dragged_onto_another_nucleus_takes_the_colour_there(labelled_viewer):
    """Drag a point (a misplaced detection) onto a nucleus. Expected: its colour (used by
    Re-label and written to the CSV's R, G, B) is read where it now is, as for a point added
    there. Actual: it keeps the colour read at its old position, so the export and Re-label
    carry colours that belong to nowhere near the neuron."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    s = widget.session
    colours = np.column_stack([s.table.colours[c] for c in "RGB"])
    j = 0
    k = int(np.argmax(np.linalg.norm(colours - colours[j], axis=1)))  # the most different colour
    data = np.asarray(layer.data).copy()
    data[j] = data[k]
    layer.data = data  # as a drag ends: a 'changed' data event with the same number of points
    assert np.allclose(s.table.xyz[j], s.table.xyz[k])
    now = np.array([s.table.colours[c][j] for c in "RGB"])
    there = np.array([s.table.colours[c][k] for c in "RGB"])
    assert np.linalg.norm(now - there) < np.linalg.norm(now - colours[j]), (now, there, colours[j])


# --- exports -------------------------------------------------------------------------------------


def test_the_export_keeps_the_other_columns_of_a_table_used_as_neurons(labelled_viewer, tmp_path):
    """docs/gui.md §6: the CSV export ends with 'the neuron table's other columns (e.g. the
    detection score)'; a table opened in napari keeps them as features. Expected: Auto-label on
    an opened detection table (Neurons = its layer) exports its `cell_id` and `score`. Actual:
    table_from_layer drops every feature but colours, so they are gone from the export."""
    viewer, widget = labelled_viewer
    from napari_fdlc.sample import load_sample

    _, truth = load_sample()
    df = pd.DataFrame({"x_um": truth.xyz[:, 0], "y_um": truth.xyz[:, 1], "z_um": truth.xyz[:, 2]})
    df["cell_id"] = np.arange(len(df)) + 1000
    df["score"] = np.linspace(0.5, 1.0, len(df))
    path = tmp_path / "my_detection.csv"
    df.to_csv(path, index=False)
    points = viewer.open(str(path), plugin="napari-fdlc")[0]
    assert {"cell_id", "score"} <= set(points.features.columns)
    widget.set_neurons(points)
    assert widget.auto_label() is not None, widget.last_error
    got = pd.read_csv(widget.export(tmp_path / "ids.csv"))
    assert {"cell_id", "score"} <= set(got.columns), list(got.columns)


def test_the_default_export_name_of_an_image_made_in_napari_is_a_plain_file_name(make_napari_viewer, identifier,
                                                                                  templates, sample_files):
    """An image made in napari (script, console, another plugin), labelled, then CSV…. Expected:
    the dialog proposes a name after the image ('my worm …_ids.csv', as the neuron-ID layer is
    named). Actual: it proposes the internal session key, 'layer:<hash>:my worm [W]_ids.csv' — a
    hash and colons in a file name (invalid on Windows, where ':' opens an NTFS stream)."""
    from napari_fdlc.sample import load_sample

    viewer = make_napari_viewer()
    stack, _ = load_sample()
    for i, role in enumerate(stack.channel_roles):
        viewer.add_image(np.asarray(stack.data[i]), name=f"my worm [{role}]", scale=stack.voxel_size_zyx)
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget.auto_label() is not None, widget.last_error
    for fmt in ("fdlc", "neuropal_id"):
        name = widget._default_export_path(fmt).name
        assert ":" not in name and name.startswith("my worm"), name


def _named_rows(session):
    return [int(i) for i in np.flatnonzero(np.asarray(session.auto_id) != "")]


def test_decisions_made_after_the_session_moved_survive_docking_the_widget_again(
        make_napari_viewer, sample_files, identifier, templates, tmp_path, monkeypatch):
    """The image's folder stops taking the session (read-only remount): the session goes on in
    the user's folder. Expected: a decision made after that is still there when the Auto-label
    dock is closed and docked again (the layer is re-adopted). Actual: the neuron-ID layer's
    metadata still names the old file beside the image, so the docked widget loads that stale
    file: the later decision is gone from the review, and the next edit's autosave writes the
    stale state over the user-folder file (the decision is lost on disk too)."""
    from napari_fdlc.review import ReviewSession

    stack_path = tmp_path / "worm.ome.tif"
    shutil.copy(sample_files[0], stack_path)
    viewer = make_napari_viewer()
    viewer.open(str(stack_path), plugin="napari-fdlc")
    dock, widget = _dock(viewer, identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    rows = _named_rows(widget.session)
    widget.accept(rows[0])
    read_only = _saving_fails_in(tmp_path)
    monkeypatch.setattr(ReviewSession, "save", read_only)
    widget.accept(rows[1])  # autosaved to the user's folder from now on
    assert widget.session.path.parent != tmp_path
    viewer.window.remove_dock_widget(dock)
    _, again = _dock(viewer, identifier, templates)
    assert again.session is not None
    assert again.session.status[rows[1]] == "accepted", "the decision made after the move is gone"


def _add_worm_b_h(viewer, tmp_path):
    """A second worm in the same viewer (the sample again, as if read from another file)."""
    from napari_fdlc._napari._layers import stack_layers
    from napari_fdlc.sample import load_sample

    stack, _ = load_sample()
    for data, kwargs, _ in stack_layers(stack, name="worm B", source_key=str(tmp_path / "worm B.ome.tif")):
        viewer.add_image(data, **kwargs)


def test_undo_after_deleting_every_point_survives_reviewing_another_worm(labelled_viewer, tmp_path):
    """Select all the points of worm A's neuron-ID layer and delete them by mistake, review worm B,
    come back to A and press Ctrl+Z. Expected (gui.md §5: the undo history is kept while napari
    runs, also for a worm reviewed again after another): the neurons and the decision come back.
    Actual: _adopt looks the session up with ``self._open_sessions.get(path) or
    ReviewSession.load(path)``; a session with no neurons is falsy (``__len__`` is 0), so it is
    read again from its file without its history: "nothing to undo", and every neuron and decision
    of worm A is gone for good (the autosave already holds the empty session)."""
    viewer, widget = labelled_viewer
    layer_a = widget.auto_label()
    session_a = widget.session
    row = _named_rows(session_a)[0]
    widget.accept(row)
    n = len(session_a)
    layer_a.selected_data = set(range(len(layer_a.data)))
    layer_a.remove_selected()
    assert len(session_a) == 0
    _add_worm_b_h(viewer, tmp_path)
    widget.set_channels(**{r: f"worm B [{r}]" for r in "RGBW"})
    assert widget.auto_label() is not None, widget.last_error
    viewer.layers.selection.active = layer_a
    widget._on_key(layer_a, lambda: None)  # a review key pressed on worm A's layer: A is reviewed again
    assert widget.layer is layer_a
    assert widget._gui(widget.undo) is not None, "nothing to undo"
    assert len(widget.session) == n and widget.session.status[row] == "accepted"


def test_undo_history_survives_closing_and_docking_the_widget_again(
        make_napari_viewer, sample_files, identifier, templates):
    """Accept a name, close the Auto-label dock (e.g. for room), open it again from the Plugins
    menu and press Undo. Expected (gui.md §5: 'The undo history is kept while napari runs'): the
    accept is undone. Actual: the history lives in the closed widget (``_open_sessions``); the new
    widget reads the session from its file, without history: "nothing to undo"."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    dock, widget = _dock(viewer, identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    row = _named_rows(widget.session)[0]
    widget.accept(row)
    viewer.window.remove_dock_widget(dock)
    _, again = _dock(viewer, identifier, templates)
    assert again.session is not None and again.session.status[row] == "accepted"
    assert again._gui(again.undo) is not None, "nothing to undo"
    assert again.session.status[row] == "auto"


def test_a_restored_session_threshold_is_the_one_the_slider_shows(labelled_viewer):
    """A session saved with threshold 0.555 (a script's ReviewSession, or an older version) is
    restored at the slider's step, 0.56: the widget's threshold (slider, label, ``w.threshold``)
    is the one the session applies. _link put round(0.555 * 100) = 56 on the slider while the
    session kept 0.555, so names at 0.555-0.56 were still shown and exported, and the next
    Auto-label on a new detection silently took 0.56."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    s = widget.session
    s.threshold = 0.555
    s.save()
    viewer.layers.remove(layer)
    image = next(lyr for lyr in viewer.layers if lyr.name == "NeuroPAL sample [W]")
    assert widget._restore_for_image(image) is not None
    assert widget.session.threshold == 0.56
    assert widget.threshold == widget.session.threshold, (widget.threshold, widget.threshold_label.text())


def _user_ids_h(path):
    try:
        return json.loads(path.read_text())["neurons"]["user_id"]
    except (ValueError, KeyError, TypeError, OSError):
        return []


def test_a_decision_not_carried_over_is_kept_when_the_session_went_to_the_user_folder(
        make_napari_viewer, sample_files, identifier, templates, tmp_path, monkeypatch):
    """The image's disk fills up: the session goes on in the user's folder, where the user names
    an isolated neuron AVAL. Auto-label again on a new detection that misses that neuron.
    Expected (gui.md §5: a session file is never written over while it holds decisions the new
    session lacks): the file holding AVAL is set aside. Actual: _new_session sets aside
    ``session_file_for(key)`` — the stale file beside the image, which never held AVAL — and the
    new session's autosave (beside fails again) falls back onto the user-folder file and writes
    over it: AVAL is in no file at all, while napari says the earlier session is kept."""
    from scipy.spatial import cKDTree

    from napari_fdlc.review import ReviewSession

    folder = tmp_path / "images"
    folder.mkdir()
    stack_path = folder / "worm.ome.tif"
    shutil.copy(sample_files[0], stack_path)
    viewer = make_napari_viewer()
    widget = _auto_label_widget(viewer, str(stack_path), identifier, templates)
    assert widget.auto_label() is not None, widget.last_error
    disk_full = _saving_fails_in(folder, errno.ENOSPC)
    monkeypatch.setattr(ReviewSession, "save", disk_full)
    xyz = widget.session.table.xyz
    d, _ = cKDTree(xyz).query(xyz, k=2)
    row = next(i for i in np.flatnonzero(d[:, 1] > 3.0) if widget.session.auto_id[i])
    widget.assign(int(row), "AVAL")
    assert widget.session.path.parent != folder and "AVAL" in _user_ids_h(widget.session.path)
    layer = widget.layer
    keep = [i for i in range(len(layer.data)) if i != row]
    viewer.add_points(np.asarray(layer.data)[keep], scale=layer.scale, name="new detection")
    widget.set_neurons("new detection")
    assert widget.auto_label() is not None, widget.last_error
    assert "AVAL" not in widget.session.user_id
    files = [p for p in (*folder.iterdir(), *widget.session.path.parent.iterdir()) if p.suffix == ".json"]
    assert any("AVAL" in _user_ids_h(p) for p in files), [p.name for p in files]


def test_auto_label_again_with_another_diameter_sets_nothing_aside(labelled_viewer, tmp_path):
    """Auto-label, then Auto-label again with another nucleus diameter: every nucleus the new
    detection lacked was counted as "added or moved by hand?", the session file was set aside
    and a warning said so, though the user had edited nothing. Only neurons the user added or
    moved count: one added by hand still does."""
    from napari.utils.notifications import notification_manager

    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    folder = widget.session.path.parent
    files_before = sorted(p.name for p in folder.iterdir())
    widget.diameter_spin.setValue(5.0)
    before = len(notification_manager.records)
    assert widget.auto_label() is not None, widget.last_error
    said = [str(r.message) for r in notification_manager.records[before:]]
    assert not any("added or moved" in m for m in said), said
    assert sorted(p.name for p in folder.iterdir()) == files_before, "a session file was set aside"

    layer = widget.layer
    layer.add(layer.data[0] + np.array([0.0, 30.0, 30.0]))
    assert widget.session.by_hand.tolist() == [False] * (len(layer.data) - 1) + [True]
    widget.diameter_spin.setValue(3.0)
    before = len(notification_manager.records)
    assert widget.auto_label() is not None, widget.last_error
    said = [str(r.message) for r in notification_manager.records[before:]]
    assert any("1 neuron(s) you added, moved or brought" in m for m in said), said


def test_clearing_a_decision_while_re_label_runs_offers_the_machines_candidates_again(labelled_viewer):
    """Correct a neuron (candidate 2), click Re-label, and Clear that neuron while Re-label runs
    in the background (napari stays usable). Expected: the cleared neuron's automatic answer and
    Candidates are the machine's, as when Clear comes after Re-label ("the automatic name applies
    again"). Instead the cleared name comes back as its automatic name, with one candidate, the
    cleared name itself at 1.00 (the constraint Re-label was given), and the machine's own
    answer and top 3 are gone."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    session = widget.session
    f = layer.features
    auto_ids = set(f["auto_id"])
    k = next(i for i in range(len(session))
             if f["auto_id"][i] and f["cand_2"][i] and f["cand_2"][i] not in auto_ids)
    before = session.candidates(k)
    widget.pick_candidate(k, 2)
    name = session.user_id[k]
    widget.relabel(wait=False)
    widget.clear(k)  # on the GUI thread, before the job's result is delivered
    widget.wait()
    assert widget.last_error is None and session.status[k] == "auto"
    got = session.candidates(k)
    assert [c for c, _ in got] == [c for c, _ in before], (
        f"neuron {k} cleared of {name} during Re-label offers {got}, not the machine's {before}")


def test_the_candidates_dropdown_says_which_candidate_another_neuron_has_from_you(labelled_viewer):
    """Give neuron a the name that is neuron b's first candidate, then go to b. Expected: its
    Candidates dropdown says that this candidate is already yours elsewhere (disabled or marked
    with the neuron that has it), as giving it is refused ("clear it there first"). Instead the
    dropdown offers it like any other, with its probability; choosing it only gets an error."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    session = widget.session
    f = layer.features
    b = next(i for i in range(len(session)) if f["cand_1"][i] and f["cand_2"][i])
    name = f["cand_1"][b]
    a = next(i for i in range(len(session))
             if i != b and session.auto_id[i] != name and name not in [c for c, _ in session.candidates(i)])
    widget.assign(a, name)
    widget.select_neuron(b)
    combo = widget.candidate_combo
    text = combo.itemText(0)
    assert text.startswith(f"1. {name}")
    enabled = combo.model().item(0).isEnabled()
    assert not enabled or f"neuron {a}" in text or "taken" in text.lower(), (
        f"the dropdown offers {text!r} although neuron {a} has {name} from the user")


def test_a_confidence_shown_at_the_threshold_is_not_hidden_as_below_it(labelled_viewer):
    """The review box and the list show each automatic confidence to two decimals, and the
    threshold slider reads two decimals. Expected: a name whose confidence reads as the
    threshold (0.50 at 0.50) is shown, or its confidence is not written as reaching the
    threshold. Instead a confidence of e.g. 0.4956 reads "0.50" in the review box and the list
    while the threshold reads 0.50, and its name is hidden (grey ring, "(no name shown)")."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    session = widget.session
    conf = session.auto_conf
    # a named neuron whose confidence rounds up to two decimals, its name otherwise shown
    widget.set_threshold(0.0)
    shown = session.auto_shown()
    i = next(j for j in np.argsort(-conf) if shown[j] and session.auto_id[j]
             and 0.05 < conf[j] < 0.95 and round(conf[j], 2) > conf[j] + 1e-9)
    i = int(i)
    widget.set_threshold(round(conf[i], 2))
    widget.select_neuron(i)
    assert widget.threshold_label.text() == f"{conf[i]:.2f}"
    row = session.review_order().index(i)
    listed = float(widget.neuron_table.item(row, 2).text())
    boxed = widget.current_label.text()
    hidden = not session.auto_shown()[i]
    assert not (hidden and listed >= widget.threshold), (
        f"neuron {i}: confidence {conf[i]:.4f} listed as {listed:.2f} and shown in the box as {boxed!r} "
        f"at threshold {widget.threshold:.2f}, yet its name is hidden as below the threshold")


def test_the_candidates_dropdown_with_several_neurons_selected_names_none_of_them(labelled_viewer):
    """Go to a neuron, then box-select several others and choose a name in the Candidates
    dropdown. Expected: as with the keys, the Name field and the Accept/Unsure/Clear buttons, a
    message asks to click the one to name, and no neuron is named. Instead the dropdown names the
    neuron shown last, which is none of those selected."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    session = widget.session
    shown_last = next(i for i in range(3, len(session)) if session.candidates(i))
    widget.select_neuron(shown_last)
    layer.selected_data = {0, 1, 2}
    widget.candidate_combo.activated.emit(0)
    assert set(session.status) == {"auto"}, (
        f"neuron {session.status.index(next(s for s in session.status if s != 'auto'))} was named "
        "with neurons 0, 1 and 2 selected")


def test_a_decision_cleared_while_auto_label_runs_again_does_not_come_back(labelled_viewer):
    """Accept a neuron, click Auto-label again (a new detection, in the background), and Clear
    that neuron while it runs. Expected: the new session has no decision there (decisions made
    while the job ran are kept, so one undone while it ran stays undone). Instead the cleared
    decision comes back from the snapshot taken when the job started: shown, autosaved, and
    not undoable (the new session's history is empty)."""
    viewer, widget = labelled_viewer
    widget.auto_label()
    session = widget.session
    k = next(i for i in range(len(session)) if session.auto_id[i])
    widget.accept(k)
    widget.auto_label(wait=False)
    widget.clear(k)  # on the GUI thread, before the job's result is delivered
    assert session.decisions() == {}
    widget.wait()
    assert widget.last_error is None and widget.session is not session
    assert widget.session.decisions() == {}, (
        f"the decision cleared while Auto-label ran is back: {widget.session.decisions()}")


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
    assert len(widget.session) == n + 1 and len(json.loads(session_a.path.read_text())["neurons"]["x_um"]) == n + 1


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
    widget.identifier = _Slow(widget.identifier, seconds=1.5)
    widget.auto_label(wait=False)
    layer.add(np.asarray(layer.data)[0] + np.array([0.0, 8.0, 8.0]))
    added_um = widget.session.table.xyz[-1].copy()
    assert widget.session.by_hand[-1] and len(json.loads(path.read_text())["neurons"]["x_um"]) == len(widget.session)  # followed and saved
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
    widget.identifier = _Slow(widget.identifier, seconds=1.5)
    widget.auto_label(wait=False)
    widget.accept(k)
    assert json.loads(path.read_text())["neurons"]["status"][k] == "accepted"  # autosaved
    viewer.layers.remove(layer)
    widget.wait()
    assert widget.last_error is None, widget.last_error
    files = sorted(path.parent.iterdir())
    assert any("accepted" in json.loads(p.read_text())["neurons"]["status"] for p in files), \
        f"the accept made while Auto-label ran is in no session file ({[p.name for p in files]})"


def _gate(monkeypatch):
    """label_neurons held until ``go`` is set (``reached`` once the job got there), so that the
    user can act while the job runs; the widget's warm-up passes through."""
    import napari_fdlc.identify as identify

    reached, go = threading.Event(), threading.Event()
    original = identify.label_neurons

    def gated(table, *args, **kwargs):
        if table.source != "warm-up":
            reached.set()
            go.wait(30)
        return original(table, *args, **kwargs)

    monkeypatch.setattr(identify, "label_neurons", gated)
    return reached, go


def test_a_voxel_size_set_while_auto_label_runs_does_not_leave_the_neurons_off_their_nuclei(labelled_viewer,
                                                                                             monkeypatch):
    """The voxel-size row stays usable while Auto-label runs. Expected: Set is refused while the
    job runs, or the result is placed at the voxel size the image has when it comes in. Instead
    the job keeps the voxel size it read and the new neuron-ID layer is drawn at it: with z
    doubled the neurons lie at half their nuclei's depth, and Set is refused from then on
    ('holds neurons placed at this image's voxel size')."""
    viewer, widget = labelled_viewer
    reached, go = _gate(monkeypatch)
    widget.auto_label(wait=False)
    assert reached.wait(60)
    w = widget._chosen_images()["W"]
    z, y, x = (float(v) for v in w.scale[-3:])
    widget.voxel_edit.setText(f"{2 * z} {y} {x}")
    widget._gui(widget._on_voxel_entered)  # Set, while the job runs
    go.set()
    assert widget.wait(60)
    assert widget.layer is not None, widget.last_error
    assert np.allclose(widget.layer.scale[-3:], w.scale[-3:]), (
        f"neuron IDs drawn at voxel size {tuple(widget.layer.scale[-3:])}, the image at {tuple(w.scale[-3:])}")


def test_an_error_said_while_auto_label_runs_does_not_turn_its_success_into_a_failure(labelled_viewer):
    """While Auto-label runs, the user presses Set on a mistyped voxel size ('abc'): refused,
    said. Expected: the run, which succeeds, ends as a success (bar full, ``auto_label()``
    returns the layer; last_error says the refusal). Instead the refusal is taken for the job's error:
    ``auto_label()`` returns None, ``last_error`` is the voxel-size message and the bar stays at
    0 % beside 'done: … neurons'."""
    from qtpy.QtCore import QTimer

    viewer, widget = labelled_viewer

    def mistyped():
        widget.voxel_edit.setText("abc")
        widget._gui(widget._on_voxel_entered)

    QTimer.singleShot(0, mistyped)  # while auto_label() waits for its job
    layer = widget.auto_label()
    assert widget.session is not None and len(widget.session) > 0  # the job did succeed
    assert layer is not None, widget.last_error
    assert "voxel size" in (widget.last_error or "")  # the refusal is still the last thing said
    assert widget.progress_bar.value() == 100, (widget.progress_bar.value(), widget.progress_bar.format())


def test_a_re_label_whose_result_is_dropped_does_not_say_done(labelled_viewer, monkeypatch):
    """Re-label runs; the user deletes a point meanwhile, so its result is dropped (a warning:
    'the neurons changed while re-labelling; run Re-label again'). Expected: the progress bar
    does not claim success (as for Auto-label in the same case: an error, bar at 0 %). Instead
    it reads 'done (100%)' and ``last_error`` is None, so ``relabel()`` returns the layer as if
    the names had been redone."""
    viewer, widget = labelled_viewer
    layer = widget.auto_label()
    widget.accept(widget.session.review_order()[-1])
    reached, go = _gate(monkeypatch)
    widget.relabel(wait=False)
    assert reached.wait(60)
    layer.selected_data = {0}
    layer.remove_selected()  # a false detection deleted while Re-label runs
    go.set()
    assert widget.wait(60)
    assert not (widget.progress_bar.value() == 100 and widget.last_error is None), widget.progress_bar.format()


def test_the_session_line_follows_a_move_of_the_autosave_made_by_the_threshold_slider(
        make_napari_viewer, sample_files, identifier, templates, tmp_path, monkeypatch):
    """docs/gui.md 5: 'The widget shows the path under the export buttons'. The image's folder
    stops taking the session (read-only remount); the next save is the slider's, on release, and
    the session goes on in the user's data folder. Expected: the line under the export buttons
    names that file. Instead it still names the file beside the image, no longer written."""
    from napari_fdlc.review import ReviewSession

    path = tmp_path / "worm.ome.tif"
    shutil.copy(sample_files[0], path)
    viewer = make_napari_viewer()
    viewer.open(str(path), plugin="napari-fdlc")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    assert widget.auto_label() is not None, widget.last_error
    save = ReviewSession.save

    def read_only(self, p=None):
        if p is not None and Path(p).parent == tmp_path:
            raise OSError(errno.EROFS, "Read-only file system")
        return save(self, p)

    monkeypatch.setattr(ReviewSession, "save", read_only)
    slider = widget.threshold_slider
    slider.setSliderDown(True)  # dragged: saved on release
    slider.setValue(slider.value() + 10)
    slider.setSliderDown(False)
    moved = widget.session.path
    assert moved.parent != tmp_path and moved.is_file()
    assert str(moved) in widget.session_label.text(), widget.session_label.text()


def _template_with(table: NeuronTable, name: str) -> NeuronTable:
    names = np.array(table.names, dtype=object).copy()
    names[int(np.flatnonzero(names != "")[0])] = name
    return NeuronTable(table.xyz, dict(table.colours), names)


def test_names_of_a_template_file_are_offered_by_the_name_field_at_once(make_napari_viewer, templates, tmp_path):
    """docs/gui.md 4: the Name field completes 'over the known neuron names', a labelled table
    file's included. Expected: once Labelled table file… has added it, its names are offered.
    Instead the completer's list is only rebuilt by a later edit (_refresh_all), so a name only
    that file has is not offered (a neuron clicked and a name typed is no edit)."""
    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    path = tmp_path / "my_worm.csv"
    write_table(_template_with(templates[0], "MYNEURONL").to_dataframe(), path)
    widget.add_template_file(path)
    assert "MYNEURONL" in widget._completer.model().stringList()


def test_names_of_templates_given_by_script_are_offered_by_the_name_field_at_once(make_napari_viewer, templates):
    """As above for ``w.set_templates([...])`` (docs/gui.md 7): expected its names in the Name
    field's completer; they are not, until a later edit."""
    viewer = make_napari_viewer()
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.set_templates([_template_with(templates[0], "OTHERNEURONR")])
    assert "OTHERNEURONR" in widget._completer.model().stringList()
