"""Segmentation benchmark: detection accuracy and speed on rendered NeuroPAL stacks.

Worm positions and colours come from the NeuroPAL corpus, read in place (never copied), or from
worms generated from the shipped atlas when no corpus is given or found. Each worm is rendered
(``napari_fdlc.render``) at several noise levels and densities, segmented
(``napari_fdlc.segment.segment_stack``) and scored: a detection matches a true centre within half
a nucleus diameter, one-to-one (``scipy.optimize.linear_sum_assignment``).

    .venv/bin/python benchmarks/segmentation.py [--corpus ../shared/data/neuropal_corpus]
        [--worms-per-lab 1] [--figure docs/images/segmentation_sample.png]
    .venv/bin/python benchmarks/segmentation.py --padding   # the sample padded with zeros, or background-subtracted

Prints a markdown table (the one in docs/segmentation.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from napari_fdlc.render import render_stack
from napari_fdlc.segment import score_detections, segment_stack
from napari_fdlc.table import NeuronTable, read_table

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CORPUS = REPO.parent / "shared" / "data" / "neuropal_corpus"
# Photons at a nucleus centre (W, average brightness) above a background of 20 photons and
# 4 counts of read noise; "realistic" is a typical NeuroPAL confocal stack's W channel.
NOISE = {"low": 400.0, "realistic": 100.0, "high": 30.0, "very high": 12.0}
# Density: fraction of neurons kept and a scale on positions (0.85 packs the head tighter,
# so more nuclei touch).
DENSITY = {"sparse (50%)": (0.5, 1.0), "as annotated": (1.0, 1.0), "dense (x0.85)": (1.0, 0.85)}


def load_worms(corpus: Path | None, per_lab: int) -> list[tuple[str, NeuronTable]]:
    if corpus is not None and corpus.is_dir():
        worms = []
        for lab in sorted(p for p in corpus.iterdir() if p.is_dir()):
            for path in sorted(lab.glob("*.csv"))[:per_lab]:
                worms.append((f"{lab.name}/{path.stem}", read_table(path)))
        if worms:
            return worms
    from napari_fdlc.reference import generate_worm

    print("no corpus found: using worms generated from the shipped atlas", file=sys.stderr)
    return [(f"generated/{s}", generate_worm(seed=s)) for s in range(5 * per_lab)]


def vary(table: NeuronTable, keep: float, scale: float, rng) -> NeuronTable:
    idx = np.sort(rng.choice(len(table), int(round(keep * len(table))), replace=False)) if keep < 1 else np.arange(len(table))
    sub = table.subset(idx)
    sub.xyz = sub.xyz * scale
    return sub


def run_condition(worms, noise: float, keep: float, scale: float, voxel, diameter: float, seed: int) -> dict:
    rows = []
    for k, (_, table) in enumerate(worms):
        rng = np.random.default_rng(seed + k)
        worm = vary(table, keep, scale, rng)
        stack, truth = render_stack(worm, seed=seed + k, peak_photons=noise, voxel_size_zyx=voxel)
        t0 = time.perf_counter()
        found = segment_stack(stack, diameter_um=diameter)
        seconds = time.perf_counter() - t0
        s = score_detections(truth.xyz, found.xyz, max_distance_um=diameter / 2)
        pairs = s["pairs"]
        rho = [
            spearmanr(truth.extra[f"{c}_int"].to_numpy()[pairs[:, 0]], found.colours[c][pairs[:, 1]])[0]
            for c in "RGB" if c in found.colours and len(pairs) > 2
        ]
        rows.append({**s, "seconds": seconds, "rho": float(np.mean(rho)) if rho else float("nan"),
                     "voxels": int(np.prod(stack.data.shape))})
    tp = sum(r["tp"] for r in rows)
    n_true = sum(r["n_true"] for r in rows)
    n_found = sum(r["n_found"] for r in rows)
    precision = tp / n_found if n_found else 0.0
    recall = tp / n_true if n_true else 0.0
    return {
        "worms": len(rows),
        "neurons": n_true / len(rows),
        "precision": precision,
        "recall": recall,
        "f1": 2 * precision * recall / (precision + recall) if precision + recall else 0.0,
        "error": float(np.nanmedian([r["median_error_um"] for r in rows])),  # a worm with no match has none
        "seconds": float(np.mean([r["seconds"] for r in rows])),
        "rho": float(np.nanmean([r["rho"] for r in rows])),
    }


def time_big_volume(voxel, diameter: float, repeats: int = 3) -> tuple[float, tuple]:
    """Median seconds to segment a 4 x 30 x 512 x 512 stack (the speed target)."""
    from napari_fdlc.render import random_worm

    worm = random_worm(180, size_um=(110, 30, 22), min_spacing_um=2.4, seed=0)
    stack, _ = render_stack(worm, seed=0, shape_zyx=(30, 512, 512), voxel_size_zyx=voxel)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        segment_stack(stack, diameter_um=diameter)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), tuple(stack.data.shape)


def padding_rows(diameter: float) -> list[str]:
    """The bundled sample as it is, padded with zeros (a 60-voxel margin in x, 4 blank planes in
    z: a stack registered or cropped by another tool), and background-subtracted (each channel
    less its 50th / 80th / 95th percentile, clipped at 0): detections and their score."""
    from napari_fdlc.io.images import Stack
    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    data = np.asarray(stack.data)
    vx = stack.voxel_size_zyx[2]
    variants = [("as bundled", data, 0.0),
                ("60 voxels of zeros before x", np.pad(data, ((0, 0), (0, 0), (0, 0), (60, 0))), 60 * vx),
                ("4 blank planes after z", np.pad(data, ((0, 0), (0, 4), (0, 0), (0, 0))), 0.0)]
    for q in (50, 80, 95):
        level = np.percentile(data, q, axis=(1, 2, 3), keepdims=True)
        variants.append((f"less its {q}th percentile, clipped at 0",
                         np.clip(data.astype(np.int32) - level, 0, None).astype(np.uint16), 0.0))
    rows = []
    for name, pixels, shift in variants:
        found = segment_stack(Stack(pixels, stack.voxel_size_zyx, stack.channel_roles), diameter_um=diameter)
        s = score_detections(truth.xyz + [shift, 0, 0], found.xyz, max_distance_um=diameter / 2)
        rows.append(f"| {name} | {len(found)} | {s['precision']:.3f} | {s['recall']:.3f} | {s['median_error_um']:.2f} |")
    return rows


def figure(path: Path, diameter: float) -> None:
    """MIP of the bundled sample: RGB composite and W, with true and detected centres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from napari_fdlc.sample import load_sample

    stack, truth = load_sample()
    found = segment_stack(stack, diameter_um=diameter)
    s = score_detections(truth.xyz, found.xyz, max_distance_um=diameter / 2)
    vz, vy, vx = stack.voxel_size_zyx
    mip = {c: stack.channel(c).max(axis=0).astype(float) for c in "RGBW"}

    def norm(a):
        lo, hi = np.percentile(a, [50, 99.7])
        return np.clip((a - lo) / (hi - lo), 0, 1) ** 0.7

    rgb = np.stack([norm(mip[c]) for c in "RGB"], axis=-1)
    extent = (-vx / 2, (mip["W"].shape[1] - 0.5) * vx, (mip["W"].shape[0] - 0.5) * vy, -vy / 2)
    fig, axes = plt.subplots(2, 1, figsize=(11, 6.2), constrained_layout=True)
    axes[0].imshow(rgb, extent=extent)
    axes[0].set_title("bundled sample: max projection of R, G, B (mNeptune2.5, CyOFP1.5, mTagBFP2)")
    axes[1].imshow(norm(mip["W"]), cmap="gray", extent=extent)
    matched = np.zeros(len(found), bool)
    matched[s["pairs"][:, 1]] = True
    missed = np.ones(len(truth), bool)
    missed[s["pairs"][:, 0]] = False
    axes[1].scatter(found.xyz[matched, 0], found.xyz[matched, 1], s=28, facecolors="none", edgecolors="lime",
                    linewidths=0.9, label=f"detected, correct ({matched.sum()})")
    axes[1].scatter(found.xyz[~matched, 0], found.xyz[~matched, 1], s=40, marker="x", c="red",
                    label=f"detected, spurious ({(~matched).sum()})")
    axes[1].scatter(truth.xyz[missed, 0], truth.xyz[missed, 1], s=40, marker="+", c="orange",
                    label=f"missed ({missed.sum()})")
    axes[1].set_title(
        f"W (TagRFP-T) max projection with detections: F1 {s['f1']:.3f}, median centre error "
        f"{s['median_error_um']:.2f} µm"
    )
    axes[1].legend(loc="lower right", fontsize=8, framealpha=0.8)
    for ax in axes:
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"figure: {path}", file=sys.stderr)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--corpus", type=Path, default=DEFAULT_CORPUS, help="NeuroPAL corpus folder (read in place)")
    parser.add_argument("--worms-per-lab", type=int, default=1)
    parser.add_argument("--voxel-size", nargs=3, type=float, default=(1.0, 0.25, 0.25), metavar=("Z", "Y", "X"))
    parser.add_argument("--diameter-um", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-timing", action="store_true", help="skip the 4 x 30 x 512 x 512 timing")
    parser.add_argument("--figure", type=Path, help="also draw the sample with detections to this PNG")
    parser.add_argument("--padding", action="store_true",
                        help="only the bundled sample padded with zeros and background-subtracted")
    args = parser.parse_args(argv)
    if args.padding:
        print("| the bundled sample | nuclei found (true: 151) | precision | recall | median centre error (µm) |")
        print("|---|---|---|---|---|")
        print("\n".join(padding_rows(args.diameter_um)))
        return 0

    worms = load_worms(args.corpus, args.worms_per_lab)
    voxel = tuple(args.voxel_size)
    print(f"{len(worms)} worms ({', '.join(n for n, _ in worms)}); voxel {voxel} µm (z, y, x); "
          f"nucleus diameter {args.diameter_um} µm, match within {args.diameter_um / 2} µm\n")
    print("| noise (W photons) | density | worms | neurons/worm | precision | recall | F1 | median centre error (µm) | colour ρ | s/volume |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for noise_name, photons in NOISE.items():
        for density_name, (keep, scale) in DENSITY.items():
            r = run_condition(worms, photons, keep, scale, voxel, args.diameter_um, args.seed)
            print(f"| {noise_name} ({photons:g}) | {density_name} | {r['worms']} | {r['neurons']:.0f} | "
                  f"{r['precision']:.3f} | {r['recall']:.3f} | {r['f1']:.3f} | {r['error']:.2f} | "
                  f"{r['rho']:.2f} | {r['seconds']:.2f} |", flush=True)
    if not args.no_timing:
        seconds, shape = time_big_volume(voxel, args.diameter_um)
        print(f"\nsegment_stack on a {' x '.join(map(str, shape))} uint16 stack: {seconds:.2f} s (median of 3)")
    if args.figure:
        figure(args.figure, args.diameter_um)
    return 0


if __name__ == "__main__":
    sys.exit(main())
