"""Review state of one labelled worm: names, the user's decisions, undo/redo, autosave, export.

This is the Qt-free heart of the napari "Auto-label" widget (the widget only displays a
:class:`ReviewSession` and forwards clicks and keys to it), so everything a user can do while
reviewing is testable without a display, and scriptable without napari::

    session = ReviewSession(table, labelling, path=session_file_for("worm.tif"))
    session.accept(3); session.assign(7, "AVAL"); session.mark_unsure(9); session.undo()
    session.export("worm_ids.csv")

Rows are the neurons of the table (0-based, in table order). Per row the session keeps

- the automatic answer: ``auto_id`` ('' = no named match), ``auto_conf`` and the top-k
  candidates ``cand`` / ``cand_p``;
- the user's decision: ``user_id`` ('' = none), ``user_conf`` (1, 0.5 for unsure, NaN = none)
  and ``status``: ``auto`` (no decision), ``accepted`` (the user confirmed the automatic name),
  ``corrected`` (the user gave another name), ``unsure`` (a name marked ``?``, confidence 0.5 as
  in NeuroPAL_ID).

The *final* name of a neuron is the user's if given, else the automatic one when its confidence
reaches the threshold and no user decision took that name, else empty. A user decision is never
overwritten by the machine: re-labelling (:meth:`set_labelling` with the user's names passed as
``fixed`` to :func:`napari_fdlc.identify.label_neurons`) only replaces automatic columns.

Every edit is undoable, and with a ``path`` every change is written at once (JSON, atomic
replace), so a killed napari loses nothing.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import pandas as pd

from .errors import FdlcError, atomic_write, warn
from .match import Labelling
from .table import (COLOUR_CHANNELS, COORDS, PIXEL_COLUMNS, MISSING_NAMES, UNSURE_CONF, NeuronTable, parse_name, write_neuropal_id,
                    write_table)

STATUSES = ("auto", "accepted", "corrected", "unsure")
K = 3  # candidates kept per neuron
DEFAULT_THRESHOLD = 0.5
SESSION_FORMAT = "napari-fdlc review session"
SESSION_VERSION = 1
SESSION_SUFFIX = ".fdlc-session.json"
MAX_HISTORY = 1000
EXPORT_FORMATS = ("fdlc", "neuropal_id")
_NAME_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-']*$")
# Columns the session writes itself: never copied from the table's extra columns.
REVIEW_COLUMNS = (
    ("auto_id", "auto_conf")
    + tuple(f"cand_{k}" for k in range(1, K + 1))
    + tuple(f"prob_{k}" for k in range(1, K + 1))
    + ("user_id", "user_conf", "status", "x_px", "y_px", "z_px", "neuron_index")
)


# ---------------------------------------------------------------------------------------------
# Where sessions live


_SESSION_DIRS: dict[str, Path] = {}


def user_session_dir() -> Path:
    """The user's data folder for sessions (``$FDLC_SESSION_DIR`` overrides platformdirs)."""
    env = os.environ.get("FDLC_SESSION_DIR")
    if env:  # '~/sessions' as a shell would mean it; a relative one from the working folder when first used
        if env not in _SESSION_DIRS:  # (not wherever a script's os.chdir has gone since)
            _SESSION_DIRS[env] = Path(env).expanduser().absolute()
        return _SESSION_DIRS[env]
    import platformdirs

    return Path(platformdirs.user_data_dir("napari-fdlc", appauthor=False)) / "sessions"


def preferences_path() -> Path:
    """The Auto-label widget's choices kept between napari sessions (beside the sessions folder)."""
    return user_session_dir().parent / "preferences.json"


def load_preferences() -> dict:
    """The widget's saved choices ({} when none, or when the file cannot be read: they are only
    preferences, never worth an error)."""
    try:
        prefs = json.loads(preferences_path().read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return prefs if isinstance(prefs, dict) else {}


def save_preferences(prefs: dict) -> None:
    """Write the widget's choices (atomically); a folder that cannot be written is skipped."""
    path = preferences_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "w", encoding="utf-8") as handle:
            json.dump(prefs, handle, indent=1)
    except OSError:
        pass


def _package_dir() -> Path:
    return Path(__file__).resolve().parent


def _is_path_key(key: str) -> bool:
    """A file path, as opposed to a key such as 'sample:neuropal' or '<memory>'."""
    if key.startswith("<"):
        return False
    return not (re.match(r"^[A-Za-z][A-Za-z0-9_+.-]+:", key) and not re.match(r"^[A-Za-z]:[\\/]", key))


def _writable_folder(folder: Path) -> bool:
    try:
        folder = folder.resolve()
    except OSError:
        return False
    if folder == _package_dir() or _package_dir() in folder.parents:
        return False  # never write into the installed package (bundled sample, editable installs)
    return _is(folder, Path.is_dir) and os.access(folder, os.W_OK | os.X_OK)


def _is(path: Path, test) -> bool:
    """``test(path)`` (Path.is_file, Path.is_dir), False where the path cannot even be probed
    (a name too long, a folder the user may not enter): not there, as far as sessions go."""
    try:
        return test(path)
    except OSError:
        return False


def user_session_file(key: str) -> Path:
    resolved = str(Path(key).resolve()) if _is_path_key(key) else key
    digest = hashlib.sha1(os.fsencode(resolved)).hexdigest()[:12]  # a file name in a legacy encoding too
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(key).name if _is_path_key(key) else key).strip("_.") or "image"
    return user_session_dir() / f"{stem[:60]}-{digest}.json"


def session_file_for(image: str | os.PathLike) -> Path:
    """Where the session of ``image`` (a file path or a key such as ``'sample:neuropal'``) is
    written: beside the image when its folder is writable, else in :func:`user_session_dir`
    under a name keyed by the image's absolute path."""
    key = str(image)
    if _is_path_key(key):
        path = Path(key)
        if _writable_folder(path.parent):
            return path.parent / (path.name + SESSION_SUFFIX)
    return user_session_file(key)


