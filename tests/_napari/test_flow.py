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
    assert f"({layer.features['prob_1'][e]:.2f})" in items[0]
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
