"""`fdlc simulate / train / atlas / handedness / evaluate` on bad input and interrupted runs: one-line
error and exit 2, never a traceback; no output lost or half-written; --resume resumes (each test
came from a review, session 27, and says what used to happen).

Everything runs on small synthetic corpora written under tmp_path (worms generated from the
shipped atlas), so no test needs the NeuroPAL corpus.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from napari_fdlc.cli import main
from napari_fdlc.reference import generate_worm
from napari_fdlc.table import NeuronTable, write_table

TINY = {"model": {"layers": 1, "dim": 32}, "steps": 3, "batch_size": 2, "eval_every": 3,
        "val_pairs_per_lab": 1, "val_worms_per_lab": 1, "max_neurons": 40}


def run(*args) -> int:
    return main([str(a) for a in args])


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fdlc: error:"), err
    return err[0]


@pytest.fixture(scope="module")
def fake_corpus(tmp_path_factory, write_corpus) -> Path:
    """Two labs of three generated (fully named) worms, laid out like the NeuroPAL corpus."""
    worms = {lab: [generate_worm(seed=100 + 3 * k + i) for i in range(3)] for k, lab in enumerate(("NP", "EY"))}
    return write_corpus(tmp_path_factory.mktemp("corpus"), worms)


@pytest.fixture
def tiny_config(tmp_path) -> Path:
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(TINY))
    return path


def _train(corpus, config, out, *flags) -> int:
    return run("train", "--config", config, "--corpus", corpus, "--no-calibrate", "--out", out, *flags)


# --------------------------------------------------------------------------------------------
# A malformed corpus folder: one line, not a pandas traceback


@pytest.mark.parametrize("case, content", [
    ("empty", ""),
    ("no_dataset_column", "lab,worm\nNP,w0\n"),
    ("header_only", "dataset,dandiset,worm,n_neurons,n_labeled\n"),
    ("unterminated_quote", 'dataset,worm\nNP,"w0\n'),
])
def test_atlas_refuses_a_malformed_worms_csv_in_one_line(tmp_path, capsys, case, content):
    """Each case raised a Python exception out of the CLI (EmptyDataError, KeyError 'dataset',
    'argmax of an empty sequence', ParserError) instead of one line naming worms.csv."""
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    (corpus / "worms.csv").write_text(content)
    out = tmp_path / "atlas.csv"
    assert run("atlas", "--corpus", corpus, "--out", out) == 2
    assert "worms.csv" in _one_line_error(capsys) or case == "header_only"
    assert not out.exists()


@pytest.mark.parametrize("case", ["unnamed", "three_neurons"])
def test_atlas_of_worms_it_cannot_use_is_one_line(tmp_path, capsys, case, write_corpus):
    """A corpus whose worms carry no names (or too few to align: 3 neurons each) gave
    `IndexError: too many indices for array` from Atlas.to_frame."""
    if case == "unnamed":
        worms = [NeuronTable(generate_worm(seed=s).xyz) for s in (1, 2, 3)]
    else:
        worms = [NeuronTable(np.array([[1.0, 2, 3], [5, 6, 7], [9, 1, 2]]), labels=np.array(["AVAL", "AVAR", "AIYL"], object))
                 for _ in range(3)]
    corpus = write_corpus(tmp_path / "corpus", {"NP": worms})
    out = tmp_path / "atlas.csv"
    assert run("atlas", "--corpus", corpus, "--out", out) == 2
    _one_line_error(capsys)
    assert not out.exists()


def test_atlas_out_onto_a_folder_names_the_output_not_a_temporary_file(tmp_path, fake_corpus, capsys):
    """`fdlc atlas --out DIR` said `fdlc: error: /…/.DIR.k3j2.tmp: Is a directory`: the hidden
    temporary file, which the user never named (atomic_write's os.replace error)."""
    folder = tmp_path / "atlas_here"
    folder.mkdir()
    assert run("atlas", "--corpus", fake_corpus, "--out", folder) == 2
    line = _one_line_error(capsys)
    assert ".tmp" not in line and "atlas_here" in line, line


# --------------------------------------------------------------------------------------------
# fdlc train: bad options and configurations


@pytest.mark.parametrize("seed", ["-1", str(2**70)])
def test_train_refuses_a_seed_out_of_range_in_one_line(tmp_path, fake_corpus, tiny_config, capsys, seed):
    """`--seed -1` gave numpy's `ValueError: expected non-negative integer`, a huge seed
    `Overflow when unpacking long long` (fdlc simulate refuses a negative seed in words)."""
    assert _train(fake_corpus, tiny_config, tmp_path / "m", "--seed", seed) == 2
    _one_line_error(capsys)
    assert not (tmp_path / "m.safetensors").exists()


@pytest.mark.parametrize("flag", ["--eval-every", "--val-pairs-per-lab"])
def test_train_refuses_zero_for_options_that_must_be_at_least_one(tmp_path, fake_corpus, tiny_config, capsys, flag):
    """`--eval-every 0` and `--val-pairs-per-lab 0` were silently ignored (`if args.eval_every:`)
    and training ran with the config's value, while -1 is refused ('must be at least 1')."""
    assert _train(fake_corpus, tiny_config, tmp_path / "m", flag, "0") == 2
    assert "at least 1" in _one_line_error(capsys)
    assert not (tmp_path / "m.safetensors").exists()


@pytest.mark.parametrize("flag", ["--train-labs", "--val-labs"])
def test_train_refuses_labs_that_are_not_in_the_corpus(tmp_path, fake_corpus, tiny_config, capsys, flag):
    """`--train-labs ZZ` crashed in numpy (`a must be a positive integer…`, no training worms);
    `--val-labs ZZ` trained with no validation at all and saved a 'best' checkpoint at top-1 0.
    `fdlc atlas --labs ZZ` and `fdlc evaluate --labs ZZ` refuse this in one line."""
    assert _train(fake_corpus, tiny_config, tmp_path / "m", flag, "ZZ") == 2
    assert "ZZ" in _one_line_error(capsys)
    assert not (tmp_path / "m.safetensors").exists()


@pytest.mark.parametrize("config", [
    [1, 2],
    {"steps": "abc"},
    {"train_labs": 5},
    {"model": {"dim": -4}},
    {"model": 3},
])
def test_train_refuses_a_malformed_config_in_one_line(tmp_path, fake_corpus, capsys, config):
    """Each gave a traceback: AttributeError ('list' has no 'get'), TypeError ('<' between str
    and int; int not iterable; int not a mapping), RuntimeError (negative dimension)."""
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(config))
    assert run("train", "--config", path, "--corpus", fake_corpus, "--no-calibrate", "--out", tmp_path / "m") == 2
    _one_line_error(capsys)


def test_train_refuses_an_unknown_device_in_one_line(tmp_path, fake_corpus, tiny_config, capsys):
    """`--device nonsense` gave torch's RuntimeError traceback (only `cuda*` is checked)."""
    assert _train(fake_corpus, tiny_config, tmp_path / "m", "--device", "nonsense") == 2
    _one_line_error(capsys)


