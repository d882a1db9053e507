"""The panel's colours measured on the recordings of one call: alone, and mixed with another lab's.

    python benchmarks/adapt_colours.py [--runs runs] [--labs NP EY KK SF SK1]

``fdlc label`` with at least 3 tests on the built-in panel names them once, measures each
name's colour on their confident names and names them again (``--adapt-colours``;
:meth:`napari_fdlc.identify.Identifier.label_panel_many`). For each corpus lab X, the fold
model that never saw it (``runs/fold_<X>/model``, from ``benchmarks/leave_one_lab_out.py``) and
a panel rebuilt without X name X's worms in one call: without adaptation, adapted on X's worms
alone, and adapted on a call that mixes X's worms with as many of another lab Y's (a call
that gathers two microscopes; scored on X's worms only). Every call is named in X's majority
handedness (by the worms' names), so that what is measured is the colour. Y was a training lab
of X's fold model, so its worms are named better than a new lab's would be. Top-1 % over the
names the panel knows. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from _folds import held_out_lab  # noqa: E402
from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.evaluate import Scores  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--runs", default="runs", help="folder of the fold models (runs/fold_<LAB>/model)")
    args = ap.parse_args(argv)
    worms = load_corpus(args.corpus)
    others = list(LABS)
    lines = ["| held-out lab X | not adapted | adapted on X alone | " + " | ".join(f"adapted with {y}'s worms" for y in others) + " |",
             "|---|---|---|" + "---|" * len(others)]
    for lab in args.labs:
        panel, tests, identifier = held_out_lab(worms, lab, args.runs)

        def top1(results):
            scores = Scores()
            for result, test in zip(results, tests):
                scores.add(result, test, panel.names)
            return f"{100 * scores.summary()['top1']:.1f}"

        first = [identifier.label_panel(t, panel, use_colour=True) for t in tests]
        cells = [top1(first), top1(identifier.label_panel_many(tests, panel, True, first=first, adapt_colours=True))]
        for other in others:
            if other == lab:
                cells.append("–")
                continue
            mixed = tests + [w.table for w in worms if w.lab == other][: len(tests)]
            cells.append(top1(identifier.label_panel_many(mixed, panel, True, adapt_colours=True)[: len(tests)]))
        lines.append(f"| {lab} | " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
