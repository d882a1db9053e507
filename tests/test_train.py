import numpy as np
import pytest
import torch

from napari_fdlc.model import CorrespondenceModel, matching_loss
from napari_fdlc.reference import generate_worm
from napari_fdlc.simulate import simulate_worm
from napari_fdlc.table import NeuronTable
from napari_fdlc.corpus import Worm
from napari_fdlc.train import TRAIN_SIM, TrainConfig, _crop, collate, held_out, make_example, split_worms


def _examples(count, seed=0):
    rng = np.random.default_rng(seed)
    cfg = TrainConfig(negative_fraction=0.0, aligned_fraction=0.0)
    out = []
    while len(out) < count:
        template = _crop(generate_worm(seed=len(out) + 10), 48, rng)
        synth = simulate_worm(template, rng, TRAIN_SIM)
        target = np.where(synth.origin >= 0, synth.origin, len(template))
        example = make_example(template, synth.table, target, rng, cfg)
        if example is not None:
            out.append(example)
    return out


def test_tiny_training_run_overfits_a_handful_of_pairs():
    """The training machinery end to end (examples, padding, colour flags, loss, optimiser):
    a small model must fit 4 pairs almost perfectly within seconds."""
    torch.manual_seed(0)
    examples = _examples(4)
    rng = np.random.default_rng(0)
    model = CorrespondenceModel({"dim": 32, "layers": 2, "colour_channels": 3})
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    batch = collate(examples, torch, colour_dropout=0.0, rng=rng)
    a, t, am, tm, target, negative, ac, tc = batch
    for _ in range(150):
        loss = matching_loss(model(a, t, am, tm, ac, tc), target, negative)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        pred = model(a, t, am, tm, ac, tc).argmax(-1)
    valid = target >= 0
    accuracy = (pred[valid] == target[valid]).float().mean().item()
    assert accuracy >= 0.95, accuracy


def test_registered_and_panel_examples_are_placed_as_inference_places_them():
    """A registered example is the template's canonical frame and the test's registration onto
    it in the right chirality (matched neurons land close); a panel example is a worm sampled
    from the atlas and the test registered onto the atlas."""
    from napari_fdlc.reference import build_atlas
    from napari_fdlc.train import _targets, sample_example

    rng = np.random.default_rng(3)
    cfg = TrainConfig()
    template = generate_worm(seed=1)
    mirrored = simulate_worm(template, rng, TRAIN_SIM).table
    mirrored.xyz[:, 2] *= -1  # a recording with the other acquisition convention
    target = _targets(template, mirrored)
    a, b, t, negative, _, _ = make_example(template, mirrored, target, rng, cfg, registered=True)
    hit = (t >= 0) & (t < len(a))
    assert not negative and np.median(np.linalg.norm(b[hit] - a[t[hit]], axis=1)) < 3.0

    worms = [Worm("A", f"w{i}", generate_worm(seed=i)) for i in range(4)]
    atlas = build_atlas(worms)
    a, b, t, _, _, _ = sample_example(worms, rng, TrainConfig(synthetic_fraction=0.0, panel_fraction=1.0), atlas)
    assert len(a) == len(atlas.names)  # the whole sampled atlas worm, like the panel's templates
    hit = (t >= 0) & (t < len(a))
    assert hit.sum() >= 10 and np.median(np.linalg.norm(b[hit] - a[t[hit]], axis=1)) < 5.0  # not placed: ~20


def test_negative_examples_target_no_match():
    log_p = torch.log_softmax(torch.randn(1, 3, 5), -1)
    target = torch.tensor([[0, 1, -1]])
    neg = matching_loss(log_p, target, torch.tensor([True]))
    expected = -(log_p[0, 0, 4] + log_p[0, 1, 4]) / 2
    assert neg.item() == pytest.approx(expected.item(), rel=1e-5)


def test_split_keeps_validation_worms_out_of_training():

    worms = [Worm(lab, f"{lab}{i}", generate_worm(seed=i)) for lab in ("A", "B") for i in range(5)]
    cfg = TrainConfig(train_labs=("A",), val_labs=("A", "B"), val_worms_per_lab=2)
    train, val = split_worms(worms, cfg, np.random.default_rng(0))
    assert {w.lab for w in train} == {"A"} and len(train) == 3
    held = {w.name for w in val["A"][:2]}
    assert not held & {w.name for w in train}
    assert len(val["B"]) == 5  # a held-out lab is validated whole


def test_training_on_the_corpus_runs(corpus_path, tmp_path):
    from napari_fdlc.model import load_model
    from napari_fdlc.train import train

    cfg = TrainConfig(corpus=str(corpus_path), steps=3, eval_every=3, batch_size=2, val_pairs_per_lab=1,
                      val_labs=("SF",), model={"dim": 16, "layers": 1}, out=str(tmp_path / "m"), calibrate=False)
    result = train(cfg, log=lambda *_: None)
    assert result["history"][-1]["step"] == 3
    load_model(tmp_path / "m")


