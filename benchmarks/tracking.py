"""Tracking accuracy and speed on synthetic sequences: fdlc track vs CPD (and a geometry-only
ablation), in one run, on the same sequences.

    python benchmarks/tracking.py [--weights PATH] [--sequences 5] [--frames 100] [--motion 1 2]
                                  [--cpd-frames 20] [--threads 2]

Each sequence is one worm sampled from the shipped atlas (``reference.generate_worm``) moving
smoothly (``track.simulate_sequence``: bend, roll, XY rotation and drift, scale interpolated
over time; per volume 3–12 % of neurons dropped, up to 8 spurious detections, 0.42 µm jitter).
``--motion`` scales the pose changes (1 = defaults: about 1 µm of motion per volume beyond the
jitter; 2 = twice as fast). The reference is the first volume. Accuracy = fraction of neurons
whose partner is in the reference that get its track ID; "untracked right" = fraction of the
others (spurious, or dropped from the reference) left untracked. Positions only (the synthetic
colours are nearly noise-free, so colour would make it trivial). CPD (``baselines.cpd_match``,
every orientation, each volume to the reference) is slow, so it runs on the first ``--cpd-frames``
volumes of each sequence, and fdlc's accuracy on the same volumes is shown beside it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see benchmarks/speed.py



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None, help="model path without suffix (default: the shipped model)")
    ap.add_argument("--sequences", type=int, default=5)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--motion", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--cpd-frames", type=int, default=20, help="volumes per sequence for CPD (0: no CPD)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=100)
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from napari_fdlc.geometry import ORIENTATIONS
    from napari_fdlc.identify import Identifier
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import SequenceParams, Sequence, TrackSettings, simulate_sequence, track, tracking_accuracy

    weights = args.weights  # None: the shipped model
    identifier = Identifier.load(weights, device="cpu")
    base = TrackSettings(use_colour=False)
    methods = {
        "fdlc track (defaults)": ("fdlc", base),
        "fdlc track, refine_steps=1": ("fdlc", replace(base, refine_steps=1)),
        "fdlc track, model alone (placement=model, no position likelihood)": (
            "fdlc", replace(base, placement="model", chunk=1, position_sigma_um=0)),
        "fdlc, full search every volume (= fdlc label)": ("fdlc", replace(base, search="full", position_sigma_um=0)),
        "geometry alone (warp chain, no model)": ("geometry", base),
    }
    print(f"# tracking: {args.sequences} sequences × {args.frames} volumes per motion level, positions only; "
          f"weights {weights or 'shipped'}; {args.threads} torch thread(s)")
    print()
    print("| motion | method | accuracy | untracked right | volumes/s | accuracy on the CPD volumes |")
    print("|---|---|---|---|---|---|")
    for motion in args.motion:
        params = SequenceParams(frames=args.frames)
        params = replace(params, bend_curvature=params.bend_curvature * motion, roll=params.roll * motion,
                         xy_rotation=params.xy_rotation * motion, drift_um=params.drift_um * motion)
        sequences = [simulate_sequence(generate_worm(seed=args.seed + k), args.seed + k, params) for k in range(args.sequences)]
        cpd_n = min(args.cpd_frames, args.frames)
        for label, (method, settings) in methods.items():
            hit = total = free = free_total = 0
            sub_hit = sub_total = 0
            elapsed = 0.0
            for volumes, origins in sequences:
                t0 = time.perf_counter()
                result = track(volumes, identifier=identifier, settings=settings, method=method)
                elapsed += time.perf_counter() - t0
                score = tracking_accuracy(result, origins, origins[0])
                hit += score["accuracy"] * score["neurons"]
                total += score["neurons"]
                free += score["untracked_right"]
                free_total += 1
                if cpd_n:
                    sub = type(result)(result.track_id[:cpd_n], result.confidence[:cpd_n], result.names, [])
                    s2 = tracking_accuracy(sub, origins[:cpd_n], origins[0])
                    sub_hit += s2["accuracy"] * s2["neurons"]
                    sub_total += s2["neurons"]
            rate = args.sequences * args.frames / elapsed
            sub = f"{100 * sub_hit / sub_total:.1f} %" if cpd_n else "–"
            print(f"| {motion:g}× | {label} | {100 * hit / total:.1f} % | {100 * free / free_total:.0f} % | {rate:.0f} | {sub} |", flush=True)
        if cpd_n:
            hit = total = free = 0
            elapsed = 0.0
            for volumes, origins in sequences:
                seq = Sequence(volumes[:cpd_n], list(range(cpd_n)))
                t0 = time.perf_counter()
                result = track(seq, settings=base, method="cpd")
                elapsed += time.perf_counter() - t0
                score = tracking_accuracy(result, origins[:cpd_n], origins[0])
                hit += score["accuracy"] * score["neurons"]
                total += score["neurons"]
                free += score["untracked_right"]
            rate = args.sequences * cpd_n / elapsed
            print(f"| {motion:g}× | CPD (pycpd, {len(ORIENTATIONS)} orientations, each volume to the reference) | – | "
                  f"{100 * free / args.sequences:.0f} % | {rate:.1f} | {100 * hit / total:.1f} % |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
