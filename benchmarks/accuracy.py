"""Accuracy, calibration and coverage on the annotated corpus; writes docs/accuracy.md.

Protocols per lab: "pairs" (each worm the template for others of its lab; fdlc position-only
and with colour, the non-learned floor, CPD) and "panel" (the built-in reference panel rebuilt
from an atlas WITHOUT the lab being scored); held-out synthetic pairs; reliability plot and the
threshold's accuracy/coverage table.

    python benchmarks/accuracy.py [--pairs-per-lab 20] [--panel-worms-per-lab 40] [--no-cpd]

Same as `fdlc evaluate --out docs/accuracy.md`. The corpus is read in place (default ../shared/data/neuropal_corpus).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from napari_fdlc._cli_evaluate import add_arguments, run  # noqa: E402

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser, default_out="docs/accuracy.md")
    sys.exit(run(parser.parse_args()))
