"""Coordinate frames shared by the model, the baselines and the simulator.

A worm lies at any angle in XY, on either side, or (as some labs image) dorso-ventrally. We
remove what can be removed without names (centre on the median, rotate XY so the principal axis
is x, level a body axis that rises out of the image plane). What cannot be removed is
enumerated here: four rolls about the body axis by 90° times the two directions of the head,
times the two chiralities (a recording mirrored in z by its acquisition convention) — 16
orientations. Training uses them (the true one, found from the
names, and wrong ones as negatives) and so does the CPD baseline; inference registers the test
onto its reference instead (:mod:`napari_fdlc.register`), which finds any roll. The model is
never made mirror-invariant: a mirror swaps left and right neurons.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial.distance import cdist

from .errors import FdlcError

def _roll(quarter_turns: int) -> np.ndarray:
    """Rotation about the body axis (x) by a multiple of 90°."""
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns % 4]
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


_HEAD_TAIL = np.diag([-1.0, -1.0, 1.0])  # 180° about z: the head points the other way
_MIRROR = np.diag([1.0, 1.0, -1.0])  # z mirrored by an acquisition convention
# Proper orientations first: 4 rolls about the body axis (lying on either side, or viewed
# dorso-ventrally as some labs image) × head left/right; then the same 8 mirrored.
_PROPER = [flip @ _roll(q) for flip in (np.eye(3), _HEAD_TAIL) for q in range(4)]
ORIENTATIONS = np.array(_PROPER + [o @ _MIRROR for o in _PROPER])
N_PROPER = len(_PROPER)
# How a test's handedness relates to its template's (or the atlas's): search both, or known.
CHIRALITIES = ("auto", "same", "mirrored")
# The non-learned floor of ../shared/docs/fdlc.md tries the four proper 180° flips only.
FLOOR_FLIPS = np.array([np.eye(3), _HEAD_TAIL, _roll(2), _HEAD_TAIL @ _roll(2)])


# A body axis that rises out of the image plane by more than this is levelled (canonical_frame).
# The corpus's worms lie flat: their principal axis rises 0.7-2.1° (median per lab), 5.2° at most,
# so none of them is levelled. EM corrects small tilts itself (10° cost nothing); before the
# levelling 20° cost EY 14 points and 30° NP 10, EY 14, SF and SK1 8 (benchmarks/robustness.py).
LEVEL_ABOVE_DEG = 8.0
MIN_LEVEL_NEURONS = 10  # fewer points do not say where a body axis rises
# Nor does a piece of a worm that is not elongated: levelled only when the spread along the
# principal axis is at least twice the next (variance ratio 4; the corpus's heads: 4.4-25).
# Without it 12 % of training's augmented examples (mostly crops to 64 neurons) were turned
# by a noisy axis; with it 0.7 %, and every tilted head of benchmarks/robustness.py still is.
MIN_ELONGATION = 4.0


def canonical_frame(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate XY so that the principal axis is x, then centre on the per-axis median.

    Returns (canonical coordinates, centre, 3×3 rotation) with ``canon = (xyz - centre) @ R.T``.
    z (the optical axis) is otherwise left alone: worms lie flat, so the body axis is in XY —
    unless it rises out of the image plane by more than ``LEVEL_ABOVE_DEG`` (a tilted mount, a
    head raised in a moving worm), when it is first levelled by a turn about the transverse
    axis. The median is taken *after* the rotation so that the frame does not depend on how
    the worm lay in XY.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    mean = xyz.mean(axis=0)
    centred = xyz - mean
    rotation = np.eye(3)
    if len(xyz) >= 2:
        with np.errstate(over="ignore", invalid="ignore"):
            cov = np.cov(centred[:, :2].T)
        if np.all(np.isfinite(cov)) and np.any(cov != 0):
            eigval, eigvec = np.linalg.eigh(cov)
            axis = eigvec[:, np.argmax(eigval)]
            angle = np.arctan2(axis[1], axis[0])
            c, s = np.cos(-angle), np.sin(-angle)
            rotation[:2, :2] = [[c, -s], [s, c]]
    rotation = _levelling(centred @ rotation.T) @ rotation
    rotated = centred @ rotation.T
    median = np.median(rotated, axis=0)
    centre = mean + median @ rotation
    return rotated - median, centre, rotation


def _levelling(points: np.ndarray) -> np.ndarray:
    """The turn about y that brings the principal axis of ``points`` (body axis along x) into
    the XY plane, when it rises more than ``LEVEL_ABOVE_DEG`` and is well defined
    (``MIN_LEVEL_NEURONS``, ``MIN_ELONGATION``); the identity otherwise."""
    if len(points) < MIN_LEVEL_NEURONS:
        return np.eye(3)
    with np.errstate(over="ignore", invalid="ignore"):
        cov = np.cov(points.T)
    if not np.all(np.isfinite(cov)):  # positions so far out that their spread overflows: no axis to level by
        return np.eye(3)
    eigval, eigvec = np.linalg.eigh(cov)  # ascending
    if not eigval[-1] >= MIN_ELONGATION * eigval[-2]:
        return np.eye(3)
    axis = eigvec[:, -1]
    rise = np.arctan2(axis[2] * np.sign(axis[0] or 1.0), np.hypot(axis[0], axis[1]))
    if not np.isfinite(rise) or abs(np.degrees(rise)) <= LEVEL_ABOVE_DEG:
        return np.eye(3)
    c, s = np.cos(rise), np.sin(rise)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


FLAT_UM = 1.0  # neurons thinner than this (SD across their plane) have no handedness; corpus worms: 3.6 or more
HEAD_SPAN_UM = 100.0  # a head's longest extent, about


def thickness_um(xyz: np.ndarray) -> float:
    """The SD of the positions across their best-fitting plane: about 0 for a table whose z was
    lost (a projection), where a worm and its mirror image are the same points."""
    xyz = _finite(xyz, "positions")
    if len(xyz) < 3:
        return 0.0
    return float(np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)[-1] / np.sqrt(len(xyz)))


def refuse_flat(xyz: np.ndarray, source: str, min_neurons: int) -> None:
    """Refuse (FdlcError) a table of ``min_neurons`` or more that lies in one plane: a worm and
    its mirror image are then the same points, and every left/right name a guess. Below a
    head's span (``HEAD_SPAN_UM``) the limit shrinks with the span: a table in millimetres is
    as thick for its size as one in µm (its units are another warning), not flat."""
    if len(xyz) < min_neurons:
        return
    span = float(np.ptp(xyz, axis=0).max())
    # ``<=``: neurons all at one point (a failed export's 0, 0, 0) lie in every plane
    if (depth := thickness_um(xyz)) <= FLAT_UM * min(1.0, span / HEAD_SPAN_UM):
        raise FdlcError(f"{source or 'the test'}: the neurons lie in a plane ({depth:.2f} µm thick), so left "
                        "cannot be told from right; a 3D table is needed (check the z positions and the voxel size in z)")


def fit_affine(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, ridge: float = 1e-3) -> np.ndarray:
    """Weighted least-squares affine map ``dst ≈ [src, 1] @ A`` (A is 4×3), regularised toward
    a pure translation so that a handful of matches cannot produce a wild shear."""
    src, dst = _finite(src, "source positions"), _finite(dst, "target positions")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, float)
    if not (len(src) == len(dst) == len(w)):
        raise FdlcError(f"fit_affine: {len(src)} source positions, {len(dst)} targets and {len(w)} weights (one each)")
    total = w.sum()
    # Solved about the points' weighted means: the normal equations of coordinates far from the
    # origin (a microscope stage's, ~1e6 µm) lose every digit a neuron's position needs.
    mu_s, mu_d = (w @ src / total, w @ dst / total) if total > 0 else (src.mean(axis=0), dst.mean(axis=0))
    homog = np.ones((len(src), 4))
    homog[:, :3] = src - mu_s
    weighted = homog.T * w
    lhs = weighted @ homog
    strength = ridge * max(total, 1.0)  # on the linear part only, toward the identity
    lhs[_LINEAR, _LINEAR] += strength
    lhs.flat[::5] += 1e-9
    rhs = weighted @ (dst - mu_d)
    rhs[:3] += strength * np.eye(3)
    solved = np.linalg.solve(lhs, rhs)
    solved[3] += mu_d - mu_s @ solved[:3]
    return solved


_LINEAR = np.arange(3)  # the rows of an affine's linear part (row 3 is the shift)


def _finite(xyz, what: str) -> np.ndarray:
    """``xyz`` as floats, refused (FdlcError) when a coordinate is not a finite number: one NaN
    makes a fit all NaN, silently, and an SVD fail with LinAlgError."""
    xyz = np.asarray(xyz, float)
    if not np.isfinite(xyz).all():
        raise FdlcError(f"{what}: a coordinate is not a finite number (NaN or infinite)")
    return xyz


def apply_affine(xyz: np.ndarray, affine: np.ndarray) -> np.ndarray:
    return xyz @ affine[:3] + affine[3]


def compose_affine(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """The 4×3 affine of ``apply_affine(apply_affine(x, first), then)``."""
    hom = np.hstack([first, np.array([[0.0], [0.0], [0.0], [1.0]])])
    return hom @ then


def true_orientation(template: np.ndarray, test: np.ndarray, pairs: np.ndarray) -> int:
    """Index into ORIENTATIONS of the orientation that puts ``test`` on ``template``, from known
    pairs (template i, test j); both in their canonical frames. Used to label training pairs.

    Chirality first: the best *proper* rotation (Kabsch) fits far worse for a mirrored pair, so
    the class (proper or mirrored) with the smaller Kabsch residual wins. Within the class, the
    four flips differ from each other by proper rotations and fit equally well after Kabsch, so
    the flip that needs the *smallest* further rotation is the one. (Comparing residuals after a
    translation alone, as a first version did, mislabels strongly bent worms.)
    """
    a = template[pairs[:, 0]]
    b = test[pairs[:, 1]]
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    residuals, angles = [], []
    for orientation in ORIENTATIONS:
        bk = b @ orientation.T
        u, _, vt = np.linalg.svd(bk.T @ a)
        d = np.sign(np.linalg.det(u @ vt)) or 1.0
        rot = u @ np.diag([1, 1, d]) @ vt  # proper rotation with a ≈ bk @ rot
        residuals.append(float(((bk @ rot - a) ** 2).sum(axis=1).mean()))
        angles.append(float(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))))
    residuals = np.array(residuals)
    same_class = residuals <= residuals.min() * (1 + 1e-6) + 1e-9
    return int(np.argmin(np.where(same_class, angles, np.inf)))


def mirrored_by_names(names, xyz: np.ndarray, worm, min_names: int) -> bool | None:
    """Whether a labelled ``worm``'s named neurons fit a reference (``names`` at ``xyz``, its
    canonical frame) better mirrored than proper; None with fewer than ``min_names`` names in
    common."""
    index = {n: i for i, n in enumerate(names) if n}
    pairs = np.array([(index[n], j) for j, n in enumerate(worm.labels) if n in index])
    if len(pairs) < min_names:
        return None
    return true_orientation(xyz, canonical_frame(worm.xyz)[0], pairs) >= N_PROPER


@dataclass
class Warp:
    """Recording µm -> a reference's frame: an affine map plus a smooth displacement (Gaussian
    radial basis functions centred on the neurons it was fitted on), so that a bent worm is
    carried onto the reference's pose, not only turned and scaled."""

    affine: np.ndarray  # 4×3, see geometry.apply_affine
    centres: np.ndarray | None = None  # (K, 3) recording µm less ``origin``
    coef: np.ndarray | None = None  # (K, 3)
    sigma: float = 12.0
    # The displacement's kernels are evaluated about this point (the fitted neurons' mean):
    # squared distances expanded far from the origin lose their digits to cancellation.
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __call__(self, xyz: np.ndarray) -> np.ndarray:
        out = apply_affine(xyz, self.affine)
        if self.centres is not None and len(self.centres):
            out = out + _gauss(xyz - self.origin, self.centres, self.sigma) @ self.coef
        return out


