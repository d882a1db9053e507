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
