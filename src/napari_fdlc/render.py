"""Synthetic NeuroPAL stacks rendered from a neuron table (for tests, benchmarks, the sample).

What makes them realistic enough to tune a detector on:

- nuclei are ellipsoids of varied size and orientation that barely overlap (a radius is capped
  by the distance to the nearest neighbour, before the axes are stretched), imaged through an
  anisotropic Gaussian PSF (the z blur of a confocal is ~4x the lateral one);
- the pan-neuronal W channel (TagRFP-T) shows every nucleus with log-normal brightness; R, G, B
  come from the table's colours (z-scores or raw values, mapped to positive intensities);
- a camera offset, background with a slow gradient, a faint haze over the worm body, gut-like
  autofluorescence (a large textured blob with granules, bright in B/G, weak in R/W) past the
  neurons at +x (``align_worm`` does not orient the body axis: in about half the worms, the
  bundled sample's among them, that is past the nose, not the posterior end; what it tests,
  a bright textured blob beside the neurons, is the same), channel bleed-through, Poisson shot
  noise and Gaussian read noise.

Each nucleus is evaluated only in a small box around it, so a 200-neuron head renders in well
under a second; the cost is dominated by the Poisson draw over the whole volume.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.special import erfc

from .io.images import FLUOROPHORES, ImageError, Stack, StackSeries
from .table import NeuronTable

CHANNELS = ("R", "G", "B", "W")

# Bleed-through: row = detected channel, column = fluorophore (R, G, B, W). CyOFP and TagRFP-T
# emit in overlapping orange bands; mNeptune's excitation catches some TagRFP-T; BFP leaks a
# little into the CyOFP (488 nm) channel.
BLEED = np.array([
    [1.00, 0.05, 0.00, 0.10],
    [0.00, 1.00, 0.05, 0.05],
    [0.00, 0.00, 1.00, 0.00],
    [0.05, 0.10, 0.00, 1.00],
])
# Photon counts far beyond what a uint16 camera records are a mistake (and overflow the draws).
MAX_PHOTONS = 1e6
# Identities are labels of a recording's neurons; each property draws max(identity) + 1 values.
MAX_IDENTITY = 10**7
# A stack of more voxels is a mistake (positions not in µm, a shape in the wrong unit): 2 GB of
# float32 photons per channel.
MAX_VOXELS = 5e8
# Relative colour of gut autofluorescence per detected channel (strong in blue/green).
GUT_COLOUR = {"R": 0.12, "G": 0.45, "B": 0.6, "W": 0.15, "GFP": 0.5}


@dataclass
class RenderParams:
    """Imaging parameters of a rendered stack (photons are per voxel at a nucleus centre)."""

    voxel_size_zyx: tuple[float, float, float] = (1.0, 0.25, 0.25)
    psf_sigma_um: tuple[float, float, float] = (0.7, 0.15, 0.15)  # z, y, x
    nucleus_radius_um: float = 1.4
    nucleus_radius_sd_um: float = 0.2
    elongation_sd: float = 0.12  # log-normal spread of the axis ratios
    brightness_sd: float = 0.35  # log-normal spread of the W brightness between nuclei
    texture: float = 0.15  # chromatin texture: SD of the multiplicative variation inside a nucleus
    peak_photons: float = 300.0  # mean W photons at a nucleus centre
    background_photons: float = 20.0
    haze: float = 0.05  # body haze, fraction of peak_photons
    gut: bool = True
    gut_strength: float = 0.6  # fraction of peak_photons
    read_noise: float = 4.0  # counts (gain 1)
    offset: float = 100.0  # camera offset, counts
    bleed: float = 1.0  # scales the off-diagonal bleed-through
    margin_um: tuple[float, float, float] = (4.0, 8.0, 8.0)  # z, y, x around the neurons
    min_spacing_um: float = 1.6  # closer centres are pushed apart (nuclei cannot overlap)


def colour_intensities(values: np.ndarray) -> np.ndarray:
    """Map one colour column (z-scores or raw) to relative intensities in about [0.05, 1.2].

    Linear (z-scores are a linear function of raw intensity) with robust ends, so the order and
    the ratios between neurons survive; the floor keeps "off" channels at a realistic faint level.
    """
    v = np.asarray(values, dtype=float)
    finite = np.isfinite(v)
    if not finite.any():
        return np.full(v.shape, 0.5)
    v = np.where(finite, v, np.median(v[finite]))  # a cell without a reading: the median, as read_table fills
    lo, hi = np.percentile(v, 2), np.percentile(v, 98)
    if not np.isfinite(hi - lo) or hi - lo <= 0:
        return np.full(v.shape, 0.5)
    return 0.05 + 0.95 * np.clip((v - lo) / (hi - lo), 0.0, 1.25)


def align_worm(xyz: np.ndarray) -> np.ndarray:
    """Rotate positions so the worm's long axis is x and its thinnest axis is z (proper rotation).

    Real stacks image a head lying on its side with the long axis in the image plane.
    """
    centred = xyz - xyz.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=len(centred) < 3)  # vt 3 x 3 for 1 or 2 neurons too
    if np.linalg.det(vt) < 0:
        vt[2] *= -1
    return centred @ vt.T


def render_stack(
    table: NeuronTable,
    params: RenderParams | None = None,
    shape_zyx: Sequence[int] | None = None,
    align: bool = True,
    gfp: bool = False,
    seed: int = 0,
    identity: np.ndarray | None = None,
    identity_seed: int = 0,
    **overrides,
) -> tuple[Stack, NeuronTable]:
    """Render a 4-channel (R, G, B, W; + GFP with ``gfp``) uint16 stack of ``table``'s neurons.

    Positions are rotated (``align``) and shifted into the stack; ``shape_zyx`` defaults to the
    neurons' extent plus margins (with a given shape the worm is centred and neurons outside are
    left out of the truth). Returns the stack and the ground truth in the stack frame: ``x_um,
    y_um, z_um`` as in :mod:`napari_fdlc.io.images`, the input colours and labels, the rendered
    ``W`` brightness, and extra columns ``radius_um`` and ``R_int, G_int, B_int`` (relative
    intensities actually rendered). ``overrides`` set :class:`RenderParams` fields.

    ``identity`` (one integer per neuron, -1 = none) keeps each neuron's own properties (size,
    shape, brightness, GFP activity; drawn from ``identity_seed``) the same in every stack
    rendered with it: the volumes of one recording. The noise comes from ``seed``.
    """
    p = _checked(RenderParams(**{**(params.__dict__ if params else {}), **overrides}))
    rng = np.random.default_rng(seed)
    if len(table) == 0:
        raise ImageError("render: the neuron table is empty")
    if not np.isfinite(table.xyz).all():
        raise ImageError("render: the neuron table has positions that are not finite numbers")
    vz, vy, vx = p.voxel_size_zyx
    vox = np.array([vz, vy, vx])
    xyz = align_worm(table.xyz) if align else table.xyz - table.xyz.mean(axis=0)
    xyz = spread_apart(xyz, p.min_spacing_um)
    zyx = xyz[:, ::-1]
    margin = np.asarray(p.margin_um, dtype=float)
    if shape_zyx is None:
        shape = _shape_of(zyx.max(axis=0) - zyx.min(axis=0) + 2 * margin, vox)
    else:
        try:
            shape = np.asarray(shape_zyx, dtype=int)
        except (TypeError, ValueError):
            shape = np.zeros(0, dtype=int)  # not sizes at all: refused below
        # the product in floats: in int64 (2**21, 2**21, 2**22) came to 0 and passed
        if shape.shape != (3,) or (shape < 1).any() or np.prod(shape.astype(float)) > MAX_VOXELS:
            raise ImageError(f"render: shape_zyx must be 3 positive sizes of at most {MAX_VOXELS:.0e} voxels in all, "
                             f"not {shape_zyx!r}")
    if np.prod(shape.astype(float)) > MAX_VOXELS:
        raise ImageError(f"render: the neurons span {tuple(int(v) for v in shape)} voxels, more than {MAX_VOXELS:.0e}: "
                         "are the positions in µm?")
    centre_um = (shape - 1) * vox / 2
    zyx = zyx - (zyx.max(axis=0) + zyx.min(axis=0)) / 2 + centre_um
    n = len(zyx)
    if identity is not None:
        identity = np.asarray(identity)
        if identity.shape != (n,) or not np.issubdtype(identity.dtype, np.integer) or identity.max(initial=0) > MAX_IDENTITY:
            raise ImageError(f"render: identity must be one whole number per neuron ({n}), -1 to {MAX_IDENTITY:.0e}")

    properties = itertools.count()  # each property's own stream of identity_seed

    def per_neuron(draw):
        """A property per neuron, ``draw(generator, count)``: from ``rng``, or the same for the
        same ``identity`` in every call (neurons without one get their own). With ``identity``
        each property has its own stream, and ``draw`` must make one call of the generator (its
        first values then do not depend on how many identities there are)."""
        stream = next(properties)
        if identity is None:
            return draw(rng, n)
        ids = np.asarray(identity, dtype=int)
        fixed = draw(np.random.default_rng([identity_seed, stream]), int(ids.max(initial=0)) + 1)[np.maximum(ids, 0)]
        return np.where((ids >= 0).reshape((n,) + (1,) * (fixed.ndim - 1)), fixed, draw(rng, n))

    # Nucleus geometry: radius capped by the nearest neighbour so nuclei touch but never overlap.
    nn = cKDTree(zyx).query(zyx, k=2)[0][:, 1] if n > 1 else np.full(n, np.inf)
    radius = per_neuron(lambda g, m: g.normal(p.nucleus_radius_um, p.nucleus_radius_sd_um, m))
    radius = np.clip(radius, 0.6 * p.nucleus_radius_um, 1.6 * p.nucleus_radius_um)
    radius = np.minimum(radius, np.maximum(0.48 * nn, 0.5))
    ratios = np.exp(per_neuron(lambda g, m: g.normal(0.0, p.elongation_sd, (m, 3))))
    ratios /= np.cbrt(ratios.prod(axis=1, keepdims=True))  # keep the volume of the sphere
    semi = radius[:, None] * ratios  # z, y, x semi-axes before the in-plane rotation
    angle = per_neuron(lambda g, m: g.uniform(0, np.pi, m))

    # Channel amplitudes (relative; W = 1 on average).
    w_bright = np.exp(per_neuron(lambda g, m: g.normal(0.0, p.brightness_sd, m)))
    if "W" in table.colours:
        w_bright *= np.exp(0.25 * _zscore(table.colours["W"]))
    colour_int = {}
    for c in ("R", "G", "B"):
        if c in table.colours:
            colour_int[c] = colour_intensities(table.colours[c])
        else:  # NeuroPAL-like: each colour channel clearly on or off in a neuron
            colour_int[c] = per_neuron(lambda g, m: _on_or_off(g.random((m, 3)), 0.55, (0.3, 1.0), (0.03, 0.1)))
    amps = np.stack([colour_int["R"], colour_int["G"], colour_int["B"], w_bright], axis=1)
    mix = np.eye(4) + p.bleed * (BLEED - np.eye(4))
    amps_detected = amps @ mix.T  # bleed-through happens per fluorophore, before noise
    channels = list(CHANNELS)
    if gfp:
        activity = per_neuron(lambda g, m: _on_or_off(g.random((m, 3)), 0.3, (0.3, 1.0), (0.0, 0.05)))
        amps_detected = np.concatenate([amps_detected, activity[:, None]], axis=1)
        channels.append("GFP")
    n_ch = len(channels)

    photons = np.zeros((n_ch,) + tuple(shape), dtype=np.float32)
    psf = np.asarray(p.psf_sigma_um, dtype=float)
    for i in range(n):
        box, profile = _nucleus_profile(zyx[i], semi[i], angle[i], psf, vox, shape)
        if profile is None:
            continue
        if p.texture > 0:  # chromatin: smooth blotches ~0.4 µm, the same in every channel
            blotch = ndimage.gaussian_filter(rng.standard_normal(profile.shape).astype(np.float32), 0.4 / vox)
            blotch *= p.texture / (blotch.std() + 1e-6)
            profile = profile * np.clip(1.0 + blotch, 0.2, None)
        for c in range(n_ch):
            photons[(c,) + box] += (p.peak_photons * amps_detected[i, c]) * profile

    _add_background(photons, zyx, p, channels, shape, vox, rng)
    brightest = float(photons.max())
    if not brightest <= MAX_PHOTONS * 1e3:  # (NaN too) numpy's Poisson draw refuses lam above ~1e19
        raise ImageError(f"render: the settings make {brightest:.1e} photons in a voxel; background_photons, haze, "
                         "gut_strength or bleed is too large")
    data = np.empty(photons.shape, dtype=np.uint16)
    for c in range(n_ch):  # one channel at a time: Poisson draws are int64, 4x the image
        counts = rng.poisson(np.maximum(photons[c], 0)).astype(np.float32)
        counts += p.offset + p.read_noise * rng.standard_normal(counts.shape, dtype=np.float32)
        np.clip(np.rint(counts), 0, 65535, out=counts)
        data[c] = counts

    inside = np.all((zyx >= -0.5 * vox) & (zyx <= (shape - 0.5) * vox), axis=1)
    stack = Stack(
        data, tuple(float(v) for v in vox), channels, source=f"<rendered seed={seed}>",
        channel_names=[FLUOROPHORES[c] for c in channels],
    )
    extra = table.extra.copy() if table.extra is not None else pd.DataFrame(index=range(n))
    extra["radius_um"] = radius
    for k, c in enumerate(("R", "G", "B")):
        extra[f"{c}_int"] = amps[:, k]
    extra["z_px"], extra["y_px"], extra["x_px"] = (zyx / vox).T
    truth = NeuronTable(
        xyz=zyx[:, ::-1],
        colours={**{c: v for c, v in table.colours_as_read().items() if c in ("R", "G", "B")}, "W": w_bright},
        labels=table.labels,
        label_conf=table.label_conf,
        extra=extra,
        source=f"{table.source} (rendered)",
    )
    for k, c in enumerate(("R", "G", "B")):  # the truth carries the colours that were actually rendered
        if c not in table.colours:
            truth.colours[c] = amps[:, k]
    return stack, truth.subset(np.flatnonzero(inside))


def render_recording(
    volumes: list[NeuronTable],
    identities: list[np.ndarray],
    params: RenderParams | None = None,
    seed: int = 0,
    **overrides,
) -> tuple[StackSeries, list[NeuronTable]]:
    """Render a recording of one worm: :func:`napari_fdlc.track.simulate_sequence`'s volumes and
    the source neuron of each of their neurons (``identities``, -1 = spurious), one stack per
    time point, all of one shape (the largest extent of any volume), each volume centred in it
    (drift in the field of view is left out) and in its own frame (no alignment: the worm turns
    and bends as the volumes do). A neuron keeps its size (within the cap that keeps it off its
    nearest neighbour in each volume), shape and brightness over time; each
    time point has its own noise (seed ``seed + 1 + t``). Returns the recording (T, C, Z, Y, X)
    and the ground truth per time point, as :func:`render_stack`'s."""
    if not volumes:
        raise ImageError("render: the recording has no volume")
    if len(identities) != len(volumes):  # zip dropped the volumes past the shorter list
        raise ImageError(f"render: {len(volumes)} volumes but {len(identities)} identity arrays; give one per volume")
    for t, v in enumerate(volumes):  # before the extent below is taken over them
        if len(v) == 0 or not np.isfinite(v.xyz).all():
            raise ImageError(f"render: volume {t} of the recording is empty or has positions that are not finite numbers")
    p = _checked(RenderParams(**{**(params.__dict__ if params else {}), **overrides}))
    vox = np.asarray(p.voxel_size_zyx, dtype=float)
    margin = np.asarray(p.margin_um, dtype=float)
    # the extent of the positions as render_stack places them (close centres pushed apart): from
    # the raw ones, with no margin, neurons pushed past the end were left out of the truth
    placed = [spread_apart(v.xyz - v.xyz.mean(axis=0), p.min_spacing_um) for v in volumes]
    shape = _shape_of(np.max([np.ptp(xyz[:, ::-1], axis=0) for xyz in placed], axis=0) + 2 * margin, vox)
    rendered = [render_stack(v, p, shape_zyx=shape, align=False, seed=seed + 1 + t, identity=ids, identity_seed=seed)
                for t, (v, ids) in enumerate(zip(volumes, identities))]
    first = rendered[0][0]
    series = StackSeries(np.stack([stack.data for stack, _ in rendered]), first.voxel_size_zyx, first.channel_roles,
                         source=f"<rendered recording seed={seed}>", channel_names=first.channel_names)
    return series, [truth for _, truth in rendered]


