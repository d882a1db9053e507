"""The built-in reference panel: a statistical atlas derived from the annotated corpus.

What ships is statistics, never a corpus worm: for every neuron name seen in enough worms, its
mean position and spread in a common frame and its mean NeuroPAL colour (per-volume normal
scores, see :mod:`napari_fdlc.colour`). Built by :func:`build_atlas`:

1. every worm is put in the canonical frame (:mod:`napari_fdlc.geometry`);
2. generalised Procrustes on the names: each worm is aligned to the current mean by a
   similarity transform (rotation, scale, translation; the mirror is allowed *only* to undo a
   recording's chirality convention, so every worm enters the atlas in one chirality), then the
   per-name means are recomputed; three rounds;
3. names seen in at least ``min_frequency`` of the worms, and in two worms at least (a spread
   needs two), are kept.

The least-squares scales of step 2 are biased low, so the atlas comes out 0.6–0.9× the size of
the worms in µm; the median ratio is kept (``Atlas.worm_scale``) so that generated worms have a
real worm's size and a partial view starts at the atlas's. Rescaling the atlas itself to the
median worm was tried and scored worse on the panel (top-1 with colour NP 60 → 38 %, SF 34 →
20 %, 8 worms per lab): the test is registered to the atlas's scale anyway, and the model's
distance prior is gentler in the smaller frame.

The panel (what ``fdlc label`` and Auto-label use without ``--template``) is the atlas's mean
worm plus worms sampled from its per-name spreads (at PANEL_SPREAD of them), all in the atlas's frame;
:func:`napari_fdlc.match.name_probabilities` averages their answers into one probability per
name. A test worm is first placed in that frame by :meth:`Atlas.register`
(:mod:`napari_fdlc.register`: the atlas as a Gaussian mixture, one component per name, its
spread plus colour). Registration instead of the 16 right-angle orientations took the panel's
top-1 with colour from 29 to 53 % averaged over the five labs (shipped model, atlas rebuilt
without the scored lab). :func:`generate_worm` samples a realistic worm from the same
statistics — the bundled sample data is made this way.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from .colour import IDENTITY_CHANNELS, has_colour, normal_scores
from .errors import FdlcError, ModelError, atomic_write
from .geometry import canonical_frame
from .register import Mixture, Placement, posterior, register
from .table import NeuronTable, with_unique_names

ATLAS_NAME = "atlas.csv"
# The built-in panel: the mean worm plus PANEL_SAMPLES worms sampled at PANEL_SPREAD times the
# atlas's spreads. Chosen on training labs only (session 5: each fold model scored on its four
# training labs, each against an atlas without it and without the held-out lab): 9 samples at
# half spread beat the 4 at full spread of sessions 1-4 in every fold, by 3.3-5.7 points of
# top-1; full-spread samples add more noise than the average removes.
PANEL_SAMPLES = 9
PANEL_SPREAD = 0.5
PANEL_SEED = 0
_REGISTRATION_SD = 1.5  # µm added to each name's spread when registering (Atlas.mixture)
# The test's stretch along its z, see register.Mixture.z_scale_range (used by the panel; a
# template's test is placed on the atlas without it: identify.Identifier._atlas_placement).
ATLAS_Z_SCALE_RANGE = (0.75, 1.33)


@dataclass
class Atlas:
    names: np.ndarray  # (K,)
    mean: np.ndarray  # (K, 3) µm, common frame (body axis x)
    sd: np.ndarray  # (K, 3) µm
    colour: np.ndarray  # (K, 3) mean normal scores of R, G, B; NaN: built from worms without colour
    colour_sd: np.ndarray  # (K, 3)
    frequency: np.ndarray  # (K,) fraction of worms that name it
    worms: int = 0
    labs: tuple[str, ...] = ()
    # A median corpus worm in µm is this many times the atlas (Procrustes shrinks the atlas)
    worm_scale: float = 1.0

    @property
    def has_colour(self) -> bool:
        return bool(np.isfinite(self.colour).all())

    def mixture(self, stretch_z: bool = True) -> Mixture:
        """The atlas as a mixture for :func:`napari_fdlc.register.register`: each name's spread
        plus ``_REGISTRATION_SD`` (segmentation error, residual pose), weighted by how often it
        is named; the scale is free within bounds (the atlas is smaller than real worms); a
        test showing part of the head is also tried at offsets along the body axis; with
        ``stretch_z``, the test is stretched along its own z within ``ATLAS_Z_SCALE_RANGE``."""
        colour, colour_var = (self.colour, self.colour_sd**2) if self.has_colour else (None, None)
        return Mixture(self.mean, self.sd**2 + _REGISTRATION_SD**2, np.log(np.maximum(self.frequency, 1e-6)),
                       colour, colour_var, scale_range=(0.8, 1.25), partial_views=True,
                       partial_view_scale=1 / self.worm_scale,
                       z_scale_range=ATLAS_Z_SCALE_RANGE if stretch_z else (1.0, 1.0))

    def register(self, test: NeuronTable, use_colour: bool = True, chiralities=(False, True),
                 stretch_z: bool = True) -> list[Placement]:
        """``test`` placed in the atlas frame, once per chirality (see napari_fdlc.register.register)."""
        return register(test, self.mixture(stretch_z), use_colour, chiralities=chiralities)

    def posterior(self, test: NeuronTable, use_colour: bool = True, mirrored: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``test`` placed in one handedness, then the probability (N, names) that each of its
        neurons is each atlas name and (N,) that it is none, from positions (and colours)
        alone: the atlas's own answer, without the model (see :func:`napari_fdlc.register.posterior`)."""
        placement = self.register(test, use_colour, chiralities=(mirrored,))[0]
        return posterior(test, self.mixture(), placement.xyz, use_colour)

    def with_colours_of(self, tables: list[NeuronTable], names: list[np.ndarray], min_worms: int = 3) -> "Atlas":
        """This atlas with each name's colour (mean and spread of the normal scores) measured
        on ``tables`` instead, where ``names[k]`` names the rows of ``tables[k]`` ('' = not
        used) and the name is given in at least ``min_worms`` of them; positions unchanged.
        Recordings of one microscope share its colour balance, which a corpus of other labs
        does not know (Identifier.label_panel_many, ``adapt_colours``)."""
        index = {n: k for k, n in enumerate(self.names)}
        seen: dict[int, list] = {}
        for table, given in zip(tables, names):
            if not has_colour(table):
                continue
            scores = _read_scores(table)
            for row, name in enumerate(given):
                if name in index:
                    seen.setdefault(index[name], []).append(scores[row])
        colour, colour_sd = self.colour.copy(), self.colour_sd.copy()
        for k, values in seen.items():  # per channel: a name read in too few worms keeps the atlas's
            values = np.asarray(values)
            enough = np.isfinite(values).sum(axis=0) >= min_worms
            colour[k, enough] = np.nanmean(values[:, enough], axis=0)
            colour_sd[k, enough] = np.nanstd(values[:, enough], axis=0)
        return replace(self, colour=colour, colour_sd=colour_sd)

    def to_frame(self) -> pd.DataFrame:
        df = pd.DataFrame({"name": self.names})
        for i, a in enumerate("xyz"):
            df[f"{a}_um"] = self.mean[:, i]
            df[f"{a}_sd"] = self.sd[:, i]
        for i, c in enumerate(IDENTITY_CHANNELS):
            df[c] = self.colour[:, i]
            df[f"{c}_sd"] = self.colour_sd[:, i]
        df["frequency"] = self.frequency
        return df

    def save(self, path: str | Path) -> None:
        with atomic_write(path, "w", encoding="utf-8", newline="") as handle:
            # ", " between labs (a lab's name may hold spaces); one lab ends in "," to say so
            labs = ", ".join(self.labs) + ("," if len(self.labs) == 1 else "")
            handle.write(f"# napari-fdlc atlas: {self.worms} worms of {labs}; worm scale {self.worm_scale:.4f}\n")
            self.to_frame().to_csv(handle, index=False, float_format="%.4f")

    @classmethod
    def load(cls, path: str | Path) -> "Atlas":
        path = Path(path)
        try:
            header = path.read_text(encoding="utf-8").splitlines()[0]  # as save wrote it, whatever the locale
            df = pd.read_csv(path, comment="#")
            counts, _, scale = header.partition("; worm scale ")
            worms = int(counts.split(":")[1].split()[0])
            labs = counts.split(" of ", 1)[1]
            # ", " between labs; atlases written before session 31 have spaces
            labs = tuple(lab.strip() for lab in labs.split(",") if lab.strip()) if "," in labs else tuple(labs.split())
            _check_numbers(df, path)
            worm_scale = float(scale) if scale else 1.0
            if not (np.isfinite(worm_scale) and worm_scale > 0):
                raise ModelError(f"{path}: not a valid atlas file (worm scale {scale.strip()}: a positive number is needed)")
            return cls(
                df["name"].to_numpy(object),
                df[["x_um", "y_um", "z_um"]].to_numpy(float),
                df[["x_sd", "y_sd", "z_sd"]].to_numpy(float),
                df[list(IDENTITY_CHANNELS)].to_numpy(float),
                df[[f"{c}_sd" for c in IDENTITY_CHANNELS]].to_numpy(float),
                df["frequency"].to_numpy(float),
                worms,
                labs,
                worm_scale,
            )
        except (OSError, KeyError, ValueError, IndexError) as exc:
            raise ModelError(f"{path}: not a valid atlas file ({exc})") from None


