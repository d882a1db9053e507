"""Shared geometry: the smooth warp that carries one worm onto another's pose."""

from __future__ import annotations

import numpy as np
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.geometry import _grid_centres, apply_affine, fit_affine, fit_warp, refuse_flat
from napari_fdlc.reference import generate_worm


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


def test_canonical_frame_levels_a_raised_body_axis_and_leaves_a_flat_one():
    """Worms lie flat: z is left alone unless the body axis rises more than LEVEL_ABOVE_DEG out
    of the image plane, when the frame turns it back into the plane (a proper rotation)."""
    from napari_fdlc.geometry import LEVEL_ABOVE_DEG, canonical_frame

    rng = np.random.default_rng(0)
    flat = np.c_[rng.uniform(-60, 60, 150), rng.normal(0, 8, 150), rng.normal(0, 6, 150)]

    def rise(canon):
        axis = np.linalg.eigh(np.cov(canon.T))[1][:, -1]
        return np.degrees(np.arcsin(abs(axis[2])))

    for degrees in (LEVEL_ABOVE_DEG / 2, 25.0):
        t = np.radians(degrees)
        pitch = np.array([[np.cos(t), 0, -np.sin(t)], [0, 1, 0], [np.sin(t), 0, np.cos(t)]])
        xyz = flat @ pitch.T @ np.array([[0.6, -0.8, 0], [0.8, 0.6, 0], [0, 0, 1]]).T + [5.0, -3.0, 2.0]
        canon, centre, rotation = canonical_frame(xyz)
        assert np.allclose(rotation @ rotation.T, np.eye(3)) and np.isclose(np.linalg.det(rotation), 1.0)
        assert np.allclose(canon, (xyz - centre) @ rotation.T)
        if degrees < LEVEL_ABOVE_DEG:  # z untouched
            assert np.allclose(rotation[2], [0, 0, 1]) and np.isclose(rise(canon), degrees, atol=1.5)
        else:
            assert rise(canon) < 0.1
    # A short, round piece of a worm has no axis to level, however it is turned.
    blob = np.c_[rng.normal(0, 10, 60), rng.normal(0, 8, 60), rng.normal(0, 6, 60)]
    t = np.radians(30)
    pitch = np.array([[np.cos(t), 0, -np.sin(t)], [0, 1, 0], [np.sin(t), 0, np.cos(t)]])
    assert np.array_equal(canonical_frame(blob @ pitch.T)[2][2], [0.0, 0.0, 1.0])


def test_no_corpus_worm_is_levelled(corpus_path):
    """The corpus's worms lie flat (their body axis rises 5.2° at most): the levelling leaves
    every one of them in its plain XY frame, so no corpus figure depends on it."""
    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.geometry import canonical_frame

    for worm in load_corpus(corpus_path):
        rotation = canonical_frame(worm.table.xyz)[2]
        assert np.array_equal(rotation[2], [0.0, 0.0, 1.0]), worm.source


def _rigid_pair(offset: float):
    worm = generate_worm(seed=3)
    angle = 0.3
    turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    return worm.xyz + offset, worm.xyz @ turn.T + np.array([3.0, -2.0, 1.0])


def test_fit_affine_is_exact_for_stage_coordinates():
    """An exact rigid map is recovered to 0.01 µm also ~1e6 µm from the origin (stage
    coordinates): the fit is solved about the points' means."""

    src, dst = _rigid_pair(1e6)
    assert np.abs(apply_affine(src, fit_affine(src, dst)) - dst).max() < 0.01


def test_fit_warp_is_exact_for_stage_coordinates():
    """The warp too, at 1e6 and 1e7 µm (its kernels are evaluated about the fitted points' mean;
    they once lost 1.2 µm, then the Cholesky factorisation)."""

    for offset in (1e6, 1e7):
        src, dst = _rigid_pair(offset)
        warp = fit_warp(src, dst, np.ones(len(src)))
        assert np.abs(warp(src) - dst).max() < 0.01, offset


def test_a_coordinate_that_is_not_a_number_is_refused():
    """One NaN position made fit_affine's whole answer NaN, silently, and refuse_flat's SVD fail
    with LinAlgError."""
    xyz = generate_worm(seed=1).xyz
    bad = xyz.copy()
    bad[0, 0] = np.nan
    with pytest.raises(FdlcError, match="not a finite number"):
        fit_affine(bad, xyz + 1.0)
    with pytest.raises(FdlcError, match="not a finite number"):
        refuse_flat(bad, "t", 10)


def test_fit_warp_takes_lists_as_fit_affine_does():
    """fit_warp indexed its input with a mask, which a list refuses (TypeError)."""
    xyz = generate_worm(seed=1).xyz
    warp = fit_warp(xyz.tolist(), (xyz + 1.0).tolist(), np.ones(len(xyz)))
    assert np.allclose(warp(xyz), xyz + 1.0, atol=1e-3)
