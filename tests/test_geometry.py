"""Shared geometry: the smooth warp that carries one worm onto another's pose."""

from __future__ import annotations

import numpy as np

from napari_fdlc.geometry import _grid_centres, fit_warp


def test_fit_warp_recovers_a_bend():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(150, 3)) * [30, 8, 6]
    dst = src.copy()
    dst[:, 1] += 0.004 * src[:, 0] ** 2  # a bend
    warp = fit_warp(src, dst, np.ones(len(src)), sigma=20.0, smoothness=0.01)
    assert np.sqrt(((warp(src) - dst) ** 2).sum(1).mean()) < 0.3
    affine_only = fit_warp(src, dst, np.ones(len(src)), sigma=0.0)
    assert np.sqrt(((affine_only(src) - dst) ** 2).sum(1).mean()) > 1.0
    # the smooth part lives on a reduced basis: one centre per occupied cell of sigma / 2
    assert len(warp.centres) < len(src) / 2


def test_grid_centres_are_the_means_of_occupied_cells():
    xyz = np.array([[0.0, 0, 0], [1, 1, 1], [12, 0, 0], [13, 2, 0], [0, 0, 14]])
    centres = _grid_centres(xyz, 10.0)
    assert sorted(map(tuple, np.round(centres, 6))) == [(0.0, 0.0, 14.0), (0.5, 0.5, 0.5), (12.5, 1.0, 0.0)]
