"""The NeuroPAL colour model.

Raw intensities and per-volume z-scores differ by a monotonic map per channel (and a lab's
microscope changes gains per channel), so we first map each channel of each volume to its
normal score: rank within the volume -> standard-normal quantile. The result is the same for raw
intensities, z-scores, or any channel rescaled by a positive factor. Two neurons are then
compared by a Gaussian log-likelihood of the difference of their normal scores; its width (and
the weight with which colour is fused with position) is fitted on the training labs.

Only R, G, B carry identity (W, the pan-neuronal marker, is in every neuron).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import ndtri

from .table import NeuronTable

IDENTITY_CHANNELS = ("R", "G", "B")


def read_channels(table: NeuronTable, channels: tuple[str, ...] = IDENTITY_CHANNELS) -> tuple[str, ...]:
    """The ``channels`` that ``table`` has a reading of: a column that is there and does not
    hold one value for every neuron. A channel not acquired and written as 0 would rank every
    neuron as the median colour: evidence, and wrong (a worm named by three such columns lost
    half its names against position only)."""
    return tuple(c for c in channels if c in table.colours and _varies(table.colours[c]))


def has_colour(table: NeuronTable) -> bool:
    """Whether ``table`` has a reading of each of R, G and B (what the model takes as input)."""
    return len(read_channels(table)) == len(IDENTITY_CHANNELS)


def _varies(values: np.ndarray) -> bool:
    finite = values[np.isfinite(values)]
    # One value for every neuron (one neuron too) is no reading: its normal score is the median's,
    # 0, whatever was measured. Taken as one, every single neuron was named alike by "colour",
    # 4-6x as confidently as by its position.
    return len(finite) >= 2 and bool(np.ptp(finite) > 0)


def shared_channels(a: NeuronTable, b: NeuronTable) -> tuple[str, ...]:
    theirs = read_channels(b)
    return tuple(c for c in read_channels(a) if c in theirs)


def normal_scores(table: NeuronTable, channels: tuple[str, ...]) -> np.ndarray:
    """(N, C) per-volume normal scores of the chosen channels (ties share a rank). Read-only:
    the answer is remembered by the colours' content, as the same tables are scored again and
    again (a panel's 10 templates and the test, each twice per call; a tracked reference once
    per volume)."""
    values = np.ascontiguousarray(table.colour_matrix(channels))
    return _normal_scores(values.tobytes(), values.dtype.str, values.shape)


@lru_cache(maxsize=64)
def _normal_scores(raw: bytes, dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    values = np.frombuffer(raw, dtype=dtype).reshape(shape)
    n = shape[0]
    known = np.isfinite(values)
    if n == 0 or shape[1] == 0:
        scores = np.zeros(shape)
    elif known.all():
        scores = ndtri((_average_ranks(values) - 0.5) / n)
    else:  # a cell without a reading says nothing: the median's score, 0 (read_table fills the median too)
        scores = np.zeros(shape)
        for c in range(shape[1]):
            rows = known[:, c]
            if rows.any():
                scores[rows, c] = ndtri((_average_ranks(values[rows, c : c + 1])[:, 0] - 0.5) / rows.sum())
    scores.setflags(write=False)
    return scores


def _average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..N down each column, ties sharing their mean rank (``rankdata``'s "average"),
    from one argsort and no Python loop: several times faster than ``rankdata``, whose
    overhead dominated the colour fusion of every answer."""
    n = len(values)
    order = np.argsort(values, axis=0, kind="stable")
    ordered = np.take_along_axis(values, order, axis=0)
    differs = ordered[1:] != ordered[:-1]  # between sorted neighbours
    edge = np.ones((1, values.shape[1]), dtype=bool)
    position = np.broadcast_to(np.arange(n)[:, None], values.shape)
    first = np.maximum.accumulate(np.where(np.vstack([edge, differs]), position, 0), axis=0)
    last = np.where(np.vstack([differs, edge]), position, n)
    last = np.minimum.accumulate(last[::-1], axis=0)[::-1]
    ranks = np.empty(values.shape)
    np.put_along_axis(ranks, order, (first + last) / 2 + 1, axis=0)  # positions first..last of a tie
    return ranks


def colour_log_likelihood(template_scores: np.ndarray, test_scores: np.ndarray, sigma: float = 0.8) -> np.ndarray:
    """(N_test, M_template) log-likelihood (up to a constant) that test j has template i's colour."""
    if template_scores.shape[1] == 0:
        return np.zeros((len(test_scores), len(template_scores)))
    # |g|^2 + |f|^2 - 2 g.f: a few hundred rows make the (N, M, C) difference array 4× slower.
    d2 = test_scores @ template_scores.T
    d2 *= -2
    d2 += (test_scores**2).sum(1)[:, None]
    d2 += (template_scores**2).sum(1)[None, :]
    np.maximum(d2, 0.0, out=d2)
    d2 *= -1 / (2 * sigma**2)
    return d2
