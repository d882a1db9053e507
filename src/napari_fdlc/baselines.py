"""Non-learned matchers, to show every figure side by side with classical methods.

* :func:`floor_match` — the no-learning floor of ``../shared/docs/fdlc.md``: canonical frame, test scaled
  to the template's RMS radius, four proper 180° flips, Hungarian on squared distance (plus
  colour), the flip of lowest cost wins.
* :func:`cpd_match` — Coherent Point Drift (pycpd): the template is deformed onto the test
  non-rigidly, for each orientation; the orientation with the best CPD fit wins.
  :func:`cpd_follow` is the tracking form: one registration from the volume before.

Both return probabilities (N_test, M_template + 1) like :meth:`Identifier.match_pair`, so the
same assignment code turns them into names.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from ._blas import one_blas_thread
from .colour import shared_channels
from .errors import FdlcError
from .geometry import FLOOR_FLIPS, ORIENTATIONS, canonical_frame
from .table import NeuronTable


def _rms(x):
    return np.sqrt((x**2).sum(1).mean()) or 1.0


def _one_hot(n: int, m: int, rows, cols) -> np.ndarray:
    probs = np.zeros((n, m + 1))
    probs[:, m] = 1.0
    probs[rows, m] = 0.0
    probs[rows, cols] = 1.0
    return probs


def _distinct_positions(table: NeuronTable) -> int:
    return len(np.unique(np.round(np.asarray(table.xyz, float), 6), axis=0))


def _check_spread(*tables: NeuronTable, method: str) -> None:
    """The baselines scale each table by its spread and CPD fits a Gaussian width to it: a table
    of fewer than 3 distinct positions has none (a division by zero, then NaN everywhere)."""
    for t in tables:
        distinct = _distinct_positions(t)
        if distinct < 3:
            raise FdlcError(f"{t.source}: {distinct} distinct neuron position(s); the {method} baseline needs at least 3")


def floor_match(template: NeuronTable, test: NeuronTable, use_colour: bool = False) -> np.ndarray:
    _check_spread(template, test, method="non-learned floor")
    a, _, _ = canonical_frame(template.xyz)
    b, _, _ = canonical_frame(test.xyz)
    b = b * _rms(a) / _rms(b)
    colour_cost = 0.0
    channels = list(shared_channels(template, test))  # a channel of one value is no reading (0 / 0 below)
    if use_colour and channels:
        def z(t):
            v = t.colour_matrix(channels)
            return (v - v.mean(0)) / np.where(v.std(0) > 0, v.std(0), 1)
        colour_cost = cdist(z(test), z(template), "sqeuclidean")
        colour_cost = 0.3 * colour_cost / colour_cost.mean()
    best = None
    for orientation in FLOOR_FLIPS:
        d = cdist(b @ orientation.T, a, "sqeuclidean")
        cost = d / d.mean() + colour_cost
        r, c = linear_sum_assignment(cost)
        total = cost[r, c].sum()
        if best is None or total < best[0]:
            best = (total, r, c)
    return _one_hot(len(b), len(a), best[1], best[2])


@one_blas_thread  # as fdlc's own calls, so that the two compare on the same footing
def cpd_match(template: NeuronTable, test: NeuronTable, use_colour: bool = False, max_iterations: int = 50) -> np.ndarray:
    """Non-rigid CPD from the template onto the test in each of the 16 orientations; the one
    with the smallest mean distance to its nearest neighbour wins. Probabilities (N_test,
    M_template + 1). Position only: ``use_colour`` is accepted for the shared signature.

    A test of 1 or 2 distinct positions (which ``fdlc label`` must answer) cannot be registered:
    every template neuron is then as likely as the others, and as "no match"."""
    if _distinct_positions(test) < 3:
        _check_spread(template, method="CPD")
        return np.full((len(test), len(template) + 1), 1.0 / (len(template) + 1))
    return cpd_search(template, test, max_iterations)[0]


def cpd_search(template: NeuronTable, test: NeuronTable, max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cpd_match`, also returning the deformed template in the test's own µm (where a CPD
    tracker starts the next volume from)."""
    _check_spread(template, test, method="CPD")
    a, _, _ = canonical_frame(template.xyz)
    b, centre, rotation = canonical_frame(test.xyz)
    a = a / _rms(a)
    b_scale = _rms(b)
    b = b / b_scale
    best = None
    for orientation in ORIENTATIONS:
        bo = b @ orientation.T
        moved, sigma2 = _cpd(bo, a, max_iterations)
        d = cdist(bo, moved, "sqeuclidean")
        fit = np.sqrt(d.min(axis=1)).mean()
        if best is None or fit < best[0]:
            best = (fit, d, sigma2, moved @ orientation)
    _, d, sigma2, moved = best
    return _cpd_probs(d, sigma2), (moved * b_scale) @ rotation + centre


def cpd_follow(previous: np.ndarray, test: NeuronTable, max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """One CPD registration of ``previous`` (a deformed reference, µm, from the volume before)
    onto the next volume of the same recording: no orientation search, as a CPD tracker does.
    Returns the probabilities and the newly deformed reference (µm) for the volume after."""
    _check_spread(test, method="CPD")
    x = np.asarray(test.xyz, float)
    centre = x.mean(axis=0)
    scale = _rms(x - centre)
    moved, sigma2 = _cpd((x - centre) / scale, (previous - centre) / scale, max_iterations)
    return _cpd_probs(cdist((x - centre) / scale, moved, "sqeuclidean"), sigma2), moved * scale + centre


def _cpd(x: np.ndarray, y: np.ndarray, max_iterations: int) -> tuple[np.ndarray, float]:
    """pycpd's non-rigid registration of ``y`` onto ``x`` (both scaled to unit RMS radius)."""
    from pycpd import DeformableRegistration

    reg = DeformableRegistration(X=x, Y=y, alpha=2.0, beta=2.0, w=0.1, max_iterations=max_iterations)
    moved, _ = reg.register()
    return moved, reg.sigma2


def _cpd_probs(d: np.ndarray, sigma2: float) -> np.ndarray:
    """Soft probabilities from CPD's own Gaussian width; "no match" takes CPD's outlier weight."""
    logits = -d / (2 * max(sigma2, 1e-6))
    logits = np.hstack([logits, np.full((len(d), 1), np.log(0.1) + logits.max(axis=1, keepdims=True) - 4.0)])
    logits -= logits.max(axis=1, keepdims=True)
    probs = np.exp(logits)
    probs /= probs.sum(axis=1, keepdims=True)
    return probs
