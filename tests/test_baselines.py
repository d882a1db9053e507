"""The non-learned baselines of the benchmarks: the floor of ../shared/docs/fdlc.md and CPD."""

import numpy as np

from napari_fdlc.table import NeuronTable


def _table(n: int, seed: int, colour: float | None = None) -> NeuronTable:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(0, 1, (n, 3)) * [20, 5, 4]
    colours = {c: (np.full(n, colour) if colour is not None else rng.gamma(2.0, 100.0, n)) for c in "RGB"}
    return NeuronTable(xyz, colours, np.array([f"N{i}" for i in range(n)], dtype=object))


def test_floor_match_with_colour_columns_of_one_value_does_not_fail():
    """R, G, B of one value in every neuron (not acquired) are no reading: the floor with colour
    answers by position, not with a 0 / 0 colour cost that linear_sum_assignment refuses."""
    from napari_fdlc.baselines import floor_match

    probs = floor_match(_table(10, 1, colour=0.0), _table(10, 2, colour=0.0), use_colour=True)
    assert probs.shape == (10, 11) and np.isfinite(probs).all()
    assert np.allclose(probs.sum(axis=1), 1.0)
