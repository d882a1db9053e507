"""From per-neuron probabilities to names: one-to-one assignment, candidates, thresholds.

Everything here is plain numpy/scipy so it can be tested exactly (brute force on tiny cases).
The model gives, for each test neuron, probabilities over template neurons plus "no match";
:func:`name_probabilities` turns those into probabilities over *names* (several templates are
averaged into one answer per name), and :func:`assign` picks one name per test neuron with
``scipy.optimize.linear_sum_assignment``, each name used at most once, "no named match" allowed.
"""

from __future__ import annotations

from collections.abc import Mapping

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .errors import FdlcError
from .table import parse_name

_TINY = 1e-12


@dataclass
class Labelling:
    """The answer for one test worm, in the test's input order."""

    names: list[str]  # vocabulary: columns of ``probs``
    probs: np.ndarray  # (N, V) probability that test neuron j is name v
    auto_id: list[str]  # assigned name per neuron, '' = no named match
    auto_conf: np.ndarray  # probability of the assignment made (or of "no named match")
    info: dict = field(default_factory=dict)

    @property
    def no_match(self) -> np.ndarray:
        return np.clip(1.0 - self.probs.sum(axis=1), 0.0, 1.0)

    def candidates(self, k: int = 3) -> tuple[list[list[str]], np.ndarray]:
        """Top-k names and their probabilities per neuron (padded with '' / 0)."""
        return top_k(self.probs, self.names, k)

    def thresholded(self, threshold: float) -> list[str]:
        """auto_id where its confidence reaches ``threshold``, else ''."""
        return [n if n and c >= threshold else "" for n, c in zip(self.auto_id, self.auto_conf)]