def find_session(image: str | os.PathLike) -> Path | None:
    """The existing session file of ``image`` (beside it first, then the user's data folder)."""
    key = str(image)
    candidates = []
    if _is_path_key(key):
        path = Path(key)
        candidates.append(path.parent / (path.name + SESSION_SUFFIX))
    candidates.append(user_session_file(key))
    existing = [c for c in candidates if _is(c, Path.is_file)]
    # The latest: after a save beside the image failed, the session went on in the user's folder.
    return max(existing, key=lambda c: c.stat().st_mtime_ns) if existing else None


# ---------------------------------------------------------------------------------------------
# The session


@dataclass
class _State:
    """Everything an edit can change (the table is treated as immutable and shared)."""

    table: NeuronTable
    auto_id: list[str]
    auto_conf: np.ndarray
    cand: list[list[str]]
    cand_p: np.ndarray
    user_id: list[str]
    user_conf: np.ndarray
    status: list[str]
    order: list[int]
    labelled: bool
    # neurons added or moved by hand: a new detection that lacks one loses the user's work
    by_hand: np.ndarray

    def copy(self) -> "_State":
        return _State(
            self.table, list(self.auto_id), self.auto_conf.copy(), [list(c) for c in self.cand],
            self.cand_p.copy(), list(self.user_id), self.user_conf.copy(), list(self.status),
            list(self.order), self.labelled, self.by_hand.copy(),
        )


@dataclass
class Edit:
    """One undoable step: the state before and after, and a one-line description."""

    description: str
    before: _State
    after: _State
    rows: list[int] | None = None  # rows touched (None = all)


@dataclass
class Decision:
    """A user's decision on one neuron, and the machine's answer there when known."""

    name: str
    conf: float
    status: str
    auto_id: str | None = None
    auto_conf: float | None = None
    candidates: tuple | None = None  # the machine's top K there: (names, probabilities)


def carry_decisions(old, xyz_um: np.ndarray, max_distance_um: float = 1.5) -> dict[int, Decision]:
    """Map the user decisions of ``old`` (a :class:`ReviewSession`, or a snapshot
    ``(old_xyz_um, old.decisions())`` taken on another thread) onto new neuron positions (e.g.
    after segmenting the image again): each decided neuron goes to the nearest new neuron within
    ``max_distance_um``, one to one, closest pairs first."""
    from scipy.spatial import cKDTree

    old_xyz, decided = (old.table.xyz, old.decisions()) if isinstance(old, ReviewSession) else old
    xyz_um = np.asarray(xyz_um, dtype=float).reshape(-1, 3)
    if not decided or len(xyz_um) == 0:
        return {}
    rows = np.array(sorted(decided))
    # the bound is exclusive in cKDTree: "within 1.5 µm" includes 1.5
    reach = np.nextafter(max_distance_um, np.inf)
    dist, idx = cKDTree(xyz_um).query(np.asarray(old_xyz)[rows], k=min(4, len(xyz_um)), distance_upper_bound=reach)
    dist, idx = dist.reshape(len(rows), -1), idx.reshape(len(rows), -1)
    pairs = sorted(
        (float(d), int(r), int(j)) for r, ds, js in zip(rows, dist, idx) for d, j in zip(ds, js) if np.isfinite(d)
    )
    out: dict[int, Decision] = {}
    used_old: set[int] = set()
    for _, r, j in pairs:
        if r in used_old or j in out:
            continue
        used_old.add(r)
        out[j] = decided[r]
    return out


def set_aside(path: str | os.PathLike) -> Path | None:
    """Rename a session file that a new session is about to replace although it holds
    decisions the new one lacks (or could not be read): ``<image>.fdlc-session.json`` becomes
    ``<image>.fdlc-session.<date-time>.json``, which is never restored by itself but keeps every
    decision. Returns the new name (None when there was no file)."""
    path = Path(path)
    if not _is(path, Path.is_file):
        return None
    stem = path.name[: -len(SESSION_SUFFIX)] if path.name.endswith(SESSION_SUFFIX) else path.stem
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    for n in range(100):
        kept = path.with_name(f"{stem}.fdlc-session.{stamp}{'' if n == 0 else f'-{n}'}.json")
        if not kept.exists():
            break
    try:
        os.replace(path, kept)
    except OSError as exc:
        raise FdlcError(f"{path}: could not be kept aside as {kept.name} ({exc.strerror or exc}); "
                        "move it away by hand to keep its decisions") from None
    return kept


def decisions_from_frame(df: pd.DataFrame) -> dict[int, Decision]:
    """User decisions stored in a frame with our export columns (``user_id``, ``status``, and
    ``auto_id``/``auto_conf`` when present), e.g. a CSV written by :meth:`ReviewSession.export`,
    or a NeuroPAL_ID export read as a table (its ``label`` is the User ID)."""
    if "user_id" not in df.columns and {"label", "User Confidence"} <= set(df.columns):
        df = df.rename(columns={"label": "user_id", "Auto ID": "auto_id", "Auto Confidence": "auto_conf"})
    if "user_id" not in df.columns:
        return {}
    out: dict[int, Decision] = {}
    status = df["status"] if "status" in df.columns else pd.Series([""] * len(df))
    for i, (raw, st) in enumerate(zip(df["user_id"], status)):
        name, conf = parse_name("" if pd.isna(raw) else raw)
        if not name:
            continue
        auto = df["auto_id"].iloc[i] if "auto_id" in df.columns else None
        auto = None if auto is None or pd.isna(auto) else str(auto)
        if conf == UNSURE_CONF:  # 'AVAL?' is unsure, whatever a status column edited beside it says
            st = "unsure"
        elif str(st) not in STATUSES or str(st) == "auto":
            st = "accepted" if name == auto else "corrected"
        ac = pd.to_numeric(df["auto_conf"].iloc[i], errors="coerce") if "auto_conf" in df.columns else np.nan
        out[i] = Decision(name, conf, st, auto, None if pd.isna(ac) else float(ac))
    return out


Listener = Callable[[str, "list[int] | None"], None]


