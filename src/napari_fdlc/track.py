"""Track neurons through a sequence of volumes of one moving worm (``fdlc track``).

Every volume is matched to one or several *reference* volumes of the same worm with the fDLC
model and the one-to-one assignment of :mod:`napari_fdlc.match`; a neuron's **track ID** is the
index of its partner in the first reference (references after the first are matched to the
first once, so they share its IDs; their neurons it lacks get new IDs after its last). When the
reference is labelled, each track also carries the reference neuron's name.

Speed comes from the worm moving smoothly. Consecutive volumes share their orientation and
nearly their pose, so only the first volume gets the full search (registration onto the
reference, :mod:`napari_fdlc.register`, and the model's choice of chirality, as ``fdlc label``
does); every later volume is *placed* in the reference's frame by a
:class:`Warp` (an affine map plus a smooth non-rigid displacement) carried over from the volume
before it. With ``placement="geometry"`` (default) the warp is carried by a cheap geometric chain
(no model; about a millisecond per volume): place with the previous warp, pair with the
reference by the one-to-one assignment on distance, refit, a few rounds (ICP-like). The chain
does not depend on the model's answers, so the model then sees a whole chunk of ``chunk``
volumes as one batch, and the result does not depend on the chunk size. A volume where fewer
than ``lost_fraction`` of the neurons pair up, whose pairs lie ``residual_ratio`` times further
apart than the last volumes', or whose tracking-model match rate falls below
``research_ratio`` of the first volume's (a jump) gets the full search again and the
chain restarts from it (or, where the search fits worse, from its own warp turned about the
optical axis). Placed volumes go through the *tracking model* (``follow_with``:
the small model trained on exactly these placements, ``train.tracking_example``; the full
searches use the identification model). Its log-probabilities (plus colour) are fused with a
same-worm position likelihood (``position_sigma_um``: within one recording a neuron stays where
the warp puts it, up to segmentation jitter) and the
one-to-one assignment gives the track IDs. ``refine_steps`` more model passes re-place each
volume by the warp fitted on its own answer. With ``placement="model"`` the warp comes from the
model's answer for the last volume of the chunk before instead (no geometric chain).

``search="full"`` runs the full search (what ``fdlc label`` does) on every volume instead.
For comparison, ``method="cpd"`` tracks with the classical CPD baseline (the first volume
searched in every orientation, then each volume registered from the one before) and
``method="geometry"`` with the geometric chain alone (no model: an ablation).

:func:`simulate_sequence` makes synthetic sequences with known tracks: the worm's pose (bend,
roll, rotation and position in XY, scale) changes smoothly over time, and each volume gets its own
segmentation noise (dropped neurons, spurious detections, position jitter).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from ._blas import one_blas_thread
from .errors import FdlcError, TableError, warn
from .geometry import Warp, canonical_frame, fit_warp, position_evidence, squared_distances
from .match import assign, assign_log, min_cost_matching
from .simulate import bend, copied_colours
from .table import COORDS, NeuronTable, file_line, read_table, read_volume, repeated_names, with_unique_names

UNTRACKED = -1
# The residual test of a jump (TrackSettings.residual_ratio): the volumes its yardstick is the
# median over, the fewest it needs (before, the floor stands in: a turn at t = 1 was never
# caught), and a residual that is never a jump (a jitter-free recording's near-zero residuals
# would otherwise make any change one).
RESIDUAL_WINDOW, RESIDUAL_HISTORY, RESIDUAL_FLOOR_UM = 8, 3, 1.0


@dataclass
class TrackSettings:
    search: str = "propagate"  # "propagate" (pose from the previous volume) or "full"
    refine_steps: int = 0  # model passes per volume after the first, each re-placed by its own warp
    chunk: int = 16  # volumes that go through the model as one batch
    lost_fraction: float = 0.5  # placement "geometry": full search again when fewer neurons than this pair up
    research_ratio: float = 0.5  # full search again when the match rate < this × the first volume's
    # placement "geometry": full search again when the chain's median pair distance exceeds
    # this × its median over the last RESIDUAL_WINDOW volumes (and RESIDUAL_FLOOR_UM). A 45° turn
    # or a 10 µm shift pairs most neurons with a neighbour about 3 µm off, against 0.4-1 µm
    # before; neither the pairs nor the match rate fell far enough (session 34: a 45° turn was
    # tracked ~10 % right from there on). 2, not 3: at 3× motion a wrong placement lay only
    # 2.5-3.3 times as far as the usual.
    residual_ratio: float = 2.0
    use_colour: bool = True
    # Whether the model that follows takes the volumes' colours as an input too (the colour
    # likelihood is fused either way). Off: colours read from each volume of a recording vary
    # more than the 5 % the tracking model saw in training, and on rendered recordings it then
    # tracked 93 % of detections instead of 99 % (benchmarks/tracking_from_images.py, tracking.md).
    follower_colour_input: bool = False
    combine: str = "best"  # several references: "best" (the one the model matches best) or "mean"
    no_match_weight: float = 0.2  # see match.assign
    # Width of the smooth non-rigid part of the propagated warp (0: affine only) and the ridge on
    # it. 30 µm and 0.1 (session 6; were 20 and 0.3) were chosen on synthetic sequences of other
    # seeds than the benchmark's (a wider, less stiff displacement follows the bending body): at
    # 3× motion on the confirming seeds, geometry alone 94.7 -> 96.8 %, fdlc 95.1 -> 97.3 %.
    warp_sigma_um: float = 30.0
    warp_smoothness: float = 0.1
    warp_min_prob: float = 0.1  # matches less likely than this do not shape the warp
    placement: str = "geometry"  # "geometry": cheap sequential pre-placement, then one model batch per chunk; "model"
    gate_um: float = 6.0  # geometric pre-placement: farther pairs stay unpaired
    # Pair-and-fit rounds of the geometric pre-placement (it stops when the pairs stop
    # changing). 8 (session 8; was 3) was chosen on recordings of the corpus's validation
    # worms, not the benchmark's: 40 volumes at 1× and 3× motion, positions only, geometry alone
    # 91.7 -> 94.8 (5) -> 95.1 % (8), for 15 % more time.
    geometry_iterations: int = 8
    position_sigma_um: float = 1.0  # same-worm position likelihood fused (0: model alone; off with placement="model")
    # Which model answers for the volumes placed from the one before: "tracking", the small
    # model trained on exactly that (fdlc_tracking, train.tracking_example), or "full", the
    # identification model. Full searches (the first volume, a lost one) always use the latter.
    follow_with: str = "tracking"

    def check(self) -> None:
        if self.search not in ("propagate", "full"):
            raise FdlcError(f"unknown search '{self.search}' (use propagate or full)")
        if self.combine not in ("best", "mean"):
            raise FdlcError(f"unknown combine '{self.combine}' (use best or mean)")
        for name, least in (("refine_steps", 0), ("chunk", 1), ("geometry_iterations", 0)):
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < least:
                raise FdlcError(f"{name.replace('_', ' ')} must be a whole number of at least {least} (got {value!r})")
        # NaN or a negative width passed before: NaN was ignored, -5 µm changed the tracks silently
        ranges = {"lost_fraction": (0, 1), "research_ratio": (0, 1), "warp_min_prob": (0, 1), "residual_ratio": (1, np.inf),
                  "warp_sigma_um": (0, np.inf), "warp_smoothness": (0, np.inf), "position_sigma_um": (0, np.inf)}
        for name, (low, high) in ranges.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not low <= value <= high \
                    or not np.isfinite(value):
                span = f"from {low} to {high:g}" if np.isfinite(high) else f"of at least {low}"
                raise FdlcError(f"{name} must be a finite number {span} (got {value!r})")
        for name in ("gate_um", "no_match_weight"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) or not 0 < value < np.inf:
                raise FdlcError(f"{name} must be a positive number (got {value!r})")
        if self.placement not in ("geometry", "model"):
            raise FdlcError(f"unknown placement '{self.placement}' (use geometry or model)")
        if self.follow_with not in ("tracking", "full"):
            raise FdlcError(f"unknown follow_with '{self.follow_with}' (use tracking or full)")


@dataclass
class Sequence:
    """Volumes of one recording in time order."""

    volumes: list[NeuronTable]
    times: list  # the time value of each volume (the CSV's t, or 0..T-1 for a folder)
    sources: list[str] = field(default_factory=list)  # file per volume ('' for a t-column CSV)

    def __len__(self) -> int:
        return len(self.volumes)


@dataclass
class TrackResult:
    track_id: list[np.ndarray]  # per volume, (N_t,) track ID per neuron, -1 = untracked
    confidence: list[np.ndarray]  # per volume, probability of the ID given (or of "untracked")
    names: list[str]  # name of each track ID ('' = unnamed)
    info: list[dict]  # per volume: reference used, match rate, whether searched in full
    times: list = field(default_factory=list)
    sources: list[str] = field(default_factory=list)

    def frame(self, volumes: list[NeuronTable]) -> pd.DataFrame:
        """One row per neuron per time point, in input order within each time point:
        ``t, neuron_index, x_um, y_um, z_um, track_id, track_conf`` (+ ``name`` when a reference
        is labelled, + ``file`` for a folder of CSVs)."""
        times = self.times or list(range(len(volumes)))
        parts = []
        named = any(self.names)
        for k, vol in enumerate(volumes):
            n = len(vol)
            df = pd.DataFrame({"t": [times[k]] * n, "neuron_index": np.arange(n)})
            for i, c in enumerate(COORDS):
                df[c] = vol.xyz[:, i]
            df["track_id"] = self.track_id[k]
            df["track_conf"] = np.round(self.confidence[k], 6)
            if named:
                df["name"] = [self.names[i] if i >= 0 else "" for i in self.track_id[k]]
            if self.sources and self.sources[k]:
                df["file"] = self.sources[k]
            parts.append(df)
        return pd.concat(parts, ignore_index=True)


# ----------------------------------------------------------------------------------------------
# Reading a sequence

def _natural_key(name: str):
    # isdecimal, not isdigit: '²' is a digit that int() refuses (and \d does not split on)
    return [int(s) if s.isdecimal() else s.lower() for s in re.split(r"(\d+)", name)]


_ONE_PER_FILE = "each file of a folder or list of CSVs is one volume: give a table of several time points alone"


def read_sequence(paths: list[str] | str) -> Sequence:
    """A sequence from one CSV with a ``t`` column, a folder of CSVs (one volume each, in natural
    name order: ``t2`` before ``t10``), or several CSVs (in the order given)."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    if not paths:
        raise FdlcError("no input: give a CSV with a t column or a folder of CSVs")
    if len(paths) == 1:
        path = Path(paths[0])
        if path.is_dir():
            # hidden files are left out: e.g. macOS's "._name.csv" beside every copied file
            files = sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() == ".csv" and not p.name.startswith(".")),
                           key=lambda p: (_natural_key(p.name), p.name))  # t1 and t01: by name, not by listing
            if not files:
                raise FdlcError(f"{path}: the folder holds no .csv file")
            return _files_sequence(files)
        return split_by_time(read_table(path, unique_names=False))  # a name once per time point
    missing = [p for p in paths if Path(p).is_dir()]
    if missing:
        raise FdlcError(f"{missing[0]}: a folder can only be given alone")
    return _files_sequence([Path(p) for p in paths])