def name_probabilities(
    per_template: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[list[str], np.ndarray]:
    """Combine ``[(probs (N, M_t), template_names (M_t,)), ...]`` into (names, (N, V)).

    Probability mass on unnamed template neurons counts as "no named match". With several
    templates the per-name probabilities are averaged: a name a template lacks gets 0 from it,
    so names that few templates know are, rightly, less likely.
    """
    n_test = per_template[0][0].shape[0]
    for probs, names in per_template:
        if probs.shape[0] != n_test or probs.shape[1] != len(names):
            raise FdlcError(f"name_probabilities: an answer of shape {probs.shape} for {len(names)} template names and "
                            f"{n_test} test neurons (one column per template neuron, one row per test neuron)")
    vocabulary = sorted({n for _, names in per_template for n in names if n})
    column = {n: i for i, n in enumerate(vocabulary)}
    total = np.zeros((n_test, len(vocabulary)))
    for probs, names in per_template:
        names = np.asarray(names, dtype=object)
        named = np.flatnonzero(names != "")
        cols = np.array([column[names[i]] for i in named], dtype=int)
        if len(np.unique(cols)) == len(cols):
            total[:, cols] += probs[:, named]  # np.add.at is 20× slower; needed only for repeats
        else:
            np.add.at(total.T, cols, probs[:, named].T)
    return vocabulary, total / len(per_template)


def assign(probs: np.ndarray, fixed: dict[int, int] | None = None, no_match_weight: float = 1.0) -> np.ndarray:
    """One name index per test neuron (-1 = no named match), maximising the summed
    log-probability, each name used at most once.

    ``fixed`` maps test rows to name columns the user decided (-1: a name without a column,
    which takes none); those are kept and their names are taken out of play for everyone else.
    ``no_match_weight`` < 1 makes leaving a neuron unnamed less attractive than its probability
    alone says: a diffuse but useful best guess (shown with its low confidence) is worth more
    to a user than an empty cell.
    """
    n, v = probs.shape
    _check_no_match_weight(no_match_weight)
    fixed = _checked_columns(fixed, n, v)
    result = np.full(n, -1, dtype=int)
    for row, col in fixed.items():
        result[row] = col
    rows = np.array([r for r in range(n) if r not in fixed], dtype=int)
    cols = np.array([c for c in range(v) if c not in set(fixed.values())], dtype=int)
    if len(rows) == 0 or len(cols) == 0:  # no one left to name, or no name left: the rest stay unnamed
        return result
    p = probs[np.ix_(rows, cols)]
    no_match = np.clip(1.0 - probs[rows].sum(axis=1), _TINY, 1.0)
    # floored after the weight, as the names are: a name of probability 0 must not beat a
    # no-match share floored first and then weighted below the floor
    chosen = min_cost_matching(-np.log(np.clip(p, _TINY, 1.0)), -np.log(np.clip(no_match * no_match_weight, _TINY, None)))
    result[rows] = np.where(chosen >= 0, cols[np.maximum(chosen, 0)], -1)
    return result


def assign_log(log_p: np.ndarray, no_match_weight: float = 1.0) -> np.ndarray:
    """:func:`assign` (no fixed rows) on log-probabilities (N, M + 1; the last column "no
    match") as a model gives them, without taking their exp and log again: the same costs,
    clipped alike."""
    _check_no_match_weight(no_match_weight)
    floor = np.log(_TINY)
    unmatched = np.maximum(log_p[:, -1] + np.log(no_match_weight), floor)  # weighted, then floored (see assign)
    return min_cost_matching(-np.maximum(log_p[:, :-1], floor), -unmatched)


def _check_no_match_weight(weight: float) -> None:
    if not 0 < weight < np.inf:
        raise FdlcError(f"no_match_weight must be a positive number (got {weight!r}): at 0 leaving a neuron unnamed "
                        "would cost infinitely, which more neurons than names cannot avoid")


def _checked_columns(fixed: dict[int, int] | None, n: int, v: int) -> dict[int, int]:
    """``fixed`` (row -> column, -1: a name without a column) checked against an (n, v) answer:
    rows 0..n-1 and columns -1..v-1, and no column given to two rows (one neuron per name)."""
    fixed = dict(fixed or {})
    taken = {}
    for row, col in fixed.items():
        if not (0 <= row < n and -1 <= col < v):
            raise FdlcError(f"decided column {col} for row {row}: outside the answer's {n} rows and {v} columns")
        if col >= 0 and col in taken:
            raise FdlcError(f"decided column {col} is on rows {taken[col]} and {row}: a name belongs to one neuron")
        taken[col] = row
    return fixed


def min_cost_matching(cost: np.ndarray, unmatched: np.ndarray) -> np.ndarray:
    """Row i -> its column (each column used at most once) or -1, minimising the summed cost
    where leaving row i unmatched costs ``unmatched[i]``: the Hungarian algorithm on costs capped
    at each row's unmatched cost, a row whose cost reaches its cap being unmatched. That is the
    optimum of a private "unmatched" column per row, on a matrix half the size (1.7× faster)."""
    n, m = cost.shape
    capped = np.minimum(cost, unmatched[:, None])
    if m < n:  # every row needs a column of its own
        capped = np.hstack([capped, np.repeat(unmatched[:, None], n - m, axis=1)])
    rows, cols = linear_sum_assignment(capped)
    keep = cols < m
    keep[keep] = cost[rows[keep], cols[keep]] < unmatched[rows[keep]]
    out = np.full(n, -1, dtype=int)
    out[rows[keep]] = cols[keep]
    return out


def top_k(probs: np.ndarray, names: list[str], k: int) -> tuple[list[list[str]], np.ndarray]:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0:
        raise FdlcError(f"candidates: k must be a whole number of at least 0 (got {k!r})")
    n, v = probs.shape
    kk = min(k, v)
    order = np.argsort(-probs, axis=1, kind="stable")[:, :kk]
    cand = [[names[i] if probs[j, i] > 0 else "" for i in order[j]] + [""] * (k - kk) for j in range(n)]
    cand_p = np.zeros((n, k))
    cand_p[:, :kk] = np.take_along_axis(probs, order, axis=1)
    return cand, cand_p


def one_to_one(probs: np.ndarray, fixed: dict[int, int] | None = None, iterations: int = 50) -> np.ndarray:
    """Per-neuron probabilities (N, V; the rest of each row is "no named match") made
    consistent with one neuron per name: alternately scale every name's column down to a total
    of at most 1 and every row (with its no-match share) back to 1 (Sinkhorn iterations with a
    dustbin). The model answers each neuron on its own, so two neighbours can both give most of
    their mass to one name; the assignment resolves that, and these marginals say so.
    Measured on held-out labs (fold models, settings refitted, session 5): the panel's top-3 up
    0.2–7.6 points, the calibration error of pairs (position only) down on 4 of 5 labs. ``fixed`` rows (row -> column, the
    user's decisions) are certain, which takes their names away from every other neuron."""
    p = np.clip(np.asarray(probs, float), 0.0, None)
    fixed = _checked_columns(fixed, *p.shape)
    if p.size == 0:
        return p
    # Each row's "no named match" share as the model gave it, before the decided names are
    # taken: a name taken from a row spreads its share over the row's other answers as the
    # Sinkhorn steps spread a name claimed twice (all of it went to "no match": a neighbour's
    # other names lost confidence, B 0.2 where a certain model gives 0.65).
    rest = np.clip(1.0 - p.sum(axis=1), 1e-9, None)
    for row, col in fixed.items():
        p[row] = 0.0  # a name without a column (col -1): certainly none of the others
        rest[row] = 1e-9 if col >= 0 else 1.0
        if col >= 0:
            p[:, col] = 0.0
            p[row, col] = 1.0
    for _ in range(iterations):
        p /= np.maximum(p.sum(axis=0), 1.0)
        total = p.sum(axis=1) + rest
        p /= total[:, None]
        rest /= total
    return p


def check_fixed(fixed: dict | None, n: int) -> dict[int, str]:
    """The user's decided names by row (``fixed``), checked against a test of ``n`` neurons:
    rows are whole numbers 0..n-1, and a name belongs to one neuron."""
    if fixed is not None and not isinstance(fixed, Mapping):
        raise FdlcError(f"decided names: a mapping of row -> name is needed, not a {type(fixed).__name__}")
    rows_of = {}
    for row, given in (fixed or {}).items():
        if isinstance(row, (bool, np.bool_)) or not isinstance(row, (int, np.integer)) or not 0 <= row < n:
            raise FdlcError(f"decided name {given!r}: {row!r} is not a row of the test (0 to {n - 1})")
        # as a table's names are read: spaces around it and an unsure mark are not the name
        name = parse_name(given)[0] if isinstance(given, str) else ""
        if not name:
            raise FdlcError(f"row {row}: {given!r} is not a neuron name")
        if name in rows_of:
            raise FdlcError(f"decided name {name!r} is on rows {rows_of[name]} and {row}: a name belongs to one neuron")
        rows_of[name] = int(row)
    return {row: name for name, row in rows_of.items()}


def make_labelling(
    names: list[str],
    probs: np.ndarray,
    fixed: dict[int, str] | None = None,
    info: dict | None = None,
    no_match_weight: float = 1.0,
    assign_probs: np.ndarray | None = None,
) -> Labelling:
    """Assign names and fill a :class:`Labelling`. ``fixed`` maps rows to user-given names;
    a user name the vocabulary does not know is kept for that row without a column.
    ``assign_probs`` (default ``probs``): what the assignment is made on, when the reported
    probabilities are hedged (the panel hedges its chirality but assigns on its best guess).
    The probabilities reported (candidates, ``auto_conf``) are :func:`one_to_one`'s; a fixed
    row keeps the model's own probability of the user's name as its ``auto_conf``."""
    if len(set(names)) != len(names):
        repeated = sorted({n for n in names if names.count(n) > 1})
        raise FdlcError(f"make_labelling: the names {', '.join(map(repr, repeated))} occur more than once; a name is one column")
    probs = np.asarray(probs, float)
    if probs.ndim != 2 or probs.shape[1] != len(names) or (assign_probs is not None and np.shape(assign_probs) != probs.shape):
        raise FdlcError(f"make_labelling: {len(names)} names for probabilities of shape {probs.shape}"
                        + ("" if assign_probs is None else f" (assign_probs {np.shape(assign_probs)})")
                        + "; one column per name")
    column = {n: i for i, n in enumerate(names)}
    fixed = check_fixed(fixed, len(probs))
    fixed_cols = {row: column.get(name, -1) for row, name in fixed.items()}
    choice = assign(probs if assign_probs is None else assign_probs, fixed_cols, no_match_weight)
    model_probs, probs = probs, one_to_one(probs, fixed_cols)
    auto_id, auto_conf = [], np.zeros(len(probs))
    no_match = np.clip(1.0 - probs.sum(axis=1), 0.0, 1.0)
    for j, col in enumerate(choice):
        if j in fixed:
            auto_id.append(fixed[j])
            auto_conf[j] = model_probs[j, col] if col >= 0 else 0.0
        elif col >= 0:
            auto_id.append(names[col])
            auto_conf[j] = probs[j, col]
        else:
            auto_id.append("")
            auto_conf[j] = no_match[j]
    return Labelling(names, probs, auto_id, auto_conf, dict(info or {}))