class ReviewSession:
    """Review state of one worm; see the module docstring."""

    def __init__(
        self,
        table: NeuronTable,
        labelling: Labelling | None = None,
        *,
        threshold: float = DEFAULT_THRESHOLD,
        voxel_size_zyx: tuple[float, float, float] | None = None,
        image: str | None = None,
        path: str | os.PathLike | None = None,
        names: Iterable[str] | None = None,
        by_hand: bool | np.ndarray = False,
    ) -> None:
        n = len(table)
        self.threshold = _check_threshold(threshold)
        self.voxel_size_zyx = _check_voxel_size(voxel_size_zyx)
        self.image = os.fspath(image) if image is not None else None  # a Path too (saved as JSON text)
        self.path = Path(path) if path is not None else None
        self.vocabulary: list[str] = sorted(set(names or ()))
        self.current: int | None = None
        self._after_deletion = False  # the current neuron is the one before a neuron just deleted
        self.settings: dict = {}  # free-form (e.g. template description, colour on/off)
        self._undo: list[Edit] = []
        self._redo: list[Edit] = []
        self._listeners: list[Listener] = []
        self.last_save_error: str | None = None
        self._s = _State(
            table=table,
            auto_id=[""] * n,
            auto_conf=np.zeros(n),
            cand=[[""] * K for _ in range(n)],
            cand_p=np.zeros((n, K)),
            user_id=[""] * n,
            user_conf=np.full(n, np.nan),
            status=["auto"] * n,
            order=list(range(n)),
            labelled=False,
            # the user's own neurons (a table of theirs: True), as against the detector's
            by_hand=np.broadcast_to(np.asarray(by_hand, dtype=bool), (n,)).copy(),
        )
        if labelling is not None:
            self._apply_labelling(self._s, labelling)

    # ----- read access ------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._s.table)

    @property
    def by_hand(self) -> np.ndarray:
        """Mask of the user's own neurons: added or moved by hand (the layer's edits), or from a
        table of theirs; a copy."""
        return self._s.by_hand.copy()

    @property
    def table(self) -> NeuronTable:
        return self._s.table

    @property
    def labelled(self) -> bool:
        """True once an automatic labelling has been set."""
        return self._s.labelled

    @property
    def auto_id(self) -> list[str]:
        return list(self._s.auto_id)

    @property
    def auto_conf(self) -> np.ndarray:
        return self._s.auto_conf.copy()

    @property
    def user_id(self) -> list[str]:
        return list(self._s.user_id)

    @property
    def user_conf(self) -> np.ndarray:
        return self._s.user_conf.copy()

    @property
    def status(self) -> list[str]:
        return list(self._s.status)

    def candidates(self, i: int) -> list[tuple[str, float]]:
        """Top-k (name, probability) of row ``i``, most likely first, without empty entries."""
        i = self._row(i)
        return [(c, float(p)) for c, p in zip(self._s.cand[i], self._s.cand_p[i]) if c]

    def is_decided(self, i: int) -> bool:
        return self._s.status[self._row(i)] != "auto"

    def user_names(self) -> dict[str, int]:
        """name -> row for every user decision."""
        return {name: i for i, name in enumerate(self._s.user_id) if name}

    def auto_shown(self) -> np.ndarray:
        """Rows whose automatic name is shown: no user decision, confidence >= threshold, and the
        name neither taken by a user decision elsewhere nor shown on a more confident row."""
        s = self._s
        taken = set(self.user_names())
        shown = np.array(
            [
                st == "auto" and bool(a) and c >= self.threshold and a not in taken
                for a, c, st in zip(s.auto_id, s.auto_conf, s.status)
            ],
            dtype=bool,
        )
        # One neuron per name: a decision cleared after a re-labelling brings back the machine's
        # earlier answer there, which the re-labelling may have given to another neuron since.
        best: dict[str, int] = {}
        for i in np.flatnonzero(shown):
            j = best.setdefault(s.auto_id[i], i)
            if j != i:
                keep, drop = (i, j) if s.auto_conf[i] > s.auto_conf[j] else (j, i)
                best[s.auto_id[i]] = keep
                shown[drop] = False
        return shown

    def final_names(self) -> list[str]:
        """Final name per row (without '?'): the user's, else the shown automatic one, else ''."""
        shown = self.auto_shown()
        return [u if st != "auto" else (a if ok else "") for u, a, st, ok in zip(self._s.user_id, self._s.auto_id, self._s.status, shown)]

    def display_names(self) -> list[str]:
        """Final names as written in a table: 'AVAL?' for an unsure decision."""
        return [n + "?" if n and st == "unsure" else n for n, st in zip(self.final_names(), self._s.status)]

    def coverage(self) -> float:
        """Fraction of neurons that carry a final name (0 for an empty session)."""
        n = len(self)
        return sum(1 for x in self.final_names() if x) / n if n else 0.0

    def counts(self) -> dict[str, int]:
        out = {s: 0 for s in STATUSES}
        for st in self._s.status:
            out[st] += 1
        # below the threshold, that is (a name taken by a decision elsewhere is not hidden by it)
        out["hidden"] = int(sum(1 for a, c, st in zip(self._s.auto_id, self._s.auto_conf, self._s.status)
                                if st == "auto" and a and c < self.threshold))
        return out

    def review_order(self) -> list[int]:
        """Rows ordered by automatic confidence, lowest first (unnamed rows count as 0). The order
        is fixed when a labelling is set, so that navigation does not jump as decisions are made."""
        return list(self._s.order)

    def review_confidence(self) -> np.ndarray:
        s = self._s
        return np.array([c if a else 0.0 for a, c in zip(s.auto_id, s.auto_conf)])

    # ----- listeners and persistence ------------------------------------------------------------
    def connect(self, listener: Listener) -> None:
        """``listener(kind, rows)`` is called after every change; kind is 'edit', 'labelling',
        'threshold', 'structure', 'current', 'save_error' or 'save_moved' (autosaved to the user's
        folder from now on: ``path`` says where) (rows None = all rows)."""
        self._listeners.append(listener)

    def disconnect(self, listener: Listener) -> None:
        if listener in self._listeners:
            self._listeners.remove(listener)

    def _emit(self, kind: str, rows: list[int] | None = None) -> None:
        for listener in list(self._listeners):
            listener(kind, rows)

    def _changed(self, kind: str, rows: list[int] | None = None) -> None:
        if kind != "current":
            self.autosave()
        self._emit(kind, rows)

    def autosave(self) -> bool:
        """Write the session to :attr:`path` (if any). If that folder turns out not to be
        writable, fall back once to the user's data folder. Returns True when written."""
        if self.path is None:
            return False
        try:
            self.save(self.path)
            self.last_save_error = None
            return True
        except (TypeError, ValueError) as exc:  # something in the session JSON cannot hold
            self.last_save_error = f"{self.path}: the session could not be saved ({exc})"
            self._emit("save_error", None)
            return False
        except OSError as exc:
            fallback = user_session_file(self.image or _image_of(self.path))
            if fallback != self.path:
                try:
                    self.save(fallback)
                    warn(f"{self.path.parent}: not writable ({exc.strerror}); session saved to {fallback}")
                    self.path = fallback
                    self.last_save_error = None
                    self._emit("save_moved", None)  # napari says where: its users do not see stderr
                    return True
                except OSError:
                    pass
            self.last_save_error = f"{self.path}: the session could not be saved ({exc.strerror or exc})"
            self._emit("save_error", None)
            return False

    def save(self, path: str | os.PathLike | None = None) -> Path:
        """Write the session as JSON (atomic replace)."""
        path = Path(path) if path is not None else self.path
        if path is None:
            raise FdlcError("no session file given")
        text = json.dumps(self.to_dict(), separators=(",", ":"), allow_nan=False)
        with atomic_write(path, "w", encoding="utf-8") as handle:
            handle.write(text)
        return path

    def to_dict(self) -> dict:
        s = self._s
        t = s.table
        neurons: dict[str, list] = {c: _floats(t.xyz[:, k]) for k, c in enumerate(COORDS)}
        colours = t.colours_as_read()
        for c in COLOUR_CHANNELS:
            if c in colours:
                neurons[c] = _floats(colours[c])
        neurons["auto_id"] = list(s.auto_id)
        neurons["auto_conf"] = _floats(s.auto_conf)
        for k in range(K):
            neurons[f"cand_{k + 1}"] = [c[k] for c in s.cand]
            neurons[f"prob_{k + 1}"] = _floats(s.cand_p[:, k])
        neurons["user_id"] = list(s.user_id)
        neurons["user_conf"] = _floats(s.user_conf)
        neurons["status"] = list(s.status)
        extra = {}
        for c in t.extra.columns:
            if str(c) in neurons or str(c) in REVIEW_COLUMNS or str(c) == "label":
                continue
            extra[str(c)] = [_json_value(v) for v in t.extra[c].tolist()]
        return {
            "format": SESSION_FORMAT,
            "version": SESSION_VERSION,
            "saved": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "image": self.image,
            "voxel_size_zyx": list(self.voxel_size_zyx) if self.voxel_size_zyx else None,
            "threshold": self.threshold,
            "labelled": s.labelled,
            "vocabulary": self.vocabulary,
            "order": list(s.order),
            "by_hand": [int(j) for j in np.flatnonzero(s.by_hand)],
            "settings": _json_safe(self.settings),
            "neurons": neurons,
            "extra": extra,
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "<session>", path: str | os.PathLike | None = None) -> "ReviewSession":
        if not isinstance(d, dict) or d.get("format") != SESSION_FORMAT:
            raise FdlcError(f"{source}: not a napari-fdlc session file")
        version = d.get("version", 0)
        if isinstance(version, bool) or not isinstance(version, int):
            raise FdlcError(f"{source}: damaged session file (version {version!r} is not a whole number)")
        if version > SESSION_VERSION:
            raise FdlcError(f"{source}: session written by a newer napari-fdlc (version {d.get('version')}); update the plugin")
        try:
            nd = d["neurons"]
            xyz = np.column_stack([np.asarray(nd[c], dtype=float) for c in COORDS])
            n = len(xyz)
            colours = {c: np.asarray(_nan(nd[c]), dtype=float) for c in COLOUR_CHANNELS if c in nd}
            extra = d.get("extra") or {}
            if not isinstance(extra, dict):
                raise TypeError(f"extra is {type(extra).__name__}, not an object of columns")
            extra = pd.DataFrame({k: v for k, v in extra.items() if isinstance(v, list) and len(v) == n}, index=range(n))
            table = NeuronTable(xyz, colours, extra=extra, source=source)
            session = cls(
                table,
                threshold=_threshold_or_default(d.get("threshold", DEFAULT_THRESHOLD)),
                voxel_size_zyx=d.get("voxel_size_zyx"),
                # entries of the wrong kind ignored (as a threshold is), not a damaged file: an
                # image key that is no text, a vocabulary that is one string (not its letters)
                image=d.get("image") if isinstance(d.get("image"), str) else None,
                path=path,
                names=[v for v in d.get("vocabulary") if isinstance(v, str)] if isinstance(d.get("vocabulary"), list) else [],
            )
            s = session._s
            s.auto_id = [str(x or "") for x in nd["auto_id"]]
            s.auto_conf = np.nan_to_num(np.asarray(_nan(nd["auto_conf"]), dtype=float))
            s.cand = [[str(nd[f"cand_{k + 1}"][j] or "") for k in range(K)] for j in range(n)]
            s.cand_p = np.nan_to_num(np.column_stack([np.asarray(_nan(nd[f"prob_{k + 1}"]), dtype=float) for k in range(K)]))
            s.user_id = [str(x or "") for x in nd["user_id"]]
            s.user_conf = np.asarray(_nan(nd["user_conf"]), dtype=float)
            s.status = [str(x) for x in nd["status"]]
            if not np.isfinite(xyz).all():  # a position of null: its export could not be read back
                raise ValueError("a neuron without a position")
            labelled = d.get("labelled")
            s.labelled = labelled if isinstance(labelled, bool) else any(s.auto_id)  # ("false" is no False)
            # an order of the wrong kind is ignored (as a threshold is), not a damaged file
            order = d.get("order")
            order = [i for i in order if isinstance(i, int) and not isinstance(i, bool)] if isinstance(order, list) else []
            s.order = order if sorted(order) == list(range(n)) else _review_order(s)
            # rows added or moved by hand; a file from before they were kept does not say: any may be
            by_hand = d.get("by_hand")
            s.by_hand = np.ones(n, dtype=bool) if not isinstance(by_hand, list) else \
                np.isin(np.arange(n), [int(j) for j in by_hand if isinstance(j, int) and not isinstance(j, bool)])
            session.settings = _known_settings(d.get("settings"))
        except (KeyError, TypeError, ValueError, IndexError, OverflowError, FdlcError) as exc:
            raise FdlcError(f"{source}: damaged session file ({type(exc).__name__}: {exc})") from None
        bad = [st for st in s.status if st not in STATUSES]
        lengths = {len(s.auto_id), len(s.user_id), len(s.status), len(s.user_conf), len(s.auto_conf), len(s.cand_p)}
        lengths |= {len(nd[f"cand_{k + 1}"]) for k in range(K)}
        if bad or lengths != {n}:
            raise FdlcError(f"{source}: damaged session file (inconsistent neuron rows)")
        _agreeing_decisions(s)
        holder: dict[str, int] = {}
        for i, (name, st) in enumerate(zip(s.user_id, s.status)):  # a hand-edited file: one neuron per name
            if st != "auto" and name and holder.setdefault(name, i) != i:
                warn(f"{source}: {name} decided for neurons {holder[name]} and {i}: kept on {holder[name]} only")
                s.user_id[i], s.user_conf[i], s.status[i] = "", np.nan, "auto"
        return session

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ReviewSession":
        """Read a session file; later changes are saved back to the same file."""
        path = Path(path)
        try:
            d = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark: Notepad's
        except FileNotFoundError:
            raise FdlcError(f"{path}: no such session file") from None
        except (OSError, ValueError, RecursionError) as exc:
            raise FdlcError(f"{path}: unreadable session file ({exc})") from None
        return cls.from_dict(d, source=str(path), path=path)

    # ----- automatic labelling ------------------------------------------------------------------
    def fixed(self) -> dict[int, str]:
        """Row -> name of every user decision: the constraints for re-labelling."""
        return {i: name for i, name in enumerate(self._s.user_id) if name}

    def _apply_labelling(self, s: _State, labelling: Labelling, fixed_rows=()) -> None:
        n = len(s.table)
        if len(labelling.auto_id) != n:
            raise FdlcError(f"the labelling has {len(labelling.auto_id)} neurons but the table has {n}")
        cand, cand_p = labelling.candidates(K)
        # decided now, or fixed when the labelling was made (a decision cleared while it ran: the
        # labelling holds the fixed name at 1.0 there, no answer of the machine's)
        fixed = set(fixed_rows)
        # (also before the first labelling: a name typed there was given the fixed 1.0 as the
        # machine's answer, and clearing it offered the user's own name back as a sure one)
        keep = {i for i, st in enumerate(s.status) if st != "auto"} | fixed
        for j in range(n):
            # A decided neuron keeps the machine's earlier answer and candidates (the labelling
            # reports the user's fixed name there, at 1.0), so 'accepted' vs 'corrected' stays
            # meaningful and clearing the decision offers the machine's choices again. One fixed
            # without an earlier answer (added by hand) gets none: the 1.0 is the user's.
            if j in keep and (any(s.cand[j]) or j in fixed):
                continue
            if j not in keep:
                s.auto_id[j] = str(labelling.auto_id[j] or "")
                s.auto_conf[j] = float(labelling.auto_conf[j])
            s.cand[j] = [str(c or "") for c in cand[j]]
            s.cand_p[j] = cand_p[j]
        s.labelled = True
        s.order = _review_order(s)
        self.vocabulary = sorted(set(self.vocabulary) | set(labelling.names))

    def set_labelling(self, labelling: Labelling, description: str = "auto-label", fixed_rows=()) -> None:
        """Replace the automatic columns (undoable). User decisions are kept as they are;
        ``fixed_rows``: the rows whose names were fixed when ``labelling`` was made, which keep
        the machine's earlier answer even if their decision has been cleared since."""
        rows = [int(i) for i in fixed_rows]
        self._commit(description, lambda s: self._apply_labelling(s, labelling, rows), kind="labelling")

    # ----- edits --------------------------------------------------------------------------------
    def _row(self, i) -> int:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):  # 1.7 is no row
            raise FdlcError(f"neuron {i!r}: give a row number")
        j = int(i)
        if not 0 <= j < len(self):
            raise FdlcError(f"neuron {j}: no such row (the layer has {len(self)} neurons, rows 0-{len(self) - 1})")
        return j

    def _commit(self, description: str, change: Callable[[_State], None], rows=None, kind: str = "edit") -> bool:
        before = self._s.copy()
        after = self._s.copy()
        change(after)
        if _same(before, after):
            return False
        self._s = after
        self._undo.append(Edit(description, before, after, rows))
        del self._undo[:-MAX_HISTORY]
        self._redo.clear()
        self._changed(kind, rows)
        return True

    def _check_name(self, name: str, row: int) -> None:
        # A typed name must look like one; a name the machine offers (its vocabulary, e.g. a
        # template's own names) is taken as it is written.
        machine = set(self.vocabulary) | set(self._s.auto_id) | {c for row_cands in self._s.cand for c in row_cands}
        if not _NAME_OK.match(name) and name not in machine:
            raise FdlcError(f"{name!r}: not a neuron name (letters, digits, '-', '_', '.', \"'\" only)")
        holder = self.user_names().get(name)
        if holder is not None and holder != row:
            raise FdlcError(f"{name} is already the name of neuron {holder}; clear it there first")

    def _decide(self, i: int, name: str, conf: float, description: str) -> bool:
        i = self._row(i)
        self._check_name(name, i)
        status = "unsure" if conf == UNSURE_CONF else ("accepted" if name == self._s.auto_id[i] else "corrected")

        def change(s: _State) -> None:
            s.user_id[i] = name
            s.user_conf[i] = 1.0 if status != "unsure" else UNSURE_CONF
            s.status[i] = status

        return self._commit(description, change, [i])

    def accept(self, i: int) -> bool:
        """Confirm the current name of neuron ``i`` (the automatic one, or make an unsure
        decision sure). Returns False when nothing changed."""
        i = self._row(i)
        s = self._s
        name = s.user_id[i] or s.auto_id[i]
        if not name:
            raise FdlcError(f"neuron {i} has no automatic name to accept; pick a candidate or type a name")
        return self._decide(i, name, 1.0, f"accept {name} for neuron {i}")

    def assign(self, i: int, name: str) -> bool:
        """Give neuron ``i`` the name ``name`` ('AVAL?' = unsure; '' clears the decision)."""
        i = self._row(i)
        text = str(name).strip()
        if text and not text.strip("?"):  # '?' or '??': 'unsure' of the current name (as U), not a name cleared
            return self.mark_unsure(i)
        if text.rstrip("?").strip() in MISSING_NAMES:  # a table reads it as no name: it was cleared, or lost on reopening
            raise FdlcError(f"{text!r}: a table reads this as a missing value, not a name; clear the name with an "
                            "empty name (C) instead")
        clean, conf = parse_name(name)
        if not clean:
            return self.clear(i)
        clean = self._spelled_as_known(clean)
        return self._decide(i, clean, conf, f"name neuron {i} {clean}{'?' if conf == UNSURE_CONF else ''}")

    def _spelled_as_known(self, name: str) -> str:
        """A typed name as the vocabulary writes it ('aval' -> 'AVAL'): typed in another case it
        was a name of its own, which no template or atlas knows. Kept as typed where it is known,
        unknown, or two known names differ only in case."""
        if name in self.vocabulary:
            return name
        same = [n for n in self.vocabulary if n.lower() == name.lower()]
        return same[0] if len(same) == 1 else name

    def pick_candidate(self, i: int, k: int) -> bool:
        """Give neuron ``i`` its k-th candidate (k = 1, 2, 3)."""
        i = self._row(i)
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= K:
            raise FdlcError(f"candidate {k!r}: give 1, 2 or 3")
        name = self._s.cand[i][int(k) - 1]
        if not name:
            raise FdlcError(f"neuron {i} has no candidate {k}")
        return self._decide(i, name, 1.0, f"pick candidate {k} ({name}) for neuron {i}")

    def mark_unsure(self, i: int) -> bool:
        """Keep the current name of neuron ``i`` but mark it unsure ('?', confidence 0.5)."""
        i = self._row(i)
        s = self._s
        name = s.user_id[i] or s.auto_id[i] or s.cand[i][0]
        if not name:
            raise FdlcError(f"neuron {i} has no name to mark unsure; type a name first")
        return self._decide(i, name, UNSURE_CONF, f"mark neuron {i} unsure ({name}?)")

    def clear(self, i: int) -> bool:
        """Remove the user's decision on neuron ``i`` (its automatic name applies again)."""
        i = self._row(i)

        def change(s: _State) -> None:
            s.user_id[i] = ""
            s.user_conf[i] = np.nan
            s.status[i] = "auto"

        return self._commit(f"clear neuron {i}", change, [i])

    def set_threshold(self, threshold: float, save: bool = True) -> None:
        """Confidence below which automatic names are hidden (not an undoable edit). ``save=False``
        skips the autosave (a slider being dragged; call :meth:`autosave` on release)."""
        threshold = _check_threshold(threshold)
        if threshold != self.threshold:
            self.threshold = threshold
            if save:
                self.autosave()
            self._emit("threshold")

    # ----- decisions carried over from elsewhere -----------------------------------------------
    def decisions(self) -> dict[int, "Decision"]:
        """Row -> :class:`Decision` for every user decision (with the machine's answer there)."""
        s = self._s
        return {
            i: Decision(s.user_id[i], float(s.user_conf[i]), s.status[i], s.auto_id[i], float(s.auto_conf[i]),
                        (tuple(s.cand[i]), tuple(float(p) for p in s.cand_p[i])))
            for i in range(len(self))
            if s.status[i] != "auto"
        }

    def seed_decisions(self, decisions: dict[int, "Decision"]) -> None:
        """Set user decisions as the starting state (not an edit: the undo history restarts from
        it), e.g. those of an earlier session or of a table read back from our CSV. Names held
        twice are dropped with a warning."""
        s = self._s
        # Every row checked before any is set: a row the table lacks leaves the session as it was.
        given = {self._row(i): d for i, d in decisions.items()}
        given = {i: d for i, d in given.items() if d.name and d.status in STATUSES and d.status != "auto"}
        # the session's own decisions elsewhere (and on rows given nothing to set) hold their names too
        seen: dict[str, int] = {name: row for row, name in enumerate(s.user_id) if name and row not in given}
        for i, d in sorted(given.items()):
            if d.name in seen:
                warn(f"{d.name} decided for neurons {seen[d.name]} and {i}: kept on {seen[d.name]} only")
                continue
            seen[d.name] = i
            s.user_id[i] = d.name
            s.user_conf[i] = UNSURE_CONF if d.status == "unsure" else 1.0
            s.status[i] = d.status
            if d.auto_id is not None:
                s.auto_id[i] = d.auto_id
                s.auto_conf[i] = d.auto_conf if d.auto_conf is not None else s.auto_conf[i]
            if d.candidates is not None and any(d.candidates[0]):  # what Clear offers again there
                s.cand[i], s.cand_p[i] = list(d.candidates[0]), np.asarray(d.candidates[1], dtype=float)
        # The starting state: the history restarts from it (set in place, an undo of an earlier
        # edit would have restored a state without the seeded decisions)
        self._undo.clear()
        self._redo.clear()
        self._changed("edit")

    # ----- neurons added, removed or moved in the layer ----------------------------------------
    def replace_table(self, table: NeuronTable, kept: list[int | None], description: str = "edit neurons") -> None:
        """New neuron table after points were added/removed/moved: ``kept[j]`` is the old row of
        new row ``j`` (None for a new neuron). Undoable."""
        if len(kept) != len(table):
            raise FdlcError("replace_table: one entry of 'kept' per new row is needed")
        old_rows = [o for o in kept if o is not None]
        if any(isinstance(o, bool) or not isinstance(o, (int, np.integer)) or not 0 <= o < len(self) for o in old_rows) \
                or len(set(old_rows)) != len(old_rows):
            raise FdlcError(f"replace_table: 'kept' must name each old row (0 to {len(self) - 1}) at most once, or None")

        def change(s: _State) -> None:
            old = s.copy()
            n = len(table)
            s.table = table
            s.auto_id, s.user_id, s.status = [""] * n, [""] * n, ["auto"] * n
            s.auto_conf, s.user_conf = np.zeros(n), np.full(n, np.nan)
            s.cand, s.cand_p = [[""] * K for _ in range(n)], np.zeros((n, K))
            s.by_hand = np.array([o is None or bool(old.by_hand[o]) or not np.array_equal(table.xyz[j], old.table.xyz[o])
                                  for j, o in enumerate(kept)], dtype=bool)
            for j, o in enumerate(kept):
                if o is None:
                    continue
                s.auto_id[j], s.auto_conf[j] = old.auto_id[o], old.auto_conf[o]
                s.cand[j], s.cand_p[j] = list(old.cand[o]), old.cand_p[o]
                s.user_id[j], s.user_conf[j], s.status[j] = old.user_id[o], old.user_conf[o], old.status[o]
            position = {o: r for r, o in enumerate(old.order)}
            s.order = sorted(range(n), key=lambda j: (-1, j) if kept[j] is None else (position.get(kept[j], j), j))

        # The review goes on where it was: at the current neuron's new row, or, when it was
        # deleted (a false detection), at the one before it, so that N goes to the one after and
        # Shift-N stays there. Set before the change is announced: the widget shows the current
        # neuron as it redraws (it showed the old row number, another neuron, and A/U/C acted on it).
        current, old_order = self.current, list(self._s.order)
        new_row = {o: j for j, o in enumerate(kept) if o is not None}
        deleted = current is not None and current not in new_row and current in old_order
        if deleted:
            current = next((o for o in reversed(old_order[: old_order.index(current)]) if o in new_row), None)
        self.current = new_row.get(current)
        self._after_deletion = deleted and self.current is not None
        self._commit(description, change, kind="structure")

    # ----- undo / redo ---------------------------------------------------------------------------
    @property
    def can_undo(self) -> bool:
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        return bool(self._redo)

    def history(self) -> list[str]:
        """Descriptions of the undoable edits, oldest first."""
        return [e.description for e in self._undo]

    def undo(self) -> str | None:
        """Undo the last edit; returns its description (None when there is nothing to undo)."""
        if not self._undo:
            return None
        edit = self._undo.pop()
        self._redo.append(edit)
        self._s = edit.before.copy()
        self._after_history_move(edit)
        return edit.description

    def redo(self) -> str | None:
        if not self._redo:
            return None
        edit = self._redo.pop()
        self._undo.append(edit)
        self._s = edit.after.copy()
        self._after_history_move(edit)
        return edit.description

    def _after_history_move(self, edit: Edit) -> None:
        structure = len(edit.before.table) != len(edit.after.table) or edit.before.table is not edit.after.table
        if self.current is not None and (self.current >= len(self) or structure):
            # Rows came back, went or moved (points deleted and as many added in one edit): the
            # current row number may now be another neuron, which A/U/C would act on
            self.current = None
        self._changed("structure" if structure else ("labelling" if edit.rows is None else "edit"), edit.rows)

    # ----- navigation ----------------------------------------------------------------------------
    def select(self, i: int | None) -> None:
        """Make ``i`` the current neuron (None: none)."""
        i = None if i is None else self._row(i)
        self._after_deletion = False
        if i != self.current:
            self.current = i
            self._changed("current", None if i is None else [i])

    def next_neuron(self, step: int = 1) -> int | None:
        """Move to the next neuron in :meth:`review_order` (lowest confidence first; wraps)."""
        order = self._s.order
        if not order:
            return None
        after_deletion, self._after_deletion = self._after_deletion, False
        if step < 0 and after_deletion and self.current in order:
            target = self.current  # the neuron before the one deleted: Shift-N goes there, not past it
        elif self.current is None or self.current not in order:
            target = order[0] if step > 0 else order[-1]
        else:
            target = order[(order.index(self.current) + step) % len(order)]
        self.current = target
        self._changed("current", [target])
        return target

    def previous_neuron(self) -> int | None:
        return self.next_neuron(-1)

    # ----- export --------------------------------------------------------------------------------
    def to_dataframe(self) -> pd.DataFrame:
        """Our CSV layout: neuron-table columns with ``label`` = final name, the review columns,
        and 0-based voxel coordinates ``x_px, y_px, z_px`` (empty when the voxel size is unknown)."""
        s = self._s
        t = s.table
        df = pd.DataFrame({c: t.xyz[:, k] for k, c in enumerate(COORDS)})
        colours = t.colours_as_read()
        for c in COLOUR_CHANNELS:
            if c in colours:
                df[c] = colours[c]
        df["label"] = self.display_names()
        df["auto_id"] = s.auto_id
        df["auto_conf"] = s.auto_conf
        for k in range(K):
            df[f"cand_{k + 1}"] = [c[k] for c in s.cand]
            df[f"prob_{k + 1}"] = s.cand_p[:, k]
        df["user_id"] = s.user_id
        df["user_conf"] = s.user_conf  # NaN -> empty cell in the CSV
        df["status"] = s.status
        if self.voxel_size_zyx is not None:
            z, y, x = self.voxel_size_zyx
            df["x_px"], df["y_px"], df["z_px"] = t.xyz[:, 0] / x, t.xyz[:, 1] / y, t.xyz[:, 2] / z
        else:
            df["x_px"] = df["y_px"] = df["z_px"] = np.nan
        for c in t.extra.columns:  # voxel coordinates written anew above (a moved neuron's were stale)
            if c not in df.columns and c not in REVIEW_COLUMNS and c not in PIXEL_COLUMNS:
                df[c] = t.extra[c].to_numpy()
        return df

    def export(self, path: str | os.PathLike, format: str = "fdlc", overwrite: bool = False) -> Path:
        """Write the reviewed names: ``format='fdlc'`` (our CSV, see :meth:`to_dataframe`) or
        ``'neuropal_id'`` (NeuroPAL_ID "Save ID Info" CSV: User ID = the user's decisions, Auto ID
        = the automatic names, 1-based internal coordinates). An existing file is replaced only
        with ``overwrite=True``."""
        if format not in EXPORT_FORMATS:
            raise FdlcError(f"export format '{format}': use 'fdlc' or 'neuropal_id'")
        if not len(self):
            raise FdlcError("no neurons to export")
        try:
            if str(path).endswith(("/", os.sep)) or Path(path).is_dir():
                raise FdlcError(f"{path}: is a folder; give a file name")
            path = Path(path)
            if self.path is not None and path.resolve() == self.path.resolve():
                # the next edit's autosave would replace the export (and the session would be gone until then)
                raise FdlcError(f"{path}: is where this session autosaves; choose another name")
            if path.exists() and not overwrite:
                raise FdlcError(f"{path}: already exists; choose another name or allow overwriting")
            if format == "fdlc":
                write_table(self.to_dataframe(), path)
            else:
                s = self._s
                t = s.table
                user = NeuronTable(t.xyz, t.colours_as_read(), labels=s.user_id, label_conf=np.nan_to_num(s.user_conf),
                                   extra=t.extra, source=t.source)  # (GFP and emphasis of a NeuroPAL_ID table read)
                # NeuroPAL_ID shows the Auto ID of a neuron without a User ID: only where the widget
                # shows it (not below the threshold, not a name a decision took elsewhere).
                shown = self.auto_shown()
                auto = [a if st != "auto" or ok else "" for a, st, ok in zip(s.auto_id, s.status, shown)]
                write_neuropal_id(user, path, self.voxel_size_zyx, auto_id=auto, auto_conf=s.auto_conf)
        except OSError as exc:
            raise FdlcError(f"{path}: cannot be written ({exc.strerror or exc})") from None
        return path


