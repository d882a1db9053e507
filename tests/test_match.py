import itertools

import numpy as np
import pytest

from napari_fdlc.errors import FdlcError

from napari_fdlc.match import (
    assign,
    assign_log,
    make_labelling,
    min_cost_matching,
    name_probabilities,
    one_to_one,
    top_k,
)


def brute_force(probs, weight=1.0):
    """Best one-to-one assignment by enumeration (-1 = no named match)."""
    n, v = probs.shape
    no_match = np.clip(1 - probs.sum(1), 1e-12, 1) * weight
    best, best_choice = -np.inf, None
    options = list(range(v)) + [-1]
    for choice in itertools.product(options, repeat=n):
        used = [c for c in choice if c >= 0]
        if len(used) != len(set(used)):
            continue
        score = sum(np.log(max(probs[j, c], 1e-12)) if c >= 0 else np.log(no_match[j]) for j, c in enumerate(choice))
        if score > best:
            best, best_choice = score, choice
    return np.array(best_choice), best


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("weight", [1.0, 0.2])
def test_assignment_equals_brute_force(seed, weight):
    rng = np.random.default_rng(seed)
    n, v = rng.integers(1, 5), rng.integers(1, 5)
    raw = rng.random((n, v + 1)) ** 3
    probs = (raw / raw.sum(1, keepdims=True))[:, :v]
    got = assign(probs, no_match_weight=weight)
    _, best = brute_force(probs, weight)
    no_match = np.clip(1 - probs.sum(1), 1e-12, 1) * weight
    score = sum(np.log(max(probs[j, c], 1e-12)) if c >= 0 else np.log(no_match[j]) for j, c in enumerate(got))
    assert score == pytest.approx(best)
    used = got[got >= 0]
    assert len(used) == len(set(used))


@pytest.mark.parametrize("shape", [(30, 40), (40, 30), (25, 25)])
def test_capped_matching_costs_what_a_dustbin_per_row_costs(shape):
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(sum(shape))
    n, m = shape
    cost, unmatched = rng.random((n, m)) * 10, rng.random(n) * 4
    got = min_cost_matching(cost, unmatched)
    dustbin = np.full((n, m + n), 1e9)
    dustbin[:, :m] = cost
    dustbin[np.arange(n), m + np.arange(n)] = unmatched
    r, c = linear_sum_assignment(dustbin)
    total = np.where(got >= 0, cost[np.arange(n), np.maximum(got, 0)], unmatched).sum()
    assert total == pytest.approx(dustbin[r, c].sum())
    used = got[got >= 0]
    assert len(used) == len(set(used)) and (got >= 0).any() and (got < 0).any()


def test_fixed_rows_are_kept_and_their_names_taken():
    probs = np.array([[0.9, 0.05], [0.8, 0.1]])
    free = assign(probs)
    assert free[0] == 0
    fixed = assign(probs, fixed={0: 1})
    assert fixed[0] == 1 and fixed[1] == 0


def test_top_k_ordering_and_sum():
    rng = np.random.default_rng(0)
    raw = rng.random((20, 11))
    probs = (raw / raw.sum(1, keepdims=True))[:, :10]
    names = [f"N{i}" for i in range(10)]
    cand, p = top_k(probs, names, 3)
    assert np.all(np.diff(p, axis=1) <= 0)
    assert np.all(p.sum(1) <= 1 + 1e-9)
    for j in range(20):
        assert cand[j][0] == names[int(np.argmax(probs[j]))]
    cand, p = top_k(probs[:, :2], names[:2], 3)
    assert all(row[2] == "" for row in cand) and np.all(p[:, 2] == 0)


def test_name_probabilities_average_templates_and_skip_unnamed():
    p1 = np.array([[0.7, 0.2]])  # template 1: A, unnamed
    p2 = np.array([[0.1, 0.8]])  # template 2: A, B
    names, probs = name_probabilities([(p1, np.array(["A", ""], object)), (p2, np.array(["A", "B"], object))])
    assert names == ["A", "B"]
    assert probs[0] == pytest.approx([0.4, 0.4])


def test_name_probabilities_add_up_a_name_a_template_repeats():
    p = np.array([[0.3, 0.2, 0.1]])
    names, probs = name_probabilities([(p, np.array(["A", "B", "A"], object))])
    assert names == ["A", "B"]
    assert probs[0] == pytest.approx([0.4, 0.2])


def test_labelling_confidence_and_threshold():
    probs = np.array([[0.9, 0.0], [0.0, 0.3]])
    lab = make_labelling(["A", "B"], probs)
    assert lab.auto_id == ["A", ""]  # 0.3 < P(no match) = 0.7
    assert lab.auto_conf == pytest.approx([0.9, 0.7])
    assert lab.thresholded(0.95) == ["", ""]
    lab = make_labelling(["A", "B"], probs, no_match_weight=0.2)
    assert lab.auto_id == ["A", "B"]


