"""The first Auto-label click on the bundled sample, as a user meets it: a fresh napari process,
the sample open, the widget docked, a few seconds to pick the channels, then Auto-label
(segmentation, naming with the built-in panel, the result in its layer), then a second click.

    xvfb-run -a python benchmarks/first_click.py [--runs 3] [--pick-seconds 3]

Each run is a new Python process (torch not yet imported, as in a new napari session), with the
widget's warm-up (``AutoLabelWidget._warm_up``: the model loaded and run once in a thread while
the user picks the channels) on and off, alternately. Prints a markdown table of the medians.
Needs a display (napari draws with OpenGL): run it under ``xvfb-run`` on a headless machine.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

ONE_RUN = r"""
import json, sys, time
sys.path.insert(0, {src!r})
import napari
from qtpy.QtWidgets import QApplication
from napari_fdlc._napari import _widget
if not {warm}:
    _widget.AutoLabelWidget._warm_up = lambda self: None
viewer = napari.Viewer(show=False)
viewer.open_sample("napari-fdlc", "neuropal")
widget = _widget.AutoLabelWidget(viewer)
start = time.perf_counter()
while time.perf_counter() - start < {pick}:  # the user picks the channels; napari's events run
    QApplication.processEvents()
    time.sleep(0.01)
times = []
for _ in range(2):
    t0 = time.perf_counter()
    layer = widget.auto_label()
    times.append(time.perf_counter() - t0)
    assert layer is not None, widget.last_error
print(json.dumps({{"first": times[0], "second": times[1], "neurons": len(layer.data)}}))
viewer.close()
"""


def run_once(warm: bool, pick: float) -> dict:
    code = ONE_RUN.format(src=str(SRC), warm=warm, pick=pick)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="fresh processes per setting (median)")
    ap.add_argument("--pick-seconds", type=float, default=3.0, help="time between docking the widget and the click")
    args = ap.parse_args(argv)
    results: dict[bool, list[dict]] = {True: [], False: []}
    for _ in range(args.runs):
        for warm in (False, True):
            results[warm].append(run_once(warm, args.pick_seconds))
            print(f"  warm-up {'on' if warm else 'off'}: {results[warm][-1]}", file=sys.stderr, flush=True)
    print(f"Auto-label on the bundled sample ({results[True][0]['neurons']} neurons found), "
          f"{args.pick_seconds:g} s after the widget is docked; median of {args.runs} fresh processes:\n")
    print("| widget warm-up | first click, s | second click, s |")
    print("|---|---|---|")
    for warm in (False, True):
        first = statistics.median(r["first"] for r in results[warm])
        second = statistics.median(r["second"] for r in results[warm])
        print(f"| {'on (what ships)' if warm else 'off'} | {first:.2f} | {second:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