def _files_sequence(files: list[Path]) -> Sequence:
    volumes = [read_volume(f, _ONE_PER_FILE, unique_names=False) for f in files]
    _unique_names_once(volumes, [f.name for f in files], "file(s)", str(files[0].parent))
    return Sequence(volumes, list(range(len(files))), [f.name for f in files])


def _unique_names_once(volumes: list[NeuronTable], keys: list[str], unit: str, where: str) -> None:
    """Each volume's repeated names left on none of its rows (as one volume is read), said in
    one line for the whole sequence, not once per volume."""
    repeated = {}
    for volume, key in zip(volumes, keys):
        names = repeated_names(volume.labels)
        if names:
            repeated[key] = names
            with_unique_names(volume, say=False)
    if repeated:
        warn(f"{where}: name(s) {', '.join(sorted(set().union(*repeated.values()))[:8])} occur more than once within "
             f"{len(repeated)} {unit} (the first {next(iter(repeated))}); those rows are read as unnamed")


def split_by_time(table: NeuronTable) -> Sequence:
    """Split a table with a ``t`` column into its time points (sorted by t)."""
    name = table.source
    if "t" not in table.extra.columns:
        raise TableError(f"{name}: no 't' column (a sequence is one CSV with a t column, or a folder of CSVs)")
    raw = table.extra["t"].astype(str).str.strip()
    t = pd.to_numeric(raw.where(raw != "", "nan"), errors="coerce").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(t)
    if bad.any():
        row = int(np.argmax(bad))
        raise TableError(f"{name}: line {file_line(table.text, row)}, column 't': {raw.iloc[row] or 'an empty cell'} "
                         "is not a finite number")
    if raw.str.fullmatch(r"[+-]?\d+").all():
        # whole numbers (frame numbers, timestamps in ns) compared exactly: beyond 2**53 two of
        # them can be one float
        t = np.array([int(v) for v in raw], dtype=object)
    values, group = np.unique(t, return_inverse=True)
    group = np.asarray(group).ravel()
    rows_by_time = np.split(np.argsort(group, kind="stable"), np.cumsum(np.bincount(group, minlength=len(values)))[:-1])
    volumes, times = [], []
    for v, rows in zip(values, rows_by_time):
        sub = table.subset(rows)
        sub.extra = sub.extra.drop(columns=["t"])
        sub.source = f"{name} (t={_time_value(v)})"
        volumes.append(sub)
        times.append(_time_value(v))
    _unique_names_once(volumes, [f"t={t}" for t in times], "time point(s)", name)
    return Sequence(volumes, times, [""] * len(volumes))


