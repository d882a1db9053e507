"""``fdlc segment``: detect nuclei in a 3D stack and write a neuron table with their colours.

A recording (a file with a time axis) gives one table with a ``t`` column, every time point
segmented alike: what ``fdlc track`` reads (and ``fdlc track`` takes the recording itself too).
"""

from __future__ import annotations

import argparse
import sys
import time

from .errors import FdlcError, check_output

_LONG_VOXELS = 20_000_000  # above this, print progress lines (a few seconds of work)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("stack", metavar="STACK",
                        help="3D stack or a recording of them over time: TIFF, OME-TIFF, ImageJ TIFF, NWB or ND2")
    add_stack_arguments(parser)
    parser.add_argument("--out", required=True, help="output neuron table (CSV; with a t column for a recording)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


# The options of add_stack_arguments with their defaults: fdlc track says which of them a table
# sequence, which is not segmented, ignores.
STACK_DEFAULTS = {"--voxel-size": ("voxel_size", None), "--channels": ("channels", None), "--axes": ("axes", None),
                  "--diameter-um": ("diameter_um", 3.0), "--threshold": ("threshold", 6.0),
                  "--no-unmix": ("no_unmix", False), "--no-colour-split": ("no_colour_split", False)}


def add_stack_arguments(parser: argparse.ArgumentParser) -> None:
    """How to read a stack and find its nuclei (``fdlc segment``, and ``fdlc track`` on a recording)."""
    parser.add_argument(
        "--voxel-size", nargs=3, type=float, metavar=("Z", "Y", "X"),
        help="voxel size in µm (overrides the file; needed when the file does not say it)",
    )
    parser.add_argument(
        "--channels", nargs="+", metavar="ROLE",
        help="role of each channel in file order: R G B W GFP, or '-' to ignore one "
        "(default: from the channel names in the file)",
    )
    parser.add_argument("--axes", help="axes of a TIFF that does not record them, e.g. ZCYX or TZCYX")
    parser.add_argument("--diameter-um", type=float, default=STACK_DEFAULTS["--diameter-um"][1], help="typical nucleus diameter in µm (default 3)")
    parser.add_argument(
        "--threshold", type=float, default=STACK_DEFAULTS["--threshold"][1],
        help="minimum detection strength in noise SDs (default 6; lower finds dimmer nuclei)",
    )
    parser.add_argument(
        "--no-unmix", action="store_true",
        help="keep the W (TagRFP-T) bleed-through in R and G (for stacks already unmixed)",
    )
    parser.add_argument(
        "--no-colour-split", action="store_true",
        help="find nuclei on W alone (by default a touching nucleus that only R, G or B separates is added)",
    )


def stack_options_given(args: argparse.Namespace) -> list[str]:
    """The options of :func:`add_stack_arguments` given other than their defaults."""
    return [flag for flag, (name, default) in STACK_DEFAULTS.items() if getattr(args, name, default) != default]


def segment_recording(args: argparse.Namespace, path: str, prog: str, check=None) -> tuple[list[int], list, int]:
    """Read ``path`` as a recording (a single stack is a recording of one) and segment every
    time point with the options of :func:`add_stack_arguments`: the time points where nuclei
    were found (0-based), their neuron tables, and the recording's number of time points.
    Progress lines on stderr (unless ``args.quiet``) for a recording or a big stack.
    ``check(series)``, before any segmentation, may refuse what the recording cannot give."""
    from .io.images import read_series
    from .segment import check_detection_options, found_time_points, segment_series, segment_stack

    check_detection_options(args.diameter_um, args.threshold, names=("--diameter-um", "--threshold"))
    series = read_series(path, voxel_size=args.voxel_size, channels=args.channels, axes=args.axes)
    if args.channels and all(role in (None, "GFP") for role in series.channel_roles):
        # every channel said: '-' (not used) is not a channel of unknown role to fall back on
        raise FdlcError(f"--channels {' '.join(args.channels)}: no channel to find nuclei in (GFP is activity, not "
                        "nuclei); give the W (pan-neuronal) channel's role, or the colour channels'")
    check_detection_options(args.diameter_um, args.threshold, names=("--diameter-um", "--threshold"),
                            voxel_size_zyx=series.voxel_size_zyx)  # the file's, when not given
    if check is not None:
        check(series)
    z, y, x = series.shape_zyx
    start = time.monotonic()
    options = dict(diameter_um=args.diameter_um, threshold=args.threshold, unmix=not args.no_unmix,
                   colour_split=not args.no_colour_split)
    try:
        if len(series) == 1:
            def report(fraction: float, message: str) -> None:
                print(f"{prog}: {100 * fraction:3.0f}% {message} ({time.monotonic() - start:.1f} s)",
                      file=sys.stderr, flush=True)

            long = not args.quiet and series.n_channels * z * y * x > _LONG_VOXELS
            tables = [segment_stack(series.volume(0), progress=report if long else None, **options)]
        else:
            def volumes_done(done: int, total: int) -> None:
                if not args.quiet:
                    print(f"{prog}: segmented {done}/{total} time points ({time.monotonic() - start:.1f} s)",
                          file=sys.stderr, flush=True)

            tables = segment_series(series, progress=volumes_done, **options)
    except MemoryError:
        raise FdlcError(f"{path}: not enough memory to segment this stack") from None
    found = found_time_points(tables, path, "check --voxel-size and --diameter-um, or lower --threshold")
    return found, [tables[t] for t in found], len(series)


def run(args: argparse.Namespace) -> int:
    from .table import write_table
    from .track import join_by_time

    check_output(args.out, [args.stack], create_folder=True)
    times, tables, length = segment_recording(args, args.stack, "fdlc segment")
    write_table(tables[0] if length == 1 else join_by_time(tables, times), args.out)
    if not args.quiet:
        found = f"{len(tables[0])} nuclei" if length == 1 else \
            f"{sum(map(len, tables))} nuclei in {len(tables)} time points"
        print(f"fdlc segment: {found} -> {args.out}", file=sys.stderr)
    return 0