def test_assignment_on_one_answer_confidence_from_another():
    """The panel assigns on its best guess and reports hedged probabilities."""
    sharp = np.array([[0.9, 0.05], [0.05, 0.9]])
    hedged = np.array([[0.6, 0.35], [0.35, 0.6]])
    lab = make_labelling(["AVAL", "AVAR"], hedged, assign_probs=sharp)
    assert lab.auto_id == ["AVAL", "AVAR"] and np.allclose(lab.auto_conf, [0.6, 0.6])
    swapped = make_labelling(["AVAL", "AVAR"], hedged, assign_probs=sharp[::-1].copy())
    assert swapped.auto_id == ["AVAR", "AVAL"] and np.allclose(swapped.auto_conf, [0.35, 0.35])


def test_one_to_one_shares_a_name_claimed_twice_and_keeps_consistent_answers():
    # two neurons both give 0.8 to A: neither can have it with more than about even odds
    shared = one_to_one(np.array([[0.8, 0.1], [0.8, 0.05]]))
    assert np.all(shared.sum(axis=0) <= 1 + 1e-6) and np.all(shared.sum(axis=1) <= 1 + 1e-9)
    assert 0.4 < shared[0, 0] < 0.6 and 0.4 < shared[1, 0] < 0.6
    assert shared[0, 1] > 0.1  # the mass A cannot take moves to the neuron's other names...
    assert 1 - shared[1].sum() > 0.15  # ...and to "no named match"
    # answers that already name each neuron differently are left as they are
    consistent = np.array([[0.7, 0.1, 0.0], [0.1, 0.6, 0.2]])
    assert np.allclose(one_to_one(consistent), consistent)


def test_one_to_one_fixed_row_takes_its_name_from_the_others():
    probs = np.array([[0.6, 0.3], [0.7, 0.2]])
    out = one_to_one(probs, {0: 0})
    assert np.allclose(out[0], [1.0, 0.0]) and out[1, 0] < 0.01
    lab = make_labelling(["A", "B"], probs, fixed={0: "A"})
    assert lab.auto_id == ["A", "B"] and lab.auto_conf[0] == pytest.approx(0.6)  # the model's own belief
    assert lab.candidates(1)[0][1] == ["B"]


def test_assign_log_is_assign_on_log_probabilities():
    from scipy.special import log_softmax

    from napari_fdlc.match import assign, assign_log

    rng = np.random.default_rng(5)
    log_p = log_softmax(rng.normal(0, 3, (40, 36)), axis=1)
    log_p[3, :-1] = -800.0  # a row certain of "no match": costs are clipped alike
    for weight in (0.2, 1.0):
        assert np.array_equal(assign_log(log_p, weight), assign(np.exp(log_p[:, :-1]), None, weight))


def test_fixed_name_unknown_to_the_vocabulary_does_not_take_another_name():
    """A name the user gave that the vocabulary lacks is kept on its row, and that row takes no
    vocabulary name behind the scenes: 'A' stays free for row 1, and row 0's auto_conf is the
    probability of 'Z' (0), not of 'A'."""
    probs = np.array([[0.9, 0.05], [0.8, 0.15]])
    result = make_labelling(["A", "B"], probs, fixed={0: "Z"})
    assert result.auto_id[0] == "Z"
    assert result.auto_id[1] == "A", result.auto_id
    assert result.auto_conf[0] == 0.0, result.auto_conf


def _probs(n: int, v: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).dirichlet(np.ones(v + 1), size=n)[:, :v]


def test_every_name_decided_leaves_the_other_neurons_unnamed():
    """The user decided every name and a neuron is left: it gets no name. assign indexed an
    empty column array (IndexError), through Identifier.label too."""
    assert make_labelling(["A", "B"], _probs(3, 2), {0: "A", 1: "B"}).auto_id == ["A", "B", ""]
    assert list(assign(np.zeros((3, 0)))) == [-1, -1, -1]


@pytest.mark.parametrize("call", [
    lambda: make_labelling(["A", "A", "C"], np.array([[0.9, 0.0, 0.0], [0.0, 0.9, 0.0]])),  # gave "A" twice
    lambda: assign(_probs(5, 5), {0: 1, 1: 1}),  # gave column 1 to both rows
    lambda: one_to_one(_probs(5, 5), {0: 1, 1: 1}),  # row 0 silently lost its decided name
    lambda: assign(_probs(5, 5), {7: 1}),  # a row outside the answer
    lambda: assign(_probs(5, 2), no_match_weight=0.0),  # scipy's "cost matrix is infeasible"
    lambda: name_probabilities([(_probs(4, 5), ["A", "B"])]),  # columns without a name were dropped
], ids=["repeated vocabulary", "assign: one column for two rows", "one_to_one: one column for two rows",
        "row outside", "no_match_weight 0", "fewer names than columns"])
def test_inconsistent_inputs_are_refused(call):
    """One name per neuron, one column per name: what breaks it is an FdlcError, not a name given
    twice, a lost decision or a scipy traceback."""
    with pytest.raises(FdlcError):
        call()