def join_by_time(volumes: list[NeuronTable], times: list | None = None) -> pd.DataFrame:
    """One table with a ``t`` column in front (default t = 0, 1, …) from a table per time
    point: what :func:`split_by_time` splits again."""
    times = list(range(len(volumes))) if times is None else list(times)
    if len(times) != len(volumes):  # zip would drop the volumes beyond the times
        raise FdlcError(f"{len(times)} times for {len(volumes)} volumes: give one time per volume")
    frames = []
    for t, volume in zip(times, volumes):
        df = volume.to_dataframe().drop(columns=["t"], errors="ignore")
        df.insert(0, "t", t)
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


def other_columns(sequence: "Sequence") -> pd.DataFrame:
    """Each neuron's own columns per time point beside what a track result writes
    (:meth:`TrackResult.frame`): colours, GFP (the activity trace of its track), a user's. An
    earlier run's track columns (its name, track, file) are not this run's and are left out."""
    df = join_by_time(sequence.volumes, sequence.times)
    written = ("t", "neuron_index", *COORDS, "label", "track_id", "track_conf", "name", "file")
    return df.drop(columns=[c for c in written if c in df.columns])


def _time_value(v: float):
    return int(v) if float(v).is_integer() else float(v)


# ----------------------------------------------------------------------------------------------
# Tracking

class _Reference:
    def __init__(self, table: NeuronTable, ids: np.ndarray):
        self.table = table
        self.xyz, _, _ = canonical_frame(table.xyz)
        self.ids = ids  # track ID of each of its neurons
        self.warp: Warp | None = None  # the last volume's recording µm -> this reference's frame
        self.first_rate = None  # the following model's match rate on the first volume (placement "model")
        self.residuals: list[float] = []  # the geometric chain's residual on the last volumes it placed


def _match_rate(log_p: np.ndarray, matchable: bool = False) -> float:
    """Geometric mean over test neurons of p(matched): how willing the model is to match this
    placement (the model puts its mass on "no match" when the worms are not aligned). With
    ``matchable``, over the likeliest as many as the reference has: the yardstick of a jump,
    where a volume with more neurons than its reference (neurons the first volume lacked) must
    not look like one. (Over every neuron it chooses better between references.)"""
    return _match_rates(log_p)[1 if matchable else 0]


def _match_rates(log_p: np.ndarray) -> tuple[float, float]:
    """:func:`_match_rate` over every neuron and over the matchable ones, from one pass."""
    matched = np.log1p(-np.exp(np.minimum(log_p[:, -1], -1e-6)))
    if not len(matched):
        return 0.0, 0.0
    can = log_p.shape[1] - 1
    best = np.sort(matched)[len(matched) - can:] if len(matched) > can else matched
    return float(np.exp(matched.mean())), float(np.exp(best.mean())) if len(best) else 0.0


