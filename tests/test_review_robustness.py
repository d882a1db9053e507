"""napari_fdlc.review under damage and misuse (sessions, autosave, set-aside files, export); each
test came from a review (session 27).

Each test asserts the behaviour the project promises (docs/gui.md §5-6, review.py's docstrings):
annotations are never lost, a bad session file is one FdlcError line, exports read back.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.match import make_labelling
from napari_fdlc.review import (
    Decision,
    ReviewSession,
    SESSION_SUFFIX,
    carry_decisions,
    find_session,
    session_file_for,
    set_aside,
)
from napari_fdlc.table import NeuronTable, UNSURE_CONF, read_table
from napari_fdlc.review import decisions_from_frame

NAMES = ["AVAL", "AVAR", "RMDL", "RMDR", "SMDVL"]
VOXEL = (1.0, 0.25, 0.25)
# neuron j most likely NAMES[j]; neuron 2's second choice is AVAR, so that once neuron 1 is
# fixed to RMDL, a re-labelling gives AVAR to neuron 2.
PROBS = np.array(
    [
        [0.90, 0.05, 0.02, 0.01, 0.01],
        [0.10, 0.70, 0.10, 0.05, 0.00],
        [0.05, 0.30, 0.60, 0.05, 0.00],
        [0.00, 0.00, 0.10, 0.50, 0.35],
    ]
)


def _table(n: int = 4) -> NeuronTable:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(5, 40, (n, 3))
    colours = {c: rng.gamma(2.0, 100.0, n) for c in "RGBW"}
    return NeuronTable(xyz, colours, extra=pd.DataFrame({"radius_um": np.full(n, 1.5)}))


def _session(**kwargs) -> ReviewSession:
    return ReviewSession(_table(), make_labelling(NAMES, PROBS), voxel_size_zyx=VOXEL, **kwargs)


@pytest.fixture(autouse=True)
def _session_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FDLC_SESSION_DIR", str(tmp_path / "user-data"))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")


def _write_session(tmp_path, d: dict):
    path = tmp_path / "s.fdlc-session.json"
    path.write_text(json.dumps(d), encoding="utf-8")
    return path


def _assert_unique_final_names_read_back(session: ReviewSession, out) -> None:
    shown = [n for n in session.final_names() if n]
    assert len(shown) == len(set(shown)), f"a name is shown on two neurons: {session.final_names()}"
    back = read_table(session.export(out))
    assert list(back.labels) == session.final_names()


# ---------------------------------------------------------------------------------------------
# 1. Clearing a decision brings back the machine's *old* answer, which the re-labelling (or the
#    new labelling a decision was carried into) has meanwhile given to another neuron: two
#    neurons show the same name, and the export read back loses both.


def test_clearing_a_decision_after_relabel_never_shows_a_name_twice(tmp_path):
    s = _session(threshold=0.2)
    s.assign(1, "RMDL")  # neuron 1's automatic answer AVAR is kept in auto_id
    s.set_labelling(make_labelling(NAMES, PROBS, fixed=s.fixed()), "re-label")  # AVAR goes to neuron 2
    s.clear(1)
    _assert_unique_final_names_read_back(s, tmp_path / "ids.csv")


def test_clearing_a_carried_decision_never_shows_a_name_twice(tmp_path):
    old = _session(threshold=0.2)
    old.assign(1, "RMDL")
    carried = carry_decisions(old, old.table.xyz)
    fixed = {i: d.name for i, d in carried.items()}
    new = ReviewSession(_table(), make_labelling(NAMES, PROBS, fixed=fixed), threshold=0.2, voxel_size_zyx=VOXEL)
    new.seed_decisions(carried)  # restores the old machine answer AVAR on neuron 1
    new.clear(1)
    _assert_unique_final_names_read_back(new, tmp_path / "ids.csv")


# ---------------------------------------------------------------------------------------------
# 2. One failed autosave beside the image moves the session to the user's data folder for good,
#    but find_session (what reopening the image restores) still prefers the stale file beside
#    the image: the later decisions are not restored.


def test_after_a_failed_autosave_reopening_restores_the_latest_decisions(tmp_path, monkeypatch):
    image = tmp_path / "worm.tif"
    image.write_bytes(b"II*\x00")
    path = session_file_for(image)
    s = _session(image=str(image), path=path)
    s.accept(0)
    real_replace = os.replace
    failing = {"on": True}

    def replace(src, dst):
        if failing["on"] and os.fspath(dst) == os.fspath(path):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    s.accept(1)  # disk full for a moment
    failing["on"] = False
    s.accept(2)
    found = find_session(image)
    assert found is not None
    restored = ReviewSession.load(found)
    assert restored.status == s.status == ["accepted", "accepted", "accepted", "auto"]


# ---------------------------------------------------------------------------------------------
# 3. Damaged session files: one FdlcError line, never a traceback (the widget only catches
#    FdlcError when it reads the saved session of an image).


@pytest.mark.parametrize("version", ["x", None, [2], "1.5", {"major": 1}])
def test_session_file_with_a_garbage_version_is_an_fdlc_error(tmp_path, version):
    d = _session().to_dict()
    d["version"] = version
    with pytest.raises(FdlcError):
        ReviewSession.load(_write_session(tmp_path, d))


def test_deeply_nested_garbage_session_file_is_an_fdlc_error(tmp_path):
    path = tmp_path / "s.fdlc-session.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(FdlcError):
        ReviewSession.load(path)


def _load_and_export(tmp_path, d: dict) -> None:
    """Loading may refuse the file (FdlcError); a loaded session must export (or refuse) in one line."""
    try:
        s = ReviewSession.load(_write_session(tmp_path, d))
    except FdlcError:
        return
    for fmt in ("fdlc", "neuropal_id"):
        try:
            s.export(tmp_path / f"out_{fmt}.csv", format=fmt)
        except FdlcError:
            pass


def test_session_file_with_a_voxel_size_of_two_values(tmp_path):
    d = _session().to_dict()
    d["voxel_size_zyx"] = [1.0, 0.25]
    _load_and_export(tmp_path, d)


def test_session_file_with_more_probabilities_than_neurons(tmp_path):
    d = _session().to_dict()
    for k in (1, 2, 3):
        d["neurons"][f"prob_{k}"] = d["neurons"][f"prob_{k}"] + [0.1]
    _load_and_export(tmp_path, d)


# ---------------------------------------------------------------------------------------------
# 4. A session file that must be set aside but cannot be renamed (read-only folder): a raw
#    PermissionError (the widget reports "unexpected error ... please report it").


def test_set_aside_in_a_read_only_folder_is_an_fdlc_error_and_keeps_the_file(tmp_path, monkeypatch):
    s = _session()
    s.accept(0)
    path = s.save(tmp_path / "worm.tif.fdlc-session.json")
    before = path.read_text()

    def replace(src, dst):
        raise PermissionError(errno.EACCES, "Permission denied", os.fspath(src))

    monkeypatch.setattr(os, "replace", replace)
    try:
        set_aside(path)
    except FdlcError:
        pass
    assert path.read_text() == before


# ---------------------------------------------------------------------------------------------
# 5. Autosave only catches OSError: a settings value JSON cannot hold makes every edit raise,
#    and the file is no longer updated (nor is a save error reported).


@pytest.mark.parametrize("value", [np.int64(3), float("nan")], ids=["numpy-int", "nan"])
def test_autosave_never_raises_out_of_an_edit(tmp_path, value):
    path = tmp_path / "worm.tif.fdlc-session.json"
    s = _session(path=path)
    s.settings["value"] = value  # settings are documented as free-form
    s.accept(0)  # must not raise
    saved = json.loads(path.read_text()) if path.exists() else None
    assert (saved is not None and saved["neurons"]["status"][0] == "accepted") or s.last_save_error


# ---------------------------------------------------------------------------------------------
# 6. NaN confidences: _same compares auto_conf / cand_p without equal_nan, so every no-op edit
#    is recorded (undo history grows, autosave runs, methods return True).


def test_no_op_edits_with_a_nan_confidence_are_not_recorded():
    lab = make_labelling(NAMES, PROBS)
    lab.auto_conf = np.array(lab.auto_conf, dtype=float)
    lab.auto_conf[1] = np.nan
    s = ReviewSession(_table(), lab)
    assert s.clear(2) is False  # nothing to clear
    assert s.accept(0) is True
    assert s.accept(0) is False  # already accepted
    assert s.history() == ["accept AVAL for neuron 0"]


# ---------------------------------------------------------------------------------------------
# 7. Exports that cannot be read back.


def test_export_of_a_session_without_neurons_is_refused_or_readable(tmp_path):
    s = ReviewSession(NeuronTable(np.zeros((0, 3))))
    for fmt in ("fdlc", "neuropal_id"):
        try:
            out = s.export(tmp_path / f"empty_{fmt}.csv", format=fmt)
        except FdlcError:
            continue
        read_table(out)  # written, so it must read back


def test_export_to_a_path_ending_in_a_separator_is_refused(tmp_path):
    s = _session()
    target = str(tmp_path / "results") + os.sep  # meant as a folder (as check_output reads it)
    with pytest.raises(FdlcError, match="folder"):
        s.export(target)
    assert not (tmp_path / "results").is_file()


def test_export_onto_the_sessions_own_file_is_refused(tmp_path):
    path = tmp_path / "worm.tif.fdlc-session.json"
    s = _session(path=path)
    s.assign(0, "AVAL")  # autosaved
    with pytest.raises(FdlcError, match="autosaves"):
        s.export(path, overwrite=True)
    assert ReviewSession.load(path).user_id[0] == "AVAL"  # the session file is intact


# ---------------------------------------------------------------------------------------------
# 8. One line per error.


def test_a_typed_name_with_a_line_break_gives_a_one_line_error():
    s = _session()
    with pytest.raises(FdlcError) as exc:
        s.assign(1, "AV\nAL")
    assert "\n" not in str(exc.value)


def test_a_name_the_machine_offers_can_be_accepted_as_written():
    """A template whose names are written unusually ("AVA L", "RMD,L") gave names that
    accept, pick_candidate and mark_unsure refused as "not a neuron name"."""
    names = ["AVA L", "RMD,L", "SMDVL"]
    probs = np.array([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]])
    s = ReviewSession(_table(3), make_labelling(names, probs))
    assert s.accept(0) and s.pick_candidate(1, 1) and s.mark_unsure(2)
    assert s.final_names() == names
    with pytest.raises(FdlcError):
        s.assign(2, "SMD VR")  # typed by hand: still checked


def test_a_row_or_candidate_that_is_not_a_whole_number_is_refused():
    """accept(1.7) acted on row 1, and pick_candidate(i, True) meant candidate 1."""
    s = _session()
    for call in (lambda: s.accept(1.7), lambda: s.accept(True), lambda: s.pick_candidate(0, True)):
        with pytest.raises(FdlcError):
            call()
    assert s.history() == []


def test_one_name_decided_twice_keeps_one_decision(tmp_path, capsys):
    """A hand-edited session file with one name decided for two neurons loaded both (the export
    read back then lost both), and seeding decisions did not check the session's own."""
    s = _session()
    s.assign(0, "AVAL")
    d = s.to_dict()
    d["neurons"]["user_id"][2], d["neurons"]["status"][2], d["neurons"]["user_conf"][2] = "AVAL", "corrected", 1.0
    loaded = ReviewSession.load(_write_session(tmp_path, d))
    assert loaded.user_id.count("AVAL") == 1 and "decided for neurons 0 and 2" in capsys.readouterr().err
    s.seed_decisions({3: Decision("AVAL", 1.0, "corrected")})
    assert s.user_id.count("AVAL") == 1


