"""The annotated NeuroPAL corpus (public DANDI data), read in place.

The corpus is never copied into the package: training, evaluation and the reference panel read
it from a folder given on the command line (default: ``../shared/data/neuropal_corpus`` beside
the checkout, or ``$FDLC_CORPUS``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from .errors import FdlcError
from .table import NeuronTable, read_table

LABS = ("NP", "EY", "KK", "SF", "SK1")


@dataclass
class Worm:
    lab: str
    name: str
    table: NeuronTable


def default_corpus_path() -> Path | None:
    """``$FDLC_CORPUS``, else ``../shared/data/neuropal_corpus`` relative to the working directory
    or to the source checkout; None when none exists."""
    candidates = []
    if os.environ.get("FDLC_CORPUS"):
        candidates.append(Path(os.environ["FDLC_CORPUS"]))
    candidates.append(Path.cwd().parent / "shared/data/neuropal_corpus")
    candidates.append(Path(__file__).resolve().parents[3] / "shared/data/neuropal_corpus")
    for path in candidates:
        if (path / "worms.csv").exists():
            return path
    return None


def load_corpus(path: str | os.PathLike | None = None, labs: tuple[str, ...] | list[str] | None = None) -> list[Worm]:
    path = Path(path) if path else default_corpus_path()
    if path is None or not (path / "worms.csv").exists():
        raise FdlcError(
            "NeuroPAL corpus not found: pass --corpus PATH (the folder with worms.csv) or set FDLC_CORPUS"
        )
    index_path = path / "worms.csv"
    try:
        index = pd.read_csv(index_path, dtype=str, keep_default_na=False)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise FdlcError(f"{index_path}: not a readable CSV ({str(exc).splitlines()[0]})") from None
    missing = [c for c in ("dataset", "worm") if c not in index.columns]
    if missing:
        raise FdlcError(f"{index_path}: no column {' or '.join(repr(c) for c in missing)} (it lists the worms: dataset, worm)")
    if index.empty:
        raise FdlcError(f"{index_path}: lists no worm")
    unknown = sorted(set(labs or ()) - set(index["dataset"]))
    if unknown:
        raise FdlcError(f"no worms of lab(s) {', '.join(unknown)} in the corpus (labs: {', '.join(sorted(set(index['dataset'])))})")
    worms = []
    for row in index.itertuples():
        if labs is not None and row.dataset not in labs:
            continue
        worms.append(Worm(row.dataset, row.worm, read_table(path / row.dataset / f"{row.worm}.csv")))
    return worms
