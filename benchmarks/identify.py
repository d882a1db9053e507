"""Identification accuracy on corpus worms: fdlc vs CPD vs the non-learned floor, side by side.

Protocol "pairs": within each lab, each worm is the template for other worms of the lab (a
fixed random subset of pairs); every method sees the same pairs in the same run. Top-1 is the
fraction of labelled test neurons whose name the template also has that the one-to-one
assignment gives that name; top-3, that it is among the 3 best candidates.

    python benchmarks/identify.py [--corpus PATH] [--pairs-per-lab 20] [--weights PATH] [--no-cpd]

The corpus is read in place (default ../shared/data/neuropal_corpus).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc._cli_evaluate import evaluate_corpus  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=None)
    ap.add_argument("--pairs-per-lab", type=int, default=20)
    ap.add_argument("--weights", default=None, help="model path without suffix (default: shipped)")
    ap.add_argument("--no-cpd", action="store_true", help="skip CPD (slow)")
    args = ap.parse_args(argv)
    print(evaluate_corpus(corpus=args.corpus, labs=args.labs, weights=args.weights, pairs_per_lab=args.pairs_per_lab,
                          panel_worms_per_lab=0, synthetic_pairs=0, with_cpd=not args.no_cpd, out=None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
