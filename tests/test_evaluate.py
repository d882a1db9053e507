"""The scoring used by `fdlc evaluate` and benchmarks/accuracy.py."""

import numpy as np

from napari_fdlc.evaluate import Scores, coverage_curve, expected_calibration_error, mirrored_relative_to
from napari_fdlc.match import make_labelling
from napari_fdlc.reference import atlas_worm, load_atlas
from napari_fdlc.table import NeuronTable


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