# ---------------------------------------------------------------------------------------------
# Session 30's review

# One path component longer than any file system allows (255 bytes): stat() on it fails with
# ENAMETOOLONG, which pathlib's exists()/is_file()/is_dir() re-raise (Python 3.11-3.13), just as
# they re-raise EACCES for a path inside a folder the user may not enter (not reproducible as root).
TOO_LONG = "w" * 300


@pytest.mark.parametrize(
    "damage",
    [
        '"extra": [1, 2]',
        '"extra": "radius_um"',
    ],
    ids=["extra-list", "extra-string"],
)
def test_a_damaged_session_file_is_one_fdlc_error_line(tmp_path, damage):
    """A damaged session file is one FdlcError line (the widget then sets it aside, docs/gui.md
    §5). An ``extra`` that is not an object (AttributeError) escaped as a traceback, and
    reopening the image failed. (An ``order`` with an infinite number is ignored since session
    36, as any order of the wrong kind.)"""
    d = _session().to_dict()
    key = damage.split(":")[0].strip('"')
    d.pop(key)
    text = json.dumps(d)[:-1] + ", " + damage + "}"
    path = tmp_path / "worm.tif.fdlc-session.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(FdlcError):
        ReviewSession.load(path)


def test_reopening_finds_the_session_when_the_file_beside_the_image_cannot_be_probed(tmp_path):
    """Where the file beside the image cannot be written (a name too long; a folder the user may
    not enter), the session goes to the user's data folder and is found there again; probing
    the path beside the image raised OSError, and the decisions were never restored."""
    image = tmp_path / (("w" * 236) + ".tif")  # 240 bytes: a valid file name
    image.write_bytes(b"II*\x00")
    s = _session(image=str(image), path=session_file_for(image))
    s.accept(0)  # beside the image fails (name too long): saved in the user's data folder
    assert s.path.is_file() and s.last_save_error is None
    assert find_session(image) == s.path


