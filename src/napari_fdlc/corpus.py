"""The annotated NeuroPAL corpus (public DANDI data), read in place.

The corpus is never copied into the package: training, evaluation and the reference panel read
it from a folder given on the command line (default: ``../shared/data/neuropal_corpus`` beside
the checkout, or ``$FDLC_CORPUS``).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import FdlcError
from .table import NeuronTable, read_volume

LABS = ("NP", "EY", "KK", "SF", "SK1")


@dataclass
class Worm:
    lab: str
    name: str
    table: NeuronTable


def default_corpus_path() -> Path | None:
    """``$FDLC_CORPUS`` when set (refused when it holds no worms.csv), else
    ``../shared/data/neuropal_corpus`` relative to the working directory or to the source
    checkout; None when neither exists."""
    if os.environ.get("FDLC_CORPUS"):  # asked for: that one or none (not another one found elsewhere)
        path = Path(os.environ["FDLC_CORPUS"])
        if not (path / "worms.csv").exists():
            raise FdlcError(f"FDLC_CORPUS={path}: no worms.csv there (set it to the corpus folder, or unset it)")
        return path
    candidates = [Path.cwd().parent / "shared/data/neuropal_corpus"]
    parents = Path(__file__).resolve().parents
    if len(parents) > 3:  # the source checkout's ../shared (installed at /opt/napari_fdlc: none)
        candidates.append(parents[3] / "shared/data/neuropal_corpus")
    for path in candidates:
        if (path / "worms.csv").exists():
            return path
    return None


def refuse_out_in_corpus(out: Path, corpus: str | os.PathLike | None, what: str) -> None:
    """Refuse an output file inside the corpus (``corpus`` as given, None: the default one):
    the corpus is read, never written; ``what`` names the output in the one-line error."""
    folder = Path(corpus) if corpus else default_corpus_path()
    if folder is not None and folder.resolve() in Path(out).resolve().parents:  # worms.csv or a worm's table
        raise FdlcError(f"{out}: inside the corpus folder {folder}, which is read, never written; write the {what} elsewhere")


def load_corpus(path: str | os.PathLike | None = None, labs: tuple[str, ...] | list[str] | None = None) -> list[Worm]:
    given = path
    path = Path(path) if path else default_corpus_path()
    if given and not (path / "worms.csv").exists():  # the folder named: said where it looked
        raise FdlcError(f"{path}: no worms.csv there; give --corpus the NeuroPAL corpus folder that holds it")
    if path is None or not (path / "worms.csv").exists():
        raise FdlcError(
            "NeuroPAL corpus not found: pass --corpus PATH (the folder with worms.csv) or set FDLC_CORPUS"
        )
    index_path = path / "worms.csv"
    try:
        # index_col=False: rows ending in a comma must not shift every column under the header
        # (pandas warns that the empty last field is dropped: it is meant)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", pd.errors.ParserWarning)
            index = pd.read_csv(index_path, dtype=str, keep_default_na=False, index_col=False, skip_blank_lines=False)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise FdlcError(f"{index_path}: not a readable CSV ({str(exc).splitlines()[0]})") from None
    index.columns = [str(c).strip() for c in index.columns]  # 'dataset, worm': spaces do not count
    # blank lines dropped here, not by pandas, so that a row's error names its line in the file
    lines = np.arange(len(index)) + 2
    filled = (index.fillna("").astype(str).apply(lambda column: column.str.strip()) != "").any(axis=1).to_numpy()
    index, lines = index[filled].reset_index(drop=True), lines[filled]
    missing = [c for c in ("dataset", "worm") if c not in index.columns]
    if missing:
        raise FdlcError(f"{index_path}: no column {' or '.join(repr(c) for c in missing)} (it lists the worms: dataset, worm)")
    if index.empty:
        raise FdlcError(f"{index_path}: lists no worm")
    index["dataset"], index["worm"] = index["dataset"].str.strip(), index["worm"].str.strip()
    labs = None if labs is None else [lab.strip() for lab in labs]  # as the corpus's own are read
    unknown = sorted(set(labs or ()) - set(index["dataset"]))
    if unknown:
        raise FdlcError(f"no worms of lab(s) {', '.join(unknown)} in the corpus (labs: {', '.join(sorted(set(index['dataset'])))})")
    blank = (index["dataset"] == "") | (index["worm"] == "")
    if blank.any():
        raise FdlcError(f"{index_path}, line {lines[int(blank.to_numpy().argmax())]}: a row without its dataset or worm; "
                        "fill it in or remove it")
    repeated = index.duplicated(["dataset", "worm"])
    if repeated.any():
        row = index[repeated].iloc[0]
        raise FdlcError(f"{index_path}: {row['dataset']}/{row['worm']} is listed more than once; remove the repeated row")
    worms = []
    for row in index.itertuples():
        if labs is not None and row.dataset not in labs:
            continue
        file = path / row.dataset / f"{row.worm}.csv"
        if not file.is_file():
            raise FdlcError(f"{file}: no such file, though {index_path} lists it; add the file or remove its row")
        worms.append(Worm(row.dataset, row.worm, read_volume(file, "one worm per corpus table: give each time point a file and a row in worms.csv")))
    return worms
