"""End to end: render a corpus worm as a NeuroPAL stack, segment it, name the detected nuclei
against another worm of its lab — and compare with naming the worm's true positions.

    python benchmarks/identify_from_images.py [--worms-per-lab 2] [--protocol pairs|panel] [--corpus PATH]

For each test worm: the renderer (napari_fdlc.render, its default noise) makes the stack;
segment_stack finds the nuclei and reads their colours; fdlc (with colour) names them against a
labelled template (the next worm of the same lab) with the atlas's answer beside it, as ``fdlc
label --template`` does (the atlas rebuilt without the test's lab). Detections are matched one-to-one to true
neurons within 1.5 µm; accuracy counts named true neurons whose name the template has (a missed
nucleus counts as wrong). The same test's true table (positions and rendered colours) named the
same way gives the "true positions" figure. With ``--protocol panel`` the names come from the
built-in panel instead (what ``fdlc label`` does without ``--template``), rebuilt from an atlas
that excludes the test's lab. The corpus is read in place.

With ``--decompose``, three more tables per lab say where the gap comes from: the true
positions with the colours read from the image at them (``segment.measure_colours``: the
colour readout alone), the detections with their true neurons' colours (detection alone), and
the true table without the neurons the segmentation missed (what the missed nuclei cost).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402
from scipy.optimize import linear_sum_assignment  # noqa: E402
from scipy.spatial.distance import cdist  # noqa: E402

from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.evaluate import mirrored_relative_to  # noqa: E402
from napari_fdlc.identify import Identifier  # noqa: E402
from napari_fdlc.reference import build_atlas, make_panel  # noqa: E402
from napari_fdlc.render import render_stack  # noqa: E402
from napari_fdlc.segment import measure_colours, segment_stack  # noqa: E402
from napari_fdlc.table import NeuronTable  # noqa: E402


def accuracy(labels: list[str], truth_names: np.ndarray, vocabulary: set[str]) -> tuple[int, int]:
    scored = [j for j, n in enumerate(truth_names) if n and n in vocabulary]
    return sum(labels[j] == truth_names[j] for j in scored), len(scored)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--worms-per-lab", type=int, default=2)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--protocol", choices=("pairs", "panel"), default="pairs")
    ap.add_argument("--chirality-given", action="store_true",
                    help="tell the model each worm's handedness (read from its names), as a user who knows the microscope would")
    ap.add_argument("--decompose", action="store_true",
                    help="also name the true positions with colours read from the image, the detections with true "
                         "colours, and the true table without the missed nuclei")
    args = ap.parse_args(argv)
    identifier = Identifier.load(args.weights)
    worms = load_corpus(args.corpus)
    rows, decomposed = [], []
    for lab in args.labs:
        tables = [w.table for w in worms if w.lab == lab]
        atlas = build_atlas([w for w in worms if w.lab != lab])
        panel = make_panel(atlas)

        def name(table, template, source):
            told = identifier
            if args.chirality_given:  # handedness relative to the panel's atlas, or to the template
                mirrored = mirrored_relative_to(atlas, source)
                if args.protocol == "pairs":
                    mirrored = mirrored != mirrored_relative_to(atlas, template)
                told = identifier.with_chirality("mirrored" if mirrored else "same")
            if args.protocol == "panel":
                return told.label_panel(table, panel, use_colour=True)
            return told.label(table, [template], use_colour=True, atlas=atlas)  # as fdlc label --template
        hit_img = n_img = hit_true = n_true = found_total = truth_total = 0
        parts = {part: np.zeros(2) for part in DECOMPOSED}
        seconds = []
        for k in range(min(args.worms_per_lab, len(tables) - 1)):
            template, source = tables[k + 1], tables[k]
            stack, truth = render_stack(source, seed=k)
            start = time.perf_counter()
            found = segment_stack(stack)
            seconds.append(time.perf_counter() - start)
            vocabulary = panel.names if args.protocol == "panel" else set(template.names)
            # from true positions (and the rendered colours)
            result = name(truth, template, source)
            h, n = accuracy(result.auto_id, truth.labels, vocabulary)
            hit_true, n_true = hit_true + h, n_true + n
            # from the image: each true neuron gets the name given to its detection (if any)
            result = name(found, template, source)
            d = cdist(truth.xyz, found.xyz)
            # the most pairs within 1.5 µm, one-to-one (on the raw distances the least total
            # distance could give up a pair within reach for a nearer one: score_detections' cut-off)
            r, c = linear_sum_assignment(np.where(d < 1.5, d, 1e6))
            given = np.full(len(truth), "", dtype=object)
            ok = d[r, c] < 1.5
            given[r[ok]] = np.asarray(result.auto_id, dtype=object)[c[ok]]
            h, n = accuracy(list(given), truth.labels, vocabulary)
            hit_img, n_img = hit_img + h, n_img + n
            found_total += int(ok.sum())
            truth_total += len(truth)
            if args.decompose:
                for part, hn in zip(parts, _decomposed(name, stack, truth, found, r[ok], c[ok], template, source, vocabulary)):
                    parts[part] += hn
        rows.append((lab, hit_true / max(n_true, 1), hit_img / max(n_img, 1), found_total / max(truth_total, 1), np.median(seconds)))
        print(f"{lab}: true {rows[-1][1]:.3f} image {rows[-1][2]:.3f} recall {rows[-1][3]:.3f}", file=sys.stderr, flush=True)
        if args.decompose:
            decomposed.append((lab, rows[-1][1], *(h / max(n, 1) for h, n in parts.values()), rows[-1][2]))
    how = "the built-in panel (atlas without the lab)" if args.protocol == "panel" else "template = another worm of the lab"
    how += ", handedness given" if args.chirality_given else ""
    print(f"\nfdlc with colour, {how}, {args.worms_per_lab} test worms per lab.\n")
    print("| lab | top-1 from true positions | top-1 from the image | difference (points) | nuclei found | segmentation s |")
    print("|---|---|---|---|---|---|")
    for lab, t, i, rec, s in rows:
        print(f"| {lab} | {100 * t:.1f} | {100 * i:.1f} | {100 * (i - t):+.1f} | {100 * rec:.0f} % | {s:.2f} |")
    if decomposed:
        print("\nWhere the gap comes from (top-1 %; each column changes one thing from the true table):\n")
        print("| lab | true positions and colours | " + " | ".join(DECOMPOSED.values()) + " | the image |")
        print("|---|---|" + "---|" * len(DECOMPOSED) + "---|")
        for lab, *values in decomposed:
            print(f"| {lab} | " + " | ".join(f"{100 * v:.1f}" for v in values) + " |")
    return 0


DECOMPOSED = {
    "colours": "true positions, colours read from the image",
    "detections": "the detections, their true neurons' colours",
    "missed": "the true table without the missed nuclei",
}


def _decomposed(name, stack, truth, found, true_rows, found_rows, template, source, vocabulary):
    """(hits, scored) for each table of DECOMPOSED: one thing of the true table replaced by
    what the image gave (see the module docstring)."""
    read = measure_colours(stack, truth.xyz)
    tables = {"colours": NeuronTable(truth.xyz, {c: read[c] for c in ("R", "G", "B", "W") if c in read}, truth.labels)}
    colours = {c: v.copy() for c, v in found.colours.items()}
    for c, v in colours.items():
        if c in truth.colours:
            true = np.asarray(truth.colours[c], dtype=float)
            v[found_rows] = ((true - true.mean()) / true.std())[true_rows]
    tables["detections"] = NeuronTable(found.xyz, colours)
    tables["missed"] = truth.subset(np.sort(true_rows))
    out = []
    for part, table in tables.items():
        ids = np.asarray(name(table, template, source).auto_id, dtype=object)
        given = np.full(len(truth), "", dtype=object)
        if part == "colours":
            given = ids
        elif part == "detections":
            given[true_rows] = ids[found_rows]
        else:
            given[np.sort(true_rows)] = ids
        out.append(np.array(accuracy(list(given), truth.labels, vocabulary)))
    return out


if __name__ == "__main__":
    sys.exit(main())