def test_train_on_a_corpus_without_a_usable_pair_stops_with_one_line(tmp_path, write_corpus):
    """Worms of 3 named neurons each: no example has the 4 matches make_example needs, and
    sample_example's `while True` draws forever: `fdlc train` hung (killed after 40 s by hand).
    It should refuse quickly."""
    worm = NeuronTable(np.array([[1.0, 2, 3], [5, 6, 7], [9, 1, 2]]), labels=np.array(["AVAL", "AVAR", "AIYL"], object))
    corpus = write_corpus(tmp_path / "corpus", {"NP": [worm] * 3, "EY": [worm] * 3})
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(TINY))
    cmd = [sys.executable, "-m", "napari_fdlc.cli", "train", "--config", str(config), "--corpus", str(corpus),
           "--no-calibrate", "--out", str(tmp_path / "m")]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**os.environ, "OMP_NUM_THREADS": "1"})
    except subprocess.TimeoutExpired:
        pytest.fail("fdlc train on worms without 4 shared names ran for 120 s (endless loop in sample_example)")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


# --------------------------------------------------------------------------------------------
# fdlc train --out and checkpoints


def test_train_writes_the_weights_where_it_says(tmp_path, fake_corpus, tiny_config, capsys):
    """`--out runs/model.v2` printed 'weights at runs/model.v2.safetensors' but wrote
    runs/model.safetensors (Path.with_suffix replaces '.v2'): a second run with
    `--out runs/model.v3` silently replaced the first's checkpoint."""
    out = tmp_path / "model.v2"
    assert _train(fake_corpus, tiny_config, out) == 0
    said = capsys.readouterr().out.strip().splitlines()[-1].rsplit("weights at ", 1)[1]
    assert Path(said).exists(), (said, sorted(p.name for p in tmp_path.iterdir()))


def test_save_model_interrupted_leaves_a_loadable_checkpoint(tmp_path, monkeypatch):
    """save_model renames the new .safetensors into place, then writes the .json: a Ctrl-C (or
    full disk) in between leaves new weights beside the old configuration, a checkpoint that
    no longer loads ('the weights do not fit the configuration')."""
    from napari_fdlc.model import CorrespondenceModel, load_model, save_model

    path = tmp_path / "model"
    save_model(CorrespondenceModel({"layers": 1, "dim": 32}), path, {})
    original = Path.write_text

    def interrupted(self, *args, **kwargs):
        if self.name.endswith(".json.tmp"):
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_model(CorrespondenceModel({"layers": 2, "dim": 64}), path, {})
    monkeypatch.undo()
    load_model(path)  # the old checkpoint or the new one, whole: not a mix of the two


# --------------------------------------------------------------------------------------------
# fdlc train --resume


@pytest.mark.parametrize("flag", ["--resume", "--init-from"])
def test_train_from_a_corrupt_checkpoint_is_one_line(tmp_path, fake_corpus, tiny_config, capsys, flag):
    """A .safetensors file that is not one gave safetensors' `SafetensorError: Error while
    deserializing header` traceback (train._load_start does not catch it; load_model does)."""
    from napari_fdlc.model import CorrespondenceModel, save_model

    checkpoint = tmp_path / "ck" / "model"
    save_model(CorrespondenceModel(TINY["model"]), checkpoint, {"best_step": 1})
    checkpoint.with_suffix(".safetensors").write_bytes(b"garbage, not safetensors")
    extra = ["--resume"] if flag == "--resume" else ["--init-from", str(checkpoint)]
    out = checkpoint if flag == "--resume" else tmp_path / "new"
    assert _train(fake_corpus, tiny_config, out, *extra) == 2
    _one_line_error(capsys)


def test_resume_refuses_a_checkpoint_of_another_model_and_keeps_it(tmp_path, fake_corpus, tiny_config, capsys):
    """`--resume` onto a checkpoint of another architecture loaded '0/35 tensors' (whatever
    fits), trained a fresh model from the checkpoint's step count and then overwrote that
    checkpoint with it: the old model was lost. Resuming must take every tensor or refuse."""
    from napari_fdlc.model import CorrespondenceModel, save_model

    checkpoint = tmp_path / "ck" / "model"
    save_model(CorrespondenceModel({"layers": 2, "dim": 64}), checkpoint, {"best_step": 3, "history": []})
    before = checkpoint.with_suffix(".safetensors").read_bytes()
    assert _train(fake_corpus, tiny_config, checkpoint, "--resume", "--steps", "6") == 2
    _one_line_error(capsys)
    assert checkpoint.with_suffix(".safetensors").read_bytes() == before


@pytest.fixture
def stopped_run(tmp_path, fake_corpus, tiny_config):
    """A 6-step run stopped after step 3 (validated and saved at step 3)."""
    out = tmp_path / "run" / "model"
    assert _train(fake_corpus, tiny_config, out, "--steps", "6", "--stop-at", "3") == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["best_step"] == 3
    return out


def test_resume_keeps_the_validation_history(stopped_run, fake_corpus, tiny_config):
    """After `--resume` the checkpoint's history held only the resumed steps ([6]): the
    validation record of steps 1-3 was dropped from the JSON."""
    assert _train(fake_corpus, tiny_config, stopped_run, "--steps", "6", "--resume") == 0
    steps = [h["step"] for h in json.loads(stopped_run.with_suffix(".json").read_text())["history"]]
    assert steps == [3, 6], steps


def test_resume_does_not_replace_a_better_checkpoint(stopped_run, fake_corpus, tiny_config):
    """train() starts `best` at -1 when resuming, so the first validation after --resume always
    overwrites the checkpoint, however much better it had validated (here: step 3 recorded at
    top-1 1.0, step 6 scores ~0.27 and still replaced it; with the real history too: step 3
    0.269, step 6 0.268 replaced it)."""
    meta_path = stopped_run.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    meta["history"][-1]["mean_top1"] = 1.0
    meta_path.write_text(json.dumps(meta))
    before = stopped_run.with_suffix(".safetensors").read_bytes()
    assert _train(fake_corpus, tiny_config, stopped_run, "--steps", "6", "--resume") == 0
    assert stopped_run.with_suffix(".safetensors").read_bytes() == before


