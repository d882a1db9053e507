"""Neuron tables: one row per neuron, positions in µm, optional NeuroPAL colours and names.

The format is the public contract of ``../shared/docs/neuron_table.md`` (columns ``x_um, y_um, z_um``,
optional ``R, G, B, W``, optional ``label``; other columns kept). NeuroPAL_ID's "Save ID Info"
CSV is read and written too. Every problem is refused with one line naming the file, the line
and the column.
"""

from __future__ import annotations

import csv
import io
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import TableError, atomic_write, warn

COORDS = ("x_um", "y_um", "z_um")
COLOUR_CHANNELS = ("R", "G", "B", "W")
UNSURE_CONF = 0.5  # NeuroPAL_ID's confidence for a name written with a trailing '?'

# NeuroPAL_ID "Save ID Info" layout: 7 preamble lines, then this header.
NEUROPAL_ID_HEADER = [
    "User ID", "User Confidence", "Emphasized?", "Auto ID", "Auto Confidence", "",
    "Real X (um)", "Real Y (um)", "Real Z (um)", "",
    "Internal X (px)", "Internal Y (px)", "Internal Z (slice)", "",
    "Z-Scored Red", "Z-Scored Green", "Z-Scored Blue", "Z-Scored White", "",
    "Estimated GFP", "Max GFP", "Normalized GFP",
]
_NPID_PREAMBLE_LINES = 7
_NPID_TO_OURS = {
    "Real X (um)": "x_um", "Real Y (um)": "y_um", "Real Z (um)": "z_um",
    "Z-Scored Red": "R", "Z-Scored Green": "G", "Z-Scored Blue": "B", "Z-Scored White": "W",
}

# A position's voxel coordinates, as our exports and NeuroPAL_ID's write them beside µm
PIXEL_COLUMNS = ("x_px", "y_px", "z_px", "Internal X (px)", "Internal Y (px)", "Internal Z (slice)")


