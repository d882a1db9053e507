"""How the panel's names hold up when a lab's tables differ from the corpus's in the ways labs differ.

    python benchmarks/robustness.py [--runs runs] [--labs NP EY KK SF SK1] [--worms 12]

Another lab's annotated worms reach ``fdlc label`` in tables that differ from the corpus's: a
z step calibrated differently, bigger or smaller worms, a field of view cut elsewhere,
sparser annotation, unannotated detections, a colour channel missing, raw intensities instead
of z-scores, another orientation in the microscope. For each corpus lab, the fold model that
never saw it (``runs/fold_<LAB>/model``, from ``benchmarks/leave_one_lab_out.py``) and a panel
rebuilt without the lab name the lab's first ``--worms`` worms one at a time, in the lab's
majority handedness (``--chirality`` as a user sets it for the microscope), each worm as it is
and transformed (seed 0). Top-1 % over the named neurons that are left and that the panel
knows (a dropped neuron is not scored; an added one has no name). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from _folds import held_out_lab  # noqa: E402
from napari_fdlc.corpus import LABS, load_corpus  # noqa: E402
from napari_fdlc.evaluate import Scores  # noqa: E402
from napari_fdlc.table import NeuronTable  # noqa: E402


def rows(table: NeuronTable, keep: np.ndarray) -> NeuronTable:
    return NeuronTable(table.xyz[keep], {c: v[keep] for c, v in table.colours.items()}, table.labels[keep],
                       table.label_conf[keep], source=table.source)


def scaled(axes):
    return lambda t, rng: replace(t, xyz=t.xyz * np.asarray(axes))


def turned(tilt_degrees: float):
    """Any turn in the image plane, a tilt out of it of ``tilt_degrees`` about a random axis in
    the plane (z stays the optical axis: worms lie flat, give or take), and a shift."""
    def transform(t, rng):
        axis = np.r_[rng.normal(size=2), 0.0]
        tilt = Rotation.from_rotvec(np.radians(tilt_degrees) * axis / np.linalg.norm(axis))
        turn = Rotation.from_euler("z", rng.uniform(0, 360), degrees=True)
        return replace(t, xyz=t.xyz @ (tilt * turn).as_matrix().T + rng.normal(0, 50, 3))
    return transform


def dropped(t, rng):
    return rows(t, rng.random(len(t)) >= 0.3)


def with_spurious(t, rng):
    """20 % more points, each 3-8 µm from a random neuron, colours of another random neuron."""
    n = int(0.2 * len(t))
    near = rng.integers(len(t), size=n)
    step = rng.normal(size=(n, 3))
    step *= rng.uniform(3, 8, n)[:, None] / np.linalg.norm(step, axis=1, keepdims=True)
    donor = rng.integers(len(t), size=n)
    return NeuronTable(np.vstack([t.xyz, t.xyz[near] + step]),
                       {c: np.concatenate([v, v[donor]]) for c, v in t.colours.items()},
                       np.concatenate([t.labels, np.full(n, "", dtype=object)]), source=t.source)


def cropped(t, rng):
    """The 60 % of the neurons at one end of the longest axis (a field of view cut there)."""
    centred = t.xyz - t.xyz.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    along = centred @ axis
    return rows(t, along <= np.quantile(along, 0.6))


def without_blue(t, rng):
    return replace(t, colours={c: v for c, v in t.colours.items() if c != "B"})


def raw_colours(t, rng):
    """Colours as raw counts: an exponential of the values (any monotone map), per channel."""
    return replace(t, colours={c: 200 * np.exp(v / (np.std(v) or 1)) + 100 for c, v in t.colours.items()})


def colour_noise(t, rng):
    return replace(t, colours={c: v + rng.normal(0, 0.3 * (np.std(v) or 1), len(v)) for c, v in t.colours.items()})


TRANSFORMS = {
    "as it is": lambda t, rng: t,
    "turned in the image plane": turned(0),
    "and tilted 10°": turned(10),
    "and tilted 20°": turned(20),
    "z × 0.8": scaled((1, 1, 0.8)),
    "z × 1.25": scaled((1, 1, 1.25)),
    "× 0.9": scaled((0.9, 0.9, 0.9)),
    "× 1.1": scaled((1.1, 1.1, 1.1)),
    "30 % dropped": dropped,
    "20 % spurious": with_spurious,
    "cropped to 60 %": cropped,
    "no B": without_blue,
    "raw colours": raw_colours,
    "colour noise 0.3 SD": colour_noise,
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus", default=None)
    ap.add_argument("--labs", nargs="+", default=list(LABS))
    ap.add_argument("--runs", default="runs", help="folder of the fold models (runs/fold_<LAB>/model)")
    ap.add_argument("--worms", type=int, default=12, help="worms per lab")
    args = ap.parse_args(argv)
    worms = load_corpus(args.corpus)
    lines = ["| held-out lab | " + " | ".join(TRANSFORMS) + " |", "|---|" + "---|" * len(TRANSFORMS)]
    for lab in args.labs:
        panel, tests, identifier = held_out_lab(worms, lab, args.runs, args.worms)
        cells = []
        for k, transform in enumerate(TRANSFORMS.values()):
            rng = np.random.default_rng(k)
            scores = Scores()
            for test in tests:
                changed = transform(test, rng)
                scores.add(identifier.label_panel(changed, panel, use_colour=True), changed, panel.names)
            cells.append(f"{100 * scores.summary()['top1']:.1f}")
        lines.append(f"| {lab} | " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr, flush=True)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