def _shape_of(extent_zyx: np.ndarray, vox: np.ndarray) -> np.ndarray:
    """Voxels (z, y, x) that hold ``extent_zyx`` µm; refused past MAX_VOXELS while still in floats
    (positions ×1e20 overflowed to a 3 × 3 × 3 stack, rendered empty without a word)."""
    voxels = np.ceil(extent_zyx / vox) + 1
    if not np.isfinite(voxels).all() or np.prod(voxels) > MAX_VOXELS:
        raise ImageError(f"render: the neurons span more than {MAX_VOXELS:.0e} voxels: are the positions in µm?")
    return np.maximum(voxels.astype(int), 3)


def spread_apart(xyz: np.ndarray, min_spacing_um: float, iterations: int = 20) -> np.ndarray:
    """Push centres closer than ``min_spacing_um`` apart (symmetrically), leaving the others.

    Generated worms sample each neuron independently, so two can land on top of each other;
    real nuclei never overlap.
    """
    xyz = np.array(xyz, dtype=float)
    if min_spacing_um <= 0 or len(xyz) < 2:
        return xyz
    for _ in range(iterations):
        pairs = cKDTree(xyz).query_pairs(min_spacing_um * 0.999, output_type="ndarray")
        if len(pairs) == 0:
            break
        d = xyz[pairs[:, 1]] - xyz[pairs[:, 0]]
        dist = np.linalg.norm(d, axis=1, keepdims=True)
        direction = np.where(dist > 1e-9, d / np.maximum(dist, 1e-9), np.array([[1.0, 0.0, 0.0]]))
        push = 0.5 * (min_spacing_um - dist) * direction
        np.add.at(xyz, pairs[:, 1], push)
        np.add.at(xyz, pairs[:, 0], -push)
    return xyz