@dataclass
class NeuronTable:
    """Neurons of one worm (one volume).

    ``labels`` holds names without the ``?`` ('' = unnamed) and ``label_conf`` the annotator's
    confidence (1 named, 0.5 unsure, 0 unnamed). ``extra`` keeps every other input column, in
    input order, so that a table read and written back loses nothing. ``text`` (tables read from
    a file) is every input column as the text read. A colour without a reading (an empty cell,
    NaN) is the volume's median in ``colours``, so that one gap does not remove the channel for
    the whole worm; ``colour_gaps`` remembers it, and the table is written back with the cell
    empty (:meth:`colours_as_read`).
    """

    xyz: np.ndarray
    colours: dict[str, np.ndarray] = field(default_factory=dict)
    labels: np.ndarray | None = None
    label_conf: np.ndarray | None = None
    extra: pd.DataFrame | None = None
    source: str = "<memory>"
    text: pd.DataFrame | None = None
    colour_gaps: dict[str, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.xyz = positions(self.xyz)
        n = len(self.xyz)
        self.colours = {c: _per_neuron(v, n, f"colour {c}", np.float64) for c, v in self.colours.items()}
        self.colour_gaps = {}
        for c, v in self.colours.items():
            gaps = ~np.isfinite(v)
            if gaps.any() and not gaps.all():  # a channel read nowhere stays NaN: no reading at all
                self.colours[c] = np.where(gaps, np.median(v[~gaps]), v)
                self.colour_gaps[c] = gaps
        if self.labels is None:
            self.labels = np.full(n, "", dtype=object)
        # As a table's names are read: 'AVAL?' is AVAL, unsure
        parsed = [parse_name(s) for s in _per_neuron(self.labels, n, "labels", object)]
        self.labels = np.array([name for name, _ in parsed], dtype=object).reshape(n)
        if self.label_conf is None:
            self.label_conf = np.array([conf for _, conf in parsed])
        self.label_conf = _per_neuron(self.label_conf, n, "label confidences", np.float64)
        if self.extra is None:
            self.extra = pd.DataFrame(index=range(n))
        self.extra = self.extra.reset_index(drop=True)

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def named(self) -> np.ndarray:
        """Boolean mask of the neurons that carry a name."""
        return self.labels != ""

    @property
    def names(self) -> list[str]:
        return [s for s in self.labels if s]

    def colours_as_read(self) -> dict[str, np.ndarray]:
        """``colours`` with NaN where a neuron had no reading (what a table is written back with)."""
        return {c: np.where(self.colour_gaps[c], np.nan, v) if c in self.colour_gaps else v
                for c, v in self.colours.items()}

    def colour_matrix(self, channels: tuple[str, ...] | list[str]) -> np.ndarray:
        """(N, len(channels)) array of the requested colour channels."""
        return np.stack([self.colours[c] for c in channels], axis=1) if channels else np.zeros((len(self), 0))

    def subset(self, index) -> "NeuronTable":
        index = np.asarray(index)
        return NeuronTable(
            xyz=self.xyz[index],
            colours={c: v[index] for c, v in self.colours_as_read().items()},
            labels=self.labels[index],
            label_conf=self.label_conf[index],
            extra=self.extra.iloc[index].reset_index(drop=True),
            source=self.source,
            text=None if self.text is None else self.text.iloc[index].reset_index(drop=True),
        )

    def label_strings(self) -> list[str]:
        """Names as written in a table: 'AVAL', 'AVAL?' for unsure, '' for unnamed."""
        return [
            (s + "?" if c == UNSURE_CONF else s) if s else ""
            for s, c in zip(self.labels, self.label_conf)
        ]

    def to_dataframe(self) -> pd.DataFrame:
        df = pd.DataFrame({c: self.xyz[:, i] for i, c in enumerate(COORDS)})
        colours = self.colours_as_read()
        for c in COLOUR_CHANNELS:
            if c in colours:
                df[c] = colours[c]
        df["label"] = self.label_strings()
        for c in self.extra.columns:
            if c not in df.columns:
                df[c] = self.extra[c].to_numpy()
        return df


# A whole adult worm is about 1 mm long and a nucleus a few µm across: neurons spread over more
# than this, or packed into less than MIN_SPAN_UM, are not in micrometres.
MAX_SPAN_UM = 2000.0
MIN_SPAN_UM = 5.0
# A complete young adult's head: NP's tables name every head neuron (189-195), and there the
# median distance from a neuron to its second-nearest is 3.49-3.88 µm (napari_fdlc.register
# takes a denser table for a smaller worm). A random n of them lie further apart, about as
# (HEAD_NEURONS / n)^(1/3).
YOUNG_ADULT_SPACING_UM = 3.4
HEAD_NEURONS = 190
# A table whose neurons lie this many times further apart than that is not in µm (pixels, most
# likely): the corpus's 97 tables reach 1.5, random subsets of them 2.8 (15 neurons; 2.0 for
# 50, 1.5 for 160), while they give 4.0 or more in pixels of 0.25 µm (2.0-2.9 at twice their
# size: not told). Judged from SPREAD_MIN_NEURONS neurons.
TOO_SPREAD = 3.0
SPREAD_MIN_NEURONS = 15


def check_named(templates: list[NeuronTable]) -> None:
    """Refuse, naming it, a template without a named neuron: it has no name to give."""
    unnamed = [t for t in templates if not t.names]
    if unnamed:
        raise TableError(f"{unnamed[0].source or 'a template'}: no named neurons; a template needs names to give them")


def neuron_spacing(xyz: np.ndarray) -> float | None:
    """The median distance (µm) from a neuron to its second-nearest one (None under 3 neurons).
    The second, not the first: a nucleus split in two by a segmentation is one close pair."""
    if len(xyz) < 3:
        return None
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(xyz).query(xyz, k=3)[0][:, 2]))


def spread_factor(xyz: np.ndarray) -> float | None:
    """How many times further apart the neurons lie than in a young adult's head of as many
    neurons (:func:`neuron_spacing` against YOUNG_ADULT_SPACING_UM at HEAD_NEURONS); None under 3."""
    spacing = neuron_spacing(xyz)
    return spacing / _head_spacing(len(xyz)) if spacing else None