def test_export_to_a_path_that_cannot_be_written_is_an_fdlc_error(tmp_path):
    """An export path that cannot even be probed (ENAMETOOLONG, EACCES) is one FdlcError line;
    the checks before the write raised a raw OSError."""
    s = _session()
    s.accept(0)
    for fmt in ("fdlc", "neuropal_id"):
        with pytest.raises(FdlcError):
            s.export(tmp_path / (TOO_LONG + ".csv"), format=fmt)
        with pytest.raises(FdlcError):
            s.export(tmp_path / TOO_LONG / "ids.csv", format=fmt)


def test_a_session_whose_image_is_given_as_a_path_is_autosaved(tmp_path):
    """``image=Path(...)`` (the natural scripting call) is autosaved; the Path went into the
    JSON and every autosave failed silently ('not JSON serializable' in last_save_error)."""
    image = tmp_path / "worm.tif"
    image.write_bytes(b"II*\x00")
    path = session_file_for(image)
    s = _session(image=image, path=path)
    s.accept(0)
    assert s.last_save_error is None, s.last_save_error
    assert path.is_file() and ReviewSession.load(path).status[0] == "accepted"


def test_seeding_decisions_for_rows_the_table_lacks_changes_nothing(tmp_path):
    """Decisions for a row the table lacks are refused before any is set; the earlier rows used
    to be set in memory already (in no file, no undo step, no listener told)."""
    path = tmp_path / "worm.tif.fdlc-session.json"
    s = _session(path=path)
    s.accept(3)  # saved
    decisions = {0: Decision("AVAL", 1.0, "accepted"), 1: Decision("RMDL", 1.0, "corrected"), 7: Decision("AVAR", 1.0, "corrected")}
    with pytest.raises(FdlcError):
        s.seed_decisions(decisions)
    on_disk = ReviewSession.load(path)
    assert s.user_id == on_disk.user_id == ["", "", "", "RMDR"]


