"""Picture of a worm and its synthetic variants (docs/images/simulator.png).

    python benchmarks/simulator_figure.py [--seed 0]

The source worm is generated from the shipped atlas (no corpus needed); the variants come from
napari_fdlc.simulate with its defaults (the published magnitudes). Each variant is shown in its
canonical frame, coloured by the source neuron's position along the body so that the
correspondence can be followed by eye; spurious neurons are black crosses.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402

from napari_fdlc.geometry import canonical_frame  # noqa: E402
from napari_fdlc.reference import generate_worm  # noqa: E402
from napari_fdlc.simulate import simulate_worm  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="docs/images/simulator.png")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    worm = generate_worm(seed=args.seed)
    canon, _, _ = canonical_frame(worm.xyz)
    hue = (canon[:, 0] - canon[:, 0].min()) / np.ptp(canon[:, 0])
    rng = np.random.default_rng(args.seed)
    fig, axes = plt.subplots(5, 1, figsize=(8, 9), sharex=True)
    axes[0].scatter(canon[:, 0], canon[:, 1], c=hue, cmap="viridis", s=12)
    axes[0].set_title("source worm (generated from the atlas), canonical frame")
    for ax in axes[1:]:
        synth = simulate_worm(worm, rng)
        pts, _, _ = canonical_frame(synth.table.xyz)
        real = synth.origin >= 0
        ax.scatter(pts[real, 0], pts[real, 1], c=hue[synth.origin[real]], cmap="viridis", s=12)
        ax.scatter(pts[~real, 0], pts[~real, 1], c="k", marker="x", s=14)
        ax.set_title(f"synthetic variant: {real.sum()} kept, {(~real).sum()} spurious", fontsize=9)
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_ylabel("y (µm)")
    axes[-1].set_xlabel("x along the body (µm)")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