# ---------------------------------------------------------------------------------------------
# helpers


def _review_order(s: _State) -> list[int]:
    """Rows in review order: the least confident automatic names first (a labelled session),
    else the table's."""
    if not s.labelled:
        return list(range(len(s.table)))
    conf = np.array([c if a else 0.0 for a, c in zip(s.auto_id, s.auto_conf)])
    return [int(i) for i in np.argsort(conf, kind="stable")]


def _known_settings(raw) -> dict:
    """A session file's settings with those of the wrong kind left out (as if never saved): the
    decisions still load, and a damaged entry cannot stop the image from opening."""
    settings = dict(raw) if isinstance(raw, dict) else {}
    shape = settings.get("image_shape")
    if shape is not None and not (isinstance(shape, list) and len(shape) == 3
                                  and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in shape)):
        del settings["image_shape"]
    if not isinstance(settings.get("layer_name", ""), str):
        del settings["layer_name"]
    if not isinstance(settings.get("voxel_size_set", False), bool):
        del settings["voxel_size_set"]
    return settings


def _check_voxel_size(voxel) -> tuple[float, float, float] | None:
    """Three finite positive numbers (µm), or None (unknown). A session saved with a zero voxel
    size could not be loaded again (its decisions out of reach) and exported x_px = inf."""
    if voxel is None:
        return None
    try:
        values = tuple(float(v) for v in voxel)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) and v > 0 for v in values):
        raise FdlcError(f"voxel_size_zyx {voxel!r} is not three positive numbers (µm)")
    return values