def _finish(identifier, ref: _Reference, volume: NeuronTable, out: tuple, s: TrackSettings, fit: bool = True) -> dict:
    """Calibrated, colour-fused log p, its one-to-one assignment onto the reference's neurons,
    and (``fit``) the warp that carries this volume onto the reference, fitted on the assignment."""
    lp, placed, saw = out
    rate, jump_rate = _match_rates(lp)
    # log likelihood ratios on the real columns, fused with the calibrated answer in one renormalisation
    evidence = identifier._colour_evidence(ref.table, volume, model_saw_colour=saw) if s.use_colour else None
    # with placement="model" the placement is the last chunk's (up to `chunk` volumes old):
    # a likelihood centred on it pulled neurons onto wrong partners (36 % tracked at 1x motion)
    if s.position_sigma_um > 0 and s.placement != "model":
        near = position_evidence(placed, ref.xyz, s.position_sigma_um)
        evidence = near if evidence is None else np.add(evidence, near, out=near)
    lp = identifier._calibrate(lp, evidence)
    choice = assign_log(lp, s.no_match_weight)
    matched = choice >= 0
    weight = np.where(matched, np.exp(lp[np.arange(len(lp)), np.maximum(choice, 0)]), 0.0)
    weight[weight < s.warp_min_prob] = 0.0
    target = ref.xyz[np.maximum(choice, 0)]
    warp = fit_warp(volume.xyz, target, weight, s.warp_sigma_um, s.warp_smoothness) if fit else None
    return {"log_p": lp, "choice": choice, "warp": warp, "rate": rate, "jump_rate": jump_rate}


def _full_search(identifier, ref: _Reference, volumes: list[NeuronTable], s: TrackSettings) -> list[tuple]:
    """(log p, placement, whether the model saw colour) of each volume found as ``fdlc label``
    finds it (no refinement)."""
    found, _ = identifier.search(ref.table, volumes, s.use_colour, refine_steps=0)
    return [(f["log_p"], f["moved"], identifier._takes_colour([ref.table, v], s.use_colour)) for f, v in zip(found, volumes)]


def _placed(identifier, ref: _Reference, volumes: list[NeuronTable], warps: list[Warp], s: TrackSettings) -> list[tuple]:
    """(log p, placement, whether the model saw colour) of each volume placed in the reference
    frame by its warp, as one batch."""
    tc, sc = identifier._model_colours(ref.table, volumes, s.use_colour and s.follower_colour_input)
    extra = () if tc is None else (tc, sc)
    placed = [w(v.xyz) for v, w in zip(volumes, warps)]
    return [(lp, xyz, tc is not None) for lp, xyz in zip(identifier._forward_many(ref.xyz, placed, *extra), placed)]


def _geometric_step(ref: _Reference, volume: NeuronTable, warp: Warp, s: TrackSettings, pairs: bool = False):
    """Cheap placement of the next volume (no model): place it with the previous warp, pair it
    with the reference by the one-to-one assignment on squared distance (pairs further apart
    than ``gate_um`` stay unpaired), and fit its own warp on those pairs. With ``pairs``,
    returns (warp, partner index per neuron or -1)."""
    n = len(volume)
    choice = np.full(n, UNTRACKED)
    gate = np.full(n, s.gate_um**2)
    for _ in range(max(1, s.geometry_iterations)):  # ICP-like: pair, fit, pair again
        previous = choice
        choice = min_cost_matching(squared_distances(warp(volume.xyz), ref.xyz), gate)
        paired = choice >= 0
        if paired.sum() < 4 or np.array_equal(choice, previous):
            break  # converged: the warp was fitted on these very pairs
        target = ref.xyz[np.maximum(choice, 0)]
        warp = fit_warp(volume.xyz, target, paired.astype(float), s.warp_sigma_um, s.warp_smoothness)
    return (warp, choice) if pairs else warp


