"""Defect hunt: the review side of the Auto-label widget (threshold, candidates, Name field,
buttons and keys, the neuron list, selection, exports and their default paths, points edited by
hand). Each test fails on the code it was written against; its docstring says expected vs actual."""

from __future__ import annotations

import numpy as np
import pandas as pd

from napari_fdlc.table import write_table


def _press(viewer, key):
    assert viewer.window._qt_viewer._key_map_handler.press_key(key), f"key {key} not bound"


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