def _image_of(session_path: Path) -> str:
    """The image a session file beside it belongs to (``worm.tif`` for
    ``worm.tif.fdlc-session.json``), where find_session looks; else the file itself."""
    text = str(session_path)
    return text[: -len(SESSION_SUFFIX)] if text.endswith(SESSION_SUFFIX) else text


def _threshold_or_default(t) -> float:
    """A session file's threshold; one of the wrong kind is ignored, as its other settings are
    (it made the whole file 'damaged', its decisions set aside)."""
    try:
        return _check_threshold(t)
    except FdlcError:
        return DEFAULT_THRESHOLD


def _agreeing_decisions(s) -> None:
    """Make a hand-edited file's decisions say one thing: a name written ``AVAL?`` is the name
    AVAL, unsure; a status follows the name (a name with status 'auto' is a decision, a decision
    without a name is none) and the confidence the status. What the session showed and what it
    exported disagreed (``AVAL??`` shown, an 'auto' name blocking it for every other neuron)."""
    for i, (raw, st) in enumerate(zip(s.user_id, s.status)):
        name, conf = parse_name(raw)
        if not name:
            s.user_id[i], s.user_conf[i], s.status[i] = "", np.nan, "auto"
            continue
        if conf == UNSURE_CONF or st == "unsure":
            st = "unsure"
        elif st not in ("accepted", "corrected"):
            st = "accepted" if name == s.auto_id[i] else "corrected"
        s.user_id[i], s.status[i] = name, st
        s.user_conf[i] = UNSURE_CONF if st == "unsure" else 1.0