def test_a_session_folder_given_with_a_tilde_is_the_home_folder(tmp_path, monkeypatch):
    """``FDLC_SESSION_DIR=~/fdlc-sessions`` where no shell expands it (a conda env var, a quoted
    export) is the home folder's, wherever napari starts; it was ``./~/fdlc-sessions`` of the
    folder napari started from, and another start did not find the sessions."""
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("FDLC_SESSION_DIR", "~/fdlc-sessions")
    first, second = tmp_path / "started-here", tmp_path / "then-here"
    first.mkdir()
    second.mkdir()
    monkeypatch.chdir(first)
    s = _session(image="sample:neuropal", path=session_file_for("sample:neuropal"))
    s.accept(0)
    assert Path(s.path).is_absolute() and home in Path(s.path).parents
    monkeypatch.chdir(second)
    found = find_session("sample:neuropal")
    assert found is not None and ReviewSession.load(found).status[0] == "accepted"


def test_seeding_never_gives_a_name_held_by_the_sessions_own_decision_to_a_second_neuron(tmp_path):
    """A row given no decision to seed (status 'auto') keeps its own name, which stays held:
    AVAL, decided on neuron 0, was also given to neuron 2 without a warning."""
    s = _session()
    s.assign(0, "AVAL")
    s.seed_decisions({0: Decision("", float("nan"), "auto"), 2: Decision("AVAL", 1.0, "corrected")})
    named = [n for n in s.final_names() if n]
    assert s.user_id.count("AVAL") == 1 and len(named) == len(set(named)), s.final_names()


# ----- session 33's review ----------------------------------------------------------------------


def test_typing_a_double_question_mark_marks_unsure_instead_of_clearing_the_decision():
    """'??' typed in Name marks the current name unsure, as '?' does; it cleared the user's
    correction ('??' parses to no name, which means clear)."""
    s = _session()
    s.assign(2, "AVAR")  # a correction: the machine said RMDL
    s.assign(2, "??")
    assert (s.user_id[2], s.status[2]) == ("AVAR", "unsure")


def test_undoing_an_edit_made_before_seeding_keeps_the_seeded_decisions():
    """Seeded decisions are the starting state: the history restarts from them. Set in place,
    an undo of an earlier edit restored a state without them (the seeded decision lost)."""
    s = _session()
    s.assign(0, "SMDVL")
    s.seed_decisions({2: Decision("RMDL", 1.0, "accepted")})
    assert s.user_id == ["SMDVL", "", "RMDL", ""]
    assert s.undo() is None  # the history restarts from the seeded state
    assert s.user_id == ["SMDVL", "", "RMDL", ""], s.user_id


def test_neuropal_id_export_with_one_missing_colour_keeps_the_other_neurons_colours(tmp_path):
    """A neuron without a colour reading leaves its cell empty in the NeuroPAL_ID export; the
    channel's z-score was NaN for every neuron (read back, the channel was gone)."""
    t = _table()
    t.colours["R"][1] = np.nan
    s = ReviewSession(t, make_labelling(NAMES, PROBS), voxel_size_zyx=VOXEL)
    out = s.export(tmp_path / "npid.csv", format="neuropal_id")
    df = pd.read_csv(out, skiprows=6)
    red = df["Z-Scored Red"].to_numpy(dtype=float)
    assert np.isfinite(np.delete(red, 1)).all(), red
    back = read_table(out)
    assert "R" in back.colours  # the channel survives the round trip


def test_a_decision_exactly_at_the_carry_distance_is_carried():
    """A decision goes to a neuron re-detected exactly 1.5 µm away ('within 1.5 µm'): the
    KD-tree's bound is exclusive, and it was dropped."""
    old = ReviewSession(NeuronTable(np.array([[10.0, 10.0, 10.0], [30.0, 30.0, 30.0]])),
                        make_labelling(["AVAL", "AVAR"], np.array([[0.9, 0.05], [0.05, 0.9]])))
    old.accept(0)
    carried = carry_decisions(old, np.array([[10.0, 10.0, 11.5], [30.0, 30.0, 30.0]]))
    assert 0 in carried and carried[0].name == "AVAL", carried