def _head_spacing(n: int) -> float:
    """The spacing (µm) of n neurons of a young adult's head (see HEAD_NEURONS)."""
    return YOUNG_ADULT_SPACING_UM * (HEAD_NEURONS / n) ** (1 / 3)


def implausible_scale(table: "NeuronTable") -> str | None:
    """A one-line reason when the neurons' extent cannot be micrometres (nanometres, metres,
    or a table of indices), or they lie much further apart than a worm's neurons do (pixel
    coordinates), else None. Tables of fewer than 10 neurons are not judged (the spacing: 15)."""
    if len(table) < 10:
        return None
    span = float(np.ptp(table.xyz, axis=0).max())
    if not MIN_SPAN_UM <= span <= MAX_SPAN_UM:
        return (f"{table.source}: the neurons span {span:.3g} along their longest axis, which cannot be µm "
                f"(a worm is ~1000 µm long, a head ~100 µm); x_um, y_um, z_um must be micrometres")
    spacing = neuron_spacing(table.xyz) if len(table) >= SPREAD_MIN_NEURONS else None
    if spacing is not None and spacing > TOO_SPREAD * _head_spacing(len(table)):
        return (f"{table.source}: its neurons lie {spacing / _head_spacing(len(table)):.1f} times further apart than a "
                f"worm's head of {len(table)} neurons would (median {spacing:.3g} to the second-nearest); x_um, y_um, "
                "z_um must be micrometres (pixel coordinates times the voxel size)")
    return None


def warn_implausible_scales(tables: list["NeuronTable"]) -> None:
    """One warning line (:func:`implausible_scale`) for each of ``tables`` that cannot be in µm."""
    for table in tables:
        reason = implausible_scale(table)
        if reason:
            warn(reason)


def positions(xyz, what: str = "positions") -> np.ndarray:
    """``xyz`` as an (N, 3) float array, one row of x, y, z per neuron (one point may be given
    flat). Refused (TableError) otherwise: a (3, N) array reshaped would scramble every neuron."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim == 2 and xyz.shape[0] == 3 and xyz.shape[1] != 3:
        raise TableError(f"{what} of shape {xyz.shape}: give one row of x, y, z per neuron (transpose them)")
    if not (xyz.ndim == 2 and xyz.shape[1] == 3 or xyz.shape == (3,) or xyz.size == 0):
        raise TableError(f"{what} of shape {xyz.shape}: give one row of x, y, z per neuron")
    return xyz.reshape(-1, 3)


def _per_neuron(values, n: int, what: str, dtype) -> np.ndarray:
    values = np.asarray(values, dtype=dtype).ravel()
    if len(values) != n:
        raise TableError(f"{len(values)} {what} for {n} neurons: give one per neuron")
    return values


# How R (write.csv, readr), MATLAB and Excel write a missing name: no neuron is called so
MISSING_NAMES = frozenset({"NA", "NaN", "nan", "#N/A"})


def _clean(name) -> str:
    if name is None or (np.ndim(name) == 0 and pd.isna(name)):  # pd.NA too (a 'string' column): no '<NA>'
        return ""
    name = str(name).strip()
    return "" if name in MISSING_NAMES else name


def parse_name(raw) -> tuple[str, float]:
    """'AVAL' -> ('AVAL', 1); 'AVAL?' or 'AVAL??' -> ('AVAL', 0.5); '?' or '' -> ('', 0)."""
    s = _clean(raw)
    if s.endswith("?"):
        s = _clean(s.rstrip("?"))  # 'NA?' is no name either (kept by a review, lost on reading)
        return (s, UNSURE_CONF) if s else ("", 0.0)
    return (s, 1.0) if s else ("", 0.0)


def neuropal_id_header(lines: list[str]) -> int | None:
    """The line of a NeuroPAL_ID export's header (quoted or not), None for another table."""
    for i, line in enumerate(lines[:12]):
        cells = [c.strip() for c in next(_csv_records(line), [])]
        if cells and cells[0] == "User ID" and "Real X (um)" in cells:
            return i
    return None