def test_calibration_does_not_depend_on_the_settings_it_starts_from():
    from dataclasses import replace

    from napari_fdlc.identify import Identifier, InferenceSettings
    from napari_fdlc.train import calibrate

    torch.manual_seed(0)
    model = CorrespondenceModel({"dim": 16, "layers": 1, "colour_channels": 3})
    rng = np.random.default_rng(0)
    worms = [generate_worm(seed=s) for s in (1, 2)]
    pairs = {"A": [(worms[0], simulate_worm(worms[1], rng).table), (worms[1], simulate_worm(worms[0], rng).table)]}
    first = calibrate(Identifier(model, InferenceSettings(), "cpu"), pairs, log=lambda *_: None)
    odd = InferenceSettings(temperature=0.3, colour_weight=0.5, no_match_weight=1.0, panel_temperature=2.0)
    assert calibrate(Identifier(model, odd, "cpu"), pairs, log=lambda *_: None) == first
    assert calibrate(Identifier(model, replace(odd, **{k: v for k, v in first.items() if k != "chirality"}), "cpu"),
                     pairs, log=lambda *_: None) == first


def test_the_panel_temperature_does_not_depend_on_the_tests_handedness():
    """The panel's temperature is fitted on answers in each test's own handedness, and the doubt
    about the handedness on `auto` (the mirrored tests, whose handedness the prior gets wrong,
    get the most doubt). Both used to be fitted jointly on `auto`, where the wrongly named
    mirrored tests raised the temperature (1.0 -> 1.4): every answer flattened."""
    from napari_fdlc.identify import Identifier
    from napari_fdlc.reference import load_atlas, make_panel
    from napari_fdlc.train import calibrate

    rng = np.random.default_rng(0)
    worms = [generate_worm(seed=s) for s in (1, 2)]
    pairs = {"A": [(worms[0], simulate_worm(worms[1], rng).table)]}
    panel = make_panel(load_atlas())
    fitted = {}
    for name, tests in (("as generated", worms), ("mirrored", [_z_flipped(w) for w in worms])):
        settings = calibrate(Identifier.load(), pairs, log=lambda *_: None, panel_tests={"A": (panel, tests)})
        fitted[name] = settings["panel_temperature"], settings["chirality_doubt"]
    assert fitted["as generated"][0] == fitted["mirrored"][0]
    assert fitted["as generated"][1] < fitted["mirrored"][1]


def _z_flipped(table):
    return NeuronTable(table.xyz * np.array([1.0, 1.0, -1.0]), table.colours, table.labels)


def test_tracking_examples_are_placed_as_the_tracker_places_them():
    """A tracking example is a recording's first volume (the reference, its canonical frame) and
    a later volume placed by the geometric chain: partners land within a few µm, and spurious
    or dropped neurons target "no match"."""
    from napari_fdlc.train import tracking_example

    worms = [Worm("A", f"w{i}", generate_worm(seed=i)) for i in range(3)]
    rng = np.random.default_rng(4)
    cfg = TrainConfig(task="track", max_neurons=80)
    for _ in range(5):
        a, b, t, negative, ca, cb = tracking_example(worms, rng, cfg)
        hit = t < len(a)
        assert not negative and ca is not None and cb is not None
        assert 0 < (~hit).sum() < 0.4 * len(t)  # some no-match (drops from the reference, spurious)
        assert np.median(np.linalg.norm(b[hit] - a[t[hit]], axis=1)) < 2.0


def test_tracking_model_trains_and_validates_on_the_corpus(corpus_path, tmp_path):
    from napari_fdlc.model import load_model
    from napari_fdlc.train import train

    cfg = TrainConfig(corpus=str(corpus_path), task="track", steps=2, eval_every=2, batch_size=2,
                      val_labs=("SF",), train_labs=("SF",), val_worms_per_lab=1,
                      model={"dim": 16, "layers": 1, "colour_channels": 3}, out=str(tmp_path / "t"))
    result = train(cfg, log=lambda *_: None)
    assert 0.5 < result["history"][-1]["val_track"]["SF"] <= 1.0
    load_model(tmp_path / "t")


