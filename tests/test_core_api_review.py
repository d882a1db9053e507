"""Defects found in a review of the core Python API (identify, match, register, reference,
colour, geometry, track): each test asserts the right behaviour and fails until it is fixed."""

from __future__ import annotations

import copy
from collections import Counter

import numpy as np
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.geometry import canonical_frame
from napari_fdlc.match import make_labelling
from napari_fdlc.reference import generate_worm, load_panel
from napari_fdlc.table import NeuronTable


@pytest.fixture(scope="module")
def identifier():
    from napari_fdlc.identify import Identifier

    return Identifier.load(device="cpu")


@pytest.fixture(scope="module")
def panel():
    return load_panel()


@pytest.fixture(scope="module")
def test_worm():
    w = generate_worm(seed=1)
    return NeuronTable(w.xyz, w.colours, source="test")  # unnamed: a table to be named


@pytest.fixture(scope="module")
def sequence():
    from napari_fdlc.track import SequenceParams, simulate_sequence

    return simulate_sequence(generate_worm(seed=1), 0, SequenceParams(frames=4))


def _long_test() -> NeuronTable:
    """A head plus 80 neurons reaching far into the body: named in its head window only."""
    w = generate_worm(seed=1)
    head = canonical_frame(w.xyz)[0]
    length = np.ptp(head[:, 0])
    rng = np.random.default_rng(0)
    body = np.column_stack([rng.uniform(head[:, 0].max() + 5, head[:, 0].max() + 2 * length, 80),
                            rng.normal(0, 3, 80), rng.normal(0, 3, 80)])
    colours = {c: np.concatenate([v, rng.choice(v, 80)]) for c, v in w.colours.items()}
    return NeuronTable(np.vstack([head, body]), colours, source="long")


# --------------------------------------------------------------------------------------------
# Names the user fixed


def test_fixed_name_unknown_to_the_vocabulary_does_not_take_another_name():
    """make_labelling: "a user name the vocabulary does not know is kept for that row without a
    column". The row's own assignment must not then also consume a vocabulary name: now row 0
    (fixed to 'Z') is assigned 'A' behind the scenes, so 'A' is withheld from row 1, which
    gets 'B', and row 0's auto_conf is the model's probability of 'A' (0.9), not of 'Z' (0).
    match.py make_labelling: fixed_cols drops unknown names, so assign() treats the row as free."""
    probs = np.array([[0.9, 0.05], [0.8, 0.15]])
    result = make_labelling(["A", "B"], probs, fixed={0: "Z"})
    assert result.auto_id[0] == "Z"
    assert result.auto_id[1] == "A", result.auto_id
    assert result.auto_conf[0] == 0.0, result.auto_conf


@pytest.mark.parametrize("reference", ["panel", "template"])
def test_fixed_name_outside_the_head_window_is_not_given_to_a_second_neuron(identifier, panel, reference):
    """A test reaching far into the body is named in its head window only; a name the user
    fixed on a row outside that window stays the user's, but it is now given a second time
    inside the window (identify._fixed_in passes only the window's fixed rows to the
    assignment, identify._widened then writes the outside ones back)."""
    test = _long_test()
    template = generate_worm(seed=2)

    def name(fixed=None):
        if reference == "panel":
            return identifier.label_panel(test, panel, fixed=fixed)
        return identifier.label(test, [template], fixed=fixed, atlas=panel.atlas)

    first = name()
    kept = first.info.get("head_window")
    assert kept is not None and kept < len(test)  # the set-up: a head window was used
    outside = next(j for j in range(len(test)) if first.auto_id[j] == "" and first.probs[j].sum() == 0)
    given = next(n for n in first.auto_id if n)
    result = name({outside: given})
    assert result.auto_id[outside] == given
    counts = Counter(n for n in result.auto_id if n)
    assert counts[given] == 1, [j for j, n in enumerate(result.auto_id) if n == given]


def test_fixed_row_out_of_range_is_a_one_line_error(identifier, panel, test_worm):
    """fixed={500: ...} on a 155-neuron test: now an IndexError traceback from
    identify._agreement_with_fixed (lp[j, i]); it must be an FdlcError."""
    with pytest.raises(FdlcError):
        identifier.label_panel(test_worm, panel, fixed={len(test_worm) + 345: "AVAL"})


def test_fixed_negative_row_is_not_silently_dropped(identifier, panel, test_worm):
    """fixed={-1: 'AVAL'}: now no neuron gets AVAL and no error is raised: match.assign writes
    result[-1] (the last row) and then overwrites it with the free rows' assignment, while
    make_labelling's `j in fixed` never matches -1. Either refuse it (FdlcError) or honour
    it on the last row."""
    try:
        result = identifier.label_panel(test_worm, panel, fixed={-1: "AVAL"})
    except FdlcError:
        return
    assert result.auto_id[-1] == "AVAL", (result.auto_id[-1], result.auto_id.count("AVAL"))


