"""Re-label after one name is decided: what one click does to the rest of the answer.

The review workflow (Auto-label, then *Re-label* with the user's decisions as constraints;
``fdlc label`` has no such option, the Python API's ``fixed=`` does). For each test, named with
a template of its lab (``pairs``, the built-in atlas beside it rebuilt without the lab) or by
the built-in panel (rebuilt without the lab, every worm of the lab):

* **confirm**: one left/right neuron the answer named right is decided (accepted) and the
  test named again: top-1 of the other neurons before and after (a confirmation should cost
  nothing);
* **swap**: where the answer gave a neuron its left/right partner's name, that neuron's true
  name is decided, and the test named again: top-1 of the others before and after. Told apart
  by the answer before: *handedness wrong* (more left/right names swapped than right: one
  correction should settle the handedness, docs/handedness.md) or *one neuron* (the handedness
  right, that neuron's name swapped: the correction should not turn the worm over).

    python benchmarks/fixed_names.py [--pairs-per-lab 10] [--panel-worms-per-lab 10] [--weights PATH]

Scored on the neurons other than the decided one whose true name the reference knows.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def _partner(name: str) -> str | None:
    """The left/right partner of a bilateral name (AVAL <-> AVAR), else None."""
    if len(name) > 2 and name[-1] in "LR":
        return name[:-1] + ("R" if name[-1] == "L" else "L")
    return None


def _top1(result, truth, known: set[str], skip: int) -> tuple[int, int]:
    rows = [j for j, name in enumerate(truth) if name and name in known and j != skip]
    return sum(result.auto_id[j] == truth[j] for j in rows), len(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=None)
    ap.add_argument("--pairs-per-lab", type=int, default=10)
    ap.add_argument("--panel-worms-per-lab", type=int, default=10)
    ap.add_argument("--weights", default=None, help="model path without suffix (default: shipped)")
    args = ap.parse_args(argv)

    from napari_fdlc.corpus import LABS, load_corpus
    from napari_fdlc.evaluate import pair_list
    from napari_fdlc.identify import Identifier
    from napari_fdlc.reference import build_atlas, make_panel

    started = time.time()
    identifier = Identifier.load(args.weights)
    worms = load_corpus(args.corpus)
    labs = args.labs or [lab for lab in LABS if any(w.lab == lab for w in worms)]
    print("| lab | protocol | case | tests | top-1 of the others before | after one decided name |")
    print("|---|---|---|---|---|---|")
    for lab in labs:
        tables = [w.table for w in worms if w.lab == lab]
        atlas = build_atlas([w for w in worms if w.lab != lab])
        panel = make_panel(atlas)
        runs = {
            "pairs": [(test, lambda test, fixed=None, t=template: identifier.label(test, [t], fixed=fixed, atlas=atlas),
                       set(template.names)) for template, test in pair_list(tables, args.pairs_per_lab, seed=0)],
            "panel": [(test, lambda test, fixed=None: identifier.label_panel(test, panel, fixed=fixed), set(panel.names))
                      for test in tables[: args.panel_worms_per_lab]],
        }
        for protocol, items in runs.items():
            # tests, hits before, hits after, neurons scored
            counts = {case: np.zeros(4, int) for case in ("confirm", "swap, one neuron", "swap, handedness wrong")}
            for test, name_it, known in items:
                truth = list(test.labels)
                unnamed = type(test)(test.xyz, test.colours, source=test.source)
                before = name_it(unnamed)
                bilateral = [j for j, n in enumerate(truth) if n in known and _partner(n) in known]
                right = [j for j in bilateral if before.auto_id[j] == truth[j]]
                swapped = [j for j in bilateral if before.auto_id[j] == _partner(truth[j])]
                swap = "swap, handedness wrong" if len(swapped) > len(right) else "swap, one neuron"
                for case, rows in (("confirm", right), (swap, swapped)):
                    if not rows:
                        continue
                    j = rows[0]
                    after = name_it(unnamed, fixed={j: truth[j]})
                    hits_before, n = _top1(before, truth, known, j)
                    hits_after, _ = _top1(after, truth, known, j)
                    counts[case] += [1, hits_before, hits_after, n]
            for case, (tests, hits_before, hits_after, n) in counts.items():
                if tests:
                    print(f"| {lab} | {protocol} | {case} | {tests} | {100 * hits_before / n:.1f} | {100 * hits_after / n:.1f} |",
                          flush=True)
    print(f"\n{time.time() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
