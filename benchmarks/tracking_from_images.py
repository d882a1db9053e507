"""Tracking from images: rendered recordings segmented at every time point, then tracked, beside
the same tracking on the recordings' true tables, in one run.

    python benchmarks/tracking_from_images.py [--sequences 3] [--frames 30] [--motion 1]
                                              [--voxel-size 1.2 0.36 0.36] [--threads 1]

Each recording is a worm sampled from the shipped atlas (``reference.generate_worm``) moving as
in benchmarks/tracking.py (``track.simulate_sequence`` at ``--motion``), but with no simulated
segmentation noise (no drops, spurious points or jitter): the segmentation makes its own. Every
volume is rendered (``render.render_recording``: the renderer's default noise, a neuron keeping
its size and brightness over time, each time point its own photon noise), segmented as ``fdlc
segment`` does (``segment.segment_series``) and tracked as ``fdlc track RECORDING.ome.tif``
does. A detection stands for a true neuron within 1.5 µm of it (one-to-one: the most pairs
within reach, ``detection_sources``); accuracy =
fraction of the detections whose neuron was detected in the reference (the first volume) that
get that detection's track ID; "untracked right" = fraction of the other detections (spurious,
or a neuron the reference missed) left untracked; "found" = fraction of the true neurons
detected. The same methods on the true tables (true positions, the worm's own colours) give
the figures without segmentation. Writes a markdown table on stdout.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def detection_sources(truth, origin, detected, max_um: float = 1.5) -> np.ndarray:
    """The source neuron of each detection, matched one-to-one with the true neurons within
    ``max_um`` (as score_detections matches), else -1: the second detection of a split nucleus
    is spurious (nearest-neuron matching gave both halves one source, and scored one wrong)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    distance = cdist(detected.xyz, truth.xyz)
    rows, cols = linear_sum_assignment(np.where(distance < max_um, distance, 1e6))
    sources = np.full(len(detected), -1)
    close = distance[rows, cols] < max_um
    sources[rows[close]] = origin[cols[close]]
    return sources


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=3)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--motion", type=float, nargs="+", default=[1.0])
    ap.add_argument("--voxel-size", type=float, nargs=3, default=[1.2, 0.36, 0.36], metavar=("Z", "Y", "X"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=400)
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from napari_fdlc.identify import default_identifier
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.render import render_recording
    from napari_fdlc.segment import segment_series
    from napari_fdlc.track import SequenceParams, TrackSettings, simulate_sequence, track, tracking_accuracy

    identifier = default_identifier()
    base = TrackSettings()
    methods = {
        "fdlc track (defaults: colour likelihood; the tracking model on positions)": ("fdlc", base),
        "fdlc track, the tracking model takes colour too (default before session 25)": (
            "fdlc", replace(base, follower_colour_input=True)),
        "fdlc track, positions only (--no-color)": ("fdlc", replace(base, use_colour=False)),
        "fdlc track, full model follows (--follow-with full)": ("fdlc", replace(base, follow_with="full")),
        "geometry alone (warp chain, no model)": ("geometry", base),
        "CPD (pycpd)": ("cpd", base),
    }
    rows = []
    for motion in args.motion:
        scores = {name: {"images": [], "truth": [], "untracked": []} for name in methods}
        found = []
        for i in range(args.sequences):
            seed = args.seed + i
            still = SequenceParams(frames=args.frames, drop_fraction=(0.0, 0.0), max_spurious=0, jitter_um=0.0).scaled(motion)
            volumes, origins = simulate_sequence(generate_worm(seed=seed), seed, still)
            start = time.perf_counter()
            series, truths = render_recording(volumes, origins, voxel_size_zyx=tuple(args.voxel_size), seed=seed)
            tables = segment_series(series)
            print(f"motion {motion}, recording {i + 1}: rendered and segmented {len(tables)} volumes in "
                  f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
            sources = [detection_sources(truth, origin, table) for truth, origin, table in zip(truths, origins, tables)]
            found += [len(set(s[s >= 0])) / len(truth) for s, truth in zip(sources, truths)]
            for name, (method, settings) in methods.items():
                kw = {"identifier": identifier} if method == "fdlc" else {}
                on_images = tracking_accuracy(track(tables, settings=settings, method=method, **kw), sources, sources[0])
                on_truth = tracking_accuracy(track(truths, settings=settings, method=method, **kw), origins, origins[0])
                scores[name]["images"].append(on_images["accuracy"])
                scores[name]["untracked"].append(on_images["untracked_right"])
                scores[name]["truth"].append(on_truth["accuracy"])
                print(f"  {name}: {100 * on_images['accuracy']:.1f} % from images, "
                      f"{100 * on_truth['accuracy']:.1f} % from true tables", file=sys.stderr, flush=True)
        for name, s in scores.items():
            rows.append(f"| {motion:g}× | {name} | {100 * np.mean(s['images']):.1f} % | {100 * np.nanmean(s['untracked']):.0f} % "
                        f"| {100 * np.mean(s['truth']):.1f} % | {100 * np.mean(found):.1f} % |")
    print(f"{args.sequences} recordings of {args.frames} volumes per motion, voxel {tuple(args.voxel_size)} µm\n")
    print("| motion | method | accuracy from images | untracked right (images) | accuracy from true tables | nuclei found |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