def _check_numbers(df: pd.DataFrame, path: Path) -> None:
    """An atlas file edited by hand: every position, spread and frequency a number (spreads and
    frequencies not negative), the colours numbers too or all empty (an atlas without colour)."""
    colour = list(IDENTITY_CHANNELS) + [f"{c}_sd" for c in IDENTITY_CHANNELS]
    kept = [c for c in ("x_um", "y_um", "z_um", "x_sd", "y_sd", "z_sd", "frequency") if c in df]
    if all(c in df for c in colour) and not df[colour].isna().all().all():
        kept += colour
    for column in kept:
        values = pd.to_numeric(df[column], errors="coerce").to_numpy(float)
        spread = column.endswith("_sd") or column == "frequency"
        bad = ~np.isfinite(values) | ((values < 0) if spread else False)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ModelError(f"{path}: not a valid atlas file (name {df['name'].iloc[row]!r}, column {column}: "
                             f"{df[column].iloc[row]!r} is not {'a number of 0 or more' if spread else 'a number'})")


def _similarity(src: np.ndarray, dst: np.ndarray, allow_mirror: bool):
    """Best ``dst ≈ s * (src - mu_s) @ R.T + mu_d``; returns (R, s, mu_s, mu_d, mean squared
    residual). With ``allow_mirror`` R may be a reflection when that fits better."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    s0, d0 = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(d0.T @ s0)
    best = None
    for mirror in ([False, True] if allow_mirror else [False]):
        flip = np.eye(3)
        if (np.linalg.det(u @ vt) < 0) != mirror:
            flip[2, 2] = -1
        rot = u @ flip @ vt
        scale = np.trace(np.diag(sig) @ flip) / max((s0**2).sum(), 1e-9)
        moved = scale * s0 @ rot.T + mu_d
        res = ((moved - dst) ** 2).sum(1).mean()
        if best is None or res < best[1]:
            best = (rot, res, scale)
    rot, res, scale = best
    return rot, scale, mu_s, mu_d, res


MIN_ATLAS_NAMES = 10  # fewer names cannot place a worm (the registration needs a body to fit)


def _read_scores(table: NeuronTable) -> np.ndarray:
    """(N, 3) normal scores of the identity colours, NaN where a cell had no reading (the
    median filler of :class:`NeuronTable` measures nothing)."""
    scores = normal_scores(table, IDENTITY_CHANNELS).copy()
    for j, c in enumerate(IDENTITY_CHANNELS):
        scores[table.colour_gaps.get(c, np.zeros(len(table), bool)), j] = np.nan
    return scores


def build_atlas(worms, min_frequency: float = 0.2, rounds: int = 3) -> Atlas:
    """Statistical atlas from labelled worms (a list of :class:`napari_fdlc.corpus.Worm`)."""
    # a name given twice in a worm (an annotation slip) on none of its rows, as the readers
    # do: counted once per neuron, it made one worm count as two (on a copy: the caller's kept)
    tables = [with_unique_names(w.table.subset(np.arange(len(w.table))), say=False) for w in worms]
    if not tables:
        raise FdlcError("no worms to build an atlas from")
    canon = [canonical_frame(t.xyz)[0] for t in tables]
    colours = [_read_scores(t) if has_colour(t) else None for t in tables]
    # the best-named worm anchors the alignment; a tie by lab and name, not by the order given
    counts = [int(t.named.sum()) for t in tables]
    reference = min(range(len(worms)), key=lambda k: (-counts[k], worms[k].lab, getattr(worms[k], "name", "")))
    mean = {n: canon[reference][i] for i, n in enumerate(tables[reference].labels) if n}
    aligned = [None] * len(tables)
    scales = []
    for _ in range(rounds):
        scales, mirrored = [], {}  # mirrored: of each worm aligned, relative to the best-named one
        for k, (t, c) in enumerate(zip(tables, canon)):
            rows = [i for i, n in enumerate(t.labels) if n in mean]
            if len(rows) < 4:
                aligned[k] = None
                continue
            dst = np.array([mean[t.labels[i]] for i in rows])
            rot, scale, mu_s, mu_d, _ = _similarity(c[rows], dst, allow_mirror=True)
            aligned[k] = scale * (c - mu_s) @ rot.T + mu_d
            scales.append(scale)
            mirrored[k] = bool(np.linalg.det(rot) < 0)
        positions: dict[str, list] = {}
        for t, a in zip(tables, aligned):
            if a is None:
                continue
            for i, n in enumerate(t.labels):
                if n:
                    positions.setdefault(n, []).append(a[i])
        mean = {n: np.mean(p, axis=0) for n, p in positions.items()}
    used = sum(a is not None for a in aligned)
    stats = {}
    for t, a, col in zip(tables, aligned, colours):
        if a is None:
            continue
        for i, n in enumerate(t.labels):
            if n:
                entry = stats.setdefault(n, {"pos": [], "col": []})
                entry["pos"].append(a[i])
                if col is not None:
                    entry["col"].append(col[i])
    # in whole worms: 0.28 × 25 is 7.000000000000001 in floats, and a name seen in 7 was dropped
    least = max(2, math.ceil(round(min_frequency * used, 9)))
    names = sorted(n for n, e in stats.items() if len(e["pos"]) >= least)
    if used < 2 or len(names) < MIN_ATLAS_NAMES:
        raise FdlcError(f"no atlas from these {len(tables)} worm(s): {used} share 4 or more names with the best-named one, "
                        f"and {len(names)} name(s) recur in enough of them; an atlas needs 2 such worms and "
                        f"{MIN_ATLAS_NAMES} names (give worms with a label column)")
    pos = [np.array(stats[n]["pos"]) for n in names]
    col = [np.array(stats[n]["col"]).reshape(-1, 3) for n in names]
    if any(c is not None for c in colours):  # per channel, over the worms with a reading of it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a channel never read: the nan-mean of nothing
            readings = [np.isfinite(c).sum(axis=0) for c in col]
            colour = np.array([np.where(r >= 1, np.nanmean(c, axis=0), 0.0) for c, r in zip(col, readings)])
            colour_sd = np.array([np.where(r >= 2, np.nanstd(c, axis=0), 1.0) for c, r in zip(col, readings)])
    else:  # no worm with colour: none in the atlas, not a made-up 0 ± 1 (its panel's colours random)
        colour = colour_sd = np.full((len(names), 3), np.nan)
    mean_pos = np.array([p.mean(0) for p in pos])
    if _mostly_mirrored(mirrored, [w.lab for w in worms]):
        mean_pos[:, 2] *= -1
    centre = np.median(mean_pos, axis=0)
    return Atlas(
        names=np.array(names, dtype=object),
        mean=mean_pos - centre,
        sd=np.array([p.std(0) for p in pos]),
        colour=colour,
        colour_sd=colour_sd,
        frequency=np.array([len(p) / used for p in pos]),
        worms=used,
        labs=tuple(sorted({w.lab for w, a in zip(worms, aligned) if a is not None})),  # the labs it was built from
        worm_scale=float(1.0 / np.median(scales)),
    )


def _mostly_mirrored(mirrored: dict[int, bool], labs: list[str]) -> bool:
    """Whether most labs' worms are mirrored relative to the best-named one (which only anchors
    the alignment), each lab by most of its worms: the atlas then takes their handedness, so that
    --chirality same / mirrored say what they mean about a lab's recordings. Counted by lab, not
    by worm: a lab's mirroring is its recording convention (SF's 33 of 36), and counted by worm
    SF alone flipped the atlas built without EY (40 of its 76 worms), mirroring every EY worm's
    names on `auto` (the EY panel 77.6 -> 10.9 %)."""
    by_lab: dict[str, list[bool]] = {}
    for k, m in mirrored.items():
        by_lab.setdefault(labs[k], []).append(m)
    lab_mirrored = [2 * sum(v) > len(v) for v in by_lab.values()]
    return 2 * sum(lab_mirrored) > len(lab_mirrored)


def atlas_worm(atlas: Atlas, rng: np.random.Generator | None = None, keep_fraction: float | None = None,
               spread: float = 1.0) -> NeuronTable:
    """The mean worm (rng None) or a worm sampled from the atlas's spreads (times ``spread``);
    names kept. With ``keep_fraction``, each name is kept with probability min(1, its frequency / it)."""
    keep = np.ones(len(atlas.names), bool)
    xyz = atlas.mean.copy()
    colour = atlas.colour.copy()
    if rng is not None:
        xyz = xyz + rng.normal(size=xyz.shape) * atlas.sd * spread
        colour = colour + rng.normal(size=colour.shape) * atlas.colour_sd * spread
        if keep_fraction is not None:
            keep = rng.random(len(keep)) < np.minimum(1.0, atlas.frequency / keep_fraction)
    colours = {c: colour[keep, i] for i, c in enumerate(IDENTITY_CHANNELS)} if atlas.has_colour else {}
    return NeuronTable(xyz[keep], colours, atlas.names[keep], source="atlas")


def shipped_atlas_path() -> Path:
    return Path(str(resources.files("napari_fdlc") / "data" / ATLAS_NAME))


_PANEL: dict = {}


def load_atlas(path: str | Path | None = None) -> Atlas:
    path = Path(path) if path else shipped_atlas_path()
    if not path.exists():
        raise ModelError(f"the built-in reference panel is missing ({path}): build it with 'fdlc atlas' or pass --template")
    return Atlas.load(path)


@dataclass
class Panel:
    """The built-in reference: an atlas and template worms drawn from it, in the atlas's frame."""

    atlas: Atlas
    templates: list[NeuronTable]
    # (samples, seed, spread) of make_panel: drawn again alike from an atlas whose colours were
    # adapted; None for templates given by hand
    recipe: tuple | None = field(default=None, compare=False)

    @property
    def names(self) -> set[str]:
        return {n for t in self.templates for n in t.names}


