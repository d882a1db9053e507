import numpy as np
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.geometry import canonical_frame
from napari_fdlc.simulate import SimulationParams, simulate_worm
from napari_fdlc.table import NeuronTable


def test_correspondence_is_known(worm):
    synth = simulate_worm(worm, rng=0)
    real = synth.origin >= 0
    assert (synth.table.labels[real] == worm.labels[synth.origin[real]]).all()
    assert (synth.table.labels[~real] == "").all()
    kept = real.sum() / len(worm)
    assert 0.7 <= kept <= 0.96  # 5–25 % dropped
    assert (~real).sum() <= 20


def test_spurious_points_keep_their_distance(worm):
    from scipy.spatial import cKDTree

    synth = simulate_worm(worm, rng=3, params=SimulationParams(noise_um=0.0, max_spurious=20))
    real = synth.origin >= 0
    if (~real).any():
        d, _ = cKDTree(synth.table.xyz[real]).query(synth.table.xyz[~real])
        assert d.min() > 1.0  # ≥ 2 µm before the global scale/shear


def test_no_mirror_images(worm):
    """The simulator only applies proper transforms: a worm and its copy keep their chirality."""
    params = SimulationParams(drop_fraction=(0.0, 0.0), max_spurious=0, noise_um=0.0, bend_curvature=0.0, shear=0.0,
                              transverse_shear=0.0, scale=0.0)
    for seed in range(5):
        synth = simulate_worm(worm, rng=seed, params=params)
        a = worm.xyz[synth.origin] - worm.xyz[synth.origin].mean(0)
        b = synth.table.xyz - synth.table.xyz.mean(0)
        u, _, vt = np.linalg.svd(b.T @ a)
        assert np.linalg.det(u @ vt) > 0


def test_deterministic_with_seed(worm):
    a = simulate_worm(worm, rng=5)
    b = simulate_worm(worm, rng=5)
    assert np.array_equal(a.table.xyz, b.table.xyz)
    assert canonical_frame(a.table.xyz)[0].shape == a.table.xyz.shape


@pytest.mark.parametrize("what", ["empty", "nan"])
def test_simulate_refuses_empty_or_non_finite_tables(what):
    """An empty table, or one with a NaN position, is refused in one line."""
    if what == "empty":
        table = NeuronTable(np.zeros((0, 3)))
    else:
        xyz = np.random.default_rng(0).normal(size=(10, 3)) * [20, 5, 4]
        xyz[2, 1] = np.nan
        table = NeuronTable(xyz)
    with pytest.raises(FdlcError) as exc:
        simulate_worm(table, 0)
    assert "\n" not in str(exc.value)