def read_table(path: str | os.PathLike, names: bool = True, unique_names: bool = True) -> NeuronTable:
    """Read and validate a neuron table (ours or a NeuroPAL_ID export). ``names=False`` leaves
    its ``label`` column unread (a table to be named: its names are not used).
    ``unique_names=False`` keeps a name that occurs more than once (a table of several time
    points names each neuron once per time point: :func:`with_unique_names` per volume)."""
    path = Path(path)
    name = str(path)
    if not path.exists():
        raise TableError(f"{name}: no such file")
    if path.is_dir():
        raise TableError(f"{name}: is a folder, not a neuron table")
    try:
        # as written: a line break inside a quoted cell ('\r\n' from Excel) stays as it is
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise TableError(f"{name}: not a UTF-8 text CSV file") from None
    except OSError as exc:
        raise TableError(f"{name}: cannot be read ({exc.strerror})") from None
    if not text.strip():
        raise TableError(f"{name}: the file is empty")
    lines = text.splitlines()
    header_line = neuropal_id_header(lines)
    if header_line is not None:
        df = _read_csv(text, name, skiprows=header_line)
        return _from_neuropal_id(df, name, first_line=header_line + 2, names=names, unique_names=unique_names)
    df = _read_csv(text, name)
    return table_from_dataframe(df, source=name, first_line=2, names=names, unique_names=unique_names)


def _read_csv(text: str, name: str, skiprows: int = 0) -> pd.DataFrame:
    """The CSV ``text`` (after ``skiprows`` lines) as strings, refused in one line where pandas
    would misread it silently: a row with more fields than the header (pandas then takes the
    first column as the index and shifts every other one), two columns of one name (pandas
    renames the second 'R.1'), columns separated by ';' or tabs. Excel's 'sep=,' line is skipped."""
    first = next(iter(text.splitlines()[skiprows:]), "").strip()
    if first.lower().startswith("sep="):
        if first[4:] != ",":
            raise TableError(f"{name}: its first line says the columns are separated by {first[4:]!r}; "
                             "save it as a comma-separated CSV (UTF-8, '.' before decimals)")
        skiprows += 1
    records = _csv_records(text)
    for _ in range(skiprows):
        next(records, None)
    header = next(records, None)
    while header is not None and not any(cell.strip() for cell in header):  # blank lines (and Excel's ',,,') above the header
        header = next(records, None)
        skiprows += 1  # pandas would take ',,,' for the header
    if header is not None and len(header) == 1:
        for separator, called in ((";", "semicolons"), ("\t", "tabs")):
            if separator in header[0]:
                raise TableError(f"{name}: the columns are separated by {called}, not commas; save it as a "
                                 "comma-separated CSV (UTF-8, '.' before decimals)")
    if header is not None:
        names = [h.strip() for h in header]
        repeated = sorted({h for h in names if h and names.count(h) > 1})  # blank ones are spacers (NeuroPAL_ID)
        if repeated:
            raise TableError(f"{name}: two columns are named '{repeated[0]}' (spaces around names do not count); "
                             "give each column its own name")
        for row in records:  # a field beyond the header's: every column would shift (or a value be lost)
            if len(row) > len(header) and any(cell.strip() for cell in row[len(header):]):
                raise TableError(f"{name}: line {records.line_num} has {len(row)} fields, the header {len(header)}; "
                                 "each row needs one value per column")
    try:
        with warnings.catch_warnings():  # empty fields beyond the header (Excel's trailing commas) are dropped
            warnings.simplefilter("ignore", pd.errors.ParserWarning)
            # the header's columns only: pandas drops empty fields beyond it on the first row
            # alone, and refused a later row's (their values were checked empty above)
            df = pd.read_csv(io.StringIO(text), skiprows=skiprows, dtype=str, keep_default_na=False, index_col=False,
                             usecols=range(len(header)) if header else None)
    except pd.errors.EmptyDataError:
        raise TableError(f"{name}: the file has no header row") from None
    except pd.errors.ParserError as exc:
        raise TableError(f"{name}: not a valid CSV file ({str(exc).splitlines()[0]})") from None
    # A column with neither a name nor a value (Excel's trailing ',,' on every line) carries nothing:
    # kept, it would be written back under pandas' name for it ('Unnamed: 3', or ' .1' for a
    # second ' '), so it is found by its place in the header
    blank_names = {k for k, h in enumerate(header or []) if not h.strip()}
    nameless = [c for k, c in enumerate(df.columns) if (k in blank_names or str(c).startswith("Unnamed: "))
                and not df[c].fillna("").str.strip().ne("").any()]
    # One with values (the index pandas' own to_csv writes first) keeps its blank name, as written
    # (the first of several: pandas' names tell the others apart)
    named_back = {}
    for k in sorted(blank_names):
        column = df.columns[k]
        if column not in nameless and header[k] not in df.columns and header[k] not in named_back.values():
            named_back[column] = header[k]
    df = df.drop(columns=nameless).rename(columns=named_back)
    # Rows of blank cells (',,,,') that Excel leaves below a table are no neurons: dropped. One
    # between neurons stays a row (pandas keeps it too: a benchmark's row numbers, neuron_index,
    # must stay the file's), and its empty position is then refused with its line.
    blank = (df.isna() | df.apply(lambda column: column.str.strip().eq(""))).all(axis=1).to_numpy()
    below = len(blank) - int(np.argmin(blank[::-1])) if not blank.all() else 0
    df = df.iloc[:below].reset_index(drop=True)
    # Kept for messages only (the file's own line of a bad cell: blank lines and quoted line
    # breaks shift the rows), and read again only then.
    df.attrs["csv"] = (text, skiprows)
    return df