def _match_chunk(identifier, follower, ref: _Reference, chunk: list[NeuronTable], s: TrackSettings) -> list[dict]:
    """Match a chunk of consecutive volumes to one reference; updates the reference's warp.
    Full searches use ``identifier``; volumes placed from the one before, ``follower``.

    The very first volume (every volume with ``search="full"``) gets the full
    search. With ``placement="geometry"`` each later volume is placed by the geometric chain
    (:func:`_geometric_step` from the volume before), which does not depend on how volumes are
    chunked; with ``placement="model"`` by the warp fitted on the model's answer for the last
    volume of the chunk before. Then ``refine_steps`` re-placements by each volume's own warp,
    fitted on its own answer."""
    found: list[dict | None] = [None] * len(chunk)
    searched = [False] * len(chunk)
    last = len(chunk) - 1
    if s.search == "full" or ref.warp is None:
        # a volume without neurons has nothing to search with: the first one with neurons is
        # searched (every one, with search="full")
        with_neurons = [i for i in range(len(chunk)) if len(chunk[i])]
        first = with_neurons if s.search == "full" else with_neurons[:1]
        for i, out in zip(first, _full_search(identifier, ref, [chunk[i] for i in first], s)):
            found[i] = _finish(identifier, ref, chunk[i], out, s)
            searched[i] = True
        if ref.warp is None and first:
            ref.warp = found[first[0]]["warp"]
        if ref.first_rate is None and first:
            # the yardstick for "lost" below, from the model that answers those volumes
            ref.first_rate = _match_rate(_placed(follower, ref, [chunk[first[0]]], [ref.warp], s)[0][0], matchable=True)
    for i in range(len(chunk)):
        if found[i] is None and not len(chunk[i]):  # no rows to answer
            found[i] = {"log_p": np.zeros((0, len(ref.xyz) + 1)), "choice": np.zeros(0, dtype=int),
                        "warp": ref.warp, "rate": 0.0, "jump_rate": 0.0, "searched": False}
    if ref.warp is None:  # no volume with neurons yet: the next chunk searches
        return found
    rest = [i for i in range(len(chunk)) if found[i] is None]
    chain = ref.warp
    # each chained volume's residual, read in volume order so that the chunk size (and chaining
    # part of a chunk again) does not change the yardstick
    earlier, residual = list(ref.residuals), {}

    def geometric_chain(indices: list[int], chain: Warp) -> list[Warp]:
        """Each volume placed from the one before. One the chain loses (it pairs under
        ``lost_fraction`` of the neurons it could pair) or places far worse than the volumes
        before (``residual_ratio``) has jumped: it is searched in full, and where that still
        fits badly, placed again from the chain turned about the optical axis (a worm turning
        on the slide); the chain goes on from whichever placement fits best."""
        warps = []
        for i in indices:
            pairable = max(1, min(len(chunk[i]), len(ref.xyz)))  # a smaller reference pairs fewer

            def placed_from(start: Warp) -> tuple[Warp, tuple[float, float]]:
                warp, choice = _geometric_step(ref, chunk[i], start, s, pairs=True)
                return warp, _fit(ref, chunk[i], warp, choice, pairable)

            warp, fit = placed_from(chain)
            recent = (earlier + [residual[j] for j in rest if j < i])[-RESIDUAL_WINDOW:]
            # too short a history (the first chained volumes): the floor as the usual residual
            usual = float(np.median(recent)) if len(recent) >= RESIDUAL_HISTORY else RESIDUAL_FLOOR_UM
            limit = max(s.residual_ratio * usual, RESIDUAL_FLOOR_UM)

            def jumped(fit) -> bool:
                return fit[0] < s.lost_fraction or fit[1] > limit

            searched[i] = False
            if jumped(fit):
                out = _full_search(identifier, ref, [chunk[i]], s)[0]
                again, fit2 = placed_from(_finish(identifier, ref, chunk[i], out, s)["warp"])
                if _fits_better(fit2, fit):
                    warp, fit, searched[i] = again, fit2, True
            if jumped(fit):
                for start in _turned_starts(ref, chunk[i], chain, s):
                    again, fit2 = placed_from(start)
                    if _fits_better(fit2, fit):
                        warp, fit, searched[i] = again, fit2, False
            residual[i] = fit[1]
            chain = warp
            warps.append(warp)
        return warps

    if rest:
        if s.placement == "geometry":
            warps = geometric_chain(rest, chain)
            chain = warps[-1]
        else:
            warps = [ref.warp] * len(rest)
        outs = _placed(follower, ref, [chunk[i] for i in rest], warps, s)
        # A warp of the volume's own is needed only to re-place it (refine steps) or, with
        # placement="model", to start the next chunk from (the last volume).
        own = s.refine_steps > 0 or s.placement == "model"
        for i, out in zip(rest, outs):
            found[i] = _finish(follower, ref, chunk[i], out, s, fit=own and (i == last or s.refine_steps > 0))
        if s.placement == "geometry":
            # A jump the geometric chain still pairs up (in a dense head a wrong placement pairs
            # most neurons with some neighbour: a 45° turn, a 10 µm shift) shows in the model's
            # match rate: that volume is searched in full, and the chain goes on from it.
            for k, i in enumerate(rest):
                if searched[i] or found[i]["jump_rate"] >= s.research_ratio * ref.first_rate:
                    continue
                again = _finish(identifier, ref, chunk[i], _full_search(identifier, ref, [chunk[i]], s)[0], s)
                # judged by the model that answered the chained placement (rates of two models
                # do not compare): the follower at the searched placement
                rate = _match_rate(_placed(follower, ref, [chunk[i]], [again["warp"]], s)[0][0], matchable=True)
                if rate <= found[i]["jump_rate"]:
                    continue
                found[i], searched[i], chain = again, True, again["warp"]
                later = rest[k + 1:]
                if later:  # the rest of the chunk chained again from there, as the first pass did
                    warps = geometric_chain(later, chain)
                    chain = warps[-1]
                    for j, out in zip(later, _placed(follower, ref, [chunk[j] for j in later], warps, s)):
                        found[j] = _finish(follower, ref, chunk[j], out, s, fit=own and (j == last or s.refine_steps > 0))
        if s.placement == "model":
            lost = [i for i in rest if found[i]["jump_rate"] < s.research_ratio * ref.first_rate]
            for i, out in zip(lost, _full_search(identifier, ref, [chunk[i] for i in lost], s)):
                again = _finish(identifier, ref, chunk[i], out, s)
                if again["rate"] > found[i]["rate"]:
                    found[i], searched[i] = again, True
    placed = [k for k in range(len(chunk)) if len(chunk[k])]
    for step in range(s.refine_steps):
        outs = _placed(follower, ref, [chunk[k] for k in placed], [found[k]["warp"] for k in placed], s)
        more = step < s.refine_steps - 1
        for k, out in zip(placed, outs):
            found[k] = _finish(follower, ref, chunk[k], out, s, fit=more or k == last)
    for f, flag in zip(found, searched):
        f["searched"] = flag
    # the next chunk chains from the warp this one's chain would go on with: the first volume's
    # unrefined one when it is the chunk's only volume placed, as within one chunk
    if s.placement == "model" or (not rest and s.search == "full"):
        ref.warp = found[last]["warp"]
    else:
        ref.warp = chain
    ref.residuals = (earlier + [residual[j] for j in rest if j in residual])[-RESIDUAL_WINDOW:]
    return found


def _fit(ref: _Reference, volume: NeuronTable, warp: Warp, choice: np.ndarray, pairable: int) -> tuple[float, float]:
    """How well the geometric chain placed a volume: the fraction of the neurons it could pair
    that it paired, and their median distance (µm) to their partners after its warp (about the
    segmentation jitter while the chain follows the worm)."""
    paired = choice >= 0
    if not paired.any():
        return 0.0, float("inf")
    distance = np.linalg.norm(warp(volume.xyz[paired]) - ref.xyz[choice[paired]], axis=1)
    return paired.sum() / pairable, float(np.median(distance))


