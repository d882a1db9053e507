import numpy as np

from napari_fdlc.colour import colour_log_likelihood, normal_scores
from napari_fdlc.table import NeuronTable


def test_normal_scores_ignore_scaling_and_zscoring():
    rng = np.random.default_rng(0)
    raw = {c: rng.gamma(2, 100, 50) for c in "RGB"}
    t_raw = NeuronTable(rng.normal(size=(50, 3)), raw)
    scaled = {c: v * f for (c, v), f in zip(raw.items(), (3.0, 0.01, 17.0))}
    zs = {c: (v - v.mean()) / v.std() for c, v in raw.items()}
    a = normal_scores(t_raw, ("R", "G", "B"))
    assert np.allclose(a, normal_scores(NeuronTable(t_raw.xyz, scaled), ("R", "G", "B")))
    assert np.allclose(a, normal_scores(NeuronTable(t_raw.xyz, zs), ("R", "G", "B")))


def test_same_colour_is_most_likely():
    rng = np.random.default_rng(1)
    f = rng.normal(size=(30, 3))
    ll = colour_log_likelihood(f, f + rng.normal(0, 0.05, f.shape))
    assert (ll.argmax(axis=1) == np.arange(30)).mean() > 0.9


def test_normal_scores_rank_as_rankdata_with_and_without_ties():
    from scipy.special import ndtri
    from scipy.stats import rankdata

    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(40, 3))
    distinct = {c: rng.normal(size=40) for c in "RGB"}
    tied = {c: np.round(rng.normal(size=40), 1) for c in "RGB"}  # many ties
    for colours in (distinct, tied):
        values = np.stack([colours[c] for c in "RGB"], axis=1)
        expected = ndtri((rankdata(values, axis=0) - 0.5) / 40)
        assert np.allclose(normal_scores(NeuronTable(xyz, colours), ("R", "G", "B")), expected)


def test_colour_log_likelihood_is_the_scaled_squared_distance():
    rng = np.random.default_rng(3)
    f, g = rng.normal(size=(7, 3)), rng.normal(size=(5, 3))
    d2 = ((g[:, None, :] - f[None, :, :]) ** 2).sum(-1)
    assert np.allclose(colour_log_likelihood(f, g, 0.5), -d2 / 0.5)
