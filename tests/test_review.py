"""The Qt-free review state behind the Auto-label widget (napari_fdlc.review)."""

from __future__ import annotations

import json
import os

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.match import make_labelling
from napari_fdlc.review import (
    SESSION_SUFFIX,
    ReviewSession,
    find_session,
    session_file_for,
    user_session_dir,
)
from napari_fdlc.table import NeuronTable, read_table

NAMES = ["AVAL", "AVAR", "RMDL", "RMDR", "SMDVL"]
VOXEL = (1.0, 0.25, 0.25)


def _table(n: int = 4) -> NeuronTable:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(5, 40, (n, 3))
    colours = {c: rng.gamma(2.0, 100.0, n) for c in "RGBW"}
    return NeuronTable(xyz, colours, extra=pd.DataFrame({"radius_um": np.full(n, 1.5)}))


def _labelling(fixed=None):
    # neuron j most likely NAMES[j]; neuron 3 unsure between RMDR (0.4) and SMDVL (0.35)
    probs = np.array(
        [
            [0.90, 0.05, 0.02, 0.01, 0.01],
            [0.10, 0.70, 0.10, 0.05, 0.00],
            [0.05, 0.05, 0.60, 0.25, 0.00],
            [0.00, 0.00, 0.10, 0.40, 0.35],
        ]
    )
    return make_labelling(NAMES, probs, fixed=fixed)


@pytest.fixture(autouse=True)
def _session_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FDLC_SESSION_DIR", str(tmp_path / "user-data"))


@pytest.fixture
def session():
    return ReviewSession(_table(), _labelling(), threshold=0.5, voxel_size_zyx=VOXEL)


def test_initial_state_and_final_names(session):
    assert session.auto_id == ["AVAL", "AVAR", "RMDL", "RMDR"]
    assert session.status == ["auto"] * 4
    assert session.candidates(3) == [("RMDR", 0.4), ("SMDVL", 0.35), ("RMDL", 0.1)]
    # RMDR (0.4) is below the 0.5 threshold: hidden
    assert session.final_names() == ["AVAL", "AVAR", "RMDL", ""]
    assert session.coverage() == pytest.approx(0.75)
    session.set_threshold(0.3)
    assert session.final_names()[3] == "RMDR" and session.coverage() == 1.0
    session.set_threshold(0.95)
    assert session.coverage() == 0.0
    with pytest.raises(FdlcError):
        session.set_threshold(1.5)


def test_status_values(session):
    session.accept(0)
    assert (session.user_id[0], session.user_conf[0], session.status[0]) == ("AVAL", 1.0, "accepted")
    session.assign(1, "RMDL")
    assert session.status[1] == "corrected" and session.user_conf[1] == 1.0
    session.mark_unsure(3)
    assert (session.user_id[3], session.user_conf[3], session.status[3]) == ("RMDR", 0.5, "unsure")
    assert session.display_names()[3] == "RMDR?"
    # a user decision is shown whatever the threshold, and takes its name from the others
    session.set_threshold(0.99)
    assert session.final_names() == ["AVAL", "RMDL", "", "RMDR"]
    session.set_threshold(0.0)
    assert session.final_names()[2] == ""  # its automatic RMDL is now the user's name of neuron 1
    session.accept(3)  # an unsure decision made sure
    assert session.status[3] == "accepted" and session.user_conf[3] == 1.0
    session.assign(2, "SMDVL?")
    assert (session.user_id[2], session.user_conf[2], session.status[2]) == ("SMDVL", 0.5, "unsure")
    session.clear(2)
    assert (session.user_id[2], np.isnan(session.user_conf[2]), session.status[2]) == ("", True, "auto")
    session.assign(2, "smdvl?")  # typed in lower case: the vocabulary's spelling (it was a name of its own)
    assert (session.user_id[2], session.status[2]) == ("SMDVL", "unsure")
    session.assign(2, "avbl")  # no such name in the vocabulary: as typed
    assert session.user_id[2] == "avbl"


def test_pick_candidate_and_errors(session):
    session.pick_candidate(3, 2)
    assert session.user_id[3] == "SMDVL" and session.status[3] == "corrected"
    with pytest.raises(FdlcError, match="already the name of neuron 3"):
        session.assign(0, "SMDVL")
    with pytest.raises(FdlcError, match="no such row"):
        session.accept(17)
    with pytest.raises(FdlcError, match="give 1, 2 or 3"):
        session.pick_candidate(0, 4)
    with pytest.raises(FdlcError, match="not a neuron name"):
        session.assign(0, "AV AL")
    assert session.assign(0, "") is False  # clearing nothing is no edit