def _fits_better(a: tuple[float, float], b: tuple[float, float], slack: float = 0.05) -> bool:
    """Placement fit ``a`` beats ``b``: clearly more pairs, or about as many (a wrong placement
    in a dense head pairs most neurons with some neighbour) lying nearer their partners."""
    return a[0] > b[0] + slack or (a[0] >= b[0] - slack and a[1] < b[1])


TURNS_DEG = tuple(range(0, 360, 30))


def _turned_starts(ref: _Reference, volume: NeuronTable, chain: Warp, s: TrackSettings) -> list[Warp]:
    """Warps that place the volume as the chain did after turning it about the optical axis
    (z) through its centroid by each of ``TURNS_DEG`` and moving its centroid onto the
    reference's (the turn 0: a sudden shift): starts for the chain after a jump, which keep
    the bend the chain has followed so far (a full search starts from the straight atlas pose,
    and found a bent worm's turn far less often)."""
    centre, starts = volume.xyz.mean(0), []
    for degrees in TURNS_DEG:
        a = np.radians(degrees)
        about_z = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        placed = chain((volume.xyz - centre) @ about_z.T + centre)
        placed += ref.xyz.mean(0) - placed.mean(0)
        starts.append(fit_warp(volume.xyz, placed, np.ones(len(volume)), s.warp_sigma_um, s.warp_smoothness))
    return starts


def _id_probs(found: dict, ref: _Reference, n_ids: int) -> np.ndarray:
    p = np.exp(found["log_p"][:, :-1])
    out = np.zeros((len(p), n_ids))
    np.add.at(out.T, ref.ids, p.T)
    return out


def _link_references(identifier, follower, tables: list[NeuronTable], s: TrackSettings) -> list[np.ndarray]:
    """Track IDs of every reference's neurons: the first reference's indices; the others are
    matched to the first once (full search, then re-placed by their own warp twice; one-to-one),
    and what it lacks gets new IDs."""
    from dataclasses import replace

    first = tables[0]
    ids = [np.arange(len(first))]
    next_id = len(first)
    for table in tables[1:]:
        link = replace(s, search="full", refine_steps=max(2, s.refine_steps),
                       use_colour=s.use_colour and _has_colour(first, table))
        own = _match_chunk(identifier, follower, _Reference(first, ids[0]), [table], link)[0]["choice"].copy()
        new = np.flatnonzero(own < 0)
        own[new] = next_id + np.arange(len(new))
        next_id += len(new)
        ids.append(own)
    return ids


def _has_colour(a: NeuronTable, b: NeuronTable) -> bool:
    from .colour import shared_channels

    return bool(shared_channels(a, b))


@one_blas_thread
def track(
    volumes: list[NeuronTable] | Sequence,
    references: list[NeuronTable] | None = None,
    identifier=None,
    settings: TrackSettings | None = None,
    progress: Callable[[int, int], None] | None = None,
    method: str = "fdlc",
    follower=None,
) -> TrackResult:
    """Track IDs (and names, when a reference is labelled) for every neuron of every volume.

    ``references`` default to the first volume. ``progress(done, total)`` is called after each
    chunk of volumes. ``identifier`` (default: the shipped model) makes the full searches;
    ``follower`` answers for the volumes placed from the one before (default: the shipped
    tracking model, or ``identifier`` with ``follow_with="full"``).
    """
    seq = volumes if isinstance(volumes, Sequence) else Sequence(list(volumes), list(range(len(volumes))))
    s = settings or TrackSettings()
    s.check()
    if method not in ("fdlc", "cpd", "geometry"):
        raise FdlcError(f"unknown method '{method}' (use fdlc, cpd or geometry)")
    if len(seq) == 0:
        raise FdlcError("the sequence has no volume")
    tables = list(references) if references else [seq.volumes[0]]
    if any(len(t) == 0 for t in tables):
        raise FdlcError("a reference volume has no neurons" if references else
                        "the first volume has no neurons: give a reference volume that has (--reference-t)")
    if method != "fdlc" and len(tables) > 1:  # the baselines follow one volume: the others' names would be lost
        raise FdlcError(f"method {method} takes one reference (got {len(tables)})")
    if method == "cpd":
        return _track_cpd(seq, tables, s, progress)
    if method == "geometry":
        return _track_geometry(seq, tables, s, progress)
    if identifier is None:
        from .identify import default_identifier

        identifier = default_identifier()
    if follower is None:
        from .identify import default_tracker

        follower = identifier if s.follow_with == "full" else default_tracker(identifier.device)
    ids = _link_references(identifier, follower, tables, s)
    refs = [_Reference(t, i) for t, i in zip(tables, ids)]
    n_ids = int(max(i.max() for i in ids)) + 1
    names = [""] * n_ids
    given = set()
    for ref in refs:  # the first reference's names win, on a track and for a name
        for i, n in zip(ref.ids, ref.table.label_strings()):  # an unsure name keeps its "?"
            if n and not names[i] and n.rstrip("?") not in given:
                names[i] = n
                given.add(n.rstrip("?"))
    result = TrackResult([], [], names, [], list(seq.times), list(seq.sources))
    total = len(seq)
    for start in range(0, total, s.chunk):
        chunk = seq.volumes[start : start + s.chunk]
        # Colour is used where a volume and the reference share a channel: each volume's colour
        # evidence checks its own (a chunk's first volume does not decide for the chunk, so
        # that the chunk size does not change the answers).
        per_ref = [_match_chunk(identifier, follower, ref, chunk, s) for ref in refs]
        for k in range(len(chunk)):
            found = [pr[k] for pr in per_ref]
            if s.combine == "best" or len(refs) == 1:
                # The assignment onto the best-matched reference's own neurons is the answer (IDs
                # relabel them); a neuron it leaves untracked (one that reference lacks) takes the
                # ID another reference gives it, if no neuron has it yet.
                order = np.argsort([-f["rate"] for f in found], kind="stable")
                used = int(order[0])
                tid, conf = _ids_from(found[used], refs[used])
                for other in order[1:]:
                    more, more_conf = _ids_from(found[other], refs[other])
                    fill = (tid == UNTRACKED) & (more != UNTRACKED) & ~np.isin(more, tid)
                    tid, conf = np.where(fill, more, tid), np.where(fill, more_conf, conf)
            else:
                probs = np.mean([_id_probs(f, ref, n_ids) for f, ref in zip(found, refs)], axis=0)
                used = -1
                tid, conf = _assign_ids(probs, s.no_match_weight)
            result.track_id.append(tid)
            result.confidence.append(conf)
            result.info.append({"reference": used, "match_rate": [f["rate"] for f in found],
                                "searched": [f["searched"] for f in found]})
        if progress is not None:
            progress(min(start + s.chunk, total), total)
    return result