def _on_or_off(u: np.ndarray, p_on: float, on: tuple[float, float], off: tuple[float, float]) -> np.ndarray:
    """Per row of uniforms ``u`` (m, 3): on (with probability ``p_on``) or off, and a level
    uniform in that state's range. One draw of the generator per property (see per_neuron)."""
    return np.where(u[:, 0] < p_on, on[0] + (on[1] - on[0]) * u[:, 1], off[0] + (off[1] - off[0]) * u[:, 2])


def _checked(p: RenderParams) -> RenderParams:
    """``p`` with its settings as floats, or an ImageError naming the first setting that cannot
    be rendered: a tuple setting (z, y, x) needs three numbers, every other one a number."""
    defaults = RenderParams()
    numbers = {}
    for name, value in vars(p).items():
        if isinstance(value, bool):  # gut
            continue
        size = np.size(getattr(defaults, name))
        try:
            v = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            v = np.array(np.nan)
        if v.size != size or not np.isfinite(v).all() or (v < 0).any():
            what = "3 finite numbers (z, y, x)" if size == 3 else "a finite number"
            raise ImageError(f"render: {name} must be {what} of 0 or more, not {value!r}")
        numbers[name] = tuple(v.ravel().tolist()) if size == 3 else float(v)
    p = RenderParams(**{**vars(p), **numbers})
    if min(p.voxel_size_zyx) <= 0 or p.nucleus_radius_um <= 0:
        raise ImageError("render: the voxel size and the nucleus radius must be above 0")
    if not 0 < p.peak_photons <= MAX_PHOTONS:
        raise ImageError(f"render: peak_photons must be above 0 and at most {MAX_PHOTONS:.0e}, not {p.peak_photons}")
    return p