def test_accept_without_a_name():
    table = _table(2)
    lab = make_labelling(["AVAL"], np.array([[0.9], [0.0]]))
    s = ReviewSession(table, lab)
    assert s.auto_id == ["AVAL", ""]
    with pytest.raises(FdlcError, match="no automatic name"):
        s.accept(1)
    with pytest.raises(FdlcError, match="no name to mark unsure"):
        s.mark_unsure(1)


def test_undo_redo(session):
    session.accept(0)
    session.assign(1, "RMDR")
    session.mark_unsure(2)
    assert session.history() == ["accept AVAL for neuron 0", "name neuron 1 RMDR", "mark neuron 2 unsure (RMDL?)"]
    assert session.undo() == "mark neuron 2 unsure (RMDL?)"
    assert session.status == ["accepted", "corrected", "auto", "auto"]
    assert session.undo() and session.undo()
    assert session.status == ["auto"] * 4 and session.undo() is None
    assert session.redo() == "accept AVAL for neuron 0"
    assert session.status[0] == "accepted"
    session.clear(0)  # a new edit drops the redo branch
    assert not session.can_redo and session.redo() is None
    assert session.accept(0) and not session.accept(0)  # no-op edits are not recorded
    assert session.history()[-1] == "accept AVAL for neuron 0" and len(session.history()) == 3


def test_relabel_keeps_user_decisions(session):
    session.assign(2, "RMDR")
    session.accept(0)
    fixed = session.fixed()
    assert fixed == {0: "AVAL", 2: "RMDR"}
    session.set_labelling(_labelling(fixed=fixed), "re-label")
    assert session.user_id == ["AVAL", "", "RMDR", ""]
    assert session.status == ["accepted", "auto", "corrected", "auto"]
    assert session.auto_id[3] == "SMDVL"  # RMDR went to neuron 2: the correction propagated
    assert session.auto_id[2] == "RMDL"  # the machine's own answer for a decided row is kept
    assert session.history()[-1] == "re-label"
    session.undo()
    assert session.auto_id[3] == "RMDR" and session.history()[-1] == "accept AVAL for neuron 0"


def test_relabel_with_the_model_respects_fixed():
    torch = pytest.importorskip("torch")
    from napari_fdlc.identify import Identifier, label_neurons
    from napari_fdlc.model import CorrespondenceModel

    torch.manual_seed(0)
    rng = np.random.default_rng(3)
    n = 25
    xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 5]
    names = np.array([f"N{i}" for i in range(n)], dtype=object)
    template = NeuronTable(xyz, labels=names)
    test = NeuronTable(xyz + rng.normal(0, 0.3, xyz.shape))
    ident = Identifier(CorrespondenceModel({"layers": 1, "dim": 32}), device="cpu")
    s = ReviewSession(test, label_neurons(test, [template], use_colour=False, identifier=ident))
    s.assign(0, "N7")
    s.mark_unsure(1)
    fixed = s.fixed()
    lab = label_neurons(test, [template], use_colour=False, fixed=fixed, identifier=ident)
    s.set_labelling(lab, "re-label")
    assert s.user_id[0] == "N7" and s.status[0] == "corrected"
    assert s.status[1] == "unsure"
    others = [a for j, a in enumerate(s.auto_id) if j not in fixed]
    assert "N7" not in others and fixed[1] not in others


def test_navigation_lowest_confidence_first(session):
    assert session.review_order() == [3, 2, 1, 0]
    assert session.next_neuron() == 3
    assert session.next_neuron() == 2
    assert session.previous_neuron() == 3
    assert session.previous_neuron() == 0  # wraps
    assert session.current == 0
    events = []
    session.connect(lambda kind, rows: events.append((kind, rows)))
    session.select(2)
    assert events == [("current", [2])]


