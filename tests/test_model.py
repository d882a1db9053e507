import json

import numpy as np
import pytest
import torch

from napari_fdlc.errors import ModelError
from napari_fdlc.identify import Identifier
from napari_fdlc.model import CorrespondenceModel, load_model, matching_loss, save_model


def test_model_is_permutation_equivariant():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32}).eval()
    a, b = torch.randn(1, 12, 3) * 20, torch.randn(1, 9, 3) * 20
    perm_a, perm_b = torch.randperm(12), torch.randperm(9)
    with torch.no_grad():
        out = model(a, b)
        out_p = model(a[:, perm_a], b[:, perm_b])
    expected = torch.cat([out[:, :, :12][:, :, perm_a], out[:, :, 12:]], dim=2)[:, perm_b]
    assert torch.allclose(out_p, expected, atol=1e-5)
    assert torch.allclose(out.exp().sum(-1), torch.ones(1, 9), atol=1e-5)


def test_padding_does_not_change_results():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32}).eval()
    a, b = torch.randn(1, 7, 3) * 20, torch.randn(1, 5, 3) * 20
    pa = torch.cat([a, torch.zeros(1, 3, 3)], 1)
    pb = torch.cat([b, torch.zeros(1, 2, 3)], 1)
    ma = torch.tensor([[True] * 7 + [False] * 3])
    mb = torch.tensor([[True] * 5 + [False] * 2])
    with torch.no_grad():
        out = model(a, b)
        padded = model(pa, pb, ma, mb)
    assert torch.allclose(padded[:, :5, :7], out[:, :, :7], atol=1e-5)
    assert torch.allclose(padded[:, :5, 10], out[:, :, 7], atol=1e-5)


def test_templates_in_one_batch_answer_as_one_at_a_time(worm, other_worm):
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32, "colour_channels": 3})
    for p in model.parameters():  # no zero-initialised branch: every input must count
        torch.nn.init.normal_(p, std=0.2)
    identifier = Identifier(model)
    rng = np.random.default_rng(0)
    templates = [worm.xyz, worm.xyz[:150] + rng.normal(0, 2, (150, 3))]  # two sizes: padded
    tests = [other_worm.xyz[:120], other_worm.xyz[10:] @ np.diag([1.0, 1.0, -1.0])]
    colours = [rng.normal(size=(len(t), 3)) for t in templates]
    test_colours = [rng.normal(size=(len(t), 3)) for t in tests]
    grid = identifier._forward_grid(templates, tests, colours, test_colours)
    for t, (xyz, colour) in enumerate(zip(templates, colours)):
        for v, one in enumerate(identifier._forward_many(xyz, tests, colour, test_colours)):
            assert grid[t][v].shape == (len(tests[v]), len(xyz) + 1)
            assert np.allclose(grid[t][v], one, atol=1e-4)


def test_loss_falls_on_one_pair():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 1, "dim": 32})
    a = torch.randn(1, 10, 3) * 20
    b = a[:, torch.randperm(10)]
    target = (b[0, :, None] == a[0, None]).all(-1).float().argmax(-1)[None]
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    first = None
    for _ in range(30):
        loss = matching_loss(model(a, b), target)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < first * 0.5


def test_weights_round_trip_and_refusals(tmp_path):
    model = CorrespondenceModel({"layers": 1, "dim": 32})
    save_model(model, tmp_path / "m", {"note": "x"})
    back = load_model(tmp_path / "m")
    for k, v in model.state_dict().items():
        assert torch.equal(v, back.state_dict()[k])
    # Corrupt weights
    (tmp_path / "m.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ModelError, match="not a valid safetensors"):
        load_model(tmp_path / "m")
    # Weights that do not fit the configuration
    save_model(model, tmp_path / "m")
    meta = json.loads((tmp_path / "m.json").read_text())
    meta["config"]["dim"] = 64
    (tmp_path / "m.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="do not fit"):
        load_model(tmp_path / "m")
    with pytest.raises(ModelError, match="missing"):
        load_model(tmp_path / "absent")




def test_load_model_refuses_weights_that_are_not_finite(tmp_path):
    """Before, weights holding NaN (a corrupt copy, a run that diverged) loaded without a word,
    and `fdlc label --weights` died in linear_sum_assignment with a traceback."""
    from safetensors.torch import load_file, save_file

    path = tmp_path / "model"
    save_model(CorrespondenceModel({"layers": 1, "dim": 32}), path, {})
    weights = path.with_suffix(".safetensors")
    state = load_file(str(weights))
    state["project.weight"][:] = float("nan")
    save_file(state, str(weights))
    with pytest.raises(ModelError, match="not finite"):
        load_model(path)


def test_save_model_long_name_keeps_weights_and_config(tmp_path):
    """save_model at a path whose stem has 40+ characters should write both files. Instead the
    two temporary names ('.<name[:40]>.tmp') are one file: the JSON overwrites the weights,
    the JSON is moved over the .safetensors, and the second replace fails (FileNotFoundError);
    the model cannot be loaded."""
    import torch

    from napari_fdlc.model import CorrespondenceModel, load_model, save_model

    torch.set_num_threads(1)
    model = CorrespondenceModel({"dim": 8, "heads": 2, "layers": 1, "fourier_bands": 2})
    path = tmp_path / ("identifier_trained_on_all_labs_seed7_" + "x" * 10)  # a 47-character stem
    save_model(model, path)
    loaded = load_model(path)
    assert loaded.config["dim"] == 8
