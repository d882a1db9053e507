"""Synthetic NeuroPAL stacks: geometry of the truth, determinism, channels, realism knobs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from napari_fdlc.errors import FdlcError
from napari_fdlc.render import align_worm, colour_intensities, random_worm, render_stack, spread_apart
from napari_fdlc.table import NeuronTable


@pytest.fixture(scope="module")
def worm():
    return random_worm(40, size_um=(36, 14, 10), seed=3)


@pytest.fixture(scope="module")
def rendered(worm):
    return render_stack(worm, seed=5)


def test_stack_layout(rendered):
    stack, truth = rendered
    assert stack.data.dtype == np.uint16 and stack.data.ndim == 4
    assert stack.channel_roles == ["R", "G", "B", "W"]
    assert stack.channel_names[3] == "TagRFP-T"
    assert stack.voxel_size_zyx == (1.0, 0.25, 0.25)
    assert len(truth) == 40
    extent = stack.extent_um()[::-1]
    assert np.all(truth.xyz >= 0) and np.all(truth.xyz <= extent)
    for c in ("x_px", "y_px", "z_px", "radius_um", "R_int", "G_int", "B_int"):
        assert c in truth.extra.columns


def test_truth_keeps_the_worm_shape(worm, rendered):
    _, truth = rendered
    # A rotation and a shift only: all pairwise distances are kept (the worm's spacing is 2.6 µm,
    # above the renderer's minimum, so nothing was pushed apart).
    np.testing.assert_allclose(pdist(truth.xyz), pdist(worm.xyz), atol=1e-6)
    np.testing.assert_array_equal(truth.colours["R"], worm.colours["R"])


def test_nuclei_are_bright_in_w_and_background_is_dim(rendered):
    stack, truth = rendered
    w = stack.channel("W").astype(float)
    idx = np.rint(truth.xyz[:, ::-1] / stack.voxel_size_zyx).astype(int)
    at_nuclei = w[tuple(idx.T)]
    background = np.percentile(w, 20)
    assert np.median(at_nuclei) > background + 150
    assert np.all(at_nuclei > background + 40)


def test_colours_follow_the_table(rendered):
    stack, truth = rendered
    idx = tuple(np.rint(truth.xyz[:, ::-1] / stack.voxel_size_zyx).astype(int).T)
    for c in "RGB":
        seen = stack.channel(c).astype(float)[idx]
        r = np.corrcoef(seen, truth.extra[f"{c}_int"])[0, 1]
        assert r > 0.7, (c, r)


def test_deterministic_with_a_seed(worm, rendered):
    again, truth = render_stack(worm, seed=5)
    np.testing.assert_array_equal(again.data, rendered[0].data)
    np.testing.assert_array_equal(truth.xyz, rendered[1].xyz)
    other, _ = render_stack(worm, seed=6)
    assert not np.array_equal(other.data, rendered[0].data)


def test_noise_level_and_options(worm):
    quiet, _ = render_stack(worm, seed=1, peak_photons=2000, gut=False, shape_zyx=(12, 60, 120))
    noisy, _ = render_stack(worm, seed=1, peak_photons=50, gut=False, shape_zyx=(12, 60, 120))
    assert quiet.data.shape == (4, 12, 60, 120)

    def snr(stack):
        w = stack.channel("W").astype(float)
        return (np.percentile(w, 99.5) - np.median(w)) / np.std(w[w < np.median(w)])

    assert snr(quiet) > 2 * snr(noisy)
    with_gfp, truth = render_stack(worm, seed=1, gfp=True, shape_zyx=(12, 60, 90))
    assert with_gfp.channel_roles[-1] == "GFP" and with_gfp.data.shape[0] == 5
    # The shape cuts the worm: only centres inside the stack are in the truth.
    assert 0 < len(truth) < len(worm)
    assert np.all(truth.xyz[:, 0] <= 90 * 0.25)


def test_gut_autofluorescence_is_blue_green(worm):
    stack, truth = render_stack(worm, seed=2, gut_strength=2.0)
    plain, _ = render_stack(worm, seed=2, gut=False)
    posterior = slice(int(truth.xyz[:, 0].max() / 0.25) + 8, None)  # past the last neuron
    extra = {c: stack.channel(c)[..., posterior].mean() - plain.channel(c)[..., posterior].mean() for c in "RGBW"}
    assert extra["B"] > extra["W"] > 0 and extra["G"] > extra["R"] > 0


def test_positions_pushed_apart_and_alignment():
    xyz = np.array([[0.0, 0, 0], [0.5, 0, 0], [10, 0, 0], [10, 3, 0]])
    out = spread_apart(xyz, 2.0)
    assert np.linalg.norm(out[1] - out[0]) >= 1.99
    np.testing.assert_allclose(out[2:], xyz[2:])
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(200, 3)) * [2, 20, 5]  # long along y, thin along x
    aligned = align_worm(cloud)
    spread = aligned.std(axis=0)
    assert spread[0] > spread[1] > spread[2]  # long axis -> x, thinnest -> z
    np.testing.assert_allclose(np.sort(spread), np.sort(cloud.std(axis=0)), rtol=0.05)


def test_colour_mapping_is_positive_and_monotone():
    z = np.array([-1.5, -0.2, 0.0, 0.7, 2.5, 9.0])
    out = colour_intensities(z)
    assert np.all(out >= 0.05) and np.all(np.diff(out) >= 0)
    assert np.all(colour_intensities(np.ones(5)) == 0.5)


def test_random_colours_when_the_table_has_none(worm):
    bare = NeuronTable(worm.xyz)
    stack, truth = render_stack(bare, seed=0, shape_zyx=(16, 70, 170))
    assert set(truth.colours) == {"R", "G", "B", "W"}


def test_empty_table_is_refused():
    with pytest.raises(FdlcError):
        render_stack(NeuronTable(np.zeros((0, 3))))