def test_resume_prints_no_python_warning(stopped_run, fake_corpus, tiny_config, capfd):
    """Fast-forwarding the LR schedule with sched.step() before any opt.step() makes torch print
    a multi-line `UserWarning: Detected call of lr_scheduler.step() before optimizer.step()`
    on every --resume."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _train(fake_corpus, tiny_config, stopped_run, "--steps", "6", "--resume") == 0
    assert not [w for w in caught if "lr_scheduler.step()" in str(w.message)]


def test_resumed_training_does_not_replay_the_examples_of_the_steps_done():
    """With --workers 0 (the default) training_batches ignores ``first_step``: a run resumed at
    step 4 is fed the very batches of steps 1, 2, 3 again (same seed, same rng state), while
    the workers' streams are seeded by the first step. A resumed run should continue the
    stream, not replay it."""
    import torch

    from napari_fdlc.corpus import Worm
    from napari_fdlc.train import TrainConfig, training_batches

    worms = [Worm("NP", f"w{i}", generate_worm(seed=200 + i)) for i in range(3)]
    cfg = TrainConfig(batch_size=1, max_neurons=30)
    first = next(training_batches(worms, cfg, None, np.random.default_rng(0), first_step=1))
    resumed = next(training_batches(worms, cfg, None, np.random.default_rng(0), first_step=4))
    same = all(a.shape == b.shape and torch.equal(a, b) for a, b in zip(first, resumed))
    assert not same, "the batch of resumed step 4 is the batch of step 1"


# --------------------------------------------------------------------------------------------
# fdlc evaluate


@pytest.mark.parametrize("meta", [
    {"config": {"layers": 1, "dim": -5}},
    {"config": {"layers": 1, "dim": 32}, "inference": [1, 2]},
])
def test_evaluate_weights_with_a_bad_configuration_are_one_line(tmp_path, untrained_weights, capsys, meta):
    """A model JSON with a negative dimension gave torch's `RuntimeError: Trying to create tensor
    with negative dimension`; an 'inference' that is not an object gave `TypeError: cannot
    convert dictionary update sequence element` (Identifier.load)."""
    weights = tmp_path / "model"
    weights.with_suffix(".safetensors").write_bytes(Path(untrained_weights).with_suffix(".safetensors").read_bytes())
    weights.with_suffix(".json").write_text(json.dumps(meta))
    assert run("evaluate", "--corpus", tmp_path / "no_corpus", "--weights", weights, "--out", tmp_path / "a.md") == 2
    _one_line_error(capsys)


def test_evaluate_out_onto_a_folder_writes_nothing_and_names_the_output(tmp_path, fake_corpus, untrained_weights, capsys):
    """`--out DIR`: the work ran to the end, the reliability plot was written into
    DIR/../images/, then the report failed with the name of a hidden temporary file
    (`/…/.acc.md.x1y2.tmp: Is a directory`). It should be refused as `fdlc label` refuses it:
    before any work, naming the output, nothing written."""
    folder = tmp_path / "acc.md"
    folder.mkdir()
    assert run("evaluate", "--corpus", fake_corpus, "--labs", "NP", "--pairs-per-lab", "1", "--panel-worms-per-lab", "0",
               "--synthetic-pairs", "0", "--no-cpd", "--weights", untrained_weights, "--out", folder) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("fdlc: error:")]
    assert "Traceback" not in err and len(errors) == 1, err
    assert ".tmp" not in errors[0] and "acc.md" in errors[0], errors[0]
    assert not (tmp_path / "images").exists()


def test_evaluate_without_matplotlib_writes_the_report_without_the_plot(tmp_path, fake_corpus, untrained_weights,
                                                                         capsys, monkeypatch):
    """matplotlib comes with the [test] extra only: without it the report is still written
    (the plot left out, one warning line), not lost to an ImportError at the end of the run."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    out = tmp_path / "acc.md"
    assert run("evaluate", "--corpus", fake_corpus, "--labs", "NP", "--pairs-per-lab", "1", "--panel-worms-per-lab", "0",
               "--synthetic-pairs", "0", "--no-cpd", "--weights", untrained_weights, "--out", out) == 0
    assert "matplotlib" in capsys.readouterr().err
    text = out.read_text()
    assert "| NP | pairs | fdlc |" in text and "calibration.png" not in text and "--out" in text
    assert not (tmp_path / "images").exists()


def test_evaluate_on_worms_too_small_for_an_atlas_is_one_line(tmp_path, untrained_weights, capsys, write_corpus):
    """Worms of 3 neurons: `IndexError: too many indices for array` from the atlas built per
    lab (reference.build_atlas with no name kept)."""
    worm = NeuronTable(np.array([[1.0, 2, 3], [5, 6, 7], [9, 1, 2]]), labels=np.array(["AVAL", "AVAR", "AIYL"], object))
    corpus = write_corpus(tmp_path / "corpus", {"NP": [worm] * 3, "EY": [worm] * 3})
    assert run("evaluate", "--corpus", corpus, "--labs", "NP", "--pairs-per-lab", "1", "--panel-worms-per-lab", "1",
               "--synthetic-pairs", "0", "--no-cpd", "--weights", untrained_weights, "--out", tmp_path / "a.md") == 2
    _one_line_error(capsys)
    assert not (tmp_path / "a.md").exists()


# --------------------------------------------------------------------------------------------
# One volume where one worm is meant; the corpus's own labs by default


@pytest.mark.parametrize("command", ["simulate", "handedness"])
def test_a_table_of_several_time_points_is_refused_where_one_worm_is_meant(tmp_path, capsys, command):
    """`fdlc simulate` merged the time points of a recording into one worm (every name then
    repeated, so unnamed); `fdlc handedness` said 'fewer than 6 named neurons'. Both now say
    the table holds several time points."""
    from napari_fdlc.track import join_by_time

    worm = generate_worm(seed=5)
    path = tmp_path / "recording.csv"
    write_table(join_by_time([worm, worm]), path)
    args = ["simulate", path, "--count", "1", "--out", tmp_path / "syn"] if command == "simulate" else ["handedness", path]
    assert run(*args) == 2
    assert "time points" in _one_line_error(capsys)


def test_evaluate_defaults_to_the_labs_the_corpus_has(fake_corpus, untrained_weights, tmp_path, capsys):
    """`fdlc evaluate` without --labs asked for all five built-in labs and failed on a corpus of
    two ('no worms of lab(s) KK, SF, SK1')."""
    out = tmp_path / "a.md"
    assert run("evaluate", "--corpus", fake_corpus, "--weights", untrained_weights, "--pairs-per-lab", "1",
               "--panel-worms-per-lab", "1", "--synthetic-pairs", "0", "--no-cpd", "--out", out) == 0
    report = out.read_text()
    assert "| NP |" in report and "| EY |" in report


def test_evaluate_scores_a_lab_named_twice_once(fake_corpus, untrained_weights, tmp_path):
    """`--labs NP NP` scored NP twice: its rows twice in the tables and twice in the pooled
    calibration and threshold figures."""
    out = tmp_path / "a.md"
    assert run("evaluate", "--corpus", fake_corpus, "--weights", untrained_weights, "--labs", "NP", "NP",
               "--pairs-per-lab", "1", "--panel-worms-per-lab", "1", "--synthetic-pairs", "0", "--no-cpd",
               "--out", out) == 0
    rows = [line for line in out.read_text().splitlines() if line.startswith("| NP | pairs | fdlc | position |")]
    assert len(rows) == 1, rows


FAST_EVALUATION = ("--pairs-per-lab", "1", "--panel-worms-per-lab", "0", "--synthetic-pairs", "0", "--no-cpd")


def test_evaluate_refuses_an_out_inside_the_corpus(tmp_path, write_corpus, untrained_weights, capsys):
    """The corpus is read, never written: `--out CORPUS/NP/w0.csv` is refused before any work.
    The report used to replace the worm's table (the corpus no longer loaded)."""
    corpus = write_corpus(tmp_path / "corpus", {lab: [generate_worm(seed=300 + 3 * k + i) for i in range(3)]
                                                for k, lab in enumerate(("NP", "EY"))})
    victim = corpus / "NP" / "w0.csv"
    before = victim.read_bytes()
    assert run("evaluate", "--corpus", corpus, "--labs", "NP", *FAST_EVALUATION, "--weights", untrained_weights,
               "--out", victim) == 2
    assert "inside the corpus" in _one_line_error(capsys)
    assert victim.read_bytes() == before


def test_evaluate_refuses_an_out_onto_its_own_weights(tmp_path, fake_corpus, untrained_weights, capsys):
    """`--weights runs/model --out runs/model.json` is refused (an output that replaces an
    input); the report used to be written over the model's configuration."""
    weights = tmp_path / "model"
    for suffix in (".safetensors", ".json"):
        Path(str(weights) + suffix).write_bytes(Path(str(untrained_weights) + suffix).read_bytes())
    config = Path(str(weights) + ".json")
    before = config.read_bytes()
    assert run("evaluate", "--corpus", fake_corpus, "--labs", "NP", *FAST_EVALUATION, "--weights", weights,
               "--out", config) == 2
    assert "replace an input" in _one_line_error(capsys)
    assert config.read_bytes() == before


def test_evaluate_report_names_the_command_that_made_it(tmp_path, fake_corpus, untrained_weights):
    """The report's "Made by" command reproduces it: --corpus, --labs and --weights were left out,
    so a report of one lab with other weights claimed every lab and the shipped model."""
    out = tmp_path / "acc.md"
    assert run("evaluate", "--corpus", fake_corpus, "--labs", "NP", *FAST_EVALUATION, "--weights", untrained_weights,
               "--out", out) == 0
    made_by = next(line for line in out.read_text().splitlines() if line.startswith("Made by"))
    assert f"--corpus {fake_corpus} --labs NP --weights {untrained_weights} --pairs-per-lab 1" in made_by, made_by


def test_evaluate_draws_synthetic_pairs_from_the_labs_asked_for(tmp_path, fake_corpus, untrained_weights, monkeypatch):
    """With `--labs NP` the synthetic pairs are NP's worms too; they were drawn from every lab."""
    import napari_fdlc.simulate as simulate

    sources, original = [], simulate.simulate_worm

    def recording(table, *args, **kwargs):
        sources.append(Path(str(table.source)).parent.name)
        return original(table, *args, **kwargs)

    monkeypatch.setattr(simulate, "simulate_worm", recording)
    assert run("evaluate", "--corpus", fake_corpus, "--labs", "NP", "--pairs-per-lab", "0", "--panel-worms-per-lab", "0",
               "--synthetic-pairs", "6", "--no-cpd", "--weights", untrained_weights, "--out", tmp_path / "acc.md") == 0
    assert sources and set(sources) == {"NP"}, sources


def test_a_new_run_from_a_checkpoints_configuration_does_not_replace_it(tmp_path, fake_corpus, tiny_config, capsys):
    """`fdlc train --config runs/model.json` (a checkpoint's JSON) without --out took the
    checkpoint's own --out, and the new run replaced the checkpoint it was configured from."""
    out = tmp_path / "run" / "model"
    assert _train(fake_corpus, tiny_config, out) == 0
    before = out.with_suffix(".safetensors").read_bytes()
    capsys.readouterr()
    assert run("train", "--config", out.with_suffix(".json"), "--corpus", fake_corpus, "--no-calibrate") == 2
    assert "--out" in _one_line_error(capsys)
    assert out.with_suffix(".safetensors").read_bytes() == before


def test_handedness_of_a_flat_worm_is_refused(tmp_path, capsys):
    """All named neurons in one z plane: `fdlc handedness` answered "same" with confidence,
    though a flat worm and its mirror image are the same worm turned over."""
    worm = generate_worm(seed=7)
    xyz = worm.xyz.copy()
    xyz[:, 2] = 5.0
    path = tmp_path / "flat.csv"
    write_table(NeuronTable(xyz, worm.colours, worm.labels), path)
    assert run("handedness", path) == 2
    assert "plane" in _one_line_error(capsys)


# --------------------------------------------------------------------------------------------
# Training settings and outputs refused before any training (session 30's review)


class TrainingStarted(Exception):
    """Raised by :func:`no_training`: the run got as far as making training batches."""


@pytest.fixture
def no_training(monkeypatch):
    """Stop any run at its first batch: these tests are about what is refused before training."""
    def sentinel(*args, **kwargs):
        raise TrainingStarted
        yield  # pragma: no cover

    monkeypatch.setattr("napari_fdlc.train.training_batches", sentinel)


def _config(tmp_path, name="tiny.json", **overrides) -> Path:
    path = tmp_path / name
    path.write_text(json.dumps({**TINY, **overrides}))
    return path


def _tiny_checkpoint(path: Path, model: dict | None = None, card: dict | None = None) -> Path:
    import torch

    from napari_fdlc.model import CorrespondenceModel, save_model

    torch.manual_seed(0)
    save_model(CorrespondenceModel(model or TINY["model"]), path, card or {})
    return path


@pytest.mark.parametrize("setting, value", [
    ("lr", -0.001), ("lr", float("nan")), ("weight_decay", -1.0), ("scale_jitter", float("nan")),
    ("max_neurons", 0), ("colour_dropout", 1.5), ("motion", [3.0, 1.0]),
])
def test_train_refuses_nonsense_numbers_in_its_configuration_in_one_line(tmp_path, fake_corpus, capsys, no_training,
                                                                          setting, value):
    """Before: the first four reached torch or numpy (`Invalid learning rate`, `high - low range
    exceeds valid bounds`), max_neurons 0 cropped every worm to nothing ('the neuron table is
    empty'), the last two ran. Now each is refused in one line naming the setting."""
    assert _train(fake_corpus, _config(tmp_path, **{setting: value}), tmp_path / "out" / "model") == 2
    assert setting in _one_line_error(capsys)


def test_train_refuses_a_device_torch_cannot_use_in_one_line(tmp_path, fake_corpus, tiny_config, capsys, no_training):
    """`--device mps` on a torch without MPS parses as a device name; before, the run went on to
    `model.to('mps')` and a RuntimeError traceback. Now a tensor is put there first."""
    import torch

    if torch.backends.mps.is_available():
        pytest.skip("this machine has MPS")
    assert _train(fake_corpus, tiny_config, tmp_path / "out" / "model", "--device", "mps") == 2
    assert "mps" in _one_line_error(capsys)


@pytest.mark.parametrize("held_out", [2, 3])
def test_train_with_fewer_than_two_training_worms_is_refused_in_one_line(tmp_path, fake_corpus, capsys, held_out):
    """A lab of 3 worms with 2 (3) held out leaves 1 (0) training worms; before, drawing a real
    pair of two different worms ended in numpy's ValueError traceback."""
    assert run("train", "--config", _config(tmp_path, val_worms_per_lab=held_out), "--corpus", fake_corpus,
               "--train-labs", "NP", "--no-calibrate", "--out", tmp_path / "out" / "model") == 2
    assert "val_worms_per_lab" in _one_line_error(capsys)


def test_a_training_lab_without_validation_pairs_still_gives_a_checkpoint(tmp_path, tiny_config, write_corpus):
    """A training lab of one worm has no validation pair (top-1 NaN). Before, the mean over
    the labs was NaN, never better than the best so far, and no checkpoint was saved, while the
    run exited 0 and printed where the weights were. Labs without pairs are left out of it."""
    root = write_corpus(tmp_path / "corpus", {"NP": [generate_worm(seed=100 + i) for i in range(3)],
                                              "EY": [generate_worm(seed=200)]})
    out = tmp_path / "out" / "model"
    assert _train(root, tiny_config, out) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert out.with_suffix(".safetensors").exists() and meta["best_step"] == TINY["steps"]


def test_train_keeps_a_configurations_calibrate_false(tmp_path, fake_corpus, monkeypatch):
    """Flags override the --config JSON, and only when given: before, `"calibrate": false` (as
    in docs/training/stage1-3.json) was turned back on when --no-calibrate was not given."""
    seen = {}

    def fake_train(cfg, log=print):
        seen["calibrate"] = cfg.calibrate
        return {"best_mean_top1": 0.0, "history": [], "minutes": 0.0}

    monkeypatch.setattr("napari_fdlc.train.train", fake_train)
    assert run("train", "--config", _config(tmp_path, calibrate=False), "--corpus", fake_corpus,
               "--out", tmp_path / "out" / "model") == 0
    assert seen["calibrate"] is False


def test_train_init_from_weights_of_which_nothing_fits_is_refused(tmp_path, fake_corpus, tiny_config, capsys, no_training):
    """Before, `--init-from` another architecture's weights logged '0/35 tensors' and trained
    from random weights as if nothing were wrong."""
    import torch
    from safetensors.torch import save_file

    other = tmp_path / "other"
    save_file({"encoder.weight": torch.zeros(4, 4)}, f"{other}.safetensors")
    assert _train(fake_corpus, tiny_config, tmp_path / "out" / "model", "--init-from", other) == 2
    assert "fits" in _one_line_error(capsys)


def test_resume_refuses_a_checkpoint_of_another_model_configuration_of_the_same_shapes(
        tmp_path, fake_corpus, tiny_config, capsys, no_training):
    """A checkpoint trained with scale_um 40 has the tensors of one trained with 20; before,
    --resume compared shapes only, trained it under 20 and rewrote its JSON with 20: weights
    for one input scale saved as a model of another."""
    checkpoint = _tiny_checkpoint(tmp_path / "ck" / "model", {**TINY["model"], "scale_um": 40.0},
                                  {"best_step": 1, "history": [{"step": 1, "mean_top1": 0.1}]})
    assert _train(fake_corpus, tiny_config, checkpoint, "--steps", "4", "--resume") == 2
    assert "configuration differs" in _one_line_error(capsys)


def test_resume_with_no_step_left_is_refused(tmp_path, fake_corpus, tiny_config, capsys, no_training):
    """A checkpoint at step 3 resumed with --steps 3 has nothing to do: before, no step ran and
    the run said where weights were that it had not written; --stop-at outside the run's steps
    was never reached."""
    checkpoint = _tiny_checkpoint(tmp_path / "ck" / "model", None, {"best_step": 3, "history": [{"step": 3, "mean_top1": 0.1}]})
    assert _train(fake_corpus, tiny_config, checkpoint, "--steps", "3", "--resume") == 2
    assert "--steps" in _one_line_error(capsys)
    assert _train(fake_corpus, tiny_config, checkpoint, "--steps", "8", "--stop-at", "2", "--resume") == 2
    assert "--stop-at" in _one_line_error(capsys)


def test_a_new_run_from_the_checkpoint_at_out_is_refused_and_keeps_it(tmp_path, fake_corpus, tiny_config, capsys, no_training):
    """`--init-from runs/model --out runs/model`: before, the new run's first validation (its
    best starts at -1) replaced the weights it started from."""
    checkpoint = _tiny_checkpoint(tmp_path / "runs" / "model")
    before = checkpoint.with_suffix(".safetensors").read_bytes()
    assert _train(fake_corpus, tiny_config, checkpoint, "--init-from", checkpoint) == 2
    assert "replace an input" in _one_line_error(capsys)
    assert checkpoint.with_suffix(".safetensors").read_bytes() == before


@pytest.mark.parametrize("where", ["under_a_file", "a_folder/"])
def test_train_out_that_cannot_be_written_is_refused_before_training(tmp_path, fake_corpus, tiny_config, capsys,
                                                                    no_training, where):
    """Before, --out under a file trained until the first validation and failed to save there;
    --out ending in a separator wrote the hidden files `.safetensors` and `.json`."""
    (tmp_path / "under_a_file").write_text("a file\n")
    out = f"{tmp_path / 'under_a_file' / 'model'}" if where == "under_a_file" else f"{tmp_path}/{where}"
    assert _train(fake_corpus, tiny_config, out) == 2
    _one_line_error(capsys)


@pytest.mark.parametrize("flag", ["--calibrate-only", "--resume"])
def test_without_config_a_checkpoint_goes_on_with_its_own_configuration(tmp_path, fake_corpus, tiny_config, monkeypatch,
                                                                         flag):
    """A fold trained on NP alone, then `fdlc train --calibrate-only --out it` (or --resume)
    without --config: before, the default configuration (all five labs, 3000 steps) was used, so
    the fold was calibrated on the very lab it holds out. The checkpoint's recorded one is used."""
    out = tmp_path / "fold" / "model"
    assert _train(fake_corpus, tiny_config, out, "--train-labs", "NP", "--steps", "6", "--stop-at", "3") == 0
    seen = {}
    monkeypatch.setattr("napari_fdlc.train.calibrate_checkpoint", lambda cfg, *a, **k: seen.update(cfg=cfg))
    monkeypatch.setattr("napari_fdlc.train.train", lambda cfg, log=print: seen.update(cfg=cfg) or
                        {"best_mean_top1": 0.5, "history": [], "minutes": 0.0})
    assert run("train", "--corpus", fake_corpus, "--out", out, flag) == 0
    assert seen["cfg"].train_labs == ("NP",) and seen["cfg"].steps == 6
    assert Path(seen["cfg"].out) == out


def test_resume_from_a_checkpoints_configuration_is_not_held_to_that_runs_stop(stopped_run, fake_corpus):
    """The stopped run recorded `stop_at` 3; resumed with its own JSON as --config (or with
    none), the run goes on to --steps instead of being refused for a stop already passed."""
    assert run("train", "--config", stopped_run.with_suffix(".json"), "--corpus", fake_corpus, "--no-calibrate",
               "--out", stopped_run, "--steps", "6", "--resume") == 0
    steps = [h["step"] for h in json.loads(stopped_run.with_suffix(".json").read_text())["history"]]
    assert steps == [3, 6], steps


# --------------------------------------------------------------------------------------------
# fdlc atlas and fdlc handedness (session 30's review)


@pytest.mark.parametrize("inside", ["worms.csv", "A/w0.csv"])
def test_atlas_refuses_an_out_inside_the_corpus(tmp_path, write_corpus, capsys, inside):
    """An atlas written into the corpus folder is refused (the corpus is read, never written);
    --out CORPUS/worms.csv (or a worm's table) used to be replaced by the atlas."""
    worms = [generate_worm(seed=s) for s in range(1, 5)]
    corpus = write_corpus(tmp_path / "corpus", {"A": worms[:2], "B": worms[2:]})
    target = corpus / inside
    before = target.read_text()
    assert run("atlas", "--corpus", corpus, "--out", target) == 2
    assert "inside the corpus folder" in _one_line_error(capsys)
    assert target.read_text() == before


def test_atlas_labs_are_matched_as_the_corpus_is_read(tmp_path, write_corpus, capsys):
    """A lab written 'B ' in worms.csv is lab B for --labs too; it was refused with 'no worms of
    lab(s) B (labs: A, B )'."""
    worms = [generate_worm(seed=s) for s in range(1, 7)]
    corpus = write_corpus(tmp_path / "corpus", {"A": worms[:3], "B": worms[3:]})
    index = corpus / "worms.csv"
    index.write_text(index.read_text().replace("\nB,", "\nB ,"))
    out = tmp_path / "atlas.csv"
    code = run("atlas", "--corpus", corpus, "--labs", "B", "--out", out)
    assert code == 0, capsys.readouterr().err
    assert "of B ->" in capsys.readouterr().out


def test_handedness_refuses_a_flat_template(tmp_path, capsys):
    """A flat template (z all equal) has no handedness to compare with: refused in one line; a
    worm and its mirror image were both answered "same"."""
    worm = generate_worm(seed=1)
    mirrored = NeuronTable(worm.xyz * [1, 1, -1], worm.colours, worm.labels)
    template = generate_worm(seed=2)
    flat = template.xyz.copy()
    flat[:, 2] = 5.0
    paths = {"worm": tmp_path / "worm.csv", "mirrored": tmp_path / "mirrored.csv", "flat": tmp_path / "flat.csv"}
    write_table(worm, paths["worm"])
    write_table(mirrored, paths["mirrored"])
    write_table(NeuronTable(flat, template.colours, template.labels), paths["flat"])
    code = run("handedness", paths["worm"], paths["mirrored"], "--template", paths["flat"])
    out = capsys.readouterr()
    assert code != 0, f"answered against a flat template: {out.out!r}"
    err = out.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fdlc: error:") and "plane" in err[0], err


def test_handedness_of_three_named_neurons_says_too_few_names(tmp_path, capsys):
    """Three named neurons always lie in a plane: the message is that 6 names are needed, not to
    check the z positions."""
    worm = generate_worm(seed=1)
    three = NeuronTable(worm.xyz[:3], {k: v[:3] for k, v in worm.colours.items()}, worm.labels[:3])
    path = tmp_path / "three.csv"
    write_table(three, path)
    assert run("handedness", path) != 0
    line = _one_line_error(capsys)
    assert "fewer than 6 named neurons in common" in line, line


# --------------------------------------------------------------------------------------------
# Session 32 (a helper review of fdlc train)


@pytest.mark.parametrize("flags, overrides", [
    ((), {"val_worms_per_lab": 0}),
    (("--train-labs", "NP", "--val-labs", "EY"), {}),
], ids=["no-held-out-worms", "only-the-held-out-lab-validated"])
def test_train_without_validation_of_a_training_lab_is_refused(tmp_path, fake_corpus, capsys, flags, overrides):
    """Nothing of a training lab to validate on: the first checkpoint was kept whatever followed
    (every score 0), or it was chosen on the held-out lab's scores, and calibration picked
    settings among NaN scores (colour switched off). Now refused before training."""
    out = tmp_path / "out" / "model"
    assert run("train", "--config", _config(tmp_path, **overrides), "--corpus", fake_corpus, *flags, "--out", out) == 2
    assert "held-out worms of a training lab" in _one_line_error(capsys)
    assert not out.with_suffix(".json").exists()


def test_train_colour_channels_other_than_three_is_refused(tmp_path, fake_corpus, capsys):
    """"colour_channels": 4 passed the checks; training ran until its first validation died with
    a RuntimeError traceback (only R, G, B are fed)."""
    config = _config(tmp_path, model={"layers": 1, "dim": 32, "colour_channels": 4})
    assert _train(fake_corpus, config, tmp_path / "m") == 2
    assert "colour_channels" in _one_line_error(capsys)


def test_train_worker_error_is_one_line(tmp_path, write_corpus, capsys):
    """With --workers, an error in a worker (here: no usable pair) came out as torch's wrapper:
    "Caught FdlcError in DataLoader worker process 0" and the worker's whole traceback."""
    small = NeuronTable(np.array([[1.0, 2, 3], [5, 6, 7], [9, 1, 2]]), labels=np.array(["AVAL", "AVAR", "AIYL"], object))
    corpus = write_corpus(tmp_path / "corpus", {"NP": [small] * 3, "EY": [small] * 3})
    assert _train(corpus, _config(tmp_path), tmp_path / "m", "--workers", "1") == 2
    line = _one_line_error(capsys)
    assert "no training example" in line and "Traceback" not in line, line[:300]


@pytest.mark.parametrize("history", [[None], [{"step": 3, "mean_top1": None}], [{"step": "x", "mean_top1": 0.2}]],
                         ids=["null-entry", "null-top1", "text-step"])
def test_resume_from_a_checkpoint_with_a_damaged_history_is_one_line(tmp_path, fake_corpus, capsys, history):
    """A checkpoint record whose history is damaged gave an AttributeError / TypeError traceback."""
    import torch

    from napari_fdlc.model import CorrespondenceModel, save_model

    torch.manual_seed(0)
    checkpoint = tmp_path / "ck" / "model"
    save_model(CorrespondenceModel(TINY["model"]), checkpoint, {"best_step": 3, "history": history})
    assert _train(fake_corpus, _config(tmp_path), checkpoint, "--steps", "6", "--resume") == 2
    assert "not a readable checkpoint record" in _one_line_error(capsys)


def test_train_out_onto_its_own_recipe_is_refused(tmp_path, fake_corpus, capsys):
    """--config runs/exp1.json --out runs/exp1: the first save replaced the recipe with the
    checkpoint's record. Now refused before training, the recipe kept."""
    config = _config(tmp_path, name="exp1.json")
    before = config.read_bytes()
    assert _train(fake_corpus, config, tmp_path / "exp1") == 2
    assert "would replace an input" in _one_line_error(capsys)
    assert config.read_bytes() == before


def test_train_no_calibrate_with_calibrate_only_is_refused(tmp_path, monkeypatch):
    """`--no-calibrate --calibrate-only` is refused (exit 2, nothing fitted): the settings were
    fitted anyway and the checkpoint's JSON rewritten."""
    import napari_fdlc.train as train_module
    from napari_fdlc.cli import main

    called = []
    monkeypatch.setattr(train_module, "calibrate_checkpoint", lambda cfg: called.append(cfg))
    rc = main(["train", "--config", str(Path(__file__).resolve().parents[1] / "docs" / "training" / "stage4.json"), "--out", str(tmp_path / "m"),
               "--calibrate-only", "--no-calibrate"])
    assert not called, "the checkpoint was calibrated although --no-calibrate was given"
    assert rc == 2


def test_a_training_run_that_diverges_stops_with_one_line(tmp_path, fake_corpus, capsys):
    """A learning rate that makes the weights diverge stops the run in one line, exit 2 (it
    ended in a scipy traceback at the next validation: NaN probabilities)."""
    config = tmp_path / "fast.json"
    config.write_text(json.dumps({**TINY, "lr": 1e4}))
    assert _train(fake_corpus, config, tmp_path / "m", "--steps", "6") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "diverged" in err[0], err


def test_max_neurons_below_a_training_pair_is_refused_before_training(tmp_path, fake_corpus, capsys):
    """max_neurons below 4 is refused before training: no example could ever be made, and the
    run spent seconds drawing pairs, then blamed the worms ('share too few named neurons')."""
    config = tmp_path / "small.json"
    config.write_text(json.dumps({**TINY, "max_neurons": 3}))
    assert _train(fake_corpus, config, tmp_path / "m") == 2
    assert "max_neurons" in capsys.readouterr().err


def test_resume_does_not_take_the_device_the_checkpoint_trained_on(stopped_run, fake_corpus, tiny_config):
    """--resume without --config takes the checkpoint's recipe, not the device it ran on: a
    checkpoint trained on CUDA was refused on a machine without one ('--device cuda: no CUDA
    device here', for a flag never given)."""
    meta_path = stopped_run.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    meta["train_config"]["device"] = "nonexistent-device"
    meta_path.write_text(json.dumps(meta))
    assert run("train", "--corpus", fake_corpus, "--no-calibrate", "--out", stopped_run, "--steps", "6", "--resume") == 0


ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, write_corpus) -> Path:
    worms = {lab: [generate_worm(seed=100 + 3 * k + i) for i in range(3)] for k, lab in enumerate(("NP", "EY"))}
    return write_corpus(tmp_path_factory.mktemp("corpus"), worms)


class TrainingStarted_h(Exception):
    pass


def _no_training(monkeypatch):
    def sentinel(*args, **kwargs):
        raise TrainingStarted_h
        yield  # pragma: no cover

    monkeypatch.setattr("napari_fdlc.train.training_batches", sentinel)


def test_calibrate_only_uses_the_threads_it_is_given(tmp_path, corpus, monkeypatch):
    """docs/model_card.md recalibrates the shipped model with `fdlc train --config ... --threads 2
    --out <a copy> --calibrate-only` (training/README.md: `--threads 1`). Expected: calibration
    runs on that many torch threads. Instead `--threads` is silently ignored there: cli._run_train
    calls calibrate_checkpoint(cfg), which never calls torch.set_num_threads (only train() does),
    so calibration runs on torch's default (all cores, which the README measured 25x slower on
    a shared 2-core machine)."""
    import torch

    import napari_fdlc.train as train_module
    from napari_fdlc.model import CorrespondenceModel, save_model
    from napari_fdlc.train import TrainConfig

    out = tmp_path / "ck" / "model"
    cfg = TrainConfig(corpus=str(corpus), out=str(out), **TINY)
    save_model(CorrespondenceModel(TINY["model"]), out, {"train_config": cfg.to_json(), "best_step": 3})
    seen = {}

    def fake_calibrate(*args, **kwargs):
        seen["threads"] = torch.get_num_threads()
        return {}

    monkeypatch.setattr(train_module, "calibrate", fake_calibrate)
    torch.set_num_threads(2)
    try:
        rc = run("train", "--corpus", corpus, "--out", out, "--calibrate-only", "--threads", "1")
    finally:
        torch.set_num_threads(1)
    assert rc == 0
    assert seen["threads"] == 1, f"--threads 1 given, calibration ran on {seen['threads']} torch threads"


def test_train_refuses_a_thread_count_torch_cannot_take_in_one_line(tmp_path, corpus, monkeypatch, capsys):
    """`fdlc train --threads 2147483648`: expected one line on stderr and exit 2, as for --seed
    out of range. Instead TrainConfig.check only asks for >= 1 and train() passes it to
    torch.set_num_threads, which raises `ValueError: Overflow when unpacking long`: a traceback
    (exit 1)."""
    _no_training(monkeypatch)
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(TINY))
    try:
        rc = run("train", "--config", config, "--corpus", corpus, "--no-calibrate", "--out", tmp_path / "m",
                 "--threads", str(2**31))
    except TrainingStarted_h:
        pytest.fail("a thread count torch cannot take was accepted")
    except Exception as exc:  # what the user sees as a traceback
        pytest.fail(f"traceback instead of one line: {type(exc).__name__}: {exc}")
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fdlc: error:"), err


def test_train_out_whose_record_cannot_be_written_is_refused_before_training(tmp_path, corpus, capsys):
    """docs/cli.md: "Everything is checked before the first step: ... that `--out` can be
    written". Without --config, only the weights path (OUT.safetensors) is checked; OUT.json is
    checked only when --config is given. With OUT.json a folder the run trains until its first
    validation, then save_model fails naming its temporary file (`fdlc: error: .../m.json.tmp:
    Is a directory`, a file the user never named) and leaves OUT.safetensors behind without the
    JSON that makes it loadable. Expected: refused before training, naming m.json, nothing written."""
    out = tmp_path / "run" / "m"
    (tmp_path / "run" / "m.json").mkdir(parents=True)
    rc = run("train", "--corpus", corpus, "--no-calibrate", "--out", out, "--steps", "2", "--batch-size", "1",
             "--eval-every", "2", "--val-pairs-per-lab", "1")
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert ".tmp" not in err[0] and "m.json" in err[0], err[0]
    assert '"step"' not in captured.out, "it trained (and validated) before refusing the --out"
    assert not out.with_suffix(".safetensors").exists(), "weights left without their JSON"


def test_saved_weights_are_readable_like_the_json_beside_them(tmp_path):
    """save_model writes OUT.safetensors with safetensors' save_file, which creates the file with
    mode 0600, while OUT.json (Path.write_text) and every atomic_write output get the permissions
    a plain open() gives (0644 under umask 022; errors.atomic_write chmods its temporary file for
    exactly that). A trained model on a shared machine is then unreadable to the other users who
    would `fdlc label --weights` it. Expected: both files with 0o666 & ~umask."""
    from napari_fdlc.model import CorrespondenceModel, save_model

    path = tmp_path / "model"
    save_model(CorrespondenceModel(TINY["model"]), path, {})
    umask = os.umask(0)
    os.umask(umask)
    expected = 0o666 & ~umask
    modes = {p.suffix: p.stat().st_mode & 0o777 for p in (path.with_suffix(".safetensors"), path.with_suffix(".json"))}
    assert modes == {".safetensors": expected, ".json": expected}, {k: oct(v) for k, v in modes.items()}


def test_a_configurations_resume_true_is_not_silently_dropped(tmp_path, corpus, capsys):
    """TrainConfig has `resume` ("continue from the checkpoint at out"), and flags override the
    --config JSON only when given (cli.md; a config's `"calibrate": false` is kept). A config
    with `"resume": true` and `"out"` naming a checkpoint, run without --resume: cli._run_train
    sets `cfg.resume = args.resume` (False), so a fresh run starts and its first validation
    (best starts at -1) replaces the checkpoint it was told to continue: weights and history
    lost. Expected: the run resumes (or is refused); the checkpoint's better record is kept."""
    out = tmp_path / "run" / "m"
    first = tmp_path / "first.json"
    first.write_text(json.dumps({**TINY, "steps": 6, "out": str(out)}))
    assert run("train", "--config", first, "--corpus", corpus, "--no-calibrate", "--stop-at", "3") == 0
    meta_path = out.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    meta["history"][-1]["mean_top1"] = 1.0  # a checkpoint no continuation can beat
    meta_path.write_text(json.dumps(meta))
    before = out.with_suffix(".safetensors").read_bytes()

    go_on = tmp_path / "go_on.json"
    go_on.write_text(json.dumps({**TINY, "steps": 6, "out": str(out), "resume": True, "seed": 7}))
    capsys.readouterr()
    run("train", "--config", go_on, "--corpus", corpus, "--no-calibrate")
    history = json.loads(meta_path.read_text())["history"]
    assert history[0]["mean_top1"] == 1.0, f"the checkpoint's record was replaced by a fresh run: {history}"
    assert out.with_suffix(".safetensors").read_bytes() == before, "the checkpoint's weights were replaced"


def test_a_stage_configuration_without_stop_at_runs_its_whole_schedule():
    """docs/training/README.md: "`--stop-at` ends the run earlier without changing the schedule
    (without it a stage runs its whole schedule: 8000-14000 steps for stages 1-4, hours ...)".
    Instead stage1-4.json each hold a `stop_at` of their own (1200, 500, 2000, 1000), which
    TrainConfig.from_json keeps: `fdlc train --config docs/training/stage3.json ...` without
    --stop-at stops at 2000 of 14000 steps. stage3/stage4's values also disagree with the
    documented lineage (--stop-at 3400 and 2000; model_card.md's table: 3400 and 2000 steps run)."""
    from napari_fdlc.train import TrainConfig

    stops = {stage: TrainConfig.from_json(ROOT / "docs" / "training" / f"{stage}.json").stop_at
             for stage in ("stage1", "stage2", "stage3", "stage4")}
    assert all(stop is None for stop in stops.values()), f"without --stop-at each stops at: {stops}"


@pytest.mark.parametrize("model", [
    {"layers": 1, "dim": 32, "prior_sigma_um": 1e-200},  # ZeroDivisionError in CorrespondenceModel
    {"layers": 1, "dim": 32, "scale_um": 1e-300},  # OverflowError in CorrespondenceModel
    {"layers": 1, "dim": 10_000_000, "heads": 1},  # torch RuntimeError: can't allocate 800 TB
])
def test_train_refuses_model_sizes_it_cannot_build_in_one_line(tmp_path, fake_corpus, capsys, model):
    """docs/cli.md (fdlc train): "Everything is checked before the first step: the
    configuration's numbers ..."; model.model_config says it refuses a configuration unless it
    names "sensible values". It only checks that lengths are positive and sizes whole, so a
    recipe's `prior_sigma_um: 1e-200` ends in `ZeroDivisionError`, `scale_um: 1e-300` in
    `OverflowError`, and `dim: 10000000` in torch's `RuntimeError: DefaultCPUAllocator: can't
    allocate memory`, each a Python traceback from `fdlc train` (not one line, exit 2)."""
    config = tmp_path / "bad.json"
    config.write_text(json.dumps({**TINY, "model": model}))
    rc = main(["train", "--config", str(config), "--corpus", str(fake_corpus), "--no-calibrate",
               "--out", str(tmp_path / "run" / "model")])
    assert rc == 2
    _one_line_error(capsys)
    assert not (tmp_path / "run" / "model.safetensors").exists()


def _weights_with_config(tmp_path, config: dict, untrained_weights) -> Path:
    """The (valid) untrained weights beside a JSON whose configuration says ``config``."""
    path = tmp_path / "bad_model"
    path.with_suffix(".safetensors").write_bytes(Path(untrained_weights).with_suffix(".safetensors").read_bytes())
    path.with_suffix(".json").write_text(json.dumps({"config": config}))
    return path


@pytest.mark.parametrize("config", [
    {"layers": 1, "dim": 32, "prior_sigma_um": 1e-200},
    {"layers": 1, "dim": 10_000_000, "heads": 1},
])
def test_load_model_refuses_a_configuration_it_cannot_build_with_a_model_error(tmp_path, untrained_weights, config):
    """load_model: "refuse anything that does not fit" (a ModelError, which every face shows as
    one line). A model JSON whose configuration passes model_config but cannot be built escapes
    as `ZeroDivisionError` (prior_sigma_um 1e-200) or torch's `RuntimeError: can't allocate
    memory` (dim 10000000): load_model only catches ValueError, KeyError, TypeError and
    ModelError around CorrespondenceModel(config), so `fdlc label --weights` prints a traceback.
    (The sizes could be checked against the safetensors header before anything is allocated.)"""
    from napari_fdlc.errors import ModelError
    from napari_fdlc.model import load_model

    with pytest.raises(ModelError):
        load_model(_weights_with_config(tmp_path, config, untrained_weights))


def test_label_with_weights_whose_fourier_bands_overflow_is_one_line_not_a_traceback(tmp_path, capsys):
    """model_config accepts any whole `fourier_bands`; at 128 or more the Fourier frequencies
    2**k overflow float32 to infinity (a non-persistent buffer, so load_model's finiteness check
    of the weights never sees it) and every log-probability is NaN. `fdlc label --weights` on
    such a (loadable, finite) checkpoint then dies in scipy with `ValueError: matrix contains
    invalid numeric entries`, a traceback. Expected: the configuration refused (ModelError, one
    line, exit 2), or at least finite answers."""
    import torch

    from napari_fdlc.model import CorrespondenceModel, save_model

    torch.manual_seed(0)
    weights = tmp_path / "bands" / "model"
    save_model(CorrespondenceModel({"layers": 1, "dim": 32, "fourier_bands": 6}), weights, {})
    meta = json.loads(weights.with_suffix(".json").read_text())
    weights.with_suffix(".json").write_text(json.dumps({**meta, "config": {**meta["config"], "fourier_bands": 130}}))
    test, template = tmp_path / "test.csv", tmp_path / "template.csv"
    write_table(generate_worm(seed=1), test)
    write_table(generate_worm(seed=2), template)
    rc = main(["label", str(test), "--template", str(template), "--no-atlas", "--weights", str(weights),
               "--out", str(tmp_path / "ids.csv")])
    assert rc == 2
    _one_line_error(capsys)


def test_build_atlas_does_not_measure_colour_on_cells_without_a_reading():
    """colour.py: "a cell without a reading says nothing"; Atlas.with_colours_of skips such
    cells (NeuronTable.colour_gaps). build_atlas (fdlc atlas) does not: NeuronTable fills an
    empty cell with the volume's median, whose normal score 0 is averaged into the name's
    atlas colour as if measured. Here a name is the brightest in R in the one worm that read
    it and unread in the two others: the atlas gives it R = 1/3 of that worm's score (and a
    spread made of the fillers) instead of the reading it has."""
    from napari_fdlc.colour import IDENTITY_CHANNELS, normal_scores
    from napari_fdlc.corpus import Worm
    from napari_fdlc.reference import build_atlas
    from napari_fdlc.table import NeuronTable

    worms = [generate_worm(seed=s) for s in (11, 12, 13)]
    shared = set(worms[0].labels) & set(worms[1].labels) & set(worms[2].labels)
    rows0 = [i for i, n in enumerate(worms[0].labels) if n in shared]
    name = worms[0].labels[max(rows0, key=lambda i: worms[0].colours["R"][i])]  # brightest R in worm 0
    tables = [worms[0]]
    for w in worms[1:]:
        red = w.colours["R"].copy()
        red[list(w.labels).index(name)] = np.nan  # not read in this worm
        tables.append(NeuronTable(w.xyz, {"R": red, "G": w.colours["G"], "B": w.colours["B"]}, w.labels))
    assert all(name in t.labels for t in tables)
    atlas = build_atlas([Worm("NP", f"w{k}", t) for k, t in enumerate(tables)], min_frequency=0.5)
    k = list(atlas.names).index(name)
    measured = normal_scores(worms[0], IDENTITY_CHANNELS)[list(worms[0].labels).index(name), 0]
    assert atlas.colour[k, 0] == pytest.approx(measured, abs=1e-6), (
        f"{name}: R read once as {measured:.3f}, atlas says {atlas.colour[k, 0]:.3f} +- {atlas.colour_sd[k, 0]:.3f}")
