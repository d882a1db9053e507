"""Several labelled worms of a new lab as templates: how much each one more is worth.

    python benchmarks/templates.py [--runs runs] [--trials 20] [--max-templates 3] [--chirality same]

For each corpus lab, the fold model that never saw it (``runs/fold_<LAB>/model``, made by
``benchmarks/leave_one_lab_out.py --train``; its settings by ``--recalibrate``) names a worm of
the lab from K other worms of the lab, each matched in its own registration and their answers
averaged (``fdlc label --template a.csv b.csv ...``), with colour and the built-in atlas rebuilt
without the lab beside them. ``--trials`` draws per K (seed 0; the same tests for every K, the
templates of K + 1 are those of K plus one). Two kinds of draw:

* any worms of the lab;
* worms of one handedness only (read from their names relative to the atlas), test included:
  one microscope's recordings, as a lab that labels a few of its own would have. The corpus
  mixes both handedness within KK, SF and SK1 (a dataset convention, not biology), and a
  template of the other handedness than the test swaps every left/right pair.

``--chirality same`` tells fdlc that test and templates share their handedness (default
``auto``: the template's handedness unless the model is far more willing to match the mirrored
placement). Top-1 / top-3 % over the test neurons whose name some template has. Prints a
markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.evaluate import Scores, mirrored_relative_to  # noqa: E402
from napari_fdlc.identify import Identifier, harmonised_templates  # noqa: E402
from napari_fdlc.reference import build_atlas  # noqa: E402


def draws(n_worms: int, trials: int, k_max: int, rng) -> list[tuple[int, list[int]]]:
    """(test, templates in order) per trial: the first K templates serve for K."""
    out = []
    for _ in range(trials):
        order = rng.permutation(n_worms)
        out.append((int(order[0]), [int(i) for i in order[1 : k_max + 1]]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--runs", default="runs", help="folder of the fold models (runs/fold_<LAB>/model)")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--max-templates", type=int, default=3)
    ap.add_argument("--chirality", choices=("auto", "same"), default="auto")
    args = ap.parse_args(argv)
    worms = load_corpus(args.corpus)
    ks = range(1, args.max_templates + 1)
    lines = ["| lab | draw | " + " | ".join(f"{k} template{'s' * (k > 1)}" for k in ks) + " |",
             "|---|---|" + "---|" * len(ks)]
    for lab in args.labs:
        tables = [w.table for w in worms if w.lab == lab]
        atlas = build_atlas([w for w in worms if w.lab != lab])
        identifier = Identifier.load(Path(args.runs) / f"fold_{lab}" / "model").with_chirality(args.chirality)
        mirrored = np.array([mirrored_relative_to(atlas, t) for t in tables])
        majority = [i for i in range(len(tables)) if mirrored[i] == (mirrored.mean() > 0.5)]
        for kind, pool in (("any worms of the lab", list(range(len(tables)))), ("one handedness", majority)):
            if len(pool) <= args.max_templates:
                continue
            trials = draws(len(pool), args.trials, args.max_templates, np.random.default_rng(0))
            cells = []
            for k in ks:
                scores = Scores()
                for test, chosen in trials:
                    templates = harmonised_templates([tables[pool[i]] for i in chosen[:k]])[0]  # as fdlc label does
                    vocabulary = set().union(*(set(t.names) for t in templates))
                    target = tables[pool[test]]
                    scores.add(identifier.label(target, templates, use_colour=True, atlas=atlas), target, vocabulary)
                s = scores.summary()
                cells.append(f"{100 * s['top1']:.1f} / {100 * s['top3']:.1f}")
            lines.append(f"| {lab} | {kind} ({len(pool)} worms) | " + " | ".join(cells) + " |")
            print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