def test_one_name_fixed_on_two_rows_is_refused(identifier, panel, test_worm):
    """docs/gui.md: "A name belongs to one neuron: giving a name that another neuron already
    has from you is refused". The API now names both rows AVAL, and match.one_to_one zeroes the
    first row's probabilities entirely (its candidates no longer contain its auto_id)."""
    with pytest.raises(FdlcError):
        identifier.label_panel(test_worm, panel, fixed={0: "AVAL", 1: "AVAL"})


# --------------------------------------------------------------------------------------------
# Inputs a script can give


def test_nan_colours_are_not_read_as_the_brightest(identifier, panel):
    """A NeuronTable made in memory with NaN in some colour cells: colour._average_ranks sorts
    NaN last, so each such cell gets one of the highest ranks: normal score ~1.3-1.4, the
    brightest neurons of the channel (38 names change against the median-filled table). A NaN is
    no reading: refused (FdlcError), or without colour evidence (as the reader's median)."""
    from napari_fdlc.colour import normal_scores

    w = generate_worm(seed=1)
    rows = np.arange(0, 150, 10)
    colours = {c: v.copy() for c, v in w.colours.items()}
    for c in colours:
        colours[c][rows] = np.nan
    try:
        table = NeuronTable(w.xyz, colours, source="nan")
        identifier.label_panel(table, panel)
    except FdlcError:
        return
    scores = normal_scores(table, ("R", "G", "B"))[rows]
    assert np.isfinite(scores).all() and np.abs(scores).max() < 0.5, scores[:3]


def test_nan_position_is_a_one_line_error(identifier, panel):
    """A NeuronTable made in memory with a NaN position: now numpy's LinAlgError ('Eigenvalues
    did not converge') from geometry.canonical_frame; it must be an FdlcError."""
    w = generate_worm(seed=1)
    xyz = w.xyz.copy()
    xyz[0] = np.nan
    with pytest.raises(FdlcError):
        identifier.label_panel(NeuronTable(xyz, w.colours), panel)


def test_a_test_without_neurons_is_a_one_line_error(identifier):
    """label_neurons on a table of no rows (a segmentation that found nothing): now a
    ValueError from a max over an empty array (identify._check / register); an FdlcError, or an
    empty answer, is right."""
    from napari_fdlc.identify import label_neurons

    empty = generate_worm(seed=1).subset(np.arange(0))
    try:
        result = label_neurons(empty, identifier=identifier)
    except FdlcError:
        return
    assert len(result.auto_id) == 0


def test_an_unnamed_template_beside_a_named_one_does_not_halve_every_probability(identifier, test_worm):
    """Identifier.label with [named template, template without names]: _check only asks that
    *any* template is named, and name_probabilities averages the unnamed one's all-zero answer
    in, so every probability is halved (label_neurons refuses such a template). Refuse it, or
    leave it out."""
    template = generate_worm(seed=2)
    unnamed = NeuronTable(template.xyz, template.colours, source="unnamed")
    try:
        both = identifier.label(test_worm, [template, unnamed])
    except FdlcError:
        return
    alone = identifier.label(test_worm, [template])
    assert np.allclose(both.probs, alone.probs, atol=1e-6), (both.probs.max(), alone.probs.max())


def test_template_own_worm_in_nanometres_does_not_exhaust_memory(identifier, sequence):
    """A test and a template of the same worm, both in nm: the warp of the second look
    (geometry.fit_warp -> _grid_centres) indexes a grid of sigma/2 cells as a dense bincount
    over the table's extent: 1.67 TiB requested (MemoryError). A table in the wrong unit gets a
    warning and a (poor) answer, or an FdlcError, not an allocation failure."""
    volumes, _ = sequence
    nm = [NeuronTable(v.xyz * 1000, v.colours, source=v.source) for v in volumes[:2]]
    names = np.array([f"N{i}" for i in range(len(nm[0]))], dtype=object)
    template = NeuronTable(nm[0].xyz, nm[0].colours, names)
    try:
        result = identifier.label(nm[1], [template])
    except FdlcError:
        return
    assert len(result.auto_id) == len(nm[1])


# --------------------------------------------------------------------------------------------
# Tracking