def test_a_session_with_a_zero_voxel_size_is_refused_or_reloads(tmp_path):
    """A voxel size of 0 is refused when the session is made: it was autosaved with every edit,
    then its own file refused on loading (the decisions out of reach), and x_px exported inf."""
    path = tmp_path / "worm.tif.fdlc-session.json"
    try:
        s = ReviewSession(_table(), make_labelling(NAMES, PROBS), voxel_size_zyx=(0.0, 0.25, 0.25), path=path)
    except FdlcError:
        return  # refused up front: fine
    s.accept(0)
    assert path.is_file()
    assert ReviewSession.load(path).status[0] == "accepted"


def _write(tmp_path, d: dict, name: str = "worm.tif" + SESSION_SUFFIX, encoding: str = "utf-8"):
    path = tmp_path / name
    path.write_text(json.dumps(d), encoding=encoding)
    return path


def test_a_hand_edited_unsure_name_with_a_question_mark_is_not_lost(tmp_path):
    """A user who edits the session file and writes an unsure name the way every table and the
    Name box write it, ``RMDL?`` (docs/gui.md §4: "`AVAL?` means unsure"), must keep that decision.
    The file's ``user_id`` is taken literally: the name 'RMDL?' is shown as 'RMDL??', does not
    hold RMDL, so RMDL can be decided for a second neuron; the export then names two neurons
    RMDL and, read back, both decisions are gone (read_table drops repeated names)."""
    d = _session().to_dict()
    d["neurons"]["user_id"][1], d["neurons"]["status"][1], d["neurons"]["user_conf"][1] = "RMDL?", "unsure", 0.5
    s = ReviewSession.load(_write(tmp_path, d))
    try:
        s.accept(2)  # neuron 2's automatic name is RMDL: refused while neuron 1 holds it
    except FdlcError:
        pass
    labels = list(read_table(s.export(tmp_path / "ids.csv")).label_strings())
    assert "RMDL?" in labels, f"the unsure RMDL decision is lost: {labels}"


def _npid_shown(path) -> list[str]:
    """What NeuroPAL_ID shows per neuron: the User ID ('?' when unsure), else the Auto ID."""
    df = pd.read_csv(path, skiprows=6, keep_default_na=False, dtype=str)
    out = []
    for user, conf, auto in zip(df["User ID"], df["User Confidence"], df["Auto ID"]):
        if user:
            out.append(user + ("?" if float(conf) == UNSURE_CONF else ""))
        else:
            out.append(auto)
    return out


@pytest.mark.parametrize(
    "row, fields",
    [
        (2, {"user_id": "AVAR", "status": "auto", "user_conf": None}),  # a name typed, status left 'auto'
        (1, {"user_id": "AVAR", "status": "unsure", "user_conf": 1.0}),  # status set to unsure, confidence left 1
        (1, {"user_id": "", "status": "accepted", "user_conf": 1.0}),  # status set, no name
    ],
    ids=["name-without-status", "unsure-with-confidence-1", "status-without-name"],
)
def test_a_hand_edited_decision_is_shown_and_exported_alike(tmp_path, row, fields):
    """A session file whose decision fields disagree (``user_id``, ``status``, ``user_conf``
    edited by hand) is loaded without reconciling them, so the session shows one thing and the
    NeuroPAL_ID export says another: e.g. neuron 2 shows its automatic RMDL while the export
    gives it the User ID AVAR (and AVAR cannot be given to anyone: "already the name of neuron
    2"), or 'AVAR?' shown but exported as a sure AVAR. Expected: the file is refused as damaged,
    or loaded consistently, so that what the widget shows is what both exports say."""
    d = _session().to_dict()
    for key, value in fields.items():
        d["neurons"][key][row] = value
    try:
        s = ReviewSession.load(_write(tmp_path, d))
    except FdlcError:
        return  # refused as damaged: fine
    shown = s.display_names()
    fdlc = list(read_table(s.export(tmp_path / "ids.csv")).label_strings())
    npid = _npid_shown(s.export(tmp_path / "npid.csv", format="neuropal_id"))
    assert fdlc == shown and npid == shown, f"shown {shown}, fdlc CSV {fdlc}, NeuroPAL_ID {npid}"


def test_a_session_file_with_a_vocabulary_of_the_wrong_kind_never_raises_out_of_an_edit(tmp_path):
    """A session file's ``vocabulary`` holding numbers (hand-edited, or written by another tool)
    is accepted by load, and every later typed name then raises AttributeError ('int' object
    has no attribute 'lower', from _spelled_as_known): a traceback in napari on each Enter.
    Expected: refused as damaged (one FdlcError line) or ignored."""
    s = _session()
    s.accept(0)
    d = s.to_dict()
    d["vocabulary"] = [7, 8]
    try:
        r = ReviewSession.load(_write(tmp_path, d))
    except FdlcError:
        return
    r.assign(1, "RMDR")
    assert r.user_id[:2] == ["AVAL", "RMDR"]


