"""Speed: per-volume latency, batched throughput and memory of fdlc, beside CPD, in one run.

    python benchmarks/speed.py [--weights PATH] [--threads 2] [--repeats 30] [--batch 64]

Latency is the median wall time for one test volume (~130 neurons) from tables in memory to the
one-to-one assignment and the top-3 candidates done, model loaded and warm. "Batched" is
volumes per second when many volumes are given at once. Configurations:

* full, 1 template: registration onto the template (``register.py``, both chiralities), the
  model on the candidate placements, chirality choice, colour, then the atlas's own answer (one
  registration of the test onto the shipped atlas) multiplied in: what ``fdlc label --template
  T`` does, i.e. the configuration of the accuracy figures;
* full, 1 template, its own worm: the same with a simulated copy of the template as the test
  (another volume of the same worm): the warp leaves it close to the template, so the model
  looks again after it and the atlas's answer is not asked (model_card.md);
* full, panel: the built-in reference panel, what Auto-label does: the test placed in the atlas
  frame (registration, both chiralities), 5 templates × 2 chiralities through the model to
  choose the handedness, the other 5 templates in the chosen one (15 passes);
  "handedness set": the same with ``--chirality same`` (one chirality, 10 passes);
* track: ``fdlc track`` defaults (full search with the identification model, as above, on the
  first volume only; every later volume placed by the warp of the one before, one pass of the
  small tracking model, assignment) on a recording of ``--frames`` volumes; latency = one volume
  at a time (chunk 1, what a live recording needs), batched = chunk 16; the first volume's
  search is included in the average; "full model follows" = ``--follow-with full`` (the
  identification model on every volume, as before session 8);
* fast mode: ``fdlc track --method geometry``, the warp chain alone (no model; accuracy in
  docs/tracking.md), one volume after the other, so latency and throughput are the same thing;
* CPD, identification: ``baselines.cpd_match`` (every orientation of ``geometry.ORIENTATIONS``,
  as the orientation of a new worm is unknown) + the same assignment and candidates;
* CPD, tracking: ``fdlc track --method cpd`` on the same sequence, one volume at a time: the
  first volume searched in every orientation, each later one a single pycpd registration from
  the volume before (what "a library CPD takes ~30 ms per pair" measures).

Two ratio columns: every row against each CPD row, so that identification can be read against
CPD with its orientation search and tracking against CPD's single registration.

Peak memory: Python/numpy allocations (tracemalloc) during one run of each configuration, and
the process's peak resident size at the end (``ru_maxrss``; includes torch itself). With CUDA,
the fdlc rows are repeated on the GPU. Then the Auto-label click on the bundled sample
(segmentation, then naming with the panel). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

import numpy as np  # noqa: E402


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    """(median wall ms, median CPU ms of this process) over ``repeats`` calls after one warm-up."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        walls.append((time.perf_counter() - t0) * 1e3)
        cpus.append((time.process_time() - c0) * 1e3)
    return statistics.median(walls), statistics.median(cpus)


def _rate(fn, volumes: int) -> float:
    fn()
    t0 = time.perf_counter()
    fn()
    return volumes / (time.perf_counter() - t0)


def _times(ratio: float) -> str:
    return f"{ratio:.0f}×" if ratio >= 10 else f"{ratio:.1f}×"


