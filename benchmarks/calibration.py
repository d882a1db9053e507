"""Why `auto_conf` is not calibrated on a lab it never saw: what a temperature could do, and what
the confidence does not see.

    python benchmarks/calibration.py [--runs runs] [--fold-prefix regfold] [--pairs 12] [--worms 12]
                                     [--labs NP EY KK SF SK1] [--out docs/calibration.md]

Per held-out lab, with its fold model (``<runs>/<prefix>_<LAB>/model``, made by
``benchmarks/leave_one_lab_out.py``; the atlas and panel rebuilt without the lab, as ``fdlc
evaluate`` does):

1. the expected calibration error of ``auto_conf`` at a grid of temperatures — pairs (``--pairs``
   of them, drawn as ``fdlc evaluate`` draws its pairs, seed 0: a draw of 12 is not the first 12
   of its 20, so the top-1 here is not accuracy.md's) position only and with colour, and the panel with
   colour (the lab's first ``--worms`` worms) — beside the temperature the fold fitted on its
   four training labs: whether any one temperature, fitted anywhere, could calibrate every lab;
2. the panel with colour on the same worms with a share of their neurons dropped at random
   (seed 0 and the lab): accuracy and mean confidence, to see whether the confidence follows what a test's
   completeness does to accuracy.

Writes a markdown report.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.errors import atomic_write  # noqa: E402
from napari_fdlc.evaluate import Scores, pair_list  # noqa: E402
from napari_fdlc.identify import Identifier  # noqa: E402
from napari_fdlc.reference import build_atlas, make_panel  # noqa: E402

PAIR_TEMPERATURES = (0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0)
PANEL_TEMPERATURES = (0.25, 0.35, 0.5, 0.7, 1.0, 1.4)
KEEP = (1.0, 0.75, 0.55, 0.4)


def ece_per_temperature(identifier, setting: str, temperatures, score) -> list[float]:
    """ECE of ``score()`` (a Scores) with ``identifier.settings.<setting>`` at each temperature."""
    fitted = getattr(identifier.settings, setting)
    try:
        out = []
        for t in temperatures:
            setattr(identifier.settings, setting, t)
            out.append(score().summary()["ece"])
        return out
    finally:
        setattr(identifier.settings, setting, fitted)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="runs")
    ap.add_argument("--fold-prefix", default="regfold")
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--pairs", type=int, default=12)
    ap.add_argument("--worms", type=int, default=12)
    ap.add_argument("--out", default="docs/calibration.md")
    args = ap.parse_args(argv)

    started = time.time()
    worms = load_corpus(None)
    temperature_rows, drop_rows = [], []
    for lab in args.labs:
        # each lab its own draws: its rows do not depend on the labs run before it
        rng = np.random.default_rng([0, sum(map(ord, lab))])
        weights = Path(args.runs) / f"{args.fold_prefix}_{lab}" / "model"
        if not weights.with_suffix(".json").exists():
            print(f"{lab}: no fold model at {weights}; skipped", file=sys.stderr)
            continue
        identifier = Identifier.load(weights)
        atlas = build_atlas([w for w in worms if w.lab != lab])
        panel = make_panel(atlas)
        tables = [w.table for w in worms if w.lab == lab]
        pairs = pair_list(tables, args.pairs, seed=0)
        tests = tables[: args.worms]

        def pair_scores(use_colour):
            s = Scores()
            for template, test in pairs:
                s.add(identifier.label(test, [template], use_colour=use_colour, atlas=atlas), test, set(template.names))
            return s

        def panel_scores(tables_=tests):
            s = Scores()
            for test in tables_:
                s.add(identifier.label_panel(test, panel, use_colour=True), test, panel.names)
            return s

        for name, setting, temps, score in (
            ("pairs, position", "temperature", PAIR_TEMPERATURES, lambda: pair_scores(False)),
            ("pairs, colour", "temperature", PAIR_TEMPERATURES, lambda: pair_scores(True)),
            ("panel, colour", "panel_temperature", PANEL_TEMPERATURES, panel_scores),
        ):
            eces = ece_per_temperature(identifier, setting, temps, score)
            fitted = getattr(identifier.settings, setting)
            temperature_rows.append((lab, name, fitted, score().summary(), dict(zip(temps, eces))))
            print(f"{lab} {name}: fitted {fitted}, ECE per temperature {np.round(eces, 3).tolist()}", file=sys.stderr)
        for keep in KEEP:
            subsets = [t.subset(np.sort(rng.choice(len(t), int(round(keep * len(t))), replace=False))) for t in tests]
            s = panel_scores(subsets)
            drop_rows.append((lab, keep, np.mean([len(t) for t in subsets]), s.summary(), float(np.mean(s.conf))))
            print(f"{lab} keep {keep}: {drop_rows[-1][3]}", file=sys.stderr)

    if not temperature_rows:
        print(f"no fold model found under {args.runs} (benchmarks/leave_one_lab_out.py makes them): "
              f"{args.out} left as it is", file=sys.stderr)
        return 1
    command = (f"python benchmarks/calibration.py --runs {args.runs} --fold-prefix {args.fold_prefix} "
               f"--labs {' '.join(args.labs)} --pairs {args.pairs} --worms {args.worms}")
    lines = [
        "# Calibration on a lab never seen",
        "",
        f"Made by `{command}` "
        f"({(time.time() - started) / 60:.1f} min; see its docstring). Each lab with its fold model "
        "(trained, checkpoint chosen and calibrated on the other four labs).",
        "",
        "## 1. Expected calibration error of `auto_conf` per temperature",
        "",
        "The fitted temperature (on the four training labs) in bold; \"best\": the lowest ECE any temperature gives.",
        "",
    ]
    for name, temps in (("pairs, position", PAIR_TEMPERATURES), ("pairs, colour", PAIR_TEMPERATURES),
                        ("panel, colour", PANEL_TEMPERATURES)):
        lines += [f"**{name}**", "", "| lab | top-1 | fitted | ECE fitted | " + " | ".join(f"T {t}" for t in temps) + " | best |",
                  "|---" * (len(temps) + 5) + "|"]
        for lab, row_name, fitted, summary, eces in temperature_rows:
            if row_name != name:
                continue
            cells = [f"**{e:.3f}**" if t == fitted else f"{e:.3f}" for t, e in eces.items()]
            lines.append(f"| {lab} | {100 * summary['top1']:.1f} | {fitted} | {summary['ece']:.3f} | "
                         + " | ".join(cells) + f" | {min(eces.values()):.3f} |")
        lines.append("")
    lines += [
        "## 2. The panel with colour on tests with neurons dropped at random",
        "",
        "| lab | neurons kept | neurons per test | top-1 | mean auto_conf | ECE |",
        "|---|---|---|---|---|---|",
    ]
    for lab, keep, n, summary, conf in drop_rows:
        lines.append(f"| {lab} | {100 * keep:.0f} % | {n:.0f} | {100 * summary['top1']:.1f} | {conf:.3f} | {summary['ece']:.3f} |")
    report = "\n".join(lines) + "\n"
    with atomic_write(Path(args.out), "w", encoding="utf-8") as handle:
        handle.write(report)
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