def _ids_from(found: dict, ref: _Reference) -> tuple[np.ndarray, np.ndarray]:
    """Track IDs and their probabilities from one reference's assignment (``found``)."""
    p = np.exp(found["log_p"])
    rows = np.arange(len(p))
    choice = np.maximum(found["choice"], 0)
    tid = np.where(found["choice"] >= 0, ref.ids[choice], UNTRACKED)
    conf = np.where(found["choice"] >= 0, p[rows, choice], np.clip(1 - p[:, :-1].sum(1), 0, 1))
    return tid, conf


def _assign_ids(probs: np.ndarray, no_match_weight: float) -> tuple[np.ndarray, np.ndarray]:
    choice = assign(probs, None, no_match_weight)
    no_match = np.clip(1.0 - probs.sum(axis=1), 0.0, 1.0)
    rows = np.arange(len(probs))
    conf = np.where(choice >= 0, probs[rows, np.maximum(choice, 0)], no_match)
    return choice.astype(int), conf


def _too_few_to_register(volume: NeuronTable) -> bool:
    """Under 3 distinct positions (an out-of-focus time point): no registration can place it."""
    return len(np.unique(volume.xyz, axis=0)) < 3


def _track_cpd(seq: Sequence, tables: list[NeuronTable], s: TrackSettings, progress) -> TrackResult:
    """The classical baseline, as a CPD tracker works: the first volume gets CPD from the first
    reference in every orientation; each later volume one registration of the reference as
    deformed onto the volume before (the worm moves little between volumes)."""
    from .baselines import cpd_follow, cpd_search

    ref = tables[0]
    names = ref.label_strings()
    result = TrackResult([], [], names, [], list(seq.times), list(seq.sources))
    moved = None
    for k, vol in enumerate(seq.volumes):
        if _too_few_to_register(vol):  # untracked, and the next volume goes on from the one before
            tid, conf = np.full(len(vol), UNTRACKED), np.ones(len(vol))
        else:
            probs, moved = cpd_search(ref, vol) if moved is None else cpd_follow(moved, vol)
            tid, conf = _assign_ids(probs[:, :-1], s.no_match_weight)
        result.track_id.append(tid)
        result.confidence.append(conf)
        result.info.append({"reference": 0})
        if progress is not None:
            progress(k + 1, len(seq))
    return result


def _track_geometry(seq: Sequence, tables: list[NeuronTable], s: TrackSettings, progress) -> TrackResult:
    """Ablation without any model: the first volume is put on the reference by the non-learned
    floor (canonical frame, best of the 4 flips, assignment on distance); every later volume by
    the propagated warp and the one-to-one assignment on distance alone (the pre-placement of
    ``placement="geometry"``), whose pairs are the answer."""
    from .baselines import floor_match

    ref = _Reference(tables[0], np.arange(len(tables[0])))
    result = TrackResult([], [], ref.table.label_strings(), [], list(seq.times), list(seq.sources))
    warp = None
    for k, vol in enumerate(seq.volumes):
        if _too_few_to_register(vol):  # as CPD: untracked, and the chain goes on from the one before
            choice = np.full(len(vol), UNTRACKED)
        else:
            if warp is None:
                probs = floor_match(ref.table, vol)[:, :-1]
                choice = np.where(probs.max(1) > 0, probs.argmax(1), UNTRACKED)
                ok = choice >= 0
                warp = fit_warp(vol.xyz, ref.xyz[np.maximum(choice, 0)], ok.astype(float), s.warp_sigma_um,
                                s.warp_smoothness)
            warp, choice = _geometric_step(ref, vol, warp, s, pairs=True)
        result.track_id.append(choice)
        # the chain is certain either way: of the partner it pairs, or that there is none
        result.confidence.append(np.ones(len(choice)))
        result.info.append({"reference": 0})
        if progress is not None:
            progress(k + 1, len(seq))
    return result


# ----------------------------------------------------------------------------------------------
# Synthetic sequences with known tracks

@dataclass
class SequenceParams:
    frames: int = 100
    bend_curvature: float = 0.006  # 1/µm: the largest |curvature| of the centreline bend
    bend_period: float = 60.0  # frames per bending cycle (crawling)
    roll: float = 0.25  # radians: largest turn about the body axis (y-z plane)
    xy_rotation: float = 0.6  # radians: largest turn in XY
    drift_um: float = 15.0  # largest translation in XY
    drift_period: float = 200.0  # frames per cycle of the XY turn and drift
    scale: float = 0.03  # each axis scaled by 1 ± this, smoothly
    drop_fraction: tuple[float, float] = (0.03, 0.12)  # of neurons missed, per volume
    max_spurious: int = 8  # spurious detections per volume, at least 2 µm from real ones
    jitter_um: float = 0.42  # Gaussian segmentation jitter per volume

    def scaled(self, motion: float) -> "SequenceParams":
        """These parameters with the pose changes (bend, roll, XY turn and drift) × ``motion``."""
        from dataclasses import replace

        return replace(self, bend_curvature=self.bend_curvature * motion, roll=self.roll * motion,
                       xy_rotation=self.xy_rotation * motion, drift_um=self.drift_um * motion)


