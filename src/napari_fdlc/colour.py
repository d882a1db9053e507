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

import numpy as np
from scipy.special import ndtri
from scipy.stats import rankdata

from .table import NeuronTable

IDENTITY_CHANNELS = ("R", "G", "B")


def shared_channels(a: NeuronTable, b: NeuronTable) -> tuple[str, ...]:
    return tuple(c for c in IDENTITY_CHANNELS if c in a.colours and c in b.colours)


def normal_scores(table: NeuronTable, channels: tuple[str, ...]) -> np.ndarray:
    """(N, C) per-volume normal scores of the chosen channels (ties share a rank)."""
    values = table.colour_matrix(channels)
    n = len(values)
    if n == 0 or not channels:
        return np.zeros((n, len(channels)))
    ranks = rankdata(values, axis=0)  # all channels in one call (its overhead dominates here)
    return ndtri((ranks - 0.5) / n)


def colour_log_likelihood(template_scores: np.ndarray, test_scores: np.ndarray, sigma: float = 0.8) -> np.ndarray:
    """(N_test, M_template) log-likelihood (up to a constant) that test j has template i's colour."""
    if template_scores.shape[1] == 0:
        return np.zeros((len(test_scores), len(template_scores)))
    d2 = ((test_scores[:, None, :] - template_scores[None, :, :]) ** 2).sum(-1)
    return -d2 / (2 * sigma**2)