def test_a_threshold_of_the_wrong_kind_does_not_keep_the_decisions_out_of_reach(tmp_path):
    """docs/gui.md §5: "A setting of the wrong kind in a session file is ignored, not a reason to
    leave the image closed." A ``threshold`` of null (what a JSON writer makes of NaN) or out of
    0-1 makes the whole file 'damaged': it is set aside and the decisions are not restored.
    Expected: the threshold falls back to the default and the decisions load."""
    s = _session()
    s.accept(0)
    for bad in (None, 5):
        d = s.to_dict()
        d["threshold"] = bad
        r = ReviewSession.load(_write(tmp_path, d))
        assert r.status[0] == "accepted" and 0.0 <= r.threshold <= 1.0


def test_a_session_file_with_a_missing_position_is_refused_or_exports_a_readable_table(tmp_path):
    """A session file with a position null (damaged, or hand-edited) loads as a neuron at NaN;
    its CSV export then has an empty x_um, which read_table (every fdlc command, this plugin)
    refuses: "line 2, column 'x_um': an empty cell is not a finite number". docs/gui.md §6
    promises the export reads back. Expected: the file refused as damaged (FdlcError) on load."""
    s = _session()
    s.accept(0)
    d = s.to_dict()
    d["neurons"]["x_um"][1] = None
    try:
        r = ReviewSession.load(_write(tmp_path, d))
    except FdlcError:
        return
    read_table(r.export(tmp_path / "ids.csv"))


def test_a_session_file_saved_with_a_byte_order_mark_loads(tmp_path):
    """A session file edited and saved in an editor that writes UTF-8 with a byte order mark
    (Windows Notepad) is refused as "unreadable session file (Unexpected UTF-8 BOM)"; napari
    then sets it aside and does not restore the decisions. Neuron tables accept the BOM
    (read_table reads utf-8-sig). Expected: the session loads."""
    s = _session()
    s.accept(0)
    path = _write(tmp_path, s.to_dict(), encoding="utf-8-sig")
    assert ReviewSession.load(path).status[0] == "accepted"


def test_a_session_made_as_the_module_docstring_shows_is_found_again_after_a_failed_save(tmp_path, monkeypatch):
    """review.py's docstring makes a session as ``ReviewSession(table, labelling,
    path=session_file_for("worm.tif"))`` (no ``image=``). When a save beside the image fails
    (disk full, a share remounted read-only), autosave goes on in the user's data folder under a
    name keyed by the *session file's* path, which find_session(image) never looks for: it
    returns the stale file beside the image, and reopening the image restores the earlier
    decisions only (later ones are lost to the user). Expected: find_session finds the latest."""
    image = tmp_path / "worm.tif"
    image.write_bytes(b"II*\x00")
    path = session_file_for(image)
    s = ReviewSession(_table(), make_labelling(NAMES, PROBS), path=path)
    s.accept(0)
    real_replace = os.replace

    def replace(src, dst):
        if os.fspath(dst) == os.fspath(path):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    s.accept(1)
    s.accept(2)
    monkeypatch.setattr(os, "replace", real_replace)
    assert s.last_save_error is None  # saved, in the user's folder
    found = find_session(image)
    assert found is not None and ReviewSession.load(found).status == s.status, (found, s.path)


def test_an_image_whose_file_name_is_not_utf8_has_a_session(tmp_path):
    """On Linux a file name in a legacy encoding (b'w\\xf6rm.tif', Latin-1) reaches Python with
    a surrogate ('w\\udcf6rm.tif'). find_session (what opening the image calls) raises a raw
    UnicodeEncodeError: user_session_file hashes the path with ``.encode('utf-8')``. Expected:
    None (no session yet) and, once saved beside the image, that file."""
    image = tmp_path / os.fsdecode(b"w\xf6rm.tif")
    image.write_bytes(b"II*\x00")
    assert find_session(image) is None
    s = _session(image=str(image), path=session_file_for(image))
    s.accept(0)
    assert find_session(image) == s.path


def test_set_aside_of_a_session_path_that_cannot_be_probed_is_none_or_an_fdlc_error(tmp_path):
    """set_aside returns None when there is no file, FdlcError when it cannot rename it. For the
    path session_file_for gives an image with a long name (beside it: the folder is writable, but
    the name is over 255 bytes) it raises a raw OSError (ENAMETOOLONG) from ``path.is_file()``,
    which the widget (catching FdlcError around set_aside) shows as a traceback."""
    image = tmp_path / ("w" * 240 + ".tif")
    image.write_bytes(b"II*\x00")
    path = session_file_for(image)
    try:
        assert set_aside(path) is None
    except FdlcError:
        pass


