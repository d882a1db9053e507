"""The speed paths give the same answers as the plain ones (they are options of one model, not a
second implementation): a shared template (batch 1) equals the template repeated; tests of
different sizes batched with padding equal one at a time; an all-real mask equals no mask;
Identifier.match_many equals match_pair."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from napari_fdlc.model import CorrespondenceModel  # noqa: E402


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    m = CorrespondenceModel({"layers": 2, "dim": 32})
    # non-zero heads so that the learned part of the scores matters, not only the prior
    with torch.no_grad():
        m.project.weight.normal_(0, 0.3)
        m.displace.weight.normal_(0, 0.05)
    return m.eval()


def _worms(seed, sizes):
    rng = np.random.default_rng(seed)
    return [torch.tensor(rng.normal(size=(n, 3)) * [30, 8, 6], dtype=torch.float32) for n in sizes]


def test_shared_template_equals_repeated_template(model):
    (a,), tests = _worms(0, [60]), _worms(1, [50, 50, 50])
    b = torch.stack(tests)
    with torch.inference_mode():
        shared = model(a[None], b)
        repeated = model(a[None].expand(3, -1, -1).contiguous(), b)
    assert torch.allclose(shared, repeated, atol=1e-5)


def test_padded_batch_equals_one_at_a_time(model):
    (a,) = _worms(2, [60])
    tests = _worms(3, [50, 41, 57])
    size = max(len(t) for t in tests)
    batch = torch.zeros(3, size, 3)
    mask = torch.zeros(3, size, dtype=torch.bool)
    for i, t in enumerate(tests):
        batch[i, : len(t)] = t
        mask[i, : len(t)] = True
    with torch.inference_mode():
        together = model(a[None], batch, None, mask)
        for i, t in enumerate(tests):
            alone = model(a[None], t[None])[0]
            assert torch.allclose(together[i, : len(t)], alone, atol=1e-5)


def test_all_real_mask_equals_no_mask_and_padding_of_template(model):
    (a,), (b,) = _worms(4, [60]), _worms(5, [45])
    with torch.inference_mode():
        plain = model(a[None], b[None])
        masked = model(a[None], b[None], torch.ones(1, 60, dtype=torch.bool), torch.ones(1, 45, dtype=torch.bool))
        padded_t = torch.cat([a, torch.zeros(7, 3)])[None]
        tmask = torch.cat([torch.ones(60, dtype=torch.bool), torch.zeros(7, dtype=torch.bool)])[None]
        with_pad = model(padded_t, b[None], tmask, None)
    assert torch.equal(plain, masked)
    assert torch.allclose(with_pad[..., :60], plain[..., :60], atol=1e-5)
    assert torch.allclose(with_pad[..., -1], plain[..., -1], atol=1e-5)
    assert torch.isinf(with_pad[..., 60:67]).all()


def test_match_many_equals_match_pair(model, worm, other_worm):
    from napari_fdlc.identify import Identifier
    from napari_fdlc.simulate import simulate_worm

    ident = Identifier(model, device="cpu")
    tests = [simulate_worm(worm, s).table for s in range(3)]
    many = ident.match_many(other_worm, tests)
    for test, (probs, info) in zip(tests, many):
        single, info1 = ident.match_pair(other_worm, test)
        assert info["mirrored"] == info1["mirrored"]
        assert np.allclose(probs, single, atol=1e-5)


def test_trace_equals_the_model_for_other_sizes_colour_and_padding():
    """The traced model (what batches on a CPU run) keeps neuron counts free and gives the
    model's numbers, with and without colour, with and without padding."""
    from napari_fdlc.model import trace_model

    torch.manual_seed(1)
    model = CorrespondenceModel({"layers": 2, "dim": 32, "colour_channels": 3}).eval()
    with torch.no_grad():
        model.project.weight.normal_(0, 0.3)
        model.colour_embed[2].weight.normal_(0, 0.3)
    (a,), tests = _worms(6, [60]), _worms(7, [50, 50])
    b = torch.stack(tests)
    ca, cb = torch.randn(1, 60, 3), torch.randn(2, 50, 3)
    mask = torch.ones(2, 50, dtype=torch.bool)
    mask[1, -7:] = False
    with torch.inference_mode():
        plain, coloured = trace_model(model, a[None], b), trace_model(model, a[None], b, None, None, ca, cb)
        padded = trace_model(model, a[None], b, None, mask, ca, cb)
        (a2,), other = _worms(8, [71]), torch.stack(_worms(9, [33, 33]))
        ca2, cb2 = torch.randn(1, 71, 3), torch.randn(2, 33, 3)
        assert torch.allclose(plain(a2[None], other), model(a2[None], other), atol=1e-5)
        assert torch.allclose(coloured(a2[None], other, ca2, cb2), model(a2[None], other, None, None, ca2, cb2), atol=1e-5)
        assert not torch.allclose(coloured(a2[None], other, ca2, cb2), plain(a2[None], other), atol=1e-3)
        mask2 = torch.ones(2, 33, dtype=torch.bool)
        mask2[0, -4:] = False
        real = mask2[:, :, None].expand(-1, -1, 72)
        expected = model(a2[None], other, None, mask2, ca2, cb2)
        assert torch.allclose(padded(a2[None], other, mask2, ca2, cb2)[real], expected[real], atol=1e-5)