def test_a_decided_name_moves_its_rivals_share_as_a_certain_answer_does():
    """A decided name spreads its rivals' share over their other answers, as a model certain of
    it would (B about 0.65): all of it went to "no named match" (B 0.2, hidden at 0.4)."""
    from napari_fdlc.match import make_labelling, one_to_one

    probs = np.array([[1.0, 0.0], [0.7, 0.2]])
    certain = one_to_one(probs)  # the model itself certain that neuron 0 is A
    decided = one_to_one(probs, {0: 0})  # the user decided it
    assert decided[1, 1] == pytest.approx(certain[1, 1], abs=0.05), (decided[1], certain[1])
    labelling = make_labelling(["A", "B"], np.array([[0.6, 0.3], [0.7, 0.2]]), fixed={0: "A"})
    assert labelling.thresholded(0.4) == ["A", "B"], (labelling.auto_conf, labelling.no_match)


def _one_neuron_too_many(rest: float = 1e-4) -> np.ndarray:
    """10 neurons each 0.999 sure of their own name, an 11th spread evenly over the 10 names;
    every row leaves ``rest`` to "no named match"."""
    m = 10
    p = np.full((m + 1, m), (1 - 0.999 - rest) / (m - 1))
    p[np.arange(m), np.arange(m)] = 0.999
    p[m] = (1 - rest) / m
    return p


@pytest.mark.xfail(strict=True, reason="known (session 34): one_to_one stops after 50 Sinkhorn iterations; the "
                   "shipped inference settings were fitted on these marginals, so converging them needs a refit")
def test_one_to_one_marginals_keep_each_name_to_one_neuron_when_neurons_outnumber_names():
    """one_to_one (the probabilities shown: candidates, auto_conf) promises every name's column
    a total of at most 1, so with 11 neurons and 10 names the "no named match" shares must add
    up to at least 1 (pigeonhole). With model answers whose no-match share is small (1e-4) the
    fixed 50 Sinkhorn iterations stop far from that: every name totals 1.089 and the no-match
    shares 0.11; run to convergence they give 1.000 and 1.00."""
    p = _one_neuron_too_many()
    out = one_to_one(p)
    assert out.sum(axis=0).max() <= 1 + 1e-3, out.sum(axis=0)
    assert (1 - out.sum(axis=1)).sum() >= 1 - 1e-3, 1 - out.sum(axis=1)


@pytest.mark.xfail(strict=True, reason="known (session 34): one_to_one stops after 50 Sinkhorn iterations; the "
                   "shipped inference settings were fitted on these marginals, so converging them needs a refit")
def test_labelling_probabilities_are_one_to_one_with_two_names_and_three_neurons():
    """Three neurons each certain it is A or B (no "no match" share): at most two can be named,
    so the shown probabilities must leave a total of at least 1 to "no named match" and give
    each name at most 1. make_labelling reports A and B each at a total of 1.17 and only 0.66
    for no-match across the three neurons."""
    lab = make_labelling(["A", "B"], np.full((3, 2), 0.5))
    assert lab.probs.sum(axis=0).max() <= 1 + 1e-3, lab.probs.sum(axis=0)
    assert lab.no_match.sum() >= 1 - 1e-3, lab.no_match


def test_assign_log_does_not_prefer_a_name_far_less_likely_than_no_match():
    """no_match_weight 0.2 makes "no named match" 5x less attractive, no more. Neuron 1 loses A
    to neuron 0; its remaining options are B at log p -60 and no-match at -40 (1e8 times more
    likely), so it should stay unnamed. Both are floored at log(1e-12) *before* the weight is
    applied, which leaves them tied and lets the weight pick B."""
    log_p = np.array([[0.0, -60.0, -60.0], [0.0, -60.0, -40.0]])
    choice = assign_log(log_p, 0.2)
    assert list(choice) == [0, -1], choice


def test_assign_does_not_give_a_neuron_a_name_of_probability_zero():
    """Two neurons both certain they are A (B has probability exactly 0 for each). One gets A;
    the other must stay unnamed: B is impossible for it. With no_match_weight 0.2 (the
    default of Identifier and the tracker) assign names it B, as both B (0) and "no named match"
    (0) are clipped to 1e-12 before the weight is applied. make_labelling then shows auto_id 'B'
    at auto_conf 0, a name missing from the neuron's own candidates."""
    probs = np.array([[1.0, 0.0], [1.0, 0.0]])
    assert list(assign(probs, no_match_weight=0.2)) == [0, -1]
    lab = make_labelling(["A", "B"], probs, no_match_weight=0.2)
    assert lab.auto_id == ["A", ""], (lab.auto_id, lab.auto_conf, lab.candidates(2)[0])


def test_make_labelling_refuses_fewer_names_than_columns():
    """make_labelling refuses inconsistent input with FdlcError (repeated names), as
    name_probabilities refuses fewer names than columns. With 1 name for a 2-column answer it
    fails with a bare IndexError (names[col]) instead."""
    with pytest.raises(FdlcError):
        make_labelling(["A"], np.array([[0.1, 0.8]]))