def _smooth(rng, frames: int, period: float) -> np.ndarray:
    """A smooth random curve in [-1, 1] over ``frames`` steps: a few sinusoids of periods
    around ``period`` with random phases."""
    t = np.arange(frames)
    curve = np.zeros(frames)
    for _ in range(3):
        f = 1.0 / (period * rng.uniform(0.7, 1.5))
        curve += rng.uniform(0.5, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return curve / max(np.abs(curve).max(), 1e-9)


def simulate_sequence(
    table: NeuronTable,
    rng: np.random.Generator | int | None = None,
    params: SequenceParams | None = None,
    only: tuple[int, ...] | None = None,
) -> tuple[list[NeuronTable], list[np.ndarray]]:
    """Volumes of ``table``'s worm moving smoothly; returns (volumes, origin per volume) where
    ``origin[t][j]`` is the source row of neuron j of volume t (-1 = spurious). ``only``: just
    these time points (training needs three of a recording): the same motion as the whole
    sequence's, with their drops, spurious points and noise drawn anew (not the same volumes)."""
    from .simulate import _spurious_points

    p = params or SequenceParams()
    if p.frames < 1:
        raise FdlcError(f"a recording needs 1 frame or more, not {p.frames}")
    if only is not None and not all(0 <= t < p.frames for t in only):
        raise FdlcError(f"time points {sorted(only)}: a recording of {p.frames} frames has 0 to {p.frames - 1}")
    rng = np.random.default_rng(rng)
    canon, centre, rotation = canonical_frame(table.xyz)
    T = p.frames
    kappa = p.bend_curvature * _smooth(rng, T, p.bend_period)
    phi = 0.2 * _smooth(rng, T, 2 * p.bend_period)
    roll = p.roll * _smooth(rng, T, 2 * p.bend_period)
    angle = p.xy_rotation * _smooth(rng, T, p.drift_period)
    drift = p.drift_um * np.column_stack([_smooth(rng, T, p.drift_period), _smooth(rng, T, p.drift_period)])
    scales = 1 + p.scale * np.column_stack([_smooth(rng, T, p.bend_period) for _ in range(3)])
    volumes, origins = [], []
    for t in range(T) if only is None else sorted(set(only)):
        pts = bend(canon, kappa[t], phi[t])
        c, s = np.cos(roll[t]), np.sin(roll[t])
        pts[:, 1:] = pts[:, 1:] @ np.array([[c, -s], [s, c]]).T
        pts = pts * scales[t]
        c, s = np.cos(angle[t]), np.sin(angle[t])
        pts = pts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
        pts[:, :2] += drift[t]
        n = len(pts)
        keep = rng.random(n) >= rng.uniform(*p.drop_fraction)
        origin = np.flatnonzero(keep)
        pts = pts[keep]
        spurious = _spurious_points(pts, int(rng.integers(0, p.max_spurious + 1)), 2.0, rng)
        pts = np.vstack([pts, spurious]) + rng.normal(0, p.jitter_um, (len(pts) + len(spurious), 3))
        origin = np.concatenate([origin, np.full(len(spurious), -1)])
        order = rng.permutation(len(pts))
        pts, origin = pts[order] @ rotation + centre, origin[order]
        colours = copied_colours(table, origin, rng, noise=0.05)
        volumes.append(NeuronTable(pts, colours, source=f"synthetic sequence t={t}"))
        origins.append(origin)
    return volumes, origins


def tracking_accuracy(result: TrackResult, origins: list[np.ndarray], reference_origin: np.ndarray,
                      reference_t: int | None = 0) -> dict:
    """Against the truth of :func:`simulate_sequence` with the reference ``reference_origin``
    (the origin array of the reference volume): ``accuracy`` = fraction of neurons whose true
    partner is in the reference that get its track ID; ``untracked_right`` = fraction of the
    others (spurious, or missing from the reference) left untracked (NaN without any). The
    reference volume itself (``reference_t``, an index into ``origins``; None: not among them)
    is not scored: its detections are the tracks, a spurious one too, whatever the tracker."""
    where = {o: i for i, o in enumerate(reference_origin) if o >= 0}
    hit = total = free_right = free_total = 0
    for t, (tid, origin) in enumerate(zip(result.track_id, origins)):
        if t == reference_t:
            continue
        truth = np.array([where.get(o, UNTRACKED) if o >= 0 else UNTRACKED for o in origin])
        has = truth >= 0
        hit += int((tid[has] == truth[has]).sum())
        total += int(has.sum())
        free_right += int((tid[~has] == UNTRACKED).sum())
        free_total += int((~has).sum())
    return {"accuracy": hit / max(total, 1), "untracked_right": free_right / free_total if free_total else float("nan"),
            "neurons": total}


def warm_up(identifier=None) -> None:
    """Track a short generated recording (a full chunk after its first volume) and throw the
    result away: the first real call then pays neither torch's import, the two models' loads
    nor their traces (the Track widget runs it when docked). Errors are left to the real call."""
    from .identify import WARM_UP_LOCK, default_identifier
    from .reference import generate_worm

    try:
        sequence, _ = simulate_sequence(generate_worm(seed=0), 0, SequenceParams(frames=TrackSettings().chunk + 1))
        with WARM_UP_LOCK:
            track(sequence, identifier=identifier or default_identifier())
    except FdlcError:
        pass