@pytest.mark.parametrize("kept", [[0, 0, 1, 2], [0, 1, 2, 9], [0, 1, 2, -1]], ids=["row-twice", "no-such-row", "negative"])
def test_replace_table_refuses_a_kept_list_that_is_not_one_old_row_per_new_neuron(kept):
    """``replace_table(table, kept)`` (public: "kept[j] is the old row of new row j") takes
    ``kept`` unchecked: an old row given twice copies its decision to two neurons (AVAL decided
    for neurons 0 and 1: "a name belongs to one neuron", and the export read back loses it), a
    row the table lacks raises a raw IndexError, and -1 silently copies the last row's
    decision. docs/gui.md §7: scripts get a core problem as an FdlcError; the session unchanged."""
    s = _session()
    s.accept(0)
    s.accept(3)
    t = s.table
    with pytest.raises(FdlcError):
        s.replace_table(NeuronTable(t.xyz), kept)
    assert s.user_id == ["AVAL", "", "", "RMDR"] and s.table is t


def test_undo_of_a_points_edit_of_the_same_length_keeps_the_current_neuron():
    """Points deleted and added in one edit (e.g. edits made with the dock closed, taken up as one
    undoable edit, docs/gui.md §4) keep the row count. replace_table moves ``current`` to the
    current neuron's new row; undo restores the old rows but leaves ``current`` at that row
    number (_after_history_move only resets it when the row count changed), so after Ctrl+Z the
    current neuron is another neuron and A/U/C act on it. Expected: after undo, ``current`` is
    the same neuron as before the edit (or None). Instead it is the neuron at old row 2."""
    s = _session()
    t = s.table
    s.select(3)
    before = t.xyz[3].copy()
    # neuron 0 deleted, a neuron added: old rows 1, 2, 3 become rows 0, 1, 2
    new = NeuronTable(np.vstack([t.xyz[[1, 2, 3]], [[1.0, 2.0, 3.0]]]),
                      {c: np.append(v[[1, 2, 3]], 50.0) for c, v in t.colours.items()})
    s.replace_table(new, [1, 2, 3, None])
    assert np.array_equal(s.table.xyz[s.current], before)  # followed to its new row
    s.undo()
    assert s.current is None or np.array_equal(s.table.xyz[s.current], before), (
        f"after undo the current neuron is row {s.current} at {s.table.xyz[s.current]}, not the one at {before}")


def test_decisions_from_a_frame_keep_a_name_written_unsure_as_unsure():
    """decisions_from_frame: a ``user_id`` written 'AVAL?' is an unsure decision (parse_name
    gives confidence 0.5), as a hand-edited session file's 'AVAL?' is (_agreeing_decisions: "a
    name written AVAL? is the name AVAL, unsure"). With the CSV's ``status`` column still
    saying 'corrected' (edited in a spreadsheet), the status column wins: the Decision is
    status 'corrected' with conf 0.5, and seed_decisions makes it a sure decision — the '?' is
    lost. Expected: status 'unsure'."""
    df = pd.DataFrame({"user_id": ["AVAL?", "", "", ""], "status": ["corrected", "auto", "auto", "auto"]})
    d = decisions_from_frame(df)
    assert d[0].status == "unsure", f"'AVAL?' read as {d[0]}"
    s = _session()
    s.seed_decisions(d)
    assert s.display_names()[0] == "AVAL?", f"seeded as {s.display_names()[0]!r} ({s.status[0]})"


@pytest.mark.parametrize("order", ["missing", [], [0, 1, 2]], ids=["missing", "empty", "short"])
def test_a_session_file_without_a_usable_order_reviews_lowest_confidence_first(tmp_path, order):
    """review_order(): "Rows ordered by automatic confidence, lowest first"; N / Shift+N go
    "lowest confidence first" (docs/gui.md §4). A labelled session file without ``order`` (older
    or hand-edited), or with one that is not a permutation of the rows, loads with the table's
    order (from_dict falls back to range(n)), so N walks the neurons in table order. Expected:
    the fallback is the confidence order the labelling gave, [3, 2, 1, 0] here."""
    s = _session()
    s.accept(0)
    expected = s.review_order()
    assert expected == [3, 2, 1, 0]
    d = s.to_dict()
    if order == "missing":
        del d["order"]
    else:
        d["order"] = order
    r = ReviewSession.load(_write(tmp_path, d))
    assert r.review_order() == expected, f"review order {r.review_order()}"