def _peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default=None, help="model path without suffix (default: the shipped model)")
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    ap.add_argument("--repeats", type=int, default=30, help="latency runs per configuration (median)")
    ap.add_argument("--batch", type=int, default=64, help="volumes for the batched identification figures")
    ap.add_argument("--frames", type=int, default=200, help="volumes of the tracked recording (the first one's search is included)")
    ap.add_argument("--cpd-repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if min(args.repeats, args.batch, args.cpd_repeats) < 1:
        ap.error("--repeats, --batch and --cpd-repeats must be at least 1")
    load = os.getloadavg()  # before the run: what other jobs put on the machine, not this one's own

    import torch

    torch.set_num_threads(args.threads)
    from napari_fdlc.baselines import cpd_match
    from napari_fdlc.geometry import ORIENTATIONS
    from napari_fdlc.identify import Identifier
    from napari_fdlc.match import make_labelling, name_probabilities
    from napari_fdlc.reference import generate_worm, load_panel
    from napari_fdlc.simulate import simulate_worm
    from napari_fdlc.track import SequenceParams, TrackSettings, simulate_sequence, track

    weights = args.weights  # None: the shipped model
    template = generate_worm(seed=1)
    source = generate_worm(seed=2)
    rng = np.random.default_rng(args.seed)
    tests = [simulate_worm(source, rng).table for _ in range(args.batch)]
    test = min(tests, key=lambda t: abs(len(t) - 130))
    # The template's own worm, simulated (as the synthetic pairs of accuracy.md): the second look
    # after a warp, no atlas opinion.
    copies = [simulate_worm(template, rng).table for _ in range(args.batch)]
    copy = min(copies, key=lambda t: abs(len(t) - 130))
    panel = load_panel()
    sequence, _ = simulate_sequence(source, args.seed, SequenceParams(frames=args.frames))

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows: dict[str, dict] = {}

    def cpd_one():
        probs = cpd_match(template, test)
        names, p = name_probabilities([(probs[:, :-1], template.labels)])
        make_labelling(names, p).candidates(3)

    for device in devices:
        ident = Identifier.load(weights, device=device)
        told = ident.with_chirality("same")  # one placement instead of two
        reps = args.repeats
        configs = {
            "fdlc full, 1 template (+ the atlas's answer)": (
                lambda: ident.label(test, [template], atlas=panel.atlas).candidates(3),
                lambda: [lab.candidates(3) for lab in ident.label_many(tests, [template], atlas=panel.atlas)],
                len(tests),
            ),
            "fdlc full, 1 template, its own worm (second look after a warp)": (
                lambda: ident.label(copy, [template], atlas=panel.atlas).candidates(3),
                lambda: [lab.candidates(3) for lab in ident.label_many(copies, [template], atlas=panel.atlas)],
                len(copies),
            ),
            f"fdlc full, panel ({len(panel.templates)} templates)": (
                lambda: ident.label_panel(test, panel).candidates(3),
                lambda: [ident.label_panel(t, panel).candidates(3) for t in tests[:16]],
                len(tests[:16]),
            ),
            "fdlc panel, handedness set (--chirality same)": (
                lambda: told.label_panel(test, panel).candidates(3),
                lambda: [told.label_panel(t, panel).candidates(3) for t in tests[:16]],
                len(tests[:16]),
            ),
            "fdlc track (propagated, chunk 1 / 16)": (
                lambda: track(sequence, identifier=ident, settings=TrackSettings(chunk=1)),
                lambda: track(sequence, identifier=ident, settings=TrackSettings(chunk=16)),
                len(sequence),
            ),
            "fdlc track, full model follows (--follow-with full)": (
                lambda: track(sequence, identifier=ident, settings=TrackSettings(chunk=1, follow_with="full")),
                lambda: track(sequence, identifier=ident, settings=TrackSettings(chunk=16, follow_with="full")),
                len(sequence),
            ),
            "fast mode: track --method geometry (no model)": (
                lambda: track(sequence, method="geometry"),
                lambda: track(sequence, method="geometry"),
                len(sequence),
            ),
        }
        if device == "cpu":
            # What is not the network: the same pipeline with an untrained 1-layer, dim-16 model
            # in its place (registrations, the atlas's answer, assignment, probabilities). A
            # smaller trained model could only save the difference to the rows above.
            from napari_fdlc.model import CorrespondenceModel

            torch.manual_seed(args.seed)
            tiny = Identifier(CorrespondenceModel({**ident.model.config, "dim": 16, "heads": 2, "layers": 1}).eval(),
                              ident.settings, device)
            configs["everything but the network, 1 template (a 1-layer dim-16 model in its place)"] = (
                lambda: tiny.label(test, [template], atlas=panel.atlas).candidates(3),
                lambda: [lab.candidates(3) for lab in tiny.label_many(tests, [template], atlas=panel.atlas)],
                len(tests),
            )
            configs[f"everything but the network, panel ({len(panel.templates)} templates)"] = (
                lambda: tiny.label_panel(test, panel).candidates(3),
                lambda: [tiny.label_panel(t, panel).candidates(3) for t in tests[:16]],
                len(tests[:16]),
            )
        for name, (one, many, count) in configs.items():
            row = rows.setdefault(name, {})
            if "track" in name:
                # latency per volume of a streamed sequence (one volume at a time)
                wall, cpu = _median_ms(one, max(1, reps // 10))
                wall, cpu = wall / len(sequence), cpu / len(sequence)
            else:
                wall, cpu = _median_ms(one, reps if "panel" not in name else max(3, reps // 5))
            row[f"{device}_ms"], row[f"{device}_cpu_ms"] = wall, cpu
            row[f"{device}_rate"] = _rate(many, count)
            if device == "cpu":
                row["peak_mb"] = _peak_mb(one)
            print(f"  {device} {name}: {wall:.1f} ms/volume, {row[f'{device}_rate']:.0f} volumes/s", file=sys.stderr, flush=True)
    # The Auto-label click on the bundled sample: segmentation, then naming with the panel (what
    # the widget runs in its worker); the target is on the naming part.
    from napari_fdlc.identify import label_neurons
    from napari_fdlc.sample import load_sample
    from napari_fdlc.segment import segment_stack

    stack, _ = load_sample()
    t0 = time.perf_counter()
    found = segment_stack(stack)
    segment_ms = (time.perf_counter() - t0) * 1e3
    ident = Identifier.load(weights)
    sample_ms, _ = _median_ms(lambda: label_neurons(found, identifier=ident).candidates(3), 5)
    print(f"  Auto-label on the sample: segmentation {segment_ms:.0f} ms, naming {sample_ms:.0f} ms", file=sys.stderr, flush=True)

    wall, cpu = _median_ms(cpd_one, args.cpd_repeats)
    cpd_name = f"CPD identification (pycpd, {len(ORIENTATIONS)} orientations)"
    rows[cpd_name] = {"cpu_ms": wall, "cpu_cpu_ms": cpu, "cpu_rate": 1000.0 / wall, "peak_mb": _peak_mb(cpd_one)}
    print(f"  cpu CPD: {wall:.1f} ms/volume", file=sys.stderr, flush=True)

    def cpd_track():
        track(sequence, method="cpd")

    wall, cpu = _median_ms(cpd_track, max(1, args.cpd_repeats // 2))
    wall, cpu = wall / len(sequence), cpu / len(sequence)
    cpd_track_name = "CPD tracking (pycpd, one registration per volume from the one before)"
    rows[cpd_track_name] = {"cpu_ms": wall, "cpu_cpu_ms": cpu, "cpu_rate": 1000.0 / wall, "peak_mb": _peak_mb(cpd_track)}
    print(f"  cpu CPD tracking: {wall:.1f} ms/volume", file=sys.stderr, flush=True)

    cpd_ms, cpd_track_ms = rows[cpd_name]["cpu_ms"], rows[cpd_track_name]["cpu_ms"]
    print(f"# speed: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, torch {torch.__version__}, "
          f"{args.threads} torch thread(s), numpy's BLAS on one thread within each call (napari_fdlc/_blas.py); weights {weights or 'shipped'}")
    print(f"test volume: {len(test)} neurons; template {len(template)} neurons; panel {len(panel.templates)} templates; "
          f"batched over {args.batch} volumes (panel: 16); tracking: a recording of {len(sequence)} volumes; "
          f"load average before the run {load[0]:.1f}")
    print()
    head = ("| configuration | latency, ms/volume (CPU ms) | batched, volumes/s | CPD identification ÷ latency "
            "| CPD tracking ÷ latency | peak Python memory, MB |")
    sep = "|---|---|---|---|---|---|"
    if "cuda" in devices:
        head += " GPU latency, ms | GPU batched, volumes/s |"
        sep += "---|---|"
    print(head)
    print(sep)
    for name, r in rows.items():
        ratios = " | ".join(_times(ms / r["cpu_ms"]) for ms in (cpd_ms, cpd_track_ms))
        line = f"| {name} | {r['cpu_ms']:.1f} ({r['cpu_cpu_ms']:.1f}) | {r['cpu_rate']:.0f} | {ratios} | {r['peak_mb']:.1f} |"
        if "cuda" in devices:
            line += f" {r['cuda_ms']:.1f} | {r['cuda_rate']:.0f} |" if "cuda_ms" in r else " – | – |"
        print(line)
    print()
    print(f"Auto-label on the bundled sample ({len(found)} neurons found): segmentation {segment_ms:.0f} ms, "
          f"then naming with the panel {sample_ms:.0f} ms (median of 5)")
    print(f"process peak resident memory: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB (torch included)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
