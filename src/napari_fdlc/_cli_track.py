"""give every neuron of a sequence of volumes its track ID (and name) over time.

Input: one neuron table with a ``t`` column (time point), a folder of neuron tables (one volume
each, natural name order), several tables (in the order given), or an image recording (a stack
file with a time axis: every time point is segmented as ``fdlc segment`` does, and the output
also gets the columns it measures, e.g. each neuron's GFP per time point). Track IDs are the row indices
of the first reference volume (default: the first time point); with a labelled reference each
track also gets the reference neuron's name. Output: one CSV, one row per neuron per time point:
``t, neuron_index, x_um, y_um, z_um, track_id, track_conf`` (+ ``name``, + ``file``);
``track_id`` is -1 for a neuron left untracked, ``track_conf`` the probability of the ID given
(or of "untracked").
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import time
from pathlib import Path

from .errors import FdlcError, check_output, warn
from .geometry import CHIRALITIES


class _InOrder(argparse.Action):
    """Appends like action="append", and records the option in ``references``: --reference and
    --reference-t in the order typed (the first reference gives the track IDs; files used to
    come first whatever the order)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), values])
        namespace.references = [*(getattr(namespace, "references", None) or []), (self.dest, values)]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="a CSV with a t column, a folder of CSVs, several CSVs (one volume each), "
                        "or an image recording (TIFF, OME-TIFF or ND2 with a time axis; segmented first)")
    parser.add_argument("--reference", action=_InOrder, default=[], metavar="R.csv",
                        help="reference volume of the same worm, labelled or not (repeatable); default: the first time point")
    parser.add_argument("--reference-t", action=_InOrder, default=[], metavar="T",
                        help="use the volume at time point T of the sequence as a reference (repeatable); "
                             "references count in the order given, the first one's rows being the track IDs")
    parser.add_argument("--search", choices=("propagate", "full"), default="propagate",
                        help="propagate (default): full search (registration) on the first volume only, then "
                        "each volume is placed from the one before; full: search every volume (slower)")
    parser.add_argument("--placement", choices=("geometry", "model"), default="geometry",
                        help="how a volume is placed from the one before (default geometry: cheap, lets volumes batch)")
    parser.add_argument("--refine-steps", type=int, default=0, help="extra model passes per volume (default 0)")
    parser.add_argument("--chunk", type=int, default=16, help="volumes per model batch (default 16)")
    parser.add_argument("--no-color", "--no-colour", dest="no_colour", action="store_true", help="positions only")
    parser.add_argument("--method", choices=("fdlc", "cpd", "geometry"), default="fdlc",
                        help="fdlc (default), cpd (classical baseline) or geometry (the warp chain alone, no model)")
    parser.add_argument("--weights", help="model weights (path without suffix); default: the shipped model")
    parser.add_argument("--follow-with", choices=("tracking", "full"), default="tracking",
                        help="model for the volumes placed from the one before: tracking (default; the small model "
                        "trained for it, 2-3 times as fast, speed.md) or full (the identification model)")
    parser.add_argument("--tracking-weights", help="tracking model weights (path without suffix); default: the shipped one")
    parser.add_argument("--chirality", choices=CHIRALITIES, default="auto",
                        help="handedness of the volumes relative to the reference(s), as for fdlc label")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads for the model (default: torch's)")
    parser.add_argument("--out", required=True, help="output CSV")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    from ._cli_segment import add_stack_arguments

    add_stack_arguments(parser.add_argument_group("an image recording as input (how fdlc segment reads it)"))


def run(args: argparse.Namespace) -> int:
    from .errors import model_files
    from .table import read_volume, warn_implausible_scales, write_table
    from .track import TrackSettings, read_sequence, track
    from .train import MAX_THREADS

    settings = TrackSettings(search=args.search, placement=args.placement, refine_steps=args.refine_steps,
                             chunk=args.chunk, use_colour=not args.no_colour, follow_with=args.follow_with)
    settings.check()
    # As fdlc segment; the models are read too, never written (the shipped ones too, by default).
    models = [f for w in (args.weights, args.tracking_weights) if w for f in model_files(w)]
    if args.method == "fdlc":
        from .identify import shipped_tracking_weights, shipped_weights

        models += [f for w, given in ((shipped_weights(), args.weights), (shipped_tracking_weights(), args.tracking_weights))
                   if not given for f in model_files(w)]
    out = check_output(args.out, [*args.inputs, *args.reference, *models], create_folder=True)
    if args.threads is not None and not 1 <= args.threads <= MAX_THREADS:  # (2**31 was a torch traceback)
        raise FdlcError(f"--threads must be from 1 to {MAX_THREADS} (got {args.threads})")
    model_options = [name for name, given in (("--weights", args.weights), ("--tracking-weights", args.tracking_weights),
                                              ("--chirality", args.chirality != "auto")) if given]
    ignored = []  # said once the input is found good: a refusal is one line, not a warning and an error
    if args.method != "fdlc" and model_options:
        ignored.append(f"{', '.join(model_options)}: for the fdlc method; ignored with --method {args.method}")
    elif args.tracking_weights and args.follow_with == "full":
        ignored.append("--tracking-weights: for --follow-with tracking; ignored with --follow-with full")
    # Validate every input before any model work (the references before a recording's segmentation).
    for raw in args.reference_t:
        _reference_time(raw)
    if args.method != "fdlc" and len(args.reference) + len(args.reference_t) > 1:
        raise FdlcError(f"--method {args.method} takes one reference")
    in_order = getattr(args, "references", None) or []
    from_file = {k: read_volume(r, "a reference is one volume: give one time point (or name it with --reference-t)")
                 for k, (kind, r) in enumerate(in_order) if kind == "reference"}

    def references_in(seq) -> list:
        return [from_file[k] if kind == "reference" else _volume_at(seq, raw) for k, (kind, raw) in enumerate(in_order)]

    recording = _image_recording(args.inputs)
    if recording is None:  # a table sequence is read before the models load
        from ._cli_segment import stack_options_given

        stack_options = stack_options_given(args)
        if stack_options:  # a table in pixels is not converted by --voxel-size: said, not silently dropped
            ignored.append(f"{', '.join(stack_options)}: for an image recording (segmented first); ignored with a "
                           "table sequence")
        seq = read_sequence(args.inputs)
        references = references_in(seq)
    for message in ignored:
        warn(message)
    # The models next: weights that cannot be read are refused before a recording's segmentation.
    identifier = follower = None
    if args.method == "fdlc":
        from .identify import Identifier, default_identifier

        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        identifier = (Identifier.load(args.weights, identifies=True) if args.weights else default_identifier()).with_chirality(args.chirality)
        if args.tracking_weights and args.follow_with == "tracking":
            follower = Identifier.load(args.tracking_weights)
    if recording is not None:
        from ._cli_segment import segment_recording
        from .track import Sequence

        def time_points_exist(series) -> None:
            for raw in args.reference_t:
                value = _reference_time(raw)
                if not (value.is_integer() and 0 <= value < len(series)):
                    raise FdlcError(f"--reference-t {raw}: the recording has time points 0 to {len(series) - 1}")

        times, volumes, _ = segment_recording(args, recording, "fdlc track", check=time_points_exist)
        seq = Sequence(volumes, times, [""] * len(volumes))
        for kind, raw in in_order:  # a frame of the recording, but left out: said so, not "no time point"
            if kind == "reference_t" and _reference_time(raw) not in times:
                raise FdlcError(f"--reference-t {raw}: no nucleus was found at that time point of the recording "
                                "(it is left out); choose another")
        references = references_in(seq)
    # a reference that is the first volume itself is warned of once
    warn_implausible_scales([seq.volumes[0], *(r for r in references if r is not seq.volumes[0])])
    start = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if not args.quiet and total > 1:
            rate = done / max(time.perf_counter() - start, 1e-9)
            print(f"fdlc track: {done}/{total} volumes ({rate:.0f}/s)", file=sys.stderr, flush=True)

    result = track(seq, references or None, identifier, settings, progress, method=args.method, follower=follower)
    import pandas as pd

    from .track import other_columns

    # with what the segmentation (or the table) measured, e.g. each neuron's GFP per time point
    write_table(pd.concat([result.frame(seq.volumes), other_columns(seq)], axis=1), out)
    return 0


def _image_recording(inputs: list[str]) -> str | None:
    """The input when it is one image file (a recording to segment first), else None."""
    from .io.images import is_image_file

    images = [p for p in inputs if Path(p).suffix.lower() != ".csv" and is_image_file(p)]
    if images and Path(images[0]).suffix.lower() == ".nwb":  # read, it tracked that one volume, silently
        raise FdlcError(f"{images[0]}: an NWB file holds NeuroPAL's one annotated volume, not a recording; fdlc "
                        f"track takes {_RECORDINGS}")
    if len(inputs) == 1 and images:
        return inputs[0]
    if images:  # else read as tables: "not a UTF-8 text CSV file", after a warning about tables
        raise FdlcError(f"{images[0]}: an image among {len(inputs)} inputs; fdlc track takes {_RECORDINGS}")
    return None


_RECORDINGS = "one recording file (TIFF, OME-TIFF or ND2 with a time axis), or the tables fdlc segment writes"


def _reference_time(raw: str) -> float:
    try:
        value = float(raw)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value):
        raise FdlcError(f"--reference-t {raw}: not a number")
    return value


def _volume_at(seq, raw: str):
    value = _reference_time(raw)
    if re.fullmatch(r"[+-]?\d+", raw.strip()):
        value = int(raw)  # exact: integer clocks (ns) pass 2**53, where floats merge neighbours
    for t, volume in zip(seq.times, seq.volumes):
        if t == value:
            return volume
    raise FdlcError(f"--reference-t {raw}: no time point {raw} in the sequence")
