"""Coordinate frames shared by the model, the baselines and the simulator.

A worm lies at any angle in XY and on either side. We remove what can be removed without names
(centre on the median, rotate XY so the principal axis is x) and enumerate what cannot: the
four proper 180° turns that keep the principal axes (identity; about z; about x = the worm's
other side; about y), times the two chiralities (a recording mirrored in z by its acquisition
convention). Which of the eight is right is decided by the matcher's score, never by making the
model mirror-invariant: a mirror swaps left and right neurons.
"""

from __future__ import annotations

import numpy as np

# Proper turns first (index 0..3), then the same with z mirrored (4..7).
_PROPER = [(1, 1, 1), (-1, -1, 1), (1, -1, -1), (-1, 1, -1)]
ORIENTATIONS = np.array([np.diag(s) for s in _PROPER] + [np.diag(s) * np.diag((1, 1, -1)) for s in _PROPER], dtype=np.float64)
PROPER_ORIENTATIONS = ORIENTATIONS[:4]


def canonical_frame(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate XY so that the principal axis is x, then centre on the per-axis median.

    Returns (canonical coordinates, centre, 3×3 rotation) with ``canon = (xyz - centre) @ R.T``.
    z (the optical axis) is left alone: worms lie flat, so the body axis is in XY. The median is
    taken *after* the rotation so that the frame does not depend on how the worm lay in XY.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    mean = xyz.mean(axis=0)
    centred = xyz - mean
    rotation = np.eye(3)
    if len(xyz) >= 2:
        cov = np.cov(centred[:, :2].T)
        if np.all(np.isfinite(cov)) and np.any(cov != 0):
            eigval, eigvec = np.linalg.eigh(cov)
            axis = eigvec[:, np.argmax(eigval)]
            angle = np.arctan2(axis[1], axis[0])
            c, s = np.cos(-angle), np.sin(-angle)
            rotation[:2, :2] = [[c, -s], [s, c]]
    rotated = centred @ rotation.T
    median = np.median(rotated, axis=0)
    centre = mean + median @ rotation
    return rotated - median, centre, rotation


def fit_affine(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, ridge: float = 1e-3) -> np.ndarray:
    """Weighted least-squares affine map ``dst ≈ [src, 1] @ A`` (A is 4×3), regularised toward
    a pure translation so that a handful of matches cannot produce a wild shear."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    homog = np.hstack([src, np.ones((len(src), 1))])
    lhs = (homog * w[:, None]).T @ homog
    rhs = (homog * w[:, None]).T @ dst
    prior = np.vstack([np.eye(3), np.zeros((1, 3))])
    reg = ridge * max(w.sum(), 1.0) * np.diag([1, 1, 1, 0])
    return np.linalg.solve(lhs + reg + 1e-9 * np.eye(4), rhs + reg @ prior)


def apply_affine(xyz: np.ndarray, affine: np.ndarray) -> np.ndarray:
    return np.hstack([xyz, np.ones((len(xyz), 1))]) @ affine


def compose_affine(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """The 4×3 affine of ``apply_affine(apply_affine(x, first), then)``."""
    hom = np.hstack([first, np.array([[0.0], [0.0], [0.0], [1.0]])])
    return hom @ then


def orientation_cost(template: np.ndarray, test: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """For each of the 8 orientations, mean squared distance of known pairs (template i, test j)
    after the best translation; used to find the true orientation of a training pair."""
    a = template[pairs[:, 0]]
    costs = []
    for orientation in ORIENTATIONS:
        b = test[pairs[:, 1]] @ orientation.T
        d = a - b
        d = d - d.mean(axis=0)
        costs.append(float((d**2).sum(axis=1).mean()))
    return np.array(costs)