def _zscore(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    sd = v.std()
    return (v - v.mean()) / sd if sd > 0 else np.zeros_like(v)


def _nucleus_profile(centre, semi, angle, psf, vox, shape):
    """Blurred ellipsoid in a local box: 0.5 erfc((|d| - r(u)) / (sqrt(2) s(u))).

    r(u) is the ellipsoid radius along the direction u and s(u) the PSF width along u: exact for
    the edge of a large object, which nuclei (r ~ 1.4 µm vs PSF 0.15-0.6 µm) are.
    """
    reach = semi.max() + 3.0 * psf + vox
    lo = np.maximum(np.floor((centre - reach) / vox).astype(int), 0)
    hi = np.minimum(np.ceil((centre + reach) / vox).astype(int) + 1, shape)
    if np.any(hi <= lo):
        return None, None
    dz, dy, dx = np.meshgrid(
        *(np.arange(a, b) * v - c for a, b, v, c in zip(lo, hi, vox, centre)), indexing="ij", sparse=True
    )
    ca, sa = np.cos(angle), np.sin(angle)
    u_y = ca * dy + sa * dx  # in-plane rotation of the ellipsoid's axes
    u_x = -sa * dy + ca * dx
    dist = np.sqrt(dz * dz + u_y * u_y + u_x * u_x)
    safe = np.maximum(dist, 1e-6)
    with np.errstate(divide="ignore"):  # a voxel at the very centre (1 / 0): replaced below
        r = 1.0 / np.sqrt((dz / safe / semi[0]) ** 2 + (u_y / safe / semi[1]) ** 2 + (u_x / safe / semi[2]) ** 2)
    # The PSF is axis-aligned (optical axis z), so its width along u uses the unrotated offsets.
    s = np.sqrt((dz / safe * psf[0]) ** 2 + (dy / safe * psf[1]) ** 2 + (dx / safe * psf[2]) ** 2)
    s = np.maximum(s, 0.05)
    at_centre = dist < 1e-6
    r = np.where(at_centre, semi.min(), r)
    s = np.where(at_centre, psf.max(), s)
    profile = 0.5 * erfc((dist - r) / (np.sqrt(2.0) * s))
    return tuple(slice(a, b) for a, b in zip(lo, hi)), profile.astype(np.float32)


def _add_background(photons, zyx, p: RenderParams, channels, shape, vox, rng) -> None:
    """Background gradient, body haze and gut autofluorescence, in place."""
    z = (np.arange(shape[0]) * vox[0])[:, None, None]
    y = (np.arange(shape[1]) * vox[1])[None, :, None]
    x = (np.arange(shape[2]) * vox[2])[None, None, :]
    ext = (np.asarray(shape) - 1) * vox
    gradient = 1.0 + 0.3 * (x / max(ext[2], 1e-6)) + 0.15 * (y / max(ext[1], 1e-6))
    centre = zyx.mean(axis=0)
    # Body haze: a soft cylinder along the worm's long axis (x after alignment).
    spread = np.maximum(zyx.std(axis=0), 1.0)
    body = np.exp(-0.5 * (((z - centre[0]) / (1.5 * spread[0])) ** 2 + ((y - centre[1]) / (1.5 * spread[1])) ** 2))
    along = np.clip((x - zyx[:, 2].min() + 10) / 10, 0, 1)
    base = (p.background_photons * gradient + p.haze * p.peak_photons * body * along).astype(np.float32)
    gut = _gut(zyx, p, shape, vox, rng) if p.gut else None
    for c, name in enumerate(channels):
        photons[c] += base
        if gut is not None:
            photons[c] += (p.gut_strength * p.peak_photons * GUT_COLOUR[name]) * gut


def _gut(zyx, p: RenderParams, shape, vox, rng) -> np.ndarray | None:
    """Relative gut autofluorescence: a textured ellipsoid past the neurons at +x (the posterior
    end only when the worm lies that way; see the module's docstring)."""
    posterior = zyx[:, 2].max()
    spread = np.maximum(zyx.std(axis=0), 2.0)
    centre = np.array([zyx[:, 0].mean(), zyx[:, 1].mean(), posterior + rng.uniform(4.0, 12.0)])
    semi = np.array([1.2 * spread[0], 1.2 * spread[1], rng.uniform(15.0, 25.0)])
    reach = semi + 4.0
    lo = np.maximum(np.floor((centre - reach) / vox).astype(int), 0)
    hi = np.minimum(np.ceil((centre + reach) / vox).astype(int) + 1, shape)
    gut = np.zeros(tuple(shape), dtype=np.float32)
    if np.any(hi <= lo):
        return None
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    dz, dy, dx = np.meshgrid(
        *(np.arange(a, b) * v - c for a, b, v, c in zip(lo, hi, vox, centre)), indexing="ij", sparse=True
    )
    rho = np.sqrt((dz / semi[0]) ** 2 + (dy / semi[1]) ** 2 + (dx / semi[2]) ** 2)
    envelope = 0.5 * erfc((rho - 1.0) * 4.0)
    # Low-frequency texture: smoothed noise on the box (cheap; the box is only part of the stack).
    noise = rng.standard_normal(envelope.shape).astype(np.float32)
    texture = ndimage.gaussian_filter(noise, sigma=np.maximum(1.5 / vox, 0.5))
    texture /= texture.std() + 1e-6
    gut[box] = envelope * np.clip(0.6 + 0.3 * texture, 0.0, None)
    # Granules: small bright spheres inside the gut (0.3-0.6 µm), much smaller than nuclei.
    n_gran = int(rng.integers(40, 120))
    pts = centre + (rng.uniform(-1, 1, (n_gran * 3, 3)) * semi)
    pts = pts[(((pts - centre) / semi) ** 2).sum(axis=1) < 0.8][:n_gran]
    for q in pts:
        r = rng.uniform(0.3, 0.6)
        b, prof = _nucleus_profile(q, np.full(3, r), 0.0, np.asarray(p.psf_sigma_um), vox, shape)
        if prof is not None:
            gut[b] += rng.uniform(0.8, 2.0) * prof
    return gut


def random_worm(
    n: int = 60,
    size_um: Sequence[float] = (50.0, 16.0, 12.0),
    min_spacing_um: float = 2.6,
    seed: int = 0,
) -> NeuronTable:
    """A quick unnamed "worm" for tests: ``n`` centres in an ellipsoid of ``size_um`` (x, y, z
    diameters) at least ``min_spacing_um`` apart, with NeuroPAL-like raw R, G, B colours.

    (``napari_fdlc.reference.generate_worm`` makes realistic, named worms from the atlas.)
    """
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ImageError(f"random_worm: n must be a whole number of neurons, at least 1 (got {n!r})")
    rng = np.random.default_rng(seed)
    semi = np.asarray(size_um, dtype=float) / 2
    points: list[np.ndarray] = []
    tries = 0
    while len(points) < n and tries < 200 * n:
        tries += 1
        q = rng.uniform(-1, 1, 3)
        if (q**2).sum() > 1:
            continue
        q = q * semi
        if points and np.min(np.linalg.norm(np.asarray(points) - q, axis=1)) < min_spacing_um:
            continue
        points.append(q)
    if len(points) < n:
        raise ImageError(f"cannot place {n} neurons {min_spacing_um} µm apart in {tuple(size_um)} µm")
    xyz = np.asarray(points) + semi
    on = rng.random((n, 3)) < 0.55
    raw = np.where(on, rng.uniform(300, 1000, (n, 3)), rng.uniform(20, 80, (n, 3)))
    return NeuronTable(xyz, {c: raw[:, i] for i, c in enumerate("RGB")}, source=f"random_worm(seed={seed})")