@pytest.mark.parametrize("order", [5, [None, 1, 2, 3], {"a": 1}], ids=["number", "null-entry", "object"])
def test_an_order_of_the_wrong_kind_does_not_keep_the_decisions_out_of_reach(tmp_path, order):
    """docs/gui.md §5: "A setting of the wrong kind in a session file is ignored, not a reason to
    leave the image closed" (a threshold of the wrong kind already falls back to the default).
    ``order`` is only the review sequence, and one that is not a permutation already falls back
    to a default; but an order that is a number, holds a null, or is an object makes the whole
    file 'damaged' (FdlcError: int() of None...), so it is set aside and its decisions are not
    restored. Expected: the file loads with the decisions, the order defaulted."""
    s = _session()
    s.accept(0)
    s.assign(1, "RMDL")
    d = s.to_dict()
    d["order"] = order
    r = ReviewSession.load(_write(tmp_path, d))
    assert r.status[:2] == ["accepted", "corrected"]
    assert sorted(r.review_order()) == [0, 1, 2, 3]



@pytest.mark.parametrize("key, value", [("vocabulary", "AVAL"), ("image", 7)])
def test_a_session_entry_of_the_wrong_kind_is_ignored_not_misread(tmp_path, key, value):
    """Entries of a hand-edited session file that are of the wrong kind are ignored, as a
    threshold of the wrong kind is (docs/gui.md §5): a vocabulary given as one string became
    its letters, and an image key that is a number made the whole file damaged (its decisions
    set aside)."""
    session = _session()
    session.assign(0, "AVAL")
    d = session.to_dict()
    d[key] = value
    back = ReviewSession.load(_write(tmp_path, d))
    assert back.user_id[0] == "AVAL"
    assert all(len(name) > 1 for name in back.vocabulary), back.vocabulary
    assert back.image is None or isinstance(back.image, str)


def test_labelled_written_as_text_is_not_read_as_true(tmp_path):
    """``"labelled": "false"`` (text, hand-edited) in the file of a session never labelled was
    read as True (bool of a non-empty string): a session without answers taken as labelled."""
    d = ReviewSession(_table(), voxel_size_zyx=VOXEL).to_dict()
    d["labelled"] = "false"
    assert ReviewSession.load(_write(tmp_path, d))._s.labelled is False


def test_a_decision_made_before_the_first_labelling_keeps_a_status_that_matches_the_machines_answer():
    """ReviewSession's docstring: ``accepted`` = the user confirmed the automatic name,
    ``corrected`` = the user gave *another* name; and ``_apply_labelling`` says a decided neuron
    without an earlier machine answer "gets none: the 1.0 is the user's".

    A session made without a labelling (``labelling`` is optional: a user's own table reviewed,
    or a script), a name typed on neuron 3 (status 'corrected', no machine answer there), then the
    first labelling set with that decision fixed, as Re-label does. Expected: the decision's
    status still agrees with the automatic name (corrected <=> user_id != auto_id), and the
    machine is not said to have answered the user's own name at 1.0. Instead, because
    ``_apply_labelling`` keeps decided rows only once ``s.labelled`` is true, neuron 3 gets
    auto_id 'RMDL' (= the user's name, from the fixed labelling) and candidates
    [('RMDL', 1.0)] while its status stays 'corrected'; clearing the decision later would
    offer the user's own name back as the machine's sure answer."""
    session = ReviewSession(_table(), voxel_size_zyx=VOXEL)  # no labelling yet
    session.assign(3, "RMDL")
    fixed = session.fixed()
    session.set_labelling(make_labelling(NAMES, PROBS, fixed=fixed), "auto-label", fixed_rows=fixed)

    user, auto, status = session.user_id[3], session.auto_id[3], session.status[3]
    expected = "accepted" if user == auto else "corrected"
    assert status == expected, (
        f"neuron 3: status {status!r} but user_id {user!r} and auto_id {auto!r} "
        f"(candidates {session.candidates(3)})")


def test_a_name_typed_unsure_that_looks_like_a_missing_value_survives_the_autosave(tmp_path):
    """Every change is autosaved "so a killed napari loses nothing", and what the session shows
    is what loading its file shows. Typing ``NA?`` on a neuron is taken (parse_name checks for
    the missing-value spellings before it strips the '?', so it is the name 'NA', unsure) and
    shown as 'NA?'; the autosaved file holds user_id 'NA', status 'unsure'. Loading that file,
    ``_agreeing_decisions`` runs parse_name('NA') -> '' (a missing value) and drops the decision
    silently. Expected: the session and its reloaded file agree (now: 'NA?' is no name, as
    'NA' is). Instead the decision is gone after reopening."""
    path = tmp_path / "worm.tif.fdlc-session.json"
    session = ReviewSession(_table(), make_labelling(NAMES, PROBS), voxel_size_zyx=VOXEL, path=path)
    try:
        session.assign(2, "NA?")
    except FdlcError:
        return  # refused: consistent
    reloaded = ReviewSession.load(path)
    assert (reloaded.user_id[2], reloaded.status[2]) == (session.user_id[2], session.status[2]), (
        f"shown {session.display_names()[2]!r} ({session.status[2]}) before, "
        f"{reloaded.display_names()[2]!r} ({reloaded.status[2]}) after reopening")