def _csv_records(text: str):
    """The rows of CSV ``text``, with no practical limit on a cell's length (pandas has none: a
    long note in a column of its own is a cell, not an error; 2**31 - 1 fits every C long)."""
    csv.field_size_limit(2**31 - 1)
    return csv.reader(io.StringIO(text, newline=""))  # as the csv module asks: "\r" ends a row, kept in a quoted cell


def _record_lines(text: str, skiprows: int) -> list[int]:
    """The file line on which each data row starts, skipping blank lines as pandas does (and,
    as :func:`_read_csv`, rows of blank cells below the table)."""
    reader = _csv_records(text)
    starts, filled, previous = [], [], 0
    for row in reader:
        start, previous = previous + 1, reader.line_num
        if start > skiprows and row and not (len(row) == 1 and not row[0].strip()):  # pandas skips a line of spaces
            starts.append(start)
            filled.append(any(cell.strip() for cell in row))
    while filled and not filled[-1]:
        starts.pop(), filled.pop()
    return starts[1:]  # the first is the header


def file_line(df: pd.DataFrame | None, row: int, first_line: int = 2) -> int:
    """The line of the file on which data row ``row`` of ``df`` (a table read from a CSV, or
    its ``text``) starts: blank lines and quoted line breaks counted, as an editor shows it."""
    lines = _record_lines(*df.attrs["csv"]) if df is not None and "csv" in df.attrs else []
    return lines[row] if df is not None and len(lines) == len(df) else row + first_line


# A kilometre: beyond any microscope stage (stage coordinates reach 1e5-1e6 µm). The
# registration's float32 squares overflowed from about 1e19 (a scipy traceback in fdlc label).
MAX_POSITION_UM = 1e9


def _numeric_column(df: pd.DataFrame, column: str, name: str, first_line: int, allow_empty: bool,
                    shown_as: str | None = None) -> np.ndarray:
    cells = df[column]  # a table in memory holds NaN for no reading, a file '' (both empty)
    raw = cells.astype(object).where(cells.notna(), "").astype(str).str.strip()
    values = pd.to_numeric(raw.where(raw != "", "nan"), errors="coerce").to_numpy(dtype=np.float64, copy=True)
    bad = ~np.isfinite(values)
    # pandas 2's parser is off by one unit in the last place on about a third of the numbers;
    # numpy's (Python's) is exact, so a position or colour written back is the one read.
    values[~bad] = raw.to_numpy(dtype=str)[~bad].astype(np.float64)
    if allow_empty:  # no reading: an empty cell, or NaN / NA / #N/A as MATLAB (NeuroPAL_ID), R and Excel write it
        bad &= ~raw.str.lower().isin(("", "nan", "na", "#n/a")).to_numpy()
    if bad.any():
        row = int(np.argmax(bad))
        shown = raw.iloc[row] or "an empty cell"
        raise TableError(f"{name}: line {file_line(df, row, first_line)}, column '{shown_as or column}': "
                         f"{shown!s} is not a finite number")
    return values