def make_panel(atlas: Atlas, samples: int = PANEL_SAMPLES, seed: int = PANEL_SEED, spread: float = PANEL_SPREAD) -> Panel:
    rng = np.random.default_rng(seed)
    return Panel(atlas, [atlas_worm(atlas)] + [atlas_worm(atlas, rng, spread=spread) for _ in range(samples)],
                 recipe=(samples, seed, spread))


def panel_on(panel: Panel, atlas: Atlas) -> Panel:
    """``panel`` drawn again from ``atlas`` (the same atlas with its colours measured anew):
    the same draws for a panel make_panel made, else its own templates with each name's colour
    moved as the atlas's moved (positions unchanged)."""
    if panel.recipe is not None:
        return make_panel(atlas, *panel.recipe)
    row = {n: i for i, n in enumerate(panel.atlas.names)}
    moved = {n: atlas.colour[i] - panel.atlas.colour[row[n]] for i, n in enumerate(atlas.names) if n in row}
    templates = []
    for t in panel.templates:
        shift = np.array([moved.get(n, np.zeros(len(IDENTITY_CHANNELS))) for n in t.labels]).reshape(len(t), -1)
        colours = {c: v + shift[:, IDENTITY_CHANNELS.index(c)] if c in IDENTITY_CHANNELS else v
                   for c, v in t.colours_as_read().items()}
        templates.append(replace(t, colours=colours))
    return Panel(atlas, templates)