def _check_threshold(t) -> float:
    try:
        t = float(t)
    except (TypeError, ValueError):
        raise FdlcError(f"threshold {t!r}: give a number between 0 and 1") from None
    if not 0.0 <= t <= 1.0:
        raise FdlcError(f"threshold {t}: give a number between 0 and 1")
    return t


def _same(a: _State, b: _State) -> bool:
    return (
        a.table is b.table
        and a.auto_id == b.auto_id
        and a.user_id == b.user_id
        and a.status == b.status
        and a.cand == b.cand
        and a.order == b.order
        and a.labelled == b.labelled
        and np.array_equal(a.auto_conf, b.auto_conf, equal_nan=True)
        and np.array_equal(a.user_conf, b.user_conf, equal_nan=True)
        and np.array_equal(a.cand_p, b.cand_p, equal_nan=True)
    )


def _floats(values) -> list:
    return [None if not math.isfinite(float(v)) else float(v) for v in np.asarray(values, dtype=float)]


def _nan(values) -> list:
    return [np.nan if v is None else v for v in values]


def _json_safe(value):
    """``value`` (free-form settings) with numpy numbers as Python ones and non-finite numbers
    as null, so that the session's JSON can always hold it."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return _json_value(value)


def _json_value(v):
    if v is None:
        return None
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(float(v)) else None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, str)):
        return v
    return str(v)
