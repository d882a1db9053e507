"""measure accuracy, calibration and coverage of the model on annotated worms

``fdlc evaluate`` runs the protocols of :mod:`napari_fdlc.evaluate` and writes a markdown report
(tables) plus a reliability plot; ``benchmarks/accuracy.py`` is the same with the defaults used
for docs/accuracy.md.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from urllib.parse import quote
from pathlib import Path

import numpy as np

from .errors import FdlcError, _is_stream, atomic_write, check_output, warn


BATCH_ROW = "colour, the lab's worms in one call"
ADAPTED_ROW = "colour, the lab's worms in one call, colours adapted"


def add_arguments(p: argparse.ArgumentParser, default_out: str = "accuracy.md") -> None:
    p.add_argument("--corpus", help="folder with worms.csv (default: ../shared/data/neuropal_corpus or $FDLC_CORPUS)")
    p.add_argument("--labs", nargs="+", default=None)
    p.add_argument("--weights", help="model path without suffix (default: shipped)")
    p.add_argument("--pairs-per-lab", type=int, default=20)
    p.add_argument("--panel-worms-per-lab", type=int, default=40,
                   help="worms of each lab named by the panel (default 40: every worm of the corpus's labs)")
    p.add_argument("--synthetic-pairs", type=int, default=40)
    p.add_argument("--no-cpd", action="store_true")
    p.add_argument("--out", default=default_out,
                   help=f"markdown report (default {default_out}; the reliability plot goes beside it in images/)")


def run(args) -> int:
    for flag in ("pairs_per_lab", "panel_worms_per_lab", "synthetic_pairs"):
        if getattr(args, flag) < 0:
            raise FdlcError(f"--{flag.replace('_', '-')} must be 0 or more (got {getattr(args, flag)})")
    from .corpus import refuse_out_in_corpus
    from .errors import model_files
    from .identify import shipped_weights

    # The model (the shipped one by default) and the corpus are read, never written: a report
    # over the weights' JSON or a worm's table would destroy them.
    refuse_out_in_corpus(Path(args.out), args.corpus, "report")  # before its folder is made
    check_output(args.out, inputs=model_files(args.weights or shipped_weights()), create_folder=True)
    report = evaluate_corpus(
        corpus=args.corpus, labs=args.labs, weights=args.weights, pairs_per_lab=args.pairs_per_lab,
        panel_worms_per_lab=args.panel_worms_per_lab, synthetic_pairs=args.synthetic_pairs,
        with_cpd=not args.no_cpd, out=Path(args.out),
    )
    print(report)
    return 0


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def evaluate_corpus(corpus=None, labs=None, weights=None, pairs_per_lab=20, panel_worms_per_lab=40,
                    synthetic_pairs=40, with_cpd=True, out: Path | None = None) -> str:
    from .baselines import cpd_match, floor_match
    from .corpus import LABS, load_corpus
    from .evaluate import Scores, baseline_labelling, coverage_curve, mirrored_relative_to, pair_list, reliability
    from .identify import Identifier
    from .reference import build_atlas, make_panel
    from .simulate import simulate_worm

    # what reproduces this report: the options given, as given
    corpus = corpus or os.environ.get("FDLC_CORPUS") or None  # the report says which corpus it read
    labs = [lab.strip() for lab in labs] if labs else labs  # as the corpus reads them
    # quoted, so that a folder with a space in its name reads back as one argument
    command = ["fdlc evaluate"] + [f"{flag} {value}" for flag, value in (
        ("--corpus", corpus and shlex.quote(str(corpus))), ("--labs", " ".join(shlex.quote(lab) for lab in labs or [])),
        ("--weights", weights and shlex.quote(str(weights)))) if value]
    command += [f"--pairs-per-lab {pairs_per_lab}", f"--panel-worms-per-lab {panel_worms_per_lab}",
                f"--synthetic-pairs {synthetic_pairs}", *([] if with_cpd else ["--no-cpd"])]
    command = " ".join(command + ([f"--out {shlex.quote(str(out))}"] if out is not None else []))
    identifier = Identifier.load(weights, identifies=True)
    worms = load_corpus(corpus)
    present = {w.lab for w in worms}
    # default: the corpus's labs (the five known ones first, in their order)
    labs = list(dict.fromkeys(labs or [lab for lab in LABS if lab in present] + sorted(present - set(LABS))))  # each once
    unknown = set(labs) - present
    if unknown:
        raise FdlcError(f"no worms of lab(s) {', '.join(sorted(unknown))} in the corpus")
    rows, calib = [], {}
    started = time.time()
    for lab in labs:
        tables = [w.table for w in worms if w.lab == lab]
        pairs = pair_list(tables, pairs_per_lab, seed=0)
        # The built-in atlas (beside a template, and the panel's) is rebuilt WITHOUT this lab, so
        # the names and positions it offers never come from the worms being scored.
        others = [w for w in worms if w.lab != lab]
        if not others:
            raise FdlcError(f"lab {lab}: the atlas beside a template and the panel are built from the other labs' "
                            "worms (a lab is never scored on its own), and the corpus has no other lab")
        try:
            atlas = build_atlas(others)
        except FdlcError as exc:
            raise FdlcError(f"lab {lab}: the atlas beside a template and the panel are built from the other labs' "
                            f"{len(others)} worm(s): {exc}") from None
        methods = {
            ("pairs", "fdlc", "position"): lambda T, t: identifier.label(t, [T], use_colour=False, atlas=atlas),
            ("pairs", "fdlc", "colour"): lambda T, t: identifier.label(t, [T], use_colour=True, atlas=atlas),
            ("pairs", "floor", "position"): lambda T, t: baseline_labelling(floor_match, t, [T], False),
            ("pairs", "floor", "colour"): lambda T, t: baseline_labelling(floor_match, t, [T], True),
        }
        if with_cpd:
            methods[("pairs", "CPD", "position")] = lambda T, t: baseline_labelling(cpd_match, t, [T], False)
        for key, fn in methods.items():
            scores = Scores()
            for template, test in pairs:
                t0 = time.perf_counter()
                result = fn(template, test)
                scores.add(result, test, set(template.names), time.perf_counter() - t0)
            rows.append((lab, *key, scores.summary()))
            if key[1] == "fdlc":
                calib.setdefault(key[2], Scores()).merge(scores)
            _log(f"{lab} {key}: {rows[-1][-1]}")
        if panel_worms_per_lab <= 0:
            continue
        panel = make_panel(atlas)
        vocabulary = panel.names
        tests = tables[:panel_worms_per_lab]
        for use_colour in (False, True):
            scores, named = Scores(), []
            for test in tests:
                t0 = time.perf_counter()
                named.append(identifier.label_panel(test, panel, use_colour=use_colour))
                scores.add(named[-1], test, vocabulary, time.perf_counter() - t0)
            rows.append((lab, "panel", "fdlc", "colour" if use_colour else "position", scores.summary()))
            _log(f"{lab} panel colour={use_colour}: {rows[-1][-1]}")
        # Every worm of the lab in one call, as `fdlc label --shared-handedness` names several
        # recordings: one handedness for all when they clearly agree (from the answers above).
        scores = Scores()
        for test, result in zip(tests, identifier.label_panel_many(tests, panel, use_colour=True, first=named)):
            scores.add(result, test, vocabulary)
        rows.append((lab, "panel", "fdlc", BATCH_ROW, scores.summary()))
        _log(f"{lab} panel {BATCH_ROW}: {rows[-1][-1]}")
        # ... and their colours measured on them (`fdlc label --shared-handedness --adapt-colours`).
        scores = Scores()
        for test, result in zip(tests, identifier.label_panel_many(tests, panel, use_colour=True, first=named, adapt_colours=True)):
            scores.add(result, test, vocabulary)
        rows.append((lab, "panel", "fdlc", ADAPTED_ROW, scores.summary()))
        _log(f"{lab} panel {ADAPTED_ROW}: {rows[-1][-1]}")
        # Told the handedness (--chirality same|mirrored), read from the names: each worm's own,
        # and the lab's majority set once for all of them (what a user who sets it for the
        # microscope gets).
        mirrored = [mirrored_relative_to(panel.atlas, t) for t in tables]
        lab_mirrored = np.mean(mirrored) > 0.5
        for inp, told in (("colour, chirality given", lambda k: mirrored[k]), ("colour, lab handedness", lambda k: lab_mirrored)):
            scores = Scores()
            for k, test in enumerate(tests):
                chirality = "mirrored" if told(k) else "same"
                scores.add(identifier.with_chirality(chirality).label_panel(test, panel, use_colour=True), test, vocabulary)
            rows.append((lab, "panel", "fdlc", inp, scores.summary()))
            _log(f"{lab} panel {inp}: {rows[-1][-1]}")
    # Held-out synthetic pairs: a worm and its simulated copy (published simulator magnitudes).
    rng = np.random.default_rng(0)
    synth = Scores()
    sources = [w for w in worms if w.lab in labs]
    for _ in range(synthetic_pairs):
        source = sources[rng.integers(len(sources))].table
        copy = simulate_worm(source, rng)
        synth.add(identifier.label(copy.table, [source], use_colour=False), copy.table, set(source.names))
    synthetic = synth.summary()
    minutes = (time.time() - started) / 60

    lines = ["| lab | protocol | method | input | top-1 | top-3 | ECE | neurons | ms / volume |", "|---|---|---|---|---|---|---|---|---|"]
    for lab, protocol, method, inp, s in rows:
        ms = "–" if np.isnan(s["ms_per_volume"]) else f"{s['ms_per_volume']:.0f}"
        lines.append(f"| {lab} | {protocol} | {method} | {inp} | {100 * s['top1']:.1f} | {100 * s['top3']:.1f} | "
                     f"{s['ece']:.3f} | {s['n']} | {ms} |")
    lines.append("")
    if synthetic_pairs:
        lines.append(f"Synthetic pairs (simulator defaults = published magnitudes, {synthetic_pairs} pairs, position only): "
                     f"top-1 {100 * synthetic['top1']:.1f} %, top-3 {100 * synthetic['top3']:.1f} %.")
    lines.append("")
    lines.append("Confidence threshold on `auto_conf` (pairs protocol, all labs): coverage and accuracy of the labels kept.")
    lines.append("")
    lines.append("| input | threshold | coverage | accuracy |")
    lines.append("|---|---|---|---|")
    for inp, s in calib.items():
        conf, correct = np.asarray(s.conf), np.asarray(s.correct, float)
        for t, cov, acc in coverage_curve(conf, correct, s.named):
            lines.append(f"| {inp} | {t:.2f} | {100 * cov:.1f} | {100 * acc:.1f} |")
    report = "\n".join(lines)
    if out is not None:
        # The plot needs matplotlib (the [test] extra); without it the report is written alone.
        plotted = False
        # named after the report (two reports in one folder had one plot), beside the report
        # itself where --out is a link (atomic_write follows it)
        plot = f"images/{out.stem}_calibration.png"
        if not _is_stream(out):  # beside a file (a stream such as /dev/null has no folder to put it in)
            try:
                plotted = _plot_reliability(calib, Path(os.path.realpath(out)).parent / plot, reliability)
            except OSError as exc:  # the finished run is not lost for its plot
                warn(f"{out.parent / plot}: the reliability plot could not be written "
                     f"({exc.strerror or exc}); the report is written without it")
        with atomic_write(out, "w", encoding="utf-8") as handle:
            handle.write("# Accuracy on the annotated corpus\n\n")
            handle.write(f"Made by `{command}` ({minutes:.1f} min). See docs/benchmarks.md for how to read it.\n\n")
            handle.write("top-1: the name assigned (`auto_id`) is the annotated one; top-3: the annotated name "
                         "is among `cand_1..3`, the review's three candidates. Names are assigned one-to-one on "
                         "the answer before its temperature and, on the panel, before the other handedness is "
                         "mixed in (neuron_table.md: `auto_id` need not be `cand_1`), so a name assigned right "
                         "can lie outside them.\n\n")
            handle.write(report + (f"\n\n![reliability]({quote(plot)})\n" if plotted else "\n"))  # a name with spaces
    return report


def _plot_reliability(calib, path: Path, reliability) -> bool:
    """The reliability diagram as a PNG; False (and one warning line) without matplotlib."""
    try:
        import matplotlib
    except ImportError:
        warn("the reliability plot needs matplotlib (pip install matplotlib); the report is written without it")
        return False

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.plot([0, 1], [0, 1], "k--", lw=1, label="perfect")
    for inp, s in calib.items():
        bins = reliability(np.asarray(s.conf), np.asarray(s.correct, float))
        ax.plot([b[0] for b in bins], [b[1] for b in bins], "o-", label=f"fdlc ({inp})")
    ax.set_xlabel("auto_conf")
    ax.set_ylabel("accuracy")
    ax.set_title("Reliability (pairs within each lab)")
    ax.legend()
    fig.tight_layout()
    with atomic_write(path, "wb") as handle:
        fig.savefig(handle, dpi=110, format="png")
    plt.close(fig)
    return True
