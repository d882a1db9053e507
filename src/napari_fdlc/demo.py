"""``make demo``: the main job on the bundled sample, then napari.

1. Load the bundled NeuroPAL-like stack (rendered from a worm the project generates from its
   atlas), segment the nuclei, name them with the shipped model and the built-in reference panel,
   and print a short table next to the truth.
2. Open napari with the sample and the Auto-label widget. Without a display, run the same flow
   under Xvfb and write ``demo_output/labels.csv`` and ``demo_output/screenshot.png``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from .errors import FdlcError, one_line

OUT_DIR = Path("demo_output")


def identify_sample(show: int = 15) -> float:
    from .identify import label_neurons
    from .sample import load_sample
    from .segment import segment_stack

    stack, truth = load_sample()
    start = time.perf_counter()
    found = segment_stack(stack)
    seg_s = time.perf_counter() - start
    start = time.perf_counter()
    result = label_neurons(found)
    label_s = time.perf_counter() - start
    # Which true neuron each detection is (within 1.5 µm), to score the names given.
    d = cdist(found.xyz, truth.xyz)
    rows, cols = linear_sum_assignment(d)
    truth_name = np.full(len(found), "", dtype=object)
    ok = d[rows, cols] < 1.5
    truth_name[rows[ok]] = truth.labels[cols[ok]]
    cand, cand_p = result.candidates(3)
    print(f"Sample stack {stack.data.shape} (CZYX), voxel {stack.voxel_size_zyx} µm")
    print(f"Segmented {len(found)} nuclei ({len(truth)} in the truth) in {seg_s:.2f} s; "
          f"named them in {label_s:.2f} s with the built-in reference panel.\n")
    print(f"{'#':>3}  {'x_um':>6} {'y_um':>6} {'z_um':>5}  {'auto_id':8} {'conf':>5}  {'top-3 candidates':34} truth")
    order = np.argsort(found.xyz[:, 0])
    for j in order[:: max(1, len(order) // show)][:show]:
        c = ", ".join(f"{n} {p:.2f}" for n, p in zip(cand[j], cand_p[j]) if n)
        mark = "✓" if result.auto_id[j] and result.auto_id[j] == truth_name[j] else " "
        print(f"{j:3d}  {found.xyz[j, 0]:6.1f} {found.xyz[j, 1]:6.1f} {found.xyz[j, 2]:5.1f}  "
              f"{result.auto_id[j] or '-':8} {result.auto_conf[j]:5.2f}  {c:34} {truth_name[j] or '-'} {mark}")
    scored = [j for j in range(len(found)) if truth_name[j] and truth_name[j] in result.names]
    accuracy = float(np.mean([result.auto_id[j] == truth_name[j] for j in scored])) if scored else float("nan")
    print(f"\nTop-1 on this sample: {100 * accuracy:.1f} % of {len(scored)} named, detected neurons.")
    return accuracy


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    usage = "usage: python -m napari_fdlc.demo [--headless]  (make demo: the sample labelled, then napari)"
    if any(a in ("-h", "--help") for a in argv):
        print(usage)
        return 0
    unknown = [a for a in argv if a != "--headless"]
    if unknown:  # (it ran the whole demo, --help included)
        print(f"{usage}\nfdlc: error: unknown argument {unknown[0]!r}", file=sys.stderr)
        return 2
    headless = "--headless" in argv
    try:
        if not headless:
            identify_sample()
        if os.environ.get("FDLC_NO_GUI"):
            return 0
        # (a macOS or Windows desktop has no DISPLAY variable: napari opens there all the same)
        has_display = not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        if headless or has_display:
            try:
                from ._napari.demo_flow import run_demo
            except ImportError as exc:  # the core installed without the [napari] extra
                missing = exc.name.split(".")[0] if exc.name else exc
                raise FdlcError(f"the napari part of the demo needs napari and Qt ({missing} is missing): "
                                "pip install 'napari-fdlc[napari]'") from None
            paths = run_demo(OUT_DIR, headless=headless)
            if paths:
                print(f"\nWrote {paths[0]} and {paths[1]}")
            return 0
        if shutil.which("xvfb-run"):
            print("\nNo display: running the napari flow under Xvfb...")
            cmd = ["xvfb-run", "-a", "-s", "-screen 0 1600x1000x24", sys.executable, "-m", "napari_fdlc.demo", "--headless"]
            return subprocess.call(cmd)
        print("\nNo display and no Xvfb: skipped the napari part (install xvfb or run with a display).")
        return 0
    except FdlcError as exc:
        print(f"fdlc: error: {one_line(exc)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
