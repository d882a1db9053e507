"""Review of how training examples, validation and calibration data are made (train.py).

Each test here fails on the code it was written against because of a defect it names, and
passes once that defect is fixed. Tests that need the NeuroPAL corpus skip without it.
"""

from __future__ import annotations

import pytest

from napari_fdlc.corpus import Worm
from napari_fdlc.reference import generate_worm
from napari_fdlc.train import TrainConfig, held_out


def _worms(labs=("NP", "EY"), per_lab=6):
    return [Worm(lab, f"{lab}{i}", generate_worm(seed=300 + 10 * k + i))
            for k, lab in enumerate(labs) for i in range(per_lab)]


def _pairs_and_trained(worms, cfg):
    """The validation pairs train() scores, and the ids of the tables it trains on."""
    train, _, pairs = held_out(worms, cfg)
    return pairs, {id(w.table) for w in train}


# ---------------------------------------------------------------------------------------------
# 1. Validation and calibration pairs score worms the model trains on


def test_validation_pairs_only_score_held_out_worms():
    """split_worms puts the 2 held-out worms of a training lab *and 4 of its training worms*
    into the validation list, and validation_pairs makes every ordered pair of that list. With
    6 worms, 20 of the 30 pairs have a training worm as the test (12 of them two training worms,
    a pair the model was trained on): the checkpoint is chosen on, and temperature / colour
    weight / no-match weight are calibrated on, worms the model has fitted. A training worm
    may serve as a template; the worm being named must be one the model never trained on."""
    worms = _worms()
    cfg = TrainConfig(train_labs=("NP", "EY"), val_labs=("NP", "EY"), val_worms_per_lab=2, val_pairs_per_lab=1000)
    pairs, trained = _pairs_and_trained(worms, cfg)
    assert all(len(p) == 2 * 5 for p in pairs.values())  # each held-out worm named from the 5 others
    scored_training_worms = {lab: sum(id(test) in trained for _, test in p) for lab, p in pairs.items()}
    assert all(n == 0 for n in scored_training_worms.values()), (
        f"validation pairs whose test is a training worm, per lab: {scored_training_worms} "
        f"of {({lab: len(p) for lab, p in pairs.items()})}")


def test_panel_validation_and_calibration_tests_are_held_out_worms():
    """_panel_tests names every worm of a lab's validation pairs with a panel built without
    that lab: those include the 4 training worms split_worms appends, so the panel's
    validation top-1 (which picks the checkpoint) and its calibration (panel temperature,
    chirality doubt, panel atlas weights) are measured mostly on worms the model trained on."""
    from napari_fdlc.train import _panel_tests

    worms = _worms()
    cfg = TrainConfig(train_labs=("NP", "EY"), val_labs=("NP", "EY"), val_worms_per_lab=2, val_pairs_per_lab=1000)
    pairs, trained = _pairs_and_trained(worms, cfg)
    panel_tests = _panel_tests(worms, pairs, cfg.train_labs)
    leaked = {lab: sum(id(t) in trained for t in tests) for lab, (_, tests) in panel_tests.items()}
    assert set(panel_tests) == {"NP", "EY"}
    assert all(n == 0 for n in leaked.values()), f"panel tests that are training worms, per lab: {leaked}"


# ---------------------------------------------------------------------------------------------
# 2. The held-out worms move with the example seed, across warm starts


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
    """The split of held-out worms is drawn from ``default_rng(cfg.seed)``, the seed of the
    example stream. The shipped recipe warm-starts stage 4 (seed 1) from stage 3 (seed 0):
    on the corpus 9 of the 10 worms stage 4 and 5 hold out (checkpoint choice, calibration)
    were training worms of stages 1-3. A stage started ``--init-from`` a checkpoint must hold
    out worms that checkpoint never trained on (a split that does not follow the example seed,
    or the one recorded with the checkpoint)."""
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


# ---------------------------------------------------------------------------------------------
# 3. Names the corpus writes without a side are taught as "no match"


def test_a_neuron_named_without_its_side_is_not_taught_no_match(corpus_path):
    """A few SF worms name a neuron without its side ('AIB', 'ADE', 'RIC', ... ; 19 such names,
    plus '-alt' names and 'VB02') where every other worm says AIBL / AIBR. Against a fully
    named template that has AIBL and AIBR, _targets makes such a neuron "no match" (column M),
    although its partner is one of the two: the loss pushes a neuron that has a partner toward
    no match. (28 named rows of 10 495 in the corpus, 13 of them in SF 2022-06-14-07: small.)
    Its target should be unknown (-1), or a side-less name read as its sided form."""
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
