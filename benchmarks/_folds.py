"""What the leave-one-lab-out benchmarks share: a held-out lab as its fold model sees it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_fdlc.evaluate import mirrored_relative_to
from napari_fdlc.identify import Identifier
from napari_fdlc.reference import Panel, build_atlas, make_panel


def held_out_lab(worms, lab: str, runs: str | Path | None, max_worms: int | None = None) -> tuple[Panel, list, Identifier]:
    """For ``lab``: the built-in panel rebuilt without it, its worms' tables (the first
    ``max_worms``), and the fold model that never saw it (``<runs>/fold_<lab>/model``, from
    ``benchmarks/leave_one_lab_out.py``; ``runs`` None: the shipped model, which saw the lab)
    told the lab's majority handedness (by the worms' names), as a user sets ``--chirality``
    for the microscope."""
    panel = make_panel(build_atlas([w for w in worms if w.lab != lab]))
    tests = [w.table for w in worms if w.lab == lab]
    majority = np.mean([mirrored_relative_to(panel.atlas, t) for t in tests]) > 0.5  # of the lab, not of the first few
    tests = tests[:max_worms]
    identifier = Identifier.load(None if runs is None else Path(runs) / f"fold_{lab}" / "model").with_chirality("mirrored" if majority else "same")
    return panel, tests, identifier
