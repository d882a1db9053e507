"""Identification accuracy on corpus worms: fdlc vs CPD vs the non-learned floor, side by side.

Protocol "pairs": within each lab, each worm is the template for the other worms; accuracy is
the fraction of labelled test neurons whose name the template also has that get that name
(top-1, from the one-to-one assignment) or have it among the 3 best candidates (top-3).
All methods see exactly the same pairs in the same run.

    python benchmarks/identify.py [--corpus PATH] [--pairs-per-lab 20] [--weights PATH] [--no-cpd]

The corpus is read in place (default ../shared/data/neuropal_corpus). Prints a markdown table.
Note: the shipped model was trained on worms of these labs (validation worms excepted), so this
is not a held-out-lab figure; see benchmarks/accuracy.py for leave-one-lab-out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc.baselines import cpd_match, floor_match  # noqa: E402
from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.evaluate import Scores, baseline_labelling, pair_list  # noqa: E402
from napari_fdlc.identify import Identifier  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--pairs-per-lab", type=int, default=20)
    ap.add_argument("--weights", default=None, help="model path without suffix (default: shipped)")
    ap.add_argument("--no-cpd", action="store_true", help="skip CPD (slow)")
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args(argv)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    identifier = Identifier.load(args.weights)
    worms = load_corpus(args.corpus, args.labs)
    methods = {
        "fdlc (position)": lambda T, t: identifier.label(t, [T], use_colour=False),
        "fdlc (+colour)": lambda T, t: identifier.label(t, [T], use_colour=True),
        "floor (position)": lambda T, t: baseline_labelling(floor_match, t, [T], False),
        "floor (+colour)": lambda T, t: baseline_labelling(floor_match, t, [T], True),
    }
    if not args.no_cpd:
        methods["CPD (position)"] = lambda T, t: baseline_labelling(cpd_match, t, [T], False)
    rows = []
    for lab in args.labs:
        tables = [w.table for w in worms if w.lab == lab]
        pairs = pair_list(tables, args.pairs_per_lab, seed=0)
        for name, fn in methods.items():
            scores = Scores()
            for template, test in pairs:
                start = time.perf_counter()
                result = fn(template, test)
                scores.add(result, test, set(template.names), time.perf_counter() - start)
            s = scores.summary()
            rows.append((lab, name, s))
            print(f"{lab:4s} {name:18s} top1 {s['top1']:.3f} top3 {s['top3']:.3f} n {s['n']} {s['ms_per_volume']:.0f} ms", file=sys.stderr, flush=True)
    print(f"\nPairs within each lab, {args.pairs_per_lab} pairs per lab, torch threads {torch.get_num_threads()}.\n")
    print("| lab | method | top-1 | top-3 | neurons | ms / pair |")
    print("|---|---|---|---|---|---|")
    for lab, name, s in rows:
        print(f"| {lab} | {name} | {100 * s['top1']:.1f} | {100 * s['top3']:.1f} | {s['n']} | {s['ms_per_volume']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
