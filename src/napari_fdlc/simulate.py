"""Synthetic worms with known correspondence (the fDLC simulator, Yu et al. 2021).

From one real neuron table we make a deformed copy whose every neuron knows where it came
from. Steps (units µm, defaults = the published magnitudes):

1. pose: without a measured centreline, the body axis is the principal axis of the head's
   points; the worm is bent along it (a random smooth curvature of the centreline) and,
   optionally, warped non-rigidly toward another real worm with CPD (pycpd; w=0.1, λ=4000,
   β=0.25 on normalised points), as the paper does;
2. transverse plane (y-z): rotation up to ±0.45π and shear up to ±0.1;
3. 5–25 % of neurons dropped, up to 20 spurious neurons added ≥ 2 µm from real ones;
4. rotation in XY (uniform), scale of each axis ±5 %, shear ±0.1;
5. Gaussian noise σ = 0.42 µm;
6. optionally the other side: a 180° turn about the body axis (a proper rotation — never a
   mirror, which would swap left and right neurons).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .errors import TableError
from .geometry import canonical_frame
from .table import PIXEL_COLUMNS, NeuronTable


@dataclass
class SimulationParams:
    bend_curvature: float = 0.004  # 1/µm: max curvature of the random centreline bend
    transverse_rotation: float = 0.45 * np.pi  # max |angle| in the y-z plane (radians)
    transverse_shear: float = 0.1
    # a drop probability drawn in this range per copy, then each neuron dropped with it: the
    # fraction dropped varies about it (defaults: 2.6-29 % over 200 copies of 155 neurons). Kept
    # so: the shipped weights were trained on these draws (model_card.md: reproducible).
    drop_fraction: tuple[float, float] = (0.05, 0.25)
    max_spurious: int = 20
    spurious_min_distance_um: float = 2.0
    xy_rotation: float = np.pi  # max |angle| in XY (π = uniform)
    scale: float = 0.05  # each axis scaled by 1 ± this
    shear: float = 0.1
    noise_um: float = 0.42
    flip_side_probability: float = 0.5  # 180° about the body axis
    warp_toward_other: bool = False  # CPD warp toward another real worm (slower)

    def as_dict(self) -> dict:
        return asdict(self)

    def check(self) -> None:
        """Refuse (one-line TableError) what would give nonsense: a negative or non-finite
        magnitude, a drop range outside 0-1, a probability outside 0-1, a scale of 1 or more (an
        axis scaled by 0 or less: a mirror image)."""
        values = {name: getattr(self, name) for name in ("bend_curvature", "transverse_rotation", "transverse_shear",
                                                         "spurious_min_distance_um", "xy_rotation", "scale", "shear",
                                                         "noise_um", "flip_side_probability")}
        for name, value in values.items():
            if not (_is_number(value) and value >= 0):
                raise TableError(f"simulate: {name} must be a number of 0 or more (got {value!r})")
        if self.scale >= 1:
            raise TableError(f"simulate: scale must be below 1 (got {self.scale}): an axis scaled by 1 - scale ≤ 0 "
                             "would mirror the worm")
        if self.flip_side_probability > 1:
            raise TableError(f"simulate: flip_side_probability must be at most 1 (got {self.flip_side_probability})")
        drop = tuple(self.drop_fraction) if isinstance(self.drop_fraction, (tuple, list)) else ()
        if len(drop) != 2 or not all(_is_number(v) and 0 <= v <= 1 for v in drop) or drop[0] > drop[1]:
            raise TableError(f"simulate: drop_fraction must be (low, high) with 0 ≤ low ≤ high ≤ 1 (got {self.drop_fraction!r})")
        if isinstance(self.max_spurious, bool) or not isinstance(self.max_spurious, (int, np.integer)) or self.max_spurious < 0:
            raise TableError(f"simulate: max_spurious must be a whole number of 0 or more (got {self.max_spurious!r})")


def _is_number(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and bool(np.isfinite(value))


@dataclass
class SyntheticWorm:
    table: NeuronTable
    origin: np.ndarray  # index of the source neuron for each neuron, -1 = spurious


def bend(canon: np.ndarray, kappa: float, phi: float) -> np.ndarray:
    """Bend the straight worm (body axis x) onto a circular arc of curvature ``kappa`` (1/µm)
    in the plane at angle ``phi`` from y toward z."""
    if abs(kappa) < 1e-9:
        return canon.copy()
    x, y, z = canon.T
    lateral = y * np.cos(phi) + z * np.sin(phi)
    other = -y * np.sin(phi) + z * np.cos(phi)
    radius = 1.0 / kappa
    theta = x / radius
    bx = (radius - lateral) * np.sin(theta)
    blat = radius - (radius - lateral) * np.cos(theta)
    return np.column_stack([bx, blat * np.cos(phi) - other * np.sin(phi), blat * np.sin(phi) + other * np.cos(phi)])


def _cpd_warp(points: np.ndarray, target: np.ndarray) -> np.ndarray:
    from pycpd import DeformableRegistration

    scale = np.sqrt((points**2).sum(1).mean()) or 1.0
    reg = DeformableRegistration(X=target / scale, Y=points / scale, alpha=4000.0, beta=0.25, w=0.1, max_iterations=30)
    moved, _ = reg.register()
    return moved * scale


def copied_colours(table: NeuronTable, origin: np.ndarray, rng: np.random.Generator, noise: float = 0.0) -> dict:
    """``table``'s colours at its neurons' copies (``origin``: each copy's source row, -1 for a
    spurious neuron, which takes some neuron's reading), times 1 ± ``noise`` (relative SD) on
    the real ones. A neuron without a reading has none in its copy."""
    real = origin >= 0
    colours = {}
    for ch, values in table.colours_as_read().items():
        read = values[np.isfinite(values)]
        v = np.full(len(origin), np.nan)
        v[real] = values[origin[real]] * (rng.normal(1.0, noise, real.sum()) if noise else 1.0)
        if (~real).any() and len(read):
            v[~real] = rng.choice(read, (~real).sum())
        colours[ch] = v
    return colours


def simulate_worm(
    table: NeuronTable,
    rng: np.random.Generator | int | None = None,
    params: SimulationParams | None = None,
    other: NeuronTable | None = None,
) -> SyntheticWorm:
    """One synthetic worm made from ``table``; names and colours travel with their neurons."""
    if len(table) == 0 or not np.isfinite(table.xyz).all():
        raise TableError("simulate: the neuron table " + ("is empty" if len(table) == 0 else
                                                        "has positions that are not finite numbers"))
    rng = np.random.default_rng(rng)
    p = params or SimulationParams()
    p.check()
    canon, centre, rotation = canonical_frame(table.xyz)
    # A random curvature; the bending plane mostly in XY (worms crawl on their side).
    pts = bend(canon, rng.uniform(-p.bend_curvature, p.bend_curvature), rng.uniform(-0.3, 0.3))
    if p.warp_toward_other and other is not None and len(other) >= 3:
        other_canon, _, _ = canonical_frame(other.xyz)
        pts = _cpd_warp(pts, other_canon)

    a = rng.uniform(-p.transverse_rotation, p.transverse_rotation)
    c, s = np.cos(a), np.sin(a)
    transverse = np.array([[c, -s], [s, c]]) @ np.array([[1, rng.uniform(-p.transverse_shear, p.transverse_shear)], [0, 1]])
    pts[:, 1:] = pts[:, 1:] @ transverse.T
    if rng.random() < p.flip_side_probability:
        pts[:, 1:] *= -1

    n = len(pts)
    keep = rng.random(n) >= rng.uniform(*p.drop_fraction)
    if not keep.any():
        keep[rng.integers(n)] = True
    origin = np.flatnonzero(keep)
    pts = pts[keep]
    spurious = _spurious_points(pts, rng.integers(0, p.max_spurious + 1), p.spurious_min_distance_um, rng)
    pts = np.vstack([pts, spurious])
    origin = np.concatenate([origin, -np.ones(len(spurious), dtype=int)])

    angle = rng.uniform(-p.xy_rotation, p.xy_rotation)
    c, s = np.cos(angle), np.sin(angle)
    linear = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    linear = linear @ np.diag(1 + rng.uniform(-p.scale, p.scale, 3))
    linear = linear @ (np.eye(3) + np.triu(rng.uniform(-p.shear, p.shear, (3, 3)), 1))
    pts = pts @ linear.T + rng.normal(0, p.noise_um, pts.shape)
    # Back into a plausible recording frame (positive coordinates near the original centre).
    pts = pts @ rotation + centre

    order = rng.permutation(len(pts))
    pts, origin = pts[order], origin[order]
    real = origin >= 0
    labels = np.full(len(pts), "", dtype=object)
    labels[real] = table.labels[origin[real]]
    conf = np.zeros(len(pts))
    conf[real] = table.label_conf[origin[real]]
    colours = copied_colours(table, origin, rng)
    extra = None
    # the real neurons' other columns go with them (empty on spurious ones), but not the voxel
    # coordinates of the positions they had
    travel = table.extra.drop(columns=[c for c in PIXEL_COLUMNS if c in table.extra.columns])
    if len(travel.columns):
        extra = travel.astype(object).reindex(np.where(real, origin, -1)).reset_index(drop=True)
    return SyntheticWorm(NeuronTable(pts, colours, labels, conf, extra, source=f"synthetic({table.source})"), origin)


def _spurious_points(pts: np.ndarray, count: int, min_distance: float, rng) -> np.ndarray:
    """Random points inside the worm's bounding box, at least ``min_distance`` from every neuron."""
    from scipy.spatial import cKDTree

    if count == 0 or len(pts) == 0:
        return np.zeros((0, 3))
    lo, hi = pts.min(0), pts.max(0)
    tree = cKDTree(pts)
    found = []
    for _ in range(20):
        cand = rng.uniform(lo, hi, (count * 4, 3))
        dist, _ = tree.query(cand)
        found.extend(cand[dist >= min_distance])
        if len(found) >= count:
            break
    return np.asarray(found[:count]).reshape(-1, 3)
