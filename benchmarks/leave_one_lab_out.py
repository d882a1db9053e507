"""Leave-one-lab-out: one fold model per lab, trained without it and scored on it.

    python benchmarks/leave_one_lab_out.py --train --minutes 20    # train the five folds, then score
    python benchmarks/leave_one_lab_out.py --stage2 25             # then stage 2 of every fold, then score
    python benchmarks/leave_one_lab_out.py                         # score folds already trained
    python benchmarks/leave_one_lab_out.py --recalibrate           # refit their inference settings first
    python benchmarks/leave_one_lab_out.py --no-evaluate --fold-prefix regfold   # only collect the reports

Folds can be made one lab at a time (``--labs NP``), two in parallel on two cores: each trains on
one thread for the minutes given.

Stage 1 of each fold is ``fdlc train --train-labs <the other four> --colour-input --minutes M
--threads 1 --steps 5000 --eval-every 1000 --val-pairs-per-lab 6 --out runs/fold_<LAB>/model``.
Stage 2 (``--stage2 M``) warm-starts from it with the examples inference now shows the model
(registered pairs and panel examples): ``fdlc train --config docs/training/fold_stage2.json
--train-labs <the other four> --init-from runs/fold_<LAB>/model --minutes M --out
runs/regfold_<LAB>/model``; scoring then uses ``runs/regfold_<LAB>`` (``--fold-prefix``).
Checkpoint choice and calibration use the four training labs only. Then ``fdlc evaluate --labs
<LAB> --weights <fold>/model --pairs-per-lab 20 --panel-worms-per-lab 40`` (the panel's atlas is
rebuilt without the lab too). Writes
docs/leave_one_lab_out.md: every protocol per lab, next to the published figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc.cli import main as fdlc  # noqa: E402
from napari_fdlc.corpus import LABS  # noqa: E402
from napari_fdlc.errors import atomic_write  # noqa: E402

# WormND (Sprague et al. 2024), panel protocol with colour: fDLC trained without the lab, and the
# best published method for the lab (CRF_ID retrained on that lab's own data).
PUBLISHED_LOLO_FDLC = {"EY": 44.1, "KK": 23.3, "SF": 55.5, "SK1": 51.7}
# Every worm of the lab against the panel (the largest lab, SF, has 36): one panel call is ~0.1 s.
PANEL_WORMS = 40
PUBLISHED_BEST = {"EY": 57.6, "KK": 55.9, "SF": 83.9, "SK1": 72.7}
COLUMNS = [
    (("pairs", "fdlc", "colour"), "pairs: fdlc + colour"),
    (("pairs", "floor", "colour"), "pairs: floor + colour"),
    (("pairs", "fdlc", "position"), "pairs: fdlc position"),
    (("pairs", "floor", "position"), "pairs: floor position"),
    (("pairs", "CPD", "position"), "pairs: CPD position"),
    (("panel", "fdlc", "position"), "panel: position"),
    (("panel", "fdlc", "colour"), "panel: colour"),
    (("panel", "fdlc", "colour, the lab's worms in one call"), "panel: colour, the lab's worms in one call"),
    (("panel", "fdlc", "colour, the lab's worms in one call, colours adapted"), "panel: colour, the lab's worms in one call, colours adapted"),
    (("panel", "fdlc", "colour, lab handedness"), "panel: colour, the lab's handedness"),
    (("panel", "fdlc", "colour, chirality given"), "panel: colour, handedness given"),
]


def read_report(path: Path, lab: str) -> dict:
    """{(protocol, method, input): (top-1, top-3, ECE)} from an `fdlc evaluate` report."""
    out = {}
    for line in path.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 7 and cells[0] == lab:
            out[tuple(cells[1:4])] = (float(cells[4]), float(cells[5]), float(cells[6]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--runs", default="runs", help="folder of the fold models (runs/fold_<LAB>/model)")
    ap.add_argument("--train", action="store_true", help="train the folds first")
    ap.add_argument("--minutes", type=float, default=20)
    ap.add_argument("--stage2", type=float, default=None, metavar="MINUTES",
                    help="train stage 2 of each fold (docs/training/fold_stage2.json) for this long, then score it")
    ap.add_argument("--fold-prefix", default=None, help="fold folders <runs>/<prefix>_<LAB> (default: regfold with --stage2, else fold)")
    ap.add_argument("--recalibrate", action="store_true",
                    help="refit each fold's inference settings with the current code (on its training labs) before scoring")
    ap.add_argument("--no-evaluate", action="store_true", help="only collect existing fold reports")
    ap.add_argument("--out", default="docs/leave_one_lab_out.md")
    args = ap.parse_args(argv)
    runs = Path(args.runs)
    prefix = args.fold_prefix or ("regfold" if args.stage2 else "fold")
    for lab in args.labs:
        first, fold = runs / f"fold_{lab}", runs / f"{prefix}_{lab}"
        others = [x for x in LABS if x != lab]
        if args.train:
            fdlc(["train", "--train-labs", *others, "--val-labs", *LABS, "--colour-input", "--minutes", str(args.minutes),
                  "--threads", "1", "--eval-every", "1000", "--val-pairs-per-lab", "6", "--steps", "5000",
                  "--out", str(first / "model")])
        if args.stage2:
            config = Path(__file__).resolve().parents[1] / "docs/training/fold_stage2.json"
            fdlc(["train", "--config", str(config), "--train-labs", *others, "--init-from", str(first / "model"),
                  "--minutes", str(args.stage2), "--out", str(fold / "model")])
        if args.recalibrate:
            fdlc(["train", "--config", str(fold / "model.json"), "--threads", "1", "--out", str(fold / "model"), "--calibrate-only"])
        if not args.no_evaluate:
            fdlc(["evaluate", "--labs", lab, "--weights", str(fold / "model"), "--pairs-per-lab", "20",
                  "--panel-worms-per-lab", str(PANEL_WORMS), "--synthetic-pairs", "0", "--out", str(runs / f"{prefix}_{lab}_accuracy.md")])
    head = "| held-out lab | " + " | ".join(name for _, name in COLUMNS) + " | published LOLO fDLC | best published |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 3)]
    ece = ["| held-out lab | pairs: fdlc position | pairs: fdlc + colour | panel: position | panel: colour | panel: colour, the lab's handedness | panel: colour, handedness given |",
           "|---|---|---|---|---|---|---|"]
    for lab in args.labs:
        report = read_report(runs / f"{prefix}_{lab}_accuracy.md", lab)
        cells = [f"{report[key][0]:.1f} / {report[key][1]:.1f}" if key in report else "–" for key, _ in COLUMNS]
        lines.append(f"| {lab} | " + " | ".join(cells) + f" | {PUBLISHED_LOLO_FDLC.get(lab, '–')} | {PUBLISHED_BEST.get(lab, '–')} |")
        keys = [("pairs", "fdlc", "position"), ("pairs", "fdlc", "colour"), ("panel", "fdlc", "position"),
                ("panel", "fdlc", "colour"), ("panel", "fdlc", "colour, lab handedness"), ("panel", "fdlc", "colour, chirality given")]
        ece.append(f"| {lab} | " + " | ".join(f"{report[k][2]:.3f}" if k in report else "–" for k in keys) + " |")
    text = "\n".join(lines) + "\n\nExpected calibration error of `auto_conf` (calibration fitted on the four training labs only):\n\n" + "\n".join(ece) + "\n"
    with atomic_write(args.out, "w", encoding="utf-8") as handle:
        shown = list(sys.argv[1:] if argv is None else argv)
        if "--out" in shown:  # where the page went is not how it was made
            i = shown.index("--out")
            del shown[i:i + 2]
        handle.write("# Leave-one-lab-out\n\nMade by `" + " ".join(["python benchmarks/leave_one_lab_out.py", *shown])
                     + "` (see its docstring for the"
                     " exact commands; how to read it: benchmarks.md). Top-1 / top-3 %, each lab scored with the"
                     " fold model that never saw it: trained on the other four labs, checkpoint and inference"
                     " settings chosen on those four only, the atlas (beside a template, and the panel's) rebuilt without the lab"
                     " (20 pairs within the lab; every worm of the lab against the panel). Published figures: WormND, panel"
                     " protocol with colour — fDLC trained without the lab, and the best published method"
                     " for the lab (CRF_ID retrained on the lab's own data).\n\n")
        handle.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