def test_identifier_traces_each_pattern_of_masks_once(model, worm, other_worm):
    from napari_fdlc.identify import Identifier

    ident = Identifier(model, device="cpu")
    (a,), (b,) = _worms(10, [60]), _worms(11, [45])
    with torch.inference_mode():
        out = ident._model_pass(a[None], b[None], None, None, None, None)
        assert torch.allclose(out, model(a[None], b[None]), atol=1e-5)
        assert list(ident._traced) == [(1, 1, False, False, False, False)]
        mask = torch.ones(1, 45, dtype=torch.bool)
        mask[0, -3:] = False
        out = ident._model_pass(a[None], b[None], None, mask, None, None)
        assert torch.allclose(out[0, :42], model(a[None], b[None], None, mask)[0, :42], atol=1e-5)
        ident._model_pass(a[None], b[None], None, mask, None, None)
    assert list(ident._traced) == [(1, 1, False, False, False, False), (1, 1, False, True, False, False)]
    assert ident.with_settings(temperature=2.0)._traced is ident._traced


def test_numpy_blas_is_held_to_one_thread_inside_calls_and_restored_after(model, worm, other_worm):
    # On two cores numpy's BLAS threads and torch's took turns on the cores: 3x slower (_blas.py).
    from threadpoolctl import threadpool_info, threadpool_limits

    from napari_fdlc import identify
    from napari_fdlc.identify import Identifier

    def blas_threads():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    seen = []
    inner = identify.register

    def spy(*args, **kwargs):  # the registration's EM is where numpy's BLAS works
        seen.append(blas_threads())
        return inner(*args, **kwargs)

    with threadpool_limits(2, user_api="blas"):
        before = blas_threads()
        ident = Identifier(model)
        try:
            identify.register = spy
            ident.label(other_worm, [worm])
        finally:
            identify.register = inner
        after = blas_threads()
    assert before and all(n == 2 for n in before), "this test needs a BLAS that can run two threads"
    assert seen and all(n == [1] * len(before) for n in seen)
    assert after == before


def test_warm_up_runs_the_model_and_leaves_errors_to_the_real_call(model, worm):
    from napari_fdlc.identify import Identifier, warm_up
    from napari_fdlc.table import NeuronTable

    ident = Identifier(model, device="cpu")
    warm_up(ident, [worm])
    assert ident._traced  # the model ran (and its traces are made) before the first real call
    unnamed = NeuronTable(worm.xyz, worm.colours, source="unnamed")
    warm_up(ident, [unnamed])  # a template without names: the real call says so, not the warm-up