def _letters(column: str) -> str:
    """A column name's letters alone, lower case, µ as u: 'X (um)' and 'x_um' are 'xum'."""
    return "".join(ch for ch in str(column).lower().replace("µ", "u") if ch.isalpha())


def table_from_dataframe(df: pd.DataFrame, source: str = "<memory>", first_line: int = 2, names: bool = True,
                         unique_names: bool = True, file_columns: dict[str, str] | None = None) -> NeuronTable:
    """Validate a data frame in our column layout and turn it into a :class:`NeuronTable`.
    ``file_columns``: our column name -> the file's, for messages about a file in another
    layout (a NeuroPAL_ID export's 'Real X (um)')."""
    df = df.copy()
    df.columns = [str(c).strip() for c in df.columns]
    twice = df.columns[df.columns.duplicated()]
    if len(twice):
        raise TableError(f"{source}: two columns are named '{twice[0]}' (spaces around names do not count); "
                         "give each column its own name")
    shown = file_columns or {}
    missing = [c for c in COORDS if c not in df.columns]
    if missing:
        # a column that is one of them written otherwise ('X (um)', 'x_UM', 'x [µm]'): say which
        alike = {c: [f for f in df.columns if _letters(f) == _letters(c)] for c in missing}
        hint = "; ".join(f"rename '{found[0]}' to {c}" for c, found in alike.items() if found)
        raise TableError(
            f"{source}: missing column(s) {', '.join(shown.get(c, c) for c in missing)} "
            f"(a neuron table needs {', '.join(shown.get(c, c) for c in COORDS)}{'; ' + hint if hint and not shown else ''})"
        )
    if len(df) == 0:
        raise TableError(f"{source}: the table has no rows")
    xyz = np.stack([_numeric_column(df, c, source, first_line, allow_empty=False, shown_as=shown.get(c, c))
                    for c in COORDS], axis=1)
    far = np.abs(xyz) > MAX_POSITION_UM
    if far.any():  # MATLAB's realmax (1.8e308) marks a missing value; such numbers overflow the geometry
        row, axis = (int(v) for v in np.argwhere(far)[0])
        raise TableError(f"{source}: line {file_line(df, row, first_line)}, column '{shown.get(COORDS[axis], COORDS[axis])}': "
                         f"{xyz[row, axis]:g} is no position in µm (beyond {MAX_POSITION_UM:g}); "
                         "a missing-value marker? remove the row or give the position")
    colours = {}
    for c in COLOUR_CHANNELS:
        if c in df.columns:
            values = _numeric_column(df, c, source, first_line, allow_empty=True, shown_as=shown.get(c, c))
            if not np.isnan(values).all():  # an empty cell: the NeuronTable fills and remembers it
                colours[c] = values
    labels = np.full(len(df), "", dtype=object)
    conf = np.zeros(len(df))
    if names and "label" in df.columns:
        parsed = [parse_name(v) for v in df["label"]]
        labels = np.array([p[0] for p in parsed], dtype=object)
        conf = np.array([p[1] for p in parsed])
        if unique_names:
            labels, conf = _drop_duplicate_names(labels, conf, source)
    kept = [c for c in df.columns if c not in COORDS + COLOUR_CHANNELS + ("label",)]
    return NeuronTable(xyz, colours, labels, conf, df[kept].reset_index(drop=True), source, text=df.reset_index(drop=True))


def with_unique_names(table: NeuronTable, say: bool = True) -> NeuronTable:
    """``table`` with a name that occurs more than once left on none of its rows, as
    :func:`read_table` reads one volume; ``say``: with one warning line (a caller splitting
    many volumes says it once for all, :func:`repeated_names`)."""
    table.labels, table.label_conf = _drop_duplicate_names(table.labels, table.label_conf, table.source, say)
    return table