def squared_distances(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, M) squared distances: scipy's cdist, 1.5-2× faster for a few hundred points than
    |x|² + |c|² - 2 x·c (itself far faster than broadcasting), and exact (no cancellation)."""
    return cdist(x, c, "sqeuclidean")


def _gauss(x: np.ndarray, c: np.ndarray, sigma: float) -> np.ndarray:
    return np.exp(squared_distances(x, c) / (-2 * sigma**2))


def fit_warp(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, sigma: float = 12.0, smoothness: float = 1.0) -> Warp:
    """Weighted fit of ``dst ≈ warp(src)``: first an affine map, then a Gaussian-RBF displacement
    of the residual with a ridge (``smoothness``) that keeps it smooth; ``sigma`` <= 0: affine only.

    The displacement is kernel ridge regression on a reduced basis (subset of regressors): its
    centres are the mean positions of the neurons in each occupied cell of a grid of sigma / 2,
    a few dozen for a head instead of one per neuron, which a displacement this smooth does
    not need. Fitting and applying the warp are then several times cheaper."""
    src, dst, weights = np.asarray(src, float), np.asarray(dst, float), np.asarray(weights, float)
    affine = fit_affine(src, dst, weights)
    keep = weights > 0
    if sigma <= 0 or keep.sum() < 4:
        return Warp(affine, sigma=sigma)
    x, w = src[keep], weights[keep]
    residual = dst[keep] - apply_affine(x, affine)
    origin = x.mean(axis=0)
    x = x - origin
    centres = _grid_centres(x, sigma / 2)
    basis = _gauss(x, centres, sigma)  # (K, C)
    weighted = basis.T * w
    # min sum_k w_k |basis_k c - r_k|^2 + smoothness c' G c, G the kernel between centres
    system = weighted @ basis + smoothness * _gauss(centres, centres, sigma)
    system.flat[:: len(system) + 1] += 1e-9 * np.trace(system)
    torch = sys.modules.get("torch")
    if torch is not None:  # beside torch's own threads, numpy/scipy's threaded OpenBLAS can take 50-500x longer
        factor = torch.linalg.cholesky(torch.from_numpy(system))
        coef = torch.cholesky_solve(torch.from_numpy(weighted @ residual), factor).numpy()
    else:  # no model in this process (fdlc track --method geometry): not worth torch's import
        coef = cho_solve(cho_factor(system), weighted @ residual)
    return Warp(affine, centres, coef, sigma, origin)


GRID_CUBES = 1e6  # above it _grid_centres counts occupied cubes only


def _grid_centres(xyz: np.ndarray, cell: float) -> np.ndarray:
    """The mean position of the points in each occupied cube of side ``cell`` (in the order of
    the cubes' index)."""
    index = np.floor((xyz - xyz.min(axis=0)) / cell).astype(np.int64)
    size = index.max(axis=0) + 1
    if np.prod(size.astype(float)) <= GRID_CUBES:  # one count per cube of the grid (5x faster than unique)
        cube = (index[:, 0] * size[1] + index[:, 1]) * size[2] + index[:, 2]
    else:  # positions in nm, say: ~1e12 cubes; count the occupied ones only (the same order)
        cube = np.unique(index, axis=0, return_inverse=True)[1].ravel()
    counts = np.bincount(cube)
    occupied = np.flatnonzero(counts)
    return np.column_stack([np.bincount(cube, weights=xyz[:, d])[occupied] for d in range(3)]) / counts[occupied, None]


def position_evidence(placed: np.ndarray, ref_xyz: np.ndarray, sigma: float) -> np.ndarray:
    """Within one worm a neuron stays where the warp puts it, up to segmentation jitter: the log
    likelihood ratio (N, M) of a Gaussian displacement (width ``sigma`` µm) against a partner
    anywhere in the worm, for the real columns ("no match" keeps ratio 1). It sharpens the
    tracking model's answer too (dropping it cost a point on held-out recordings) and is what
    the identification model, trained across worms, lacks most here."""
    llr = squared_distances(placed, ref_xyz)
    volume = float(np.prod(np.ptp(ref_xyz, axis=0) + 2 * sigma))
    llr *= -1 / (2 * sigma**2)
    llr += np.log(volume) - 1.5 * np.log(2 * np.pi * sigma**2)
    return llr
