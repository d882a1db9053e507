"""Helpers of the benchmark scripts (benchmarks/ is not a package: imported by path)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

from napari_fdlc.table import NeuronTable

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _bench(name: str):
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _result(track_ids):
    from napari_fdlc.track import TrackResult

    return TrackResult([np.asarray(t) for t in track_ids], [np.ones(len(t)) for t in track_ids], [], [])


def test_tracking_from_images_split_nucleus_makes_a_perfect_tracker_score_below_100():
    """A tracker giving each detection of an unchanged volume its own ID scores 100 %, also with
    a nucleus split in two: detections were matched to their nearest true neuron, both halves
    took one source, and one half's right ID counted wrong (67 %)."""
    tfi = _bench("tracking_from_images")
    from napari_fdlc.track import tracking_accuracy

    truth = NeuronTable(np.array([[0.0, 0, 0], [10.0, 0, 0]]))
    origin = np.array([0, 1])
    detected = NeuronTable(np.array([[-0.6, 0, 0], [0.6, 0, 0], [10.0, 0, 0]]))  # nucleus 0 split in two
    sources = tfi.detection_sources(truth, origin, detected)
    # the same volume twice (a worm that did not move), each detection given its own reference ID
    score = tracking_accuracy(_result([[0, 1, 2], [0, 1, 2]]), [sources, sources], sources)
    assert score["accuracy"] == 1.0, (sources, score)
