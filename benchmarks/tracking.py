"""Tracking accuracy and speed on synthetic sequences: fdlc track vs CPD (and a geometry-only
ablation), in one run, on the same sequences.

    python benchmarks/tracking.py [--weights PATH] [--sequences 5] [--frames 100] [--motion 1 2]
                                  [--no-cpd] [--threads 2] [--jump turn|shift]

Each sequence is one worm sampled from the shipped atlas (``reference.generate_worm``) moving
smoothly (``track.simulate_sequence``: bend, roll, XY rotation and drift, scale interpolated
over time; per volume 3–12 % of neurons dropped, up to 8 spurious detections, 0.42 µm jitter).
``--motion`` scales the pose changes (1 = defaults: about 1 µm of motion per volume beyond the
jitter; 2 = twice as fast). The reference is the first volume. Accuracy = fraction of neurons
whose partner is in the reference that get its track ID; "untracked right" = fraction of the
others (spurious, or dropped from the reference) left untracked. Positions only (the synthetic
colours are nearly noise-free, so colour would make it trivial). CPD tracks as a CPD tracker
does (``track(method="cpd")``: the first volume searched in all 16 orientations with
``baselines.cpd_search``, every later volume one registration of the reference as deformed onto
the volume before, ``baselines.cpd_follow``), on the same volumes (``--no-cpd`` leaves it out).
``--jump`` adds one sudden move halfway through every sequence, kept to its end (the worm
slipping under the objective, a stage step): ``turn`` = 45° about the optical axis (through the
centroid of the first volume moved), ``shift`` = 10 µm along x.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def _turned(volume, centre, degrees: float = 45.0):
    from napari_fdlc.table import NeuronTable

    a = np.radians(degrees)
    about_z = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return NeuronTable((volume.xyz - centre) @ about_z.T + centre, dict(volume.colours))


def _shifted(volume, centre, um: float = 10.0):
    from napari_fdlc.table import NeuronTable

    return NeuronTable(volume.xyz + [um, 0, 0], dict(volume.colours))


JUMPS = {"turn": _turned, "shift": _shifted}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None, help="model path without suffix (default: the shipped model)")
    ap.add_argument("--tracking-weights", default=None, help="tracking model path without suffix (default: the shipped one)")
    ap.add_argument("--sequences", type=int, default=5)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--motion", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--no-cpd", action="store_true", help="leave CPD out (about 30 ms per volume)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--jump", choices=sorted(JUMPS), help="a sudden move halfway through each sequence (see above)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from napari_fdlc.identify import Identifier
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.track import SequenceParams, TrackSettings, simulate_sequence, track, tracking_accuracy

    weights = args.weights  # None: the shipped model
    identifier = Identifier.load(weights, device="cpu")
    tracker = Identifier.load(args.tracking_weights, device="cpu") if args.tracking_weights else None
    base = TrackSettings(use_colour=False)
    methods = {
        "fdlc track (defaults: the tracking model follows)": ("fdlc", base),
        "fdlc track, full model follows (--follow-with full)": ("fdlc", replace(base, follow_with="full")),
        "fdlc track, refine_steps=1": ("fdlc", replace(base, refine_steps=1)),
        "fdlc track, model alone (placement=model, no position likelihood)": (
            "fdlc", replace(base, placement="model", chunk=1, position_sigma_um=0)),
        "fdlc, full search every volume (= fdlc label)": ("fdlc", replace(base, search="full", position_sigma_um=0)),
        "geometry alone (warp chain, no model)": ("geometry", base),
    }
    if not args.no_cpd:
        methods["CPD (pycpd; 16 orientations on the first volume, then one registration from the volume before)"] = ("cpd", base)
    jump = f"; a {args.jump} halfway" if args.jump else ""
    print(f"# tracking: {args.sequences} sequences × {args.frames} volumes per motion level{jump}, positions only; "
          f"weights {weights or 'shipped'}, tracking weights {args.tracking_weights or 'shipped'}; {args.threads} torch thread(s)")
    print()
    print("| motion | method | accuracy | untracked right | volumes/s |")
    print("|---|---|---|---|---|")
    warm = False
    for motion in args.motion:
        params = SequenceParams(frames=args.frames).scaled(motion)
        sequences = [simulate_sequence(generate_worm(seed=args.seed + k), args.seed + k, params) for k in range(args.sequences)]
        if args.jump:  # about one centre (the first moved volume's centroid): one move, not one per volume
            half = args.frames // 2
            sequences = [([v if t < half else JUMPS[args.jump](v, volumes[half].xyz.mean(0)) for t, v in enumerate(volumes)],
                          origins) for volumes, origins in sequences]
        for label, (method, settings) in methods.items():
            follower = tracker if settings.follow_with == "tracking" else None
            if not warm:  # the first call of each method loads its models and traces them: not timed
                track(sequences[0][0][:20], identifier=identifier, settings=settings, method=method, follower=follower)
            hit = total = 0
            free = []  # per recording (NaN: nothing to leave untracked)
            elapsed = 0.0
            for volumes, origins in sequences:
                t0 = time.perf_counter()
                result = track(volumes, identifier=identifier, settings=settings, method=method, follower=follower)
                elapsed += time.perf_counter() - t0
                score = tracking_accuracy(result, origins, origins[0])
                hit += score["accuracy"] * score["neurons"]
                total += score["neurons"]
                free.append(score["untracked_right"])
            rate = args.sequences * args.frames / elapsed
            print(f"| {motion:g}× | {label} | {100 * hit / total:.1f} % | {100 * np.nanmean(free):.0f} % | {rate:.0f} |", flush=True)
        warm = True
    return 0


if __name__ == "__main__":
    sys.exit(main())