def repeated_names(labels: np.ndarray) -> set[str]:
    """The names that occur more than once in ``labels``."""
    names, counts = np.unique(labels[labels != ""], return_counts=True)
    return set(names[counts > 1])


def _drop_duplicate_names(labels: np.ndarray, conf: np.ndarray, source: str, say: bool = True):
    duplicated = repeated_names(labels)
    if duplicated:
        mask = np.isin(labels, list(duplicated))
        labels = labels.copy()
        conf = conf.copy()
        labels[mask] = ""
        conf[mask] = 0.0
        if say:
            shown = ", ".join(sorted(duplicated)[:8]) + (" ..." if len(duplicated) > 8 else "")
            warn(f"{source}: name(s) {shown} occur more than once; those rows are read as unnamed")
    return labels, conf


def _from_neuropal_id(df: pd.DataFrame, name: str, first_line: int, names: bool = True, unique_names: bool = True) -> NeuronTable:
    df = df.rename(columns=lambda c: str(c).strip())  # 'User ID, User Confidence, …' is recognised so too
    ours = df.rename(columns={k: v for k, v in _NPID_TO_OURS.items() if k in df.columns})
    if "User ID" in ours.columns:
        ids = ours["User ID"].astype(str).str.strip()
        if "User Confidence" in ours.columns:
            # NeuroPAL_ID writes the unsure mark in the confidence column, not in the name.
            conf = pd.to_numeric(ours["User Confidence"], errors="coerce")
            unsure = (conf == UNSURE_CONF) & (ids != "") & ~ids.str.endswith("?")
            ids = ids.where(~unsure, ids + "?")
        ours["label"] = ids
        ours = ours.drop(columns=["User ID"])
    ours = ours.loc[:, [c for c in ours.columns if c and not c.startswith("Unnamed:")]]
    theirs = {v: k for k, v in _NPID_TO_OURS.items() if k in df.columns or v not in df.columns}
    return table_from_dataframe(ours, source=name, first_line=first_line, names=names, unique_names=unique_names,
                                file_columns=theirs)


def write_table(table: NeuronTable | pd.DataFrame, path: str | os.PathLike) -> None:
    """Write our CSV layout atomically (temporary file, then rename)."""
    df = table.to_dataframe() if isinstance(table, NeuronTable) else table
    # Positions, times and colours to the last digit that tells two floats apart (the shortest
    # text that reads back the same): 6 significant digits put a neuron 0.5 µm off at a stage
    # offset of 1e5 µm, made time stamps 1700000000.2 and .4 one time point, and changed raw
    # intensities of 7 digits that a table copied on (fdlc simulate) should carry as they were.
    # Other numbers (probabilities, scores) keep 6.
    exact = [c for c in (*COORDS, "t", *COLOUR_CHANNELS, "GFP") if c in df.columns and pd.api.types.is_float_dtype(df[c])]
    if exact:
        df = df.assign(**{c: [repr(v) if np.isfinite(v) else "" for v in df[c].to_numpy(float).tolist()] for c in exact})
    # A text cell holding a lone '\r' is quoted only where '\r' ends the records (the csv module
    # quotes a field for its line terminator's characters): written unquoted it broke the file
    crlf = any(isinstance(v, str) and "\r" in v for c in df.columns if not pd.api.types.is_numeric_dtype(df[c])
               for v in df[c])
    with atomic_write(path, "w", encoding="utf-8", newline="") as handle:
        df.to_csv(handle, index=False, float_format="%.6g", lineterminator="\r\n" if crlf else "\n")