def test_autosave_every_edit_and_restore(tmp_path):
    image = tmp_path / "worm.tif"
    image.write_bytes(b"II*\x00")
    path = session_file_for(image)
    assert path == tmp_path / ("worm.tif" + SESSION_SUFFIX)
    s = ReviewSession(_table(), _labelling(), voxel_size_zyx=VOXEL, image=str(image), path=path)
    s.set_threshold(0.3)
    s.accept(0)
    saved = json.loads(path.read_text())
    assert saved["neurons"]["status"][0] == "accepted" and saved["threshold"] == 0.3
    s.assign(1, "RMDL?")
    # nothing else needed: the file is complete after every edit (as if napari were killed now)
    assert find_session(image) == path
    r = ReviewSession.load(path)
    assert r.user_id == s.user_id and r.status == s.status
    assert np.array_equal(r.user_conf, s.user_conf, equal_nan=True)
    assert r.auto_id == s.auto_id and np.allclose(r.auto_conf, s.auto_conf)
    assert r.candidates(3) == s.candidates(3) and r.review_order() == s.review_order()
    assert np.allclose(r.table.xyz, s.table.xyz) and np.allclose(r.table.colours["G"], s.table.colours["G"])
    assert r.threshold == 0.3 and r.voxel_size_zyx == VOXEL
    assert list(r.table.extra["radius_um"]) == [1.5] * 4
    r.clear(1)  # edits of the restored session go back to the same file
    assert ReviewSession.load(path).status[1] == "auto"
    assert not list(tmp_path.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_session_location_for_unwritable_and_packaged_images(tmp_path):
    import napari_fdlc

    packaged = os.path.join(os.path.dirname(napari_fdlc.__file__), "data", "sample.tif")
    p = session_file_for(packaged)
    assert p.parent == user_session_dir() and p.name.startswith("sample.tif-")
    assert session_file_for("sample:napari-fdlc").parent == user_session_dir()
    assert session_file_for(packaged) != session_file_for(str(tmp_path / "data" / "sample.tif"))
    # a folder that cannot be written: the session goes to the user's data folder on first save
    folder = tmp_path / "ro"
    folder.mkdir()
    image = folder / "w.tif"
    s = ReviewSession(_table(), _labelling(), image=str(image), path=folder / "missing" / "x.json")
    (folder / "missing").write_text("a file where the folder should be")
    s.accept(0)
    assert s.path.parent == user_session_dir() and s.path.is_file()
    assert ReviewSession.load(s.path).status[0] == "accepted"
    assert find_session(image) == s.path


def test_damaged_session_file(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text("{not json")
    with pytest.raises(FdlcError, match="unreadable session"):
        ReviewSession.load(bad)
    bad.write_text(json.dumps({"format": "something else"}))
    with pytest.raises(FdlcError, match="not a napari-fdlc session"):
        ReviewSession.load(bad)


def test_export_fdlc_csv(tmp_path, session):
    session.accept(0)
    session.pick_candidate(3, 2)
    session.mark_unsure(1)
    out = session.export(tmp_path / "ids.csv")
    df = pd.read_csv(out, keep_default_na=False)
    assert list(df["label"]) == ["AVAL", "AVAR?", "RMDL", "SMDVL"]
    assert list(df["status"]) == ["accepted", "unsure", "auto", "corrected"]
    assert list(df["user_id"]) == ["AVAL", "AVAR", "", "SMDVL"]
    assert list(df["user_conf"].astype(str)) == ["1", "0.5", "", "1"]
    for c in ["auto_id", "auto_conf", "cand_1", "cand_2", "cand_3", "prob_1", "prob_2", "prob_3", "radius_um", "R", "W"]:
        assert c in df.columns
    t = session.table
    assert np.allclose(df["x_px"], t.xyz[:, 0] / 0.25, atol=1e-4)
    assert np.allclose(df["z_px"], t.xyz[:, 2] / 1.0, atol=1e-4)
    # a neuron table like any other: names and unsure marks survive read_table
    back = read_table(out)
    assert list(back.labels) == ["AVAL", "AVAR", "RMDL", "SMDVL"] and list(back.label_conf) == [1, 0.5, 1, 1]
    with pytest.raises(FdlcError, match="already exists"):
        session.export(out)
    session.clear(0)
    session.export(out, overwrite=True)
    assert pd.read_csv(out, keep_default_na=False)["status"][0] == "auto"
    with pytest.raises(FdlcError, match="format"):
        session.export(tmp_path / "x.csv", format="xls")


def test_export_neuropal_id(tmp_path, session):
    session.accept(0)
    session.mark_unsure(1)
    out = session.export(tmp_path / "npid.csv", format="neuropal_id")
    df = pd.read_csv(out, skiprows=6, keep_default_na=False)
    assert list(df["User ID"]) == ["AVAL", "AVAR", "", ""]
    assert [float(x) for x in df["User Confidence"]] == [1.0, 0.5, 0.0, 0.0]
    assert list(df["Auto ID"]) == ["AVAL", "AVAR", "RMDL", ""]  # RMDR (0.4) is below the threshold: not shown
    t = session.table
    assert np.allclose(df["Internal X (px)"].astype(float), t.xyz[:, 0] / 0.25 + 1, atol=1e-2)
    assert np.allclose(df["Internal Z (slice)"].astype(float), t.xyz[:, 2] + 1, atol=1e-2)
    back = read_table(out)
    assert list(back.labels) == ["AVAL", "AVAR", "", ""] and back.label_conf[1] == 0.5


def test_replace_table_after_points_edited(session):
    session.accept(0)
    session.assign(2, "SMDVL")
    t = session.table
    new = NeuronTable(np.vstack([t.xyz[[0, 2, 3]], [[1, 2, 3]]]), {c: np.append(v[[0, 2, 3]], 0) for c, v in t.colours.items()})
    session.replace_table(new, [0, 2, 3, None])
    assert len(session) == 4
    assert session.status == ["accepted", "corrected", "auto", "auto"]
    assert session.user_id[:2] == ["AVAL", "SMDVL"] and session.auto_id[3] == ""
    session.undo()
    assert session.table is t and session.status[2] == "corrected"


def test_carry_decisions_to_a_new_detection(session):
    from napari_fdlc.review import carry_decisions

    session.accept(0)
    session.assign(2, "SMDVL?")
    t = session.table
    # new detection: neurons in another order, one moved 1 µm, neuron 0 lost
    new_xyz = np.vstack([t.xyz[2] + [1.0, 0, 0], t.xyz[1], t.xyz[3], [[90, 90, 9]]])
    carried = carry_decisions(session, new_xyz)
    assert set(carried) == {0} and carried[0].name == "SMDVL" and carried[0].status == "unsure"
    new = ReviewSession(NeuronTable(new_xyz), _labelling())
    new.seed_decisions(carried)
    assert new.status == ["unsure", "auto", "auto", "auto"] and new.user_conf[0] == 0.5
    assert not new.can_undo  # a starting state, not an edit
    assert new.auto_id[0] == "RMDL"  # the machine's answer of the carried row


def test_a_replaced_session_file_is_set_aside_not_lost(tmp_path, session):
    from napari_fdlc.review import SESSION_SUFFIX, set_aside

    session.accept(0)
    path = session.save(tmp_path / f"worm.tif{SESSION_SUFFIX}")
    assert set_aside(tmp_path / f"other.tif{SESSION_SUFFIX}") is None  # nothing there
    first = set_aside(path)
    path.write_text("{}")
    second = set_aside(path)  # twice within a second: another name
    assert not path.exists() and first != second
    assert first.name.startswith("worm.tif.fdlc-session.") and first.suffix == ".json"
    assert ReviewSession.load(first).status[0] == "accepted" and second.read_text() == "{}"
    assert find_session(tmp_path / "worm.tif") is None  # never restored by itself


def test_decisions_read_back_from_an_export(tmp_path, session):
    from napari_fdlc.review import decisions_from_frame

    session.accept(0)
    session.pick_candidate(3, 2)
    session.mark_unsure(1)
    out = session.export(tmp_path / "ids.csv")
    d = decisions_from_frame(pd.read_csv(out, keep_default_na=False))
    assert {i: (x.name, x.status) for i, x in d.items()} == {0: ("AVAL", "accepted"), 1: ("AVAR", "unsure"), 3: ("SMDVL", "corrected")}
    assert d[3].auto_id == "RMDR"


def test_a_lone_question_mark_marks_the_current_name_unsure(session):
    """Typing `?` alone (meaning "unsure") cleared a correction, silently."""
    session.assign(2, "AVAR")
    session.assign(2, "?")
    assert (session.user_id[2], session.status[2]) == ("AVAR", "unsure")


def test_a_neuropal_id_export_shows_each_name_once(tmp_path, session):
    """A name typed on neuron 3 that neuron 0 had automatically: the NeuroPAL_ID export still gave
    neuron 0 that Auto ID, and NeuroPAL_ID (which shows the Auto ID where there is no User ID)
    showed the name twice; the widget shows it once."""
    session.assign(3, "AVAL")
    df = pd.read_csv(session.export(tmp_path / "npid.csv", format="neuropal_id"), skiprows=6, keep_default_na=False)
    shown = [u or a for u, a in zip(df["User ID"], df["Auto ID"])]
    assert shown == [n.rstrip("?") for n in session.display_names()]


def test_a_colour_without_reading_stays_empty_in_the_export_and_the_session_file(tmp_path):
    """A neuron whose colour cell was empty: the export and the session file wrote the median the
    model used in its place, a reading made up. Both keep it empty, and a session read back
    still knows the gap."""
    table = _table()
    table = NeuronTable(table.xyz, {**table.colours, "G": np.array([1.0, np.nan, 3.0, 4.0])}, extra=table.extra)
    s = ReviewSession(table, _labelling(), voxel_size_zyx=VOXEL, path=tmp_path / "s.json")
    out = s.export(tmp_path / "ids.csv")
    assert pd.read_csv(out)["G"].isna().tolist() == [False, True, False, False]
    s.save()
    back = ReviewSession.load(tmp_path / "s.json")
    assert back.table.colour_gaps["G"].tolist() == [False, True, False, False]
    assert back.table.colours["G"][1] == 3.0


def test_neurons_added_or_moved_by_hand_are_remembered(tmp_path):
    """A new detection (Auto-label again) may lack a neuron: lost work only when the user added or
    moved it. The session keeps which (through undo and its file); a file that does not say
    counts every neuron as possibly made by hand."""
    table = _table()
    s = ReviewSession(table, _labelling(), path=tmp_path / "s.json")
    assert s.by_hand.tolist() == [False] * 4
    xyz = np.vstack([table.xyz, [[1.0, 2.0, 3.0]]])
    xyz[1] += 0.5
    s.replace_table(NeuronTable(xyz, {}), [0, 1, 2, 3, None], "add")
    assert s.by_hand.tolist() == [False, True, False, False, True]
    s.replace_table(NeuronTable(xyz[[1, 2, 4]], {}), [1, 2, 4], "remove")
    assert s.by_hand.tolist() == [True, False, True]
    s.save()
    assert ReviewSession.load(tmp_path / "s.json").by_hand.tolist() == [True, False, True]
    s.undo()
    assert s.by_hand.tolist() == [False, True, False, False, True]
    d = json.loads((tmp_path / "s.json").read_text())
    del d["by_hand"]
    (tmp_path / "old.json").write_text(json.dumps(d))
    assert ReviewSession.load(tmp_path / "old.json").by_hand.all()


def test_review_neuropal_export_leaves_a_colour_gap_empty(gap_table, tmp_path):
    """A neuron without an R reading, in a review session exported as a NeuroPAL_ID CSV,
    should have its 'Z-Scored Red' cell empty (as the fdlc export and write_neuropal_id do
    since session 35). ReviewSession.export builds a new NeuronTable from the filled
    ``t.colours``, so the gap is lost and the volume's median is written as a measurement."""
    from napari_fdlc.review import ReviewSession

    session = ReviewSession(gap_table)
    out = session.export(tmp_path / "npid.csv", format="neuropal_id")
    back = read_table(out)
    assert "R" in back.colour_gaps and back.colour_gaps["R"][3], "the gap came back as a reading"


def test_a_hand_added_neuron_cleared_while_re_label_ran_is_not_offered_its_name_at_1():
    """ReviewSession.set_labelling(fixed_rows=...): "the rows whose names were fixed when the
    labelling was made keep the machine's earlier answer even if their decision has been
    cleared since" (a cleared decision must not leave "only its name at 1.00 as candidate").
    A neuron added by hand has no earlier answer: _apply_labelling keeps its (empty) auto_id
    but, finding no earlier candidates, takes the labelling's, which at a fixed row is the
    user's name at 1.0. Expected: the cleared neuron is not offered the cleared name as the
    machine's sure candidate. Instead candidates(3) == [('RMDR', 0.999999999)]."""
    from test_review import VOXEL, _labelling, _table

    from napari_fdlc.review import ReviewSession

    session = ReviewSession(_table(), _labelling(), threshold=0.5, voxel_size_zyx=VOXEL)
    t = session.table
    added = NeuronTable(np.vstack([t.xyz[[0, 1, 2]], [[1.0, 2.0, 3.0]]]),
                        {c: np.append(v[[0, 1, 2]], 0) for c, v in t.colours.items()},
                        extra=pd.DataFrame({"radius_um": np.full(4, 1.5)}))
    session.replace_table(added, [0, 1, 2, None])  # neuron 3 added by hand
    session.assign(3, "RMDR")
    fixed = session.fixed()  # Re-label starts with RMDR fixed at neuron 3
    session.clear(3)  # cleared while it runs
    session.set_labelling(_labelling(fixed=fixed), "re-label", fixed_rows=fixed)
    cands = session.candidates(3)
    assert not (cands and cands[0][0] == "RMDR" and cands[0][1] > 0.99), (
        f"the cleared name is offered as the machine's sure answer: {cands}")