@pytest.mark.parametrize("config, flags, message", [
    ({"task": "dance"}, [], "unknown training task 'dance'"),
    ({"task": "track"}, ["--calibrate-only"], "a tracking model has no inference settings"),
])
def test_train_cli_refuses_what_cannot_be_done(tmp_path, capsys, config, flags, message):
    import json

    from napari_fdlc.cli import main

    path = tmp_path / "c.json"
    path.write_text(json.dumps(config))
    assert main(["train", "--config", str(path), "--out", str(tmp_path / "m"), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "m.safetensors").exists()


def test_mixed_handedness_rate_counts_pairs_of_a_lab_that_differ():
    """1 of lab A's 4 worms is mirrored (z flipped): 6 of its 12 ordered pairs differ; lab B's
    2 worms agree (0 of 2): 6 of 14."""
    from napari_fdlc.train import mixed_handedness_rate

    worms = [Worm("A", str(s), generate_worm(seed=s)) for s in range(3)]
    worms += [Worm("A", "m", _z_flipped(generate_worm(seed=3))), Worm("B", "4", generate_worm(seed=4)),
              Worm("B", "5", generate_worm(seed=5))]
    assert mixed_handedness_rate(worms) == pytest.approx(6 / 14)
    assert mixed_handedness_rate(worms[:3]) == 0.0


def test_worker_processes_make_the_same_batches_for_the_same_seed():
    """``workers`` moves example making into other processes: batches come padded as the
    training step expects them, and the stream is fixed by the seed and the worker count."""
    from napari_fdlc.train import training_batches

    worms = [Worm("lab", f"w{k}", generate_worm(seed=k)) for k in range(4)]
    cfg = TrainConfig(batch_size=3, workers=1, seed=5)

    def first_two():
        stream = training_batches(worms, cfg, None, np.random.default_rng(0))
        return [next(stream) for _ in range(2)]

    one, two = first_two(), first_two()
    for batch_one, batch_two in zip(one, two):
        a, t, am, tm, target, negative, ac, tc = batch_one
        assert a.shape[0] == t.shape[0] == target.shape[0] == 3
        assert am.any() and tm.any() and (target[tm] >= -1).all()
        for x, y in zip(batch_one, batch_two):
            assert torch.equal(x, y)
    assert not torch.equal(one[0][1], one[1][1])  # a stream, not one batch repeated


def test_memoised_calls_keyed_by_id_never_answer_for_a_freed_object():
    """Calibration caches registrations by the test's id; the head window passes a new table on
    every call, and a freed table's id is reused by the next one. The cache must not answer the
    next table with the freed one's registration."""
    from napari_fdlc.train import memoised

    rows = memoised(lambda table: len(table), lambda table: (id(table),), {})
    sizes = (3, 5, 7, 3, 5, 7)
    assert [rows([0] * n) for n in sizes] == list(sizes)  # each list freed before the next


def _worms(labs=("NP", "EY"), per_lab=6):
    return [Worm(lab, f"{lab}{i}", generate_worm(seed=300 + 10 * k + i))
            for k, lab in enumerate(labs) for i in range(per_lab)]


def _pairs_and_trained(worms, cfg):
    """The validation pairs train() scores, and the ids of the tables it trains on."""
    train, _, pairs = held_out(worms, cfg)
    return pairs, {id(w.table) for w in train}


def test_validation_pairs_only_score_held_out_worms():
    """The worm named in a validation pair is always a held-out worm; a training worm may serve
    as the template. (Until session 28 two thirds of the pairs named training worms, and they
    chose the checkpoint and calibrated the inference settings.)"""
    worms = _worms()
    cfg = TrainConfig(train_labs=("NP", "EY"), val_labs=("NP", "EY"), val_worms_per_lab=2, val_pairs_per_lab=1000)
    pairs, trained = _pairs_and_trained(worms, cfg)
    assert all(len(p) == 2 * 5 for p in pairs.values())  # each held-out worm named from the 5 others
    scored_training_worms = {lab: sum(id(test) in trained for _, test in p) for lab, p in pairs.items()}
    assert all(n == 0 for n in scored_training_worms.values()), (
        f"validation pairs whose test is a training worm, per lab: {scored_training_worms} "
        f"of {({lab: len(p) for lab, p in pairs.items()})}")


def test_panel_validation_and_calibration_tests_are_held_out_worms():
    """The panel's validation and calibration tests are held-out worms only."""
    from napari_fdlc.train import _panel_tests

    worms = _worms()
    cfg = TrainConfig(train_labs=("NP", "EY"), val_labs=("NP", "EY"), val_worms_per_lab=2, val_pairs_per_lab=1000)
    pairs, trained = _pairs_and_trained(worms, cfg)
    panel_tests = _panel_tests(worms, pairs, cfg.train_labs)
    leaked = {lab: sum(id(t) in trained for t in tests) for lab, (_, tests) in panel_tests.items()}
    assert set(panel_tests) == {"NP", "EY"}
    assert all(n == 0 for n in leaked.values()), f"panel tests that are training worms, per lab: {leaked}"


class _Stop(Exception):
    pass


def _split_seen_by_train(monkeypatch, cfg):
    """The (train, val) split that train() makes for ``cfg`` (stopped right after it)."""
    import napari_fdlc.train as T

    seen = {}
    real_split = T.split_worms

    def split(worms, c, rng):
        seen["split"] = real_split(worms, c, rng)
        return seen["split"]

    def stop(*args, **kwargs):
        raise _Stop

    monkeypatch.setattr(T, "split_worms", split)
    monkeypatch.setattr(T, "validation_pairs", stop)
    with pytest.raises(_Stop):
        T.train(cfg, log=lambda *_: None)
    return seen["split"]


def test_a_warm_started_stage_validates_on_worms_its_start_never_trained_on(tmp_path, monkeypatch, write_corpus):
    """The held-out worms come from ``split_seed``, not the example seed: a stage warm-started
    with another seed (the shipped recipe's stage 4, seed 1, from stage 3, seed 0) holds out
    worms its start never trained on."""
    from napari_fdlc.model import CorrespondenceModel, save_model

    root = write_corpus(tmp_path / "corpus", {lab: [w.table for w in _worms((lab,), 6)] for lab in ("NP", "EY")})

    base = dict(corpus=str(root), train_labs=("NP", "EY"), val_labs=("NP", "EY"), val_worms_per_lab=2,
                model={"layers": 1, "dim": 16}, steps=2, calibrate=False)
    first = TrainConfig(**base, seed=0, out=str(tmp_path / "stage3"))
    train0, _ = _split_seen_by_train(monkeypatch, first)
    save_model(CorrespondenceModel(first.model), first.out, {"train_config": first.to_json()})

    second = TrainConfig(**base, seed=1, init_from=first.out, out=str(tmp_path / "stage4"))
    train1, _ = _split_seen_by_train(monkeypatch, second)
    trained0 = {(w.lab, w.name) for w in train0}
    held1 = {(w.lab, w.name) for w in _worms_of(root)} - {(w.lab, w.name) for w in train1}
    assert held1
    assert not held1 & trained0, (
        f"worms held out by the warm-started stage that its start trained on: {sorted(held1 & trained0)}")


def _worms_of(root):
    from napari_fdlc.corpus import load_corpus

    return load_corpus(root)


def test_a_neuron_named_without_its_side_is_not_taught_no_match(corpus_path):
    """A neuron some SF worms name without its side ('AIB' where the template has AIBL and
    AIBR) has a partner in the template: its target is unknown (-1), not "no match"."""
    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.train import _targets

    import pandas as pd

    worms = load_corpus(corpus_path, labs=["SF"])
    test = next(w.table for w in worms if w.name == "2023-01-09-08")
    template = next(w.table for w in worms
                    if (w.table.labels == "").mean() < 0.1 and {"AIBL", "AIBR", "RICL", "RICR"} <= set(w.table.labels))
    names = set(template.labels) - {""}
    # the names as the file writes them (rows in file order), whatever reading makes of them
    written = pd.read_csv(corpus_path / "SF" / "2023-01-09-08.csv", dtype=str, keep_default_na=False)["label"]
    assert len(written) == len(test)
    sideless = [j for j, n in enumerate(written.str.rstrip("?"))
                if n and n not in names and (n + "L" in names or n + "R" in names)]
    assert sideless, "the corpus no longer has side-less names in this worm"
    target = _targets(template, test)
    taught_no_match = [written[j] for j in sideless if target[j] == len(template)]
    assert not taught_no_match, f"neurons whose partner the template has, taught as no match: {taught_no_match}"


def test_a_template_name_written_without_its_side_does_not_teach_its_partner_no_match():
    """A fully named template that names a neuron without its side ('ADE') does not teach the
    test's ADEL 'no match' (its partner is there, which one unknown): only the test side's
    side-less names were handled (429 test neurons of 35 SF pairs taught 'no match' by one such
    template)."""
    from napari_fdlc.train import _targets

    rng = np.random.default_rng(0)
    template = NeuronTable(rng.normal(size=(20, 3)) * 10, labels=["ADE"] + [f"N{i}" for i in range(19)])
    test = NeuronTable(rng.normal(size=(3, 3)) * 10, labels=["ADEL", "N1", "XYZ"])
    assert _targets(template, test).tolist() == [-1, 2, 20]


def test_matching_loss_with_no_valid_target_in_a_padded_batch_is_zero_not_nan():
    """No target to learn from in a batch with padded template columns (-inf): the loss is 0,
    not NaN (-inf summed, times 0)."""
    log_p = torch.full((1, 3, 5), -1.0)
    log_p[..., 2:4] = -torch.inf  # padded template columns; the last is "no match"
    loss = matching_loss(log_p, torch.full((1, 3), -1))
    assert torch.isfinite(loss) and loss.item() == 0.0
