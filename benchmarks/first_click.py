"""The first click of a widget, as a user meets it: a fresh napari process, the widget docked, a
few seconds to pick the inputs, then the job, then a second click.

    xvfb-run -a python benchmarks/first_click.py [--widget auto-label|track] [--runs 3] [--pick-seconds 3]

``auto-label``: the bundled sample open, Auto-label (segmentation, naming with the built-in
panel, the result in its layer). ``track``: the Track widget on a generated recording of 200
volumes (``track.simulate_sequence``, written as one CSV), its tracks and points layers.
Each run is a new Python process (torch not yet imported, as in a new napari session), with the
widget's warm-up (``_warm_up``: the model(s) loaded and run once in a thread while the user
picks the inputs) on and off, alternately. Prints a markdown table of the medians.
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
import json, sys, tempfile, time
sys.path.insert(0, {src!r})
import napari
from qtpy.QtWidgets import QApplication
from napari_fdlc._napari import _widget, tracks
widget_class = tracks.TrackWidget if {track} else _widget.AutoLabelWidget
if not {warm}:
    widget_class._warm_up = lambda self: None
viewer = napari.Viewer(show=False)
if {track}:
    import pandas as pd
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.table import write_table
    from napari_fdlc.track import SequenceParams, simulate_sequence
    volumes, _ = simulate_sequence(generate_worm(seed=2), 0, SequenceParams(frames=200))
    frames = [v.to_dataframe().drop(columns=["label"]).assign(t=t) for t, v in enumerate(volumes)]
    path = tempfile.mkdtemp() + "/recording.csv"
    write_table(pd.concat(frames, ignore_index=True), path)
    widget = widget_class(viewer)
    widget.set_sequence(path)
    job, count = widget.run, lambda out: sum(len(v) for v in volumes)
else:
    viewer.open_sample("napari-fdlc", "neuropal")
    widget = widget_class(viewer)
    job, count = widget.auto_label, lambda out: len(out.data)
start = time.perf_counter()
while time.perf_counter() - start < {pick}:  # the user picks the inputs; napari's events run
    QApplication.processEvents()
    time.sleep(0.01)
times = []
for _ in range(2):
    t0 = time.perf_counter()
    out = job()
    times.append(time.perf_counter() - t0)
    assert out is not None, widget.last_error
print(json.dumps({{"first": times[0], "second": times[1], "neurons": count(out)}}))
viewer.close()
"""


def run_once(warm: bool, pick: float, track: bool) -> dict:
    code = ONE_RUN.format(src=str(SRC), warm=warm, pick=pick, track=track)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widget", choices=("auto-label", "track"), default="auto-label")
    ap.add_argument("--runs", type=int, default=3, help="fresh processes per setting (median)")
    ap.add_argument("--pick-seconds", type=float, default=3.0, help="time between docking the widget and the click")
    args = ap.parse_args(argv)
    results: dict[bool, list[dict]] = {True: [], False: []}
    for _ in range(args.runs):
        for warm in (False, True):
            results[warm].append(run_once(warm, args.pick_seconds, args.widget == "track"))
            print(f"  warm-up {'on' if warm else 'off'}: {results[warm][-1]}", file=sys.stderr, flush=True)
    what = ("Track on a generated recording of 200 volumes" if args.widget == "track"
            else "Auto-label on the bundled sample")
    print(f"{what} ({results[True][0]['neurons']} neurons), {args.pick_seconds:g} s after the widget is docked; "
          f"median of {args.runs} fresh processes:\n")
    print("| widget warm-up | first click, s | second click, s |")
    print("|---|---|---|")
    for warm in (False, True):
        first = statistics.median(r["first"] for r in results[warm])
        second = statistics.median(r["second"] for r in results[warm])
        print(f"| {'on (what ships)' if warm else 'off'} | {first:.2f} | {second:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
