"""Several recordings of one microscope deciding their handedness together: how often right.

    python benchmarks/handedness.py [--runs runs] [--batch 30] [--draws 200] [--out docs/handedness.md]

A recording mirrored by its acquisition looks like a normal worm with every left/right pair
swapped; one worm barely shows which it is. ``fdlc label`` with several tests on the built-in
panel (``--chirality auto``) names them in one handedness when their evidence clearly agrees
(:func:`napari_fdlc.identify.decide_handedness`). Per corpus lab, each worm is named by the
panel alone (an atlas and panel rebuilt without the lab) and its evidence kept: its mirrored
placement's score minus the other's, by the model's willingness to match and by the
registration's likelihood; its true handedness comes from its names. Then the decision two
ways: the willingness alone votes (sessions 5-12, opt-in), or a worm votes only when both
pieces lean the same way (session 13, the default) — for the lab's worms in one call, and for
``--draws`` batches of ``--batch`` recordings resampled from the lab (seed 0; with
replacement, so a lab of 9 worms stands for a microscope that records 30). Two models: the
fold model that never saw the lab (``runs/fold_<LAB>/model``, made by
``benchmarks/leave_one_lab_out.py``; skipped where missing) and the shipped one (which saw the
other worms of these labs). Writes a markdown table.
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
from napari_fdlc.evaluate import mirrored_relative_to  # noqa: E402
from napari_fdlc.identify import Identifier, decide_handedness, handedness_evidence  # noqa: E402
from napari_fdlc.reference import build_atlas, make_panel  # noqa: E402

RULES = (("the model alone", False), ("model and registration", True))


def lab_evidence(identifier: Identifier, worms, lab: str) -> tuple[np.ndarray, np.ndarray]:
    """(worms, 2) evidence for the lab's worms against a panel without the lab, and their truth."""
    atlas = build_atlas([w for w in worms if w.lab != lab])
    panel = make_panel(atlas)
    tables = [w.table for w in worms if w.lab == lab]
    evidence = [handedness_evidence(identifier.label_panel(t, panel, use_colour=True), identifier.settings.mirror_penalty)
                for t in tables]
    return np.array(evidence), np.array([mirrored_relative_to(atlas, t) for t in tables])


def decide(evidence: np.ndarray, with_registration: bool):
    return decide_handedness(evidence[:, 0], evidence[:, 1] if with_registration else None)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--runs", default="runs", help="folder of the fold models (runs/fold_<LAB>/model)")
    ap.add_argument("--batch", type=int, default=30)
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--out", default="docs/handedness.md")
    args = ap.parse_args(argv)
    started = time.time()
    worms = load_corpus(args.corpus)
    shipped = Identifier.load()
    lines = ["| model | lab | mirrored worms | lean mirrored: model / registration | rule | the lab in one call: votes for mirrored / votes, decided | "
             f"batches of {args.batch}: decided right / wrong / undecided |",
             "|---|---|---|---|---|---|---|"]
    for lab in args.labs:
        fold = Path(args.runs) / f"fold_{lab}" / "model"
        models = [("shipped", shipped)]
        if fold.with_suffix(".safetensors").exists():
            models.insert(0, ("fold (never saw the lab)", Identifier.load(fold)))
        for name, identifier in models:
            evidence, truth = lab_evidence(identifier, worms, lab)
            majority = "mirrored" if truth.mean() > 0.5 else "same"
            rng = np.random.default_rng(0)
            draws = [rng.integers(len(truth), size=args.batch) for _ in range(args.draws)]
            for rule, with_registration in RULES:
                decided, k, n = decide(evidence, with_registration)
                outcomes = [decide(evidence[d], with_registration)[0] for d in draws]
                right = sum(o == majority for o in outcomes)
                undecided = sum(o is None for o in outcomes)
                lines.append(f"| {name} | {lab} | {truth.sum()} of {len(truth)} | {(evidence[:, 0] > 0).sum()} / {(evidence[:, 1] > 0).sum()} | "
                             f"{rule} | {k} / {n}, {decided or '–'} | {right} / {len(draws) - right - undecided} / {undecided} |")
            print(*lines[-2:], sep="\n", flush=True)
    text = (f"# Handedness decided together\n\nMade by `python benchmarks/handedness.py --batch {args.batch} --draws {args.draws}` "
            f"({(time.time() - started) / 60:.1f} min; see its docstring and benchmarks.md). \"Right\": the lab's majority "
            "handedness (by the worms' names).\n\n" + "\n".join(lines) + "\n")
    with atomic_write(Path(args.out), "w", encoding="utf-8") as handle:
        handle.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