def load_panel(path: str | Path | None = None) -> Panel:
    """The built-in reference panel: templates generated from the shipped atlas."""
    file = Path(path) if path else shipped_atlas_path()
    key = (str(file), file.stat().st_mtime_ns if file.exists() else None)  # an atlas saved again is read again
    if key not in _PANEL:
        _PANEL[key] = make_panel(load_atlas(path))
    return _PANEL[key]


def generate_worm(seed: int = 0, atlas: Atlas | None = None, n_unnamed: int = 0) -> NeuronTable:
    """A plausible labelled worm sampled from the atlas at the size of a median corpus worm,
    placed in a recording frame (random XY angle, positive coordinates), with raw-looking
    positive colours (none from an atlas without colour); ``n_unnamed`` extra unlabelled
    neurons as a segmentation would find."""
    if n_unnamed < 0:
        raise FdlcError(f"generate_worm: n_unnamed must be 0 or more (got {n_unnamed})")
    atlas = atlas or load_atlas()
    rng = np.random.default_rng(seed)
    worm = atlas_worm(atlas, rng, keep_fraction=0.6)
    xyz = worm.xyz * atlas.worm_scale
    if n_unnamed:
        lo, hi = xyz.min(0), xyz.max(0)
        extra = rng.uniform(lo, hi, (n_unnamed, 3))
        xyz = np.vstack([xyz, extra])
    angle = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(angle), np.sin(angle)
    xyz = xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    xyz = xyz - xyz.min(0) + np.array([5.0, 5.0, 3.0])
    labels = np.concatenate([worm.labels, np.full(n_unnamed, "", dtype=object)])
    colours = {}
    for ch in IDENTITY_CHANNELS if atlas.has_colour else ():  # an atlas of worms without colour has none to give
        v = np.concatenate([worm.colours[ch], rng.normal(0, 1, n_unnamed)])
        colours[ch] = np.round(200 * np.exp(0.8 * v), 1)  # raw-looking positive intensities
    return NeuronTable(xyz, colours, labels, source=f"generated(seed={seed})")
