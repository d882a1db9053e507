"""Tracking throughput of this checkout against another one, interleaved in one process.

    git worktree add /tmp/base <commit>
    python benchmarks/speed_ab.py --base /tmp/base/src [--threads 2] [--rounds 20] [--frames 200]

On a shared two-core machine the time of one run moves by 20 % or more from one minute to the
next, so two versions timed one after the other cannot be told apart by a few percent. Here
both are imported into one process (the other checkout's package under another name), track
the same recording (``fdlc track`` defaults, chunk 16, the shipped models) in alternating order,
and each pair of runs gives a ratio; the median ratio and its quartiles are printed, with the
answers of both compared (track IDs must agree).
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402

OTHER = "fdlc_base"  # the other checkout's package, imported under this name


def _import_other(src: Path, where: Path):
    """The package of the checkout at ``src`` (its ``src`` folder), importable as OTHER. Its
    modules import each other relatively, so a renamed copy works; its resources (weights) are
    looked up under the name napari_fdlc, i.e. this checkout's (the weights must be the same)."""
    shutil.copytree(src / "napari_fdlc", where / OTHER)
    sys.path.insert(0, str(where))
    return importlib.import_module(f"{OTHER}.track"), importlib.import_module(f"{OTHER}.identify")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, type=Path, help="the other checkout's src folder")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=20, help="pairs of runs")
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args(argv)
    if args.rounds < 2:
        ap.error("--rounds must be at least 2 (the quartiles of the ratios need two)")
    if not (args.base / "napari_fdlc" / "track.py").exists():
        ap.error(f"{args.base}: no napari_fdlc package there (give a checkout's src folder)")

    import torch

    torch.set_num_threads(args.threads)
    import napari_fdlc.identify as new_identify
    import napari_fdlc.track as new_track
    from napari_fdlc.reference import generate_worm

    with tempfile.TemporaryDirectory() as tmp:
        base_track, base_identify = _import_other(args.base, Path(tmp))
        # one recording, simulated by this checkout: both time the same volumes, whatever the
        # other checkout's simulator does
        sequence, _ = new_track.simulate_sequence(generate_worm(seed=2), 0, new_track.SequenceParams(frames=args.frames))
        runs = {}
        for name, track_mod, identify_mod in (("new", new_track, new_identify), ("base", base_track, base_identify)):
            identifier, follower = identify_mod.Identifier.load(None), identify_mod.default_tracker("cpu")
            runs[name] = (lambda t=track_mod, s=sequence, i=identifier, f=follower: t.track(s, identifier=i, follower=f))
        answers = {name: np.concatenate(run().track_id) for name, run in runs.items()}  # also warms up
        times = {"new": [], "base": []}
        for r in range(args.rounds):
            for name in (("new", "base") if r % 2 else ("base", "new")):
                start = time.perf_counter()
                runs[name]()
                times[name].append(time.perf_counter() - start)
    ratios = [b / n for b, n in zip(times["base"], times["new"])]
    q1, _, q3 = statistics.quantiles(ratios, n=4)
    rate = {name: args.frames / statistics.median(t) for name, t in times.items()}
    print(f"{args.rounds} pairs, {args.threads} torch threads, {args.frames} volumes: base {rate['base']:.0f} volumes/s, "
          f"this checkout {rate['new']:.0f} (medians); speed-up {statistics.median(ratios):.3f}× "
          f"(quartiles {q1:.3f}-{q3:.3f}); same track IDs: {bool(np.array_equal(answers['new'], answers['base']))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
