"""The scoring used by `fdlc evaluate` and benchmarks/accuracy.py."""

import warnings

import numpy as np
import pytest

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.evaluate import Scores, coverage_curve, expected_calibration_error, mirrored_relative_to
from napari_fdlc.match import Labelling, make_labelling
from napari_fdlc.reference import atlas_worm, generate_worm, load_atlas
from napari_fdlc.table import NeuronTable


def run(*args) -> int:
    return main([str(a) for a in args])


def test_calibration_error_and_coverage():
    conf = np.array([0.9, 0.9, 0.9, 0.9, 0.2, 0.2, 0.2, 0.2, 0.2])
    correct = np.array([1, 1, 1, 0, 0, 0, 0, 0, 1], float)
    # bin 0.9: accuracy 0.75 (error 0.15, 4 of 9); bin 0.2: accuracy 0.2 (error 0)
    assert np.isclose(expected_calibration_error(conf, correct), 4 / 9 * 0.15)
    assert expected_calibration_error(np.full(4, 0.5), np.array([1, 0, 1, 0.0])) == 0.0
    curve = {t: (cov, acc) for t, cov, acc in coverage_curve(conf, correct)}
    assert curve[0.0] == (1.0, correct.mean())
    assert np.isclose(curve[0.5][0], 4 / 9) and np.isclose(curve[0.5][1], 0.75)


def test_scores_count_only_names_the_template_knows():
    test = NeuronTable(np.zeros((3, 3)), labels=np.array(["AVAL", "AVAR", "XYZ"], dtype=object))
    probs = np.array([[0.8, 0.1], [0.7, 0.2], [0.1, 0.1]])  # names AVAL, AVAR
    result = make_labelling(["AVAL", "AVAR"], probs)
    scores = Scores()
    scores.add(result, test, {"AVAL", "AVAR"})
    assert scores.correct == [True, True]  # XYZ is not scored; AVAR goes to row 1 (one-to-one)
    assert scores.summary()["top1"] == 1.0


def test_mirrored_relative_to_the_atlas():
    atlas = load_atlas()
    worm = atlas_worm(atlas, np.random.default_rng(0))
    turned = worm.xyz @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T  # a proper rotation
    assert not mirrored_relative_to(atlas, NeuronTable(turned, labels=worm.labels))
    assert mirrored_relative_to(atlas, NeuronTable(turned * [1, 1, -1], labels=worm.labels))


def test_calibration_bins_put_a_confidence_on_an_edge_in_the_bin_above():
    """A confidence on a bin edge goes to the bin above: np.linspace's 0.30000000000000004 once
    put 0.3 (and 0.6, 0.7) in the bin below, so conf (0.3, 0.2), correct (1, 0) scored 0.25, not 0.45."""
    from napari_fdlc.evaluate import expected_calibration_error, reliability

    conf, correct = np.array([0.3, 0.2]), np.array([1.0, 0.0])
    assert np.isclose(expected_calibration_error(conf, correct), 0.45)
    assert [b[2] for b in reliability(conf, correct)] == [1, 1]


def test_evaluate_on_a_lab_of_one_worm_prints_no_numpy_warning(tmp_path, write_corpus, untrained_weights):
    """A lab of one worm has no pair: its coverage is NaN without numpy's 'Mean of empty slice'."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": [generate_worm(seed=1)],
                                                "EY": [generate_worm(seed=2), generate_worm(seed=3)]})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = run("evaluate", "--corpus", corpus, "--labs", "NP", "--pairs-per-lab", "2", "--panel-worms-per-lab", "0",
                   "--synthetic-pairs", "0", "--no-cpd", "--weights", untrained_weights, "--out", tmp_path / "a.md")
    assert code in (0, 2)
    numpy_warnings = [f"{w.filename}:{w.lineno}: {w.message}" for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not numpy_warnings, numpy_warnings


def test_evaluate_on_a_corpus_worm_without_names_names_its_file(tmp_path, write_corpus, untrained_weights, capsys):
    """A corpus worm without names stops `fdlc evaluate` with a line naming its file."""
    worms = [generate_worm(seed=s) for s in (1, 2, 3)]
    worms[0] = NeuronTable(worms[0].xyz, worms[0].colours)
    corpus = write_corpus(tmp_path / "corpus", {"NP": worms, "EY": [generate_worm(seed=4), generate_worm(seed=5)]})
    run("evaluate", "--corpus", corpus, "--labs", "NP", "--pairs-per-lab", "6", "--panel-worms-per-lab", "0",
        "--synthetic-pairs", "0", "--no-cpd", "--weights", untrained_weights, "--out", tmp_path / "a.md")
    err = capsys.readouterr().err
    assert "Traceback" not in err and "w0.csv" in err, err


def test_baseline_labelling_against_an_unnamed_template_is_one_line():
    """The floor and CPD refuse a template without names in one line naming it, as fdlc does
    (not an IndexError)."""
    from napari_fdlc.baselines import floor_match
    from napari_fdlc.evaluate import baseline_labelling

    worm = generate_worm(seed=1)
    template = NeuronTable(worm.xyz, worm.colours, source="unnamed.csv")
    with pytest.raises(FdlcError, match="unnamed.csv"):
        baseline_labelling(floor_match, generate_worm(seed=2), [template], False)


def _scored_pair():
    """A test of two named neurons, A and B, both names in the vocabulary. The answer names the
    first A (right, auto_conf 0.6) and leaves the second without a name, its auto_conf 0.95: the
    model is 95 % sure it has no named match, which is wrong (it is B)."""
    test = NeuronTable(np.array([[0.0, 0, 0], [5.0, 0, 0]]), labels=np.array(["A", "B"], dtype=object))
    probs = np.array([[0.6, 0.0], [0.0, 0.05]])
    result = Labelling(["A", "B"], probs, ["A", ""], np.array([0.6, 0.95]))
    scores = Scores()
    scores.add(result, test, {"A", "B"})
    return scores, result


def test_calibration_error_is_that_of_auto_conf_including_unnamed_neurons():
    """The ECE is that of `auto_conf` as the contract gives it: for a neuron left unnamed, the
    probability of no named match, wrong when its truth is named: here mean(|0.6 - 1|,
    |0.95 - 0|) = 0.675. A stand-in confidence 0 made such a confident "no match" perfectly
    calibrated (ECE 0.2; seen on corpus pairs at auto_conf up to 1.0)."""
    scores, _ = _scored_pair()
    assert np.isclose(scores.summary()["ece"], 0.675), scores.summary()["ece"]


def test_coverage_at_threshold_zero_counts_only_neurons_given_a_name():
    """The coverage curve keeps what the slider shows (Labelling.thresholded): at threshold 0
    the named neuron only, 50 % coverage at 100 % accuracy. It counted the unnamed neuron as a
    label kept (100 % at 50 %)."""
    scores, result = _scored_pair()
    shown = result.thresholded(0.0)
    expected_coverage = np.mean([bool(s) for s in shown])  # 0.5
    curve = {t: (cov, acc) for t, cov, acc in coverage_curve(np.asarray(scores.conf), np.asarray(scores.correct, float),
                                                                 scores.named)}
    coverage, accuracy = curve[0.0]
    assert np.isclose(coverage, expected_coverage) and np.isclose(accuracy, 1.0), (coverage, accuracy)