def write_neuropal_id(
    table: NeuronTable,
    path: str | os.PathLike,
    voxel_size_zyx: tuple[float, float, float] | None = None,
    auto_id: list[str] | None = None,
    auto_conf: np.ndarray | None = None,
) -> None:
    """Write a NeuroPAL_ID "Save ID Info" CSV (1-based internal voxel coordinates)."""
    n = len(table)
    rows = {h: [""] * n for h in NEUROPAL_ID_HEADER if h}
    rows["Emphasized?"] = ["0"] * n
    # what a NeuroPAL_ID table read brought along (GFP, emphasis, its Auto ID), unless given anew
    # below; voxel coordinates only from voxel_size_zyx (a moved neuron's would be stale)
    for h in rows:
        if h in table.extra.columns and h not in PIXEL_COLUMNS:
            rows[h] = ["" if pd.isna(v) else str(v) for v in table.extra[h]]
    rows["User ID"] = list(table.labels)
    rows["User Confidence"] = [f"{c:g}" if s else "0" for s, c in zip(table.labels, table.label_conf)]
    if auto_id is not None:
        rows["Auto ID"] = [str(a or "") for a in _per_neuron(auto_id, n, "automatic names", object)]
        if auto_conf is not None:  # an Auto ID without its confidence says none
            confs = _per_neuron(auto_conf, n, "automatic confidences", np.float64)
            rows["Auto Confidence"] = [f"{c:.4f}" if a else "" for a, c in zip(rows["Auto ID"], confs)]
    for axis, col in enumerate(["Real X (um)", "Real Y (um)", "Real Z (um)"]):
        rows[col] = [f"{v:.4f}" for v in table.xyz[:, axis]]
    if voxel_size_zyx is not None:
        z, y, x = voxel_size_zyx
        for axis, (col, size) in enumerate(
            zip(["Internal X (px)", "Internal Y (px)", "Internal Z (slice)"], [x, y, z])
        ):
            rows[col] = [f"{v / size + 1:.3f}" for v in table.xyz[:, axis]]
    # each colour z-scored over the neurons; the preamble says with which mean and SD (a
    # NeuroPAL_ID table read is z-scored again: its values change, the preamble undoes it)
    means, sds = [0.0] * 4, [1.0] * 4
    for k, (ours, theirs) in enumerate([("R", "Z-Scored Red"), ("G", "Z-Scored Green"), ("B", "Z-Scored Blue"),
                                         ("W", "Z-Scored White")]):
        if ours in table.colours:
            v = table.colours_as_read()[ours]
            finite = np.isfinite(v)  # a neuron without a reading leaves its cell empty, not the column NaN
            if finite.any():
                means[k], sds[k] = float(v[finite].mean()), float(v[finite].std()) or 1.0
            z = (v - means[k]) / sds[k]
            rows[theirs] = [f"{x:.4f}" if np.isfinite(x) else "" for x in z]
    preamble = [
        "Version,napari-fdlc",
        "GFP,0",
        "Z-Score Means," + ",".join(f"{m:.6g}" for m in means),
        "Z-Score SDs," + ",".join(f"{d:.6g}" for d in sds),
        "Neuron Count," + str(n),
        "Comment,written by napari-fdlc",
        "",
    ]
    assert len(preamble) == _NPID_PREAMBLE_LINES
    columns = [rows[h] if h else [""] * n for h in NEUROPAL_ID_HEADER]
    df = pd.DataFrame(list(zip(*columns)), columns=NEUROPAL_ID_HEADER)
    with atomic_write(path, "w", encoding="utf-8", newline="") as handle:
        handle.write("\n".join(preamble) + "\n")
        df.to_csv(handle, index=False)


def read_volume(path: str | os.PathLike, instead: str, names: bool = True, unique_names: bool = True) -> NeuronTable:
    """:func:`read_table` for a table that must be one volume: a table of several time points
    (a ``t`` column, as ``fdlc segment`` writes for a recording) is refused in one line, before
    its names are checked for repeats (each time point names a neuron again; ``unique_names``
    False: left to the caller). ``instead`` says what to give."""
    table = read_table(path, names=names, unique_names=False)
    if table.text is not None and "t" in table.text.columns:
        text = table.text["t"].astype(str).str.strip()
        value = pd.to_numeric(text, errors="coerce")  # '1' and '1.0' are one time point
        times = pd.Series(np.where(value.notna(), value.astype(str), text)).nunique()
        if times > 1:
            raise TableError(f"{table.source}: a recording of {times} time points (a 't' column), taken whole it "
                             f"would mix them; {instead}")
    return with_unique_names(table) if names and unique_names else table
