"""ReviewSession driven by seeded random operation sequences (session 37 hunt, area "reviewfuzz").

A fuzzer (accept / assign / pick candidate / unsure / clear / replace_table / set_labelling /
set_threshold / undo / redo / autosave + load / export in both formats, invariants checked after
every step) was run on small seeded tables; each test below is one failing sequence, reduced by
hand to the few steps that show it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.match import make_labelling
from napari_fdlc.review import ReviewSession

NAMES = ["AVAL", "AVAR", "RMDL", "RMDR", "SMDVL"]
VOXEL = (1.0, 0.25, 0.25)
PROBS = np.array(
    [
        [0.90, 0.05, 0.02, 0.01, 0.01],
        [0.10, 0.70, 0.10, 0.05, 0.00],
        [0.05, 0.05, 0.60, 0.25, 0.00],
        [0.00, 0.00, 0.10, 0.40, 0.35],
        [0.02, 0.02, 0.02, 0.02, 0.50],
    ]
)


def _table(n: int = 5):
    from napari_fdlc.table import NeuronTable

    rng = np.random.default_rng(0)
    xyz = rng.uniform(5, 40, (n, 3))
    colours = {c: rng.gamma(2.0, 100.0, n) for c in "RGBW"}
    return NeuronTable(xyz, colours, extra=pd.DataFrame({"radius_um": np.full(n, 1.5)}))


@pytest.fixture(autouse=True)
def _session_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FDLC_SESSION_DIR", str(tmp_path / "user-data"))
    monkeypatch.setenv("OMP_NUM_THREADS", "1")


def test_a_decision_made_before_the_first_labelling_keeps_a_status_that_matches_the_machines_answer():
    """ReviewSession's docstring: ``accepted`` = the user confirmed the automatic name,
    ``corrected`` = the user gave *another* name; and ``_apply_labelling`` says a decided neuron
    without an earlier machine answer "gets none: the 1.0 is the user's".

    A session made without a labelling (``labelling`` is optional: a user's own table reviewed,
    or a script), a name typed on neuron 4 (status 'corrected', no machine answer there), then the
    first labelling set with that decision fixed, as Re-label does. Expected: the decision's
    status still agrees with the automatic name (corrected <=> user_id != auto_id), and the
    machine is not said to have answered the user's own name at 1.0. Instead, because
    ``_apply_labelling`` keeps decided rows only once ``s.labelled`` is true, neuron 4 gets
    auto_id 'RMDL' (= the user's name, from the fixed labelling) and candidates
    [('RMDL', 1.0)] while its status stays 'corrected'; clearing the decision later would
    offer the user's own name back as the machine's sure answer."""
    session = ReviewSession(_table(), voxel_size_zyx=VOXEL)  # no labelling yet
    session.assign(4, "RMDL")
    fixed = session.fixed()
    session.set_labelling(make_labelling(NAMES, PROBS, fixed=fixed), "auto-label", fixed_rows=fixed)

    user, auto, status = session.user_id[4], session.auto_id[4], session.status[4]
    expected = "accepted" if user == auto else "corrected"
    assert status == expected, (
        f"neuron 4: status {status!r} but user_id {user!r} and auto_id {auto!r} "
        f"(candidates {session.candidates(4)})")


def test_a_name_typed_unsure_that_looks_like_a_missing_value_survives_the_autosave(tmp_path):
    """Every change is autosaved "so a killed napari loses nothing", and what the session shows
    is what loading its file shows. Typing ``NA?`` on a neuron is taken (parse_name checks for
    the missing-value spellings before it strips the '?', so it is the name 'NA', unsure) and
    shown as 'NA?'; the autosaved file holds user_id 'NA', status 'unsure'. Loading that file,
    ``_agreeing_decisions`` runs parse_name('NA') -> '' (a missing value) and drops the decision
    silently. Expected: either the name is refused when typed (FdlcError), or the reloaded
    session keeps it. Instead the decision is gone after reopening."""
    path = tmp_path / "worm.tif.fdlc-session.json"
    session = ReviewSession(_table(), make_labelling(NAMES, PROBS), voxel_size_zyx=VOXEL, path=path)
    try:
        session.assign(2, "NA?")
    except FdlcError:
        return  # refused: consistent
    assert session.display_names()[2] == "NA?"
    reloaded = ReviewSession.load(path)
    assert (reloaded.user_id[2], reloaded.status[2]) == (session.user_id[2], session.status[2]), (
        f"shown {session.display_names()[2]!r} ({session.status[2]}) before, "
        f"{reloaded.display_names()[2]!r} ({reloaded.status[2]}) after reopening")
