"""``fdlc segment``: detect nuclei in a 3D stack and write a neuron table with their colours."""

from __future__ import annotations

import argparse
import sys
import time

from .errors import FdlcError

_LONG_VOXELS = 20_000_000  # above this, print progress lines (a few seconds of work)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("stack", metavar="STACK", help="3D stack: TIFF, OME-TIFF, ImageJ TIFF, NWB or ND2")
    parser.add_argument(
        "--voxel-size", nargs=3, type=float, metavar=("Z", "Y", "X"),
        help="voxel size in µm (overrides the file; needed when the file does not say it)",
    )
    parser.add_argument(
        "--channels", nargs="+", metavar="ROLE",
        help="role of each channel in file order: R G B W GFP, or '-' to ignore one "
        "(default: from the channel names in the file)",
    )
    parser.add_argument("--axes", help="axes of a TIFF that does not record them, e.g. ZCYX")
    parser.add_argument("--diameter-um", type=float, default=3.0, help="typical nucleus diameter in µm (default 3)")
    parser.add_argument(
        "--threshold", type=float, default=6.0,
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
    parser.add_argument("--out", required=True, help="output neuron table (CSV)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def run(args: argparse.Namespace) -> int:
    from .io.images import read_stack
    from .segment import segment_stack
    from .table import write_table

    try:
        if not (args.diameter_um > 0):
            raise FdlcError(f"--diameter-um must be a positive number of µm (got {args.diameter_um})")
        stack = read_stack(args.stack, voxel_size=args.voxel_size, channels=args.channels, axes=args.axes)
        voxels = stack.n_channels * int(stack.shape_zyx[0]) * int(stack.shape_zyx[1]) * int(stack.shape_zyx[2])
        progress = None
        if not args.quiet and voxels > _LONG_VOXELS:
            start = time.monotonic()

            def progress(fraction: float, message: str) -> None:
                print(f"fdlc segment: {100 * fraction:3.0f}% {message} ({time.monotonic() - start:.1f} s)",
                      file=sys.stderr, flush=True)

        table = segment_stack(stack, diameter_um=args.diameter_um, threshold=args.threshold, progress=progress,
                              unmix=not args.no_unmix, colour_split=not args.no_colour_split)
        if len(table) == 0:
            raise FdlcError(
                f"{args.stack}: no nuclei found; check --voxel-size and --diameter-um, or lower --threshold"
            )
        write_table(table, args.out)
    except FdlcError as exc:
        print(f"fdlc: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"fdlc: error: {args.stack}: not enough memory to segment this stack", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"fdlc segment: {len(table)} nuclei -> {args.out}", file=sys.stderr)
    return 0