def test_track_positions_in_nanometres_do_not_exhaust_memory(identifier, sequence):
    """track() on a recording in nm: geometry._grid_centres asks numpy for 653 GiB
    (np.bincount over a dense grid key) and fdlc track says 'out of memory' for 4 small
    volumes."""
    from napari_fdlc.track import track

    volumes, _ = sequence
    nm = [NeuronTable(v.xyz * 1000, v.colours, source=v.source) for v in volumes[:3]]
    try:
        result = track(nm, identifier=identifier)
    except FdlcError:
        return
    assert [len(t) for t in result.track_id] == [len(v) for v in nm]


def test_track_with_an_empty_first_volume_and_no_reference(identifier, sequence):
    """The reference defaults to the first volume; when it is empty, track() fails with
    'zero-size array to reduction operation maximum' (track.py: n_ids = max(i.max() ...)).
    Refuse it in one line, or follow from the first volume with neurons."""
    from napari_fdlc.track import track

    volumes, _ = sequence
    empty = volumes[0].subset(np.arange(0))
    try:
        result = track([empty, *volumes[1:]], identifier=identifier)
    except FdlcError:
        return
    assert len(result.track_id[0]) == 0


def test_track_with_an_empty_reference_is_a_one_line_error(identifier, sequence):
    """references=[a table without neurons]: now the same ValueError traceback (track.py
    n_ids = max(i.max() ...)); nothing can be tracked onto it: FdlcError."""
    from napari_fdlc.track import track

    volumes, _ = sequence
    with pytest.raises(FdlcError):
        track(volumes, references=[volumes[0].subset(np.arange(0))], identifier=identifier)


@pytest.mark.parametrize("case", ["no frames", "time point beyond the frames"])
def test_simulate_sequence_bad_request_is_a_one_line_error(case):
    """simulate_sequence with frames=0 (ValueError from _smooth's max of an empty curve) or
    only=(12,) of 10 frames (IndexError on kappa[t]): an FdlcError (or, for no frames, an
    empty sequence), not a traceback."""
    from napari_fdlc.track import SequenceParams, simulate_sequence

    worm = generate_worm(seed=1)
    try:
        if case == "no frames":
            volumes, origins = simulate_sequence(worm, 0, SequenceParams(frames=0))
            assert volumes == [] and origins == []
        else:
            simulate_sequence(worm, 0, SequenceParams(frames=10), only=(12,))
            pytest.fail("a time point beyond the sequence was simulated")
    except FdlcError:
        pass


# --------------------------------------------------------------------------------------------
# State kept between calls


def test_template_changed_in_place_is_not_answered_from_the_cache(identifier, panel, test_worm):
    """Identifier._atlas_placement caches the template's handedness relative to the atlas by
    object identity; a template mirrored in place (xyz[:, 2] *= -1) keeps the stale handedness,
    so the atlas joins in the wrong one: 5 names and probabilities up to 0.83 differ from a fresh
    Identifier's answer to the same call."""
    template = generate_worm(seed=2)
    identifier.label(test_worm, [template], atlas=panel.atlas)
    template.xyz[:, 2] *= -1
    again = identifier.label(test_worm, [template], atlas=panel.atlas)
    fresh = identifier.with_settings().label(test_worm, [template], atlas=panel.atlas)
    assert again.auto_id == fresh.auto_id
    assert np.allclose(again.probs, fresh.probs, atol=1e-6)


def test_load_panel_sees_an_atlas_rebuilt_at_the_same_path(tmp_path):
    """reference.load_panel caches by str(path) forever: an atlas rebuilt and saved at the
    same path in one session is not seen; the old panel's answer comes back."""
    from napari_fdlc.corpus import Worm
    from napari_fdlc.reference import build_atlas, load_atlas

    worms = [Worm("L", f"w{i}", generate_worm(seed=i)) for i in range(6)]
    path = tmp_path / "atlas.csv"
    build_atlas(worms[:3]).save(path)
    load_panel(path)
    build_atlas(worms[3:]).save(path)
    assert list(load_panel(path).atlas.names) == list(load_atlas(path).names)


def test_label_panel_many_leaves_the_first_answers_alone(identifier, panel):
    """label_panel_many(first=...) writes info["batch_handedness"] into the caller's own
    Labelling objects; a later call with share_handedness=False returns them with a decision it
    never made (fdlc label warns from results[0].info['batch_handedness'])."""
    tests = [NeuronTable(generate_worm(seed=s).xyz, generate_worm(seed=s).colours, source=f"s{s}") for s in (1, 2)]
    first = [identifier.label_panel(t, panel) for t in tests]
    before = copy.deepcopy([f.info for f in first])
    identifier.label_panel_many(tests, panel, first=first)
    assert [f.info for f in first] == before
    later = identifier.label_panel_many(tests, panel, first=first, share_handedness=False)
    assert all("batch_handedness" not in r.info for r in later)
