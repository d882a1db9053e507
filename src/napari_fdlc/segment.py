"""Nuclei centres and NeuroPAL colours from a 3D stack.

Detection runs on the pan-neuronal W channel (TagRFP-T), or on the sum of the channels (each
scaled to its own range) when no channel is marked W:

1. bin in x/y (mean of b x b voxels) until a voxel is about a sixth of a nucleus across: NeuroPAL
   stacks are sampled much finer in x/y than in z, and nuclei are 2-4 µm, so this loses nothing
   and makes everything after it several times faster;
2. band-pass with a difference of Gaussians whose widths are set in µm, so anisotropic voxels
   get anisotropic sigmas. The narrow one (0.2 diameter) and the wide one (0.4 diameter) make it
   close to a Laplacian of Gaussian: it responds to the curvature of a nucleus rather than to its
   brightness, so a dim nucleus pressed against a bright one still has its own maximum (a plain
   smoothing would turn it into a shoulder of its neighbour), and smooth background, haze and
   gut autofluorescence are removed;
3. local maxima of the response (a box a little smaller than a nucleus), kept when they exceed a
   noise threshold (a multiple of the response's robust SD) and a fraction of the bright nuclei's
   response (so a very clean image does not turn texture into detections);
4. sub-voxel centres by fitting a parabola through the response along each axis;
5. maxima closer than 0.8 diameter are merged unless the response dips between them (the
   "valley" test, sampled along the segment joining them): a large or elongated nucleus has
   several maxima on one plateau, two touching nuclei have a valley. A fixed minimum distance
   would have to choose between splitting big nuclei and merging small touching ones;
6. steps 2-5 again at 0.8 of the diameter and twice the threshold; fine-scale nuclei more than
   0.6 diameter from every detection are added (a small dim nucleus pressed against a bright one);
7. NeuroPAL colours neighbours differently: a nucleus that W shows only as a shoulder of its
   neighbour but R, G or B separates is added (:func:`split_by_colour`).

Colours are read at each centre in a small ellipsoid (radius in µm): the 75th percentile of the
voxels there (robust to a neighbour's edge and to the nucleus being smaller than the ellipsoid),
minus the local background (20th percentile of a shell around it). The pan-neuronal marker
bleeds into the colour channels (TagRFP-T into the mNeptune and CyOFP channels): its share is
estimated from the volume itself, as the slope of the lower envelope of each colour against W
(most neurons lack any one colour, so their readout there is floor plus bleed), and removed
from R and G (:func:`w_bleed_slopes`). Then each channel is z-scored across the volume, as
NeuroPAL_ID does.

Everything is vectorised with scipy.ndimage / numpy; see ``docs/segmentation.md`` for accuracy
and speed.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pandas as pd
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import FdlcError, warn
from .io.images import ImageError, Stack, StackSeries
from .table import NeuronTable, positions

Progress = Callable[[float, str], None]
MAX_DIAMETER_UM = 20.0  # a nucleus diameter beyond this is not a nucleus (neurons' are 2-4 µm)
SATURATED_MIN_VOXELS = 8  # voxels at the volume's maximum that make a clipped plateau
MAX_THRESHOLD = 1000.0  # noise SDs: nuclei stand 10-100 SDs above the noise; beyond this, nothing
# Below it noise maxima pass as nuclei, more of them than a worm has neurons, and slowly: the
# bundled sample (151 nuclei) gives 159 at 2 SDs, 6521 at 1.5 and 16508 at 0.5 (in 84 s).
MIN_THRESHOLD = 2.0
# Voxels sampled around a nucleus for its colour, at most (a shell at 0.05 µm voxels holds
# ~460 000: gigabytes for a head's neurons; NeuroPAL's voxel sizes take a few hundred).
MAX_OFFSETS = 4096
BLANK_MIN_FRACTION = 0.01  # of the volume at its lowest value before a blank region is looked for (_fill_blank)
FINE_SCALE = 0.8  # second detection scale, a fraction of the nucleus diameter (see detect_nuclei)
# split_by_colour: a colour maximum between COLOUR_NEAR and FINE_SEPARATION diameters from a
# detection (1.35-1.8 µm at 3 µm) is a nucleus of its own only where that colour is weaker than
# COLOUR_RATIO of its own at the detection: a neighbour of another colour, not the edge of a big
# nucleus of the same colour (fitted on 8 rendered worms per lab, docs/segmentation.md).
COLOUR_NEAR = 0.45
COLOUR_RATIO = 0.7
FINE_SEPARATION = 0.6  # diameters: a fine-scale maximum nearer a nominal detection is that nucleus
# A colour-channel maximum counts as a nucleus when W there responds at least this fraction as
# strongly as at the median detection (rendered corpus worms: nuclei 0.39-0.95, others <= 0.17).
COLOUR_SPLIT_MIN_W = 0.3
COLOUR_ROLES = ("R", "G", "B")  # NeuroPAL's identity colours (W is in every neuron)


def _report(progress: Progress | None, fraction: float, message: str) -> None:
    if progress is not None:
        progress(float(fraction), message)


def _narrow(values: np.ndarray) -> np.ndarray:
    """Pixels that float32 holds as they are (8/16-bit, float32), or else (float64, 32/64-bit
    integers: beyond float32's range, or a large offset it would round away) centred on their
    median and scaled by their spread, as float32. The band-pass is linear and detection is in
    noise SDs, so this moves no nucleus."""
    values = np.asarray(values)
    if values.dtype.itemsize <= 2:
        return values
    if values.dtype == np.float32 and not np.nanmax(np.abs(values[:: max(1, values.shape[0] // 8)]), initial=0) > 1e37:
        return values  # (near float32's maximum, binning's sums overflowed: rescaled below)
    sub = values[:: max(1, values.shape[0] // 8), ::4, ::4].astype(np.float64)
    lo, hi = np.percentile(sub, [50, 99.9])
    spread = hi - lo if hi > lo else float(np.max(np.abs(sub - lo))) or 1.0
    return ((values.astype(np.float64) - lo) / spread).astype(np.float32)


def detection_image(stack: Stack) -> np.ndarray:
    """The Z, Y, X float32 volume that nuclei are found on: W, else the scaled sum of the
    channels with a role (of all channels when none has one), GFP left out."""
    w = stack.role_index("W")
    if w is not None:
        return _narrow(stack.channel(w)).astype(np.float32, copy=False)
    roles = stack.channel_roles
    use = [i for i, r in enumerate(roles) if r not in (None, "GFP")] or [i for i, r in enumerate(roles) if r != "GFP"]
    if not use:
        raise ImageError(f"{stack.source}: no channel to find nuclei in (GFP is activity, not nuclei); "
                         "give the W (pan-neuronal) channel's role, or the colour channels'")
    total = np.zeros(stack.shape_zyx, dtype=np.float32)
    for i in use:
        ch = _narrow(stack.channel(i)).astype(np.float32, copy=False)
        sub = ch[:: max(1, ch.shape[0] // 8), ::4, ::4]
        lo, hi = np.percentile(sub, [50, 99.9])
        # Equal weight per channel whatever its gain; a channel dark but for a few spots (its
        # 99.9th percentile at its median) is scaled by its brightest voxel instead.
        spread = hi - lo if hi > lo else float(ch.max()) - lo
        if spread > 0:
            total += (ch - lo) / spread
    return total


def check_detection_options(diameter_um: float, threshold: float, names=("nucleus diameter", "detection threshold"),
                            voxel_size_zyx=None) -> None:
    """Refuse a nucleus diameter or a detection threshold that cannot be meant (before any
    work: a diameter of metres would bin the stack away, slowly), or voxels coarser than a
    nucleus across (more than two in z): nm taken for µm found 382 'nuclei' among 20, silently,
    and 1e160 µm overflowed into a traceback. ``names`` say them as the caller's options."""
    if not (0 < diameter_um <= MAX_DIAMETER_UM):
        raise ImageError(f"{names[0]} must be a number of µm above 0 and at most {MAX_DIAMETER_UM:g} "
                         f"(C. elegans neuron nuclei are 2-4 µm; got {diameter_um})")
    if not (np.isfinite(threshold) and MIN_THRESHOLD <= threshold <= MAX_THRESHOLD):
        raise ImageError(f"{names[1]} must be a number of noise SDs from {MIN_THRESHOLD:g} to {MAX_THRESHOLD:g} "
                         f"(got {threshold}; below {MIN_THRESHOLD:g}, noise passes as nuclei)")
    # after the diameter's own check (a diameter of 0 is not the voxels' fault); three numbers
    # only (any other voxel size is refused, in its words, where it is read)
    try:
        voxel = np.asarray(voxel_size_zyx, dtype=float) if voxel_size_zyx is not None else None
    except (TypeError, ValueError):
        voxel = None
    if voxel is not None and voxel.shape == (3,):
        widest = np.array([2.0, 1.0, 1.0]) * diameter_um
        if np.any(voxel > widest):
            raise ImageError(f"voxel size {' × '.join(f'{v:g}' for v in voxel_size_zyx)} µm (z, y, x) is coarser than a "
                             f"nucleus of {diameter_um:g} µm (at most {widest[0]:g} in z, {widest[1]:g} in y and x): "
                             "no nucleus can be found at that sampling; is it in µm (not nm)?")


def _bin_factors(voxel_size_zyx, diameter_um: float) -> tuple[int, int, int]:
    target = diameter_um / 6.0
    return tuple(max(1, int(target // v)) for v in voxel_size_zyx)  # type: ignore[return-value]


def _bin(volume: np.ndarray, factors) -> np.ndarray:
    """Mean of each block of ``factors`` voxels, as float32 (any input dtype; an edge that does
    not fill a block is dropped). Summed from strided views: 7x faster than a reshaped mean over
    every other axis, which numpy walks with poor locality."""
    volume = _narrow(np.asarray(volume))  # a lazy (dask) channel is read here
    if all(f == 1 for f in factors):
        return volume.astype(np.float32, copy=False)
    shape = tuple(s // f for s, f in zip(volume.shape, factors))
    if np.prod(factors) > 512:  # a block this large: one reshaped mean, not a Python loop per offset
        block = volume[tuple(slice(0, n * f) for n, f in zip(shape, factors))].astype(np.float32)
        return block.reshape(shape[0], factors[0], shape[1], factors[1], shape[2], factors[2]).mean(axis=(1, 3, 5))
    out = np.zeros(shape, dtype=np.float32)
    for offset in np.ndindex(*factors):
        out += volume[tuple(slice(o, n * f, f) for o, n, f in zip(offset, shape, factors))]
    out *= np.float32(1.0 / np.prod(factors))
    return out


def detect_nuclei(volume: np.ndarray, voxel_size_zyx: tuple[float, float, float], diameter_um: float = 3.0,
                  threshold: float = 6.0, **options) -> tuple[np.ndarray, np.ndarray]:
    """Nucleus centres in a Z, Y, X volume (``options``: the keywords below, defaults in
    :func:`_detect_nuclei`).

    Returns ``(zyx_um, score)``: centres in µm (voxel ``i`` at ``i * size``) and the band-pass
    response at each centre in units of the response's noise SD, strongest first.

    ``threshold``: minimum score. ``min_relative``: minimum response as a fraction of the 95th
    percentile of the candidates' responses. ``sigma_fraction``: the two DoG widths as fractions
    of ``diameter_um``. ``saddle``: two maxima closer than ``merge_distance_um`` (default 0.8
    diameter) are kept apart only if the response between them falls below ``saddle`` times the
    weaker one, and by more than ``valley_sd`` noise SDs. ``min_distance_um`` (default 0.3
    diameter): closer maxima are always merged. ``fine_scale``: also detect at this fraction of
    the diameter, at twice the threshold, and add what lies more than ``FINE_SEPARATION``
    diameters from every detection (None: one scale only). ``band_passed``: the volume's
    :func:`_band_pass` at this diameter when the caller has it already.
    """
    check_detection_options(diameter_um, threshold, voxel_size_zyx=voxel_size_zyx)
    return _detect_nuclei(volume, voxel_size_zyx, diameter_um, threshold, **options)


def _detect_nuclei(
    volume: np.ndarray,
    voxel_size_zyx: tuple[float, float, float],
    diameter_um: float = 3.0,
    threshold: float = 6.0,
    min_relative: float = 0.08,
    min_distance_um: float | None = None,
    progress: Progress | None = None,
    sigma_fraction: tuple[float, float] = (0.2, 0.4),
    saddle: float = 0.9,
    merge_distance_um: float | None = None,
    valley_sd: float = 0.0,
    fine_scale: float | None = FINE_SCALE,
    band_passed: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`detect_nuclei` without its options' check: the finer scale runs at twice the
    threshold, which may pass the largest a user may give."""
    vox = np.asarray(voxel_size_zyx, dtype=float)
    if vox.shape != (3,) or not (np.isfinite(vox).all() and (vox > 0).all()):
        raise ImageError(f"voxel size {tuple(voxel_size_zyx)} (z, y, x µm): give three positive numbers")
    if min_distance_um is None:
        min_distance_um = 0.3 * diameter_um
    _report(progress, 0.1, "band-pass filtering")
    response, factors, med, noise = band_passed or _band_pass(volume, vox, diameter_um, sigma_fraction)
    bvox = vox * factors

    _report(progress, 0.5, "finding maxima")
    half = np.maximum(np.floor(0.5 * min_distance_um / bvox), 1).astype(int)
    size = tuple(2 * half + 1)
    maxed = ndimage.maximum_filter(response, size=size, mode="nearest")
    peaks = (response == maxed) & (response > med + threshold * noise)
    idx = np.argwhere(peaks)
    if len(idx) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    values = response[tuple(idx.T)]
    ref = np.percentile(values, 95)
    keep = values >= med + min_relative * (ref - med)
    idx, values = idx[keep], values[keep]

    _report(progress, 0.7, "refining centres")
    order = np.argsort(-values)
    idx, values = idx[order], values[order]
    sub_idx = idx + _parabola_offsets(response, idx)  # binned voxel units
    # Binned voxel j covers original voxels j*f .. j*f+f-1, so its centre is at j*f + (f-1)/2.
    zyx = (sub_idx * factors + (factors - 1) / 2.0) * vox
    keep = _merge_without_valley(
        response - med, sub_idx, zyx, values - med, min_distance_um, merge_distance_um or 0.8 * diameter_um,
        saddle, valley_sd * noise,
    )
    zyx, score = zyx[keep], (values[keep] - med) / noise
    if volume is not None:
        zyx, score = _one_per_saturated_nucleus(volume, vox, zyx, score, diameter_um)
    if fine_scale:
        # A small, dim nucleus pressed against a brighter one (2.2 µm apart, 2.5x dimmer) is a
        # shoulder at the nominal scale; a finer band-pass separates them. Only strong fine
        # maxima away from every nominal detection are added, so noise and big nuclei gain
        # nothing: on rendered corpus worms recall rose 0.96 -> 0.98 (0.92 -> 0.95 dense) at
        # realistic noise with precision >= 0.99, and nothing changed at very high noise
        # (docs/segmentation.md).
        fine, fine_score = _detect_nuclei(
            volume, voxel_size_zyx, fine_scale * diameter_um, 2 * threshold, min_relative,
            sigma_fraction=sigma_fraction, saddle=saddle, valley_sd=valley_sd, fine_scale=None)
        if len(zyx) and len(fine):
            away = cKDTree(zyx).query(fine)[0] > FINE_SEPARATION * diameter_um
            fine, fine_score = fine[away], fine_score[away]
        zyx, score = np.vstack([zyx, fine]), np.concatenate([score, fine_score])
        order = np.argsort(-score, kind="stable")
        zyx, score = zyx[order], score[order]
    return zyx, score


def _band_pass(volume: np.ndarray, vox: np.ndarray, diameter_um: float, sigma_fraction=(0.2, 0.4)):
    """The difference-of-Gaussians response of ``volume`` binned in x/y (see detect_nuclei),
    its binning factors, and the median and noise SD of the response."""
    factors = np.asarray(_bin_factors(vox, diameter_um))
    if any(n < f for n, f in zip(np.shape(volume), factors)):
        extent = " × ".join(f"{n * v:.3g}" for n, v in zip(np.shape(volume), vox))
        raise ImageError(f"the stack spans {extent} µm (z, y, x), less than a sixth of a {diameter_um:g} µm nucleus "
                         f"along an axis: check the voxel size (µm per voxel: {', '.join(f'{v:g}' for v in vox)})")
    img = _fill_blank(_bin(volume, factors))
    bvox = vox * factors
    # Truncate at 3 SD: the tails carry nothing at this scale and cost a third of the time.
    response = ndimage.gaussian_filter(img, sigma_fraction[0] * diameter_um / bvox, truncate=3.0)
    response -= ndimage.gaussian_filter(img, sigma_fraction[1] * diameter_um / bvox, truncate=3.0)
    # Noise SD of the response: MAD over the lower half of the volume's values, where nuclei
    # (bright, positive response) do not dominate even in a dense head.
    sub = response[:: max(1, response.shape[0] // 16), ::2, ::2].ravel()
    # A blank region (zero padding, voids read as the median) has no noise: left out, or the
    # noise it shows would be none and noise elsewhere would pass for nuclei.
    flat = np.abs(sub) <= 1e-5 * (float(np.max(np.abs(sub))) or 1.0)
    if 0.05 < flat.mean() < 0.95:
        sub = sub[~flat]
    med = float(np.median(sub))
    low = sub[sub <= med]
    noise = 1.4826 * np.median(med - low) if low.size else 0.0
    noise = float(noise) if noise > 0 else float(np.std(sub)) or 1.0
    return response, factors, med, noise


def _fill_blank(img: np.ndarray) -> np.ndarray:
    """``img`` with its blank region — a plateau at its lowest value, such as the zeros that pad
    a stack registered, rotated or cropped by another tool — at the level of the voxels around
    it (their median). A step from the background down to the padding is a ridge to a
    band-pass, which found hundreds of nuclei along it (the sample padded with zeros: 326 false
    nuclei beside a 60-voxel margin, 923 beside 4 blank planes). Where the blank region is the
    background itself (a background-subtracted stack clipped at 0) the voxels around it are
    near 0 too, and the fill changes little. Scattered voxels at the minimum are no region: the
    plateau is opened with a 3 × 3 block in each plane."""
    low = img.min()
    if np.mean(img[:, ::4, ::4] == low) < BLANK_MIN_FRACTION:  # the usual case, decided on a 16th of the voxels
        return img
    plateau = img == low
    blank = ndimage.binary_opening(plateau, structure=np.ones((1, 3, 3), bool))
    around = ndimage.binary_dilation(blank, structure=np.ones((3, 3, 3), bool)) & ~blank
    if not around.any():
        return img
    filled = img.copy()
    filled[blank] = np.median(img[around])
    return filled


def _response_at(response: np.ndarray, factors: np.ndarray, vox: np.ndarray, zyx_um: np.ndarray) -> np.ndarray:
    """The binned response at centres in µm (linear interpolation)."""
    idx = (zyx_um / vox - (factors - 1) / 2.0) / factors
    return ndimage.map_coordinates(response, idx.T, order=1, mode="nearest")


def split_by_colour(
    stack: Stack, zyx_um: np.ndarray, diameter_um: float = 3.0, threshold: float = 6.0,
    min_relative: float = 0.08, min_w: float = COLOUR_SPLIT_MIN_W, w_volume: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Nuclei that W shows only as a shoulder of a touching neighbour but a colour channel
    separates: NeuroPAL gives neighbours different colours, so two nuclei 1.6-2.5 µm apart that
    are one blob in W are often two blobs in R, G or B. Maxima of each colour channel at the
    finer scale (twice the threshold, as for W's finer scale) more than ``FINE_SEPARATION``
    diameters from every detection are added if W there responds above the threshold and at
    least ``min_w`` times as strongly as at the median detection: every neuron has W, while a
    colour maximum between nuclei (an edge, a gut granule) has little. Between ``COLOUR_NEAR``
    and ``FINE_SEPARATION`` diameters from a detection (NP's nuclei pressed together: 1.6-2.3 µm
    apart), a maximum is added only where its colour at that detection is below
    ``COLOUR_RATIO`` of its own: two nuclei of different colours. Returns the added
    centres (µm, z y x) and their W response at the finer scale in noise SDs. ``w_volume``: the
    W channel already read (segment_stack's detection image), so that a stack on disk is not
    read for it again."""
    colour_roles = [r for r in COLOUR_ROLES if stack.role_index(r) is not None]
    w = stack.role_index("W")
    if w is None or not colour_roles or len(zyx_um) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    vox = np.asarray(stack.voxel_size_zyx, dtype=float)
    fine = FINE_SCALE * diameter_um
    # Binned as for the nominal scale (a voxel about a sixth of a nucleus): half the time of
    # the finer scale's own binning, and no worse at finding these nuclei (NP recall 0.982
    # binned, 0.979 not; 2 worms).
    factors = np.asarray(_bin_factors(vox, diameter_um))
    bvox = vox * factors
    offset = (factors - 1) / 2.0 * vox  # a binned voxel's centre, in the original frame
    w_response, w_factors, med, noise = _band_pass(_bin(stack.channel(w) if w_volume is None else w_volume, factors), bvox, fine)
    typical = np.median(_response_at(w_response, w_factors, bvox, zyx_um - offset)) - med
    passes = [_band_pass(_bin(stack.channel(r), factors), bvox, fine) for r in colour_roles]
    found = [_detect_nuclei(None, bvox, fine, 2 * threshold, min_relative, fine_scale=None, band_passed=bp)[0]
             for bp in passes]
    channel_of = np.concatenate([np.full(len(f), k) for k, f in enumerate(found)])
    candidates = np.vstack(found) + offset
    w_at = _response_at(w_response, w_factors, bvox, candidates - offset) - med
    strong = np.flatnonzero((w_at >= min_w * typical) & (w_at >= threshold * noise))
    near_ok = np.zeros(len(candidates), dtype=bool)
    if len(strong):  # the band where the colour must tell the candidate from its neighbour
        dist, nearest = cKDTree(zyx_um).query(candidates)
        band = np.flatnonzero((dist > COLOUR_NEAR * diameter_um) & (dist <= FINE_SEPARATION * diameter_um))
        for k, (resp, rf, cmed, _) in enumerate(passes):
            mine = band[channel_of[band] == k]
            here = _response_at(resp, rf, bvox, candidates[mine] - offset) - cmed
            there = _response_at(resp, rf, bvox, zyx_um[nearest[mine]] - offset) - cmed
            near_ok[mine] = there < COLOUR_RATIO * here
    kept: list[int] = []
    for i in strong[np.argsort(-w_at[strong], kind="stable")]:  # one by one: channels may find the same nucleus
        d = cKDTree(np.vstack([zyx_um, candidates[kept]])).query(candidates[i])[0]
        if d > FINE_SEPARATION * diameter_um or (near_ok[i] and d > COLOUR_NEAR * diameter_um):
            kept.append(i)
    return candidates[kept].reshape(-1, 3), w_at[kept] / noise


def _parabola_offsets(response: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Sub-voxel offset of each maximum: vertex of the parabola through 3 samples per axis."""
    offsets = np.zeros(idx.shape, dtype=float)
    centre = response[tuple(idx.T)]
    for axis in range(3):
        lo = idx.copy()
        hi = idx.copy()
        lo[:, axis] = np.maximum(idx[:, axis] - 1, 0)
        hi[:, axis] = np.minimum(idx[:, axis] + 1, response.shape[axis] - 1)
        f_lo, f_hi = response[tuple(lo.T)], response[tuple(hi.T)]
        denom = f_lo - 2 * centre + f_hi
        valid = (denom < 0) & (lo[:, axis] != idx[:, axis]) & (hi[:, axis] != idx[:, axis])
        step = np.where(valid, 0.5 * (f_lo - f_hi) / np.where(valid, denom, -1.0), 0.0)
        # In the first or last plane: the parabola through it and the two samples inside (a
        # nucleus between the first two planes was put on the first)
        for edge, inward in ((0, 1), (response.shape[axis] - 1, -1)):
            at = idx[:, axis] == edge
            if response.shape[axis] < 3 or not at.any():
                continue
            one, two = idx[at].copy(), idx[at].copy()
            one[:, axis], two[:, axis] = edge + inward, edge + 2 * inward
            f0, f1, f2 = centre[at], response[tuple(one.T)], response[tuple(two.T)]
            curve, slope = 0.5 * (f0 - 2 * f1 + f2), 0.5 * (4 * f1 - 3 * f0 - f2)  # f0 + slope x + curve x², x inward
            bent = curve < 0  # inward only: a vertex beyond the edge is a guess outside the image
            step[at] = np.clip(np.where(bent, -slope / (2 * np.where(bent, curve, -1.0)), 0.0), 0.0, 0.5) * inward
        offsets[:, axis] = np.clip(step, -0.5, 0.5)
    return offsets


def _one_per_saturated_nucleus(volume, vox: np.ndarray, zyx: np.ndarray, score: np.ndarray, diameter_um: float):
    """Detections on one saturated nucleus (voxels at the volume's maximum, a clipped camera)
    made one, at the centre of its plateau: a flat-topped nucleus band-passes to a ring, whose
    maxima (2.5-3 µm apart) were kept as two or three nuclei, and a lone one stayed on the ring
    (0.7-0.9 µm off). A plateau is split into its nuclei first: clipped neighbours blurred into
    one plateau (touching side by side, or stacked in z) join at a waist, and each bulge about
    a maximum of the distance to the plateau's edge is one nucleus (a lone nucleus, however
    the PSF stretches it in z, has one). Left alone without a plateau of
    ``SATURATED_MIN_VOXELS`` (an unclipped maximum is a voxel or two)."""
    if len(zyx) == 0:
        return zyx, score
    top = np.max(volume)
    plateau = np.asarray(volume == top)
    if plateau.sum() < SATURATED_MIN_VOXELS:
        return zyx, score
    regions, _ = ndimage.label(plateau, np.ones((3, 3, 3), bool))
    reach = np.maximum(np.round(diameter_um / 3 / vox), 1).astype(int)
    on_regions = _nearest_label(regions, zyx, vox, reach, diameter_um / 3)
    # The plateaus a detection lies on (an 8-bit stack has thousands), each split into its
    # nuclei: the maxima of its distance to the edge (µm) within 0.8 of a nucleus (a flat
    # ridge's voxels join into one), each voxel going to the nearest
    parts, made = np.zeros(regions.shape, np.int32), 0
    size = tuple(np.maximum(np.round(0.8 * diameter_um / vox), 1).astype(int) | 1)
    boxes = ndimage.find_objects(regions)
    for r in np.unique(on_regions[on_regions > 0]):
        box = boxes[r - 1]
        mask = regions[box] == r
        depth = ndimage.distance_transform_edt(np.pad(mask, 1), sampling=vox)[1:-1, 1:-1, 1:-1]
        peaks = mask & (depth == ndimage.maximum_filter(depth, size=size, mode="constant"))
        seeds, found = ndimage.label(peaks, np.ones((3, 3, 3), bool))
        cut = mask.astype(np.int32)
        if found > 1:
            centres = np.array(ndimage.center_of_mass(peaks, seeds, range(1, found + 1))) * vox
            inside = np.argwhere(mask)
            cut[tuple(inside.T)] = cKDTree(centres).query(inside * vox)[1] + 1
        parts[box][mask] = cut[mask] + made
        made += max(found, 1)
    # The ring's maxima lie just off the plateau: each detection joins the part nearest it
    # within a third of a nucleus (plateaus apart stay apart: two clipped neighbours are two).
    part = _nearest_label(parts, zyx, vox, reach, diameter_um / 3)
    held = [int(r) for r in np.unique(part[part > 0])]
    keep = np.ones(len(zyx), bool)
    zyx, score = zyx.copy(), score.copy()
    for r, centre in zip(held, ndimage.center_of_mass(plateau, parts, held)):
        on = np.flatnonzero(part == r)
        first = on[np.argmax(score[on])]
        zyx[first] = np.asarray(centre) * vox
        keep[on[on != first]] = False
    return zyx[keep], score[keep]


def _nearest_label(labels: np.ndarray, zyx: np.ndarray, vox: np.ndarray, reach: np.ndarray, within_um: float) -> np.ndarray:
    """Per point (µm): the label of the labelled voxel nearest it within ``within_um`` (0: none),
    looked for in a box of ``reach`` voxels about it."""
    out = np.zeros(len(zyx), int)
    for i, centre in enumerate(np.clip(np.round(zyx / vox).astype(int), 0, np.array(labels.shape) - 1)):
        low = np.maximum(centre - reach, 0)
        window = labels[tuple(slice(a, b + 1) for a, b in zip(low, centre + reach))]
        near = np.argwhere(window > 0)
        if len(near):
            distance = np.linalg.norm((near + low) * vox - zyx[i], axis=1)
            if distance.min() <= within_um:
                out[i] = window[tuple(near[np.argmin(distance)])]
    return out


def _merge_without_valley(
    response: np.ndarray,
    sub_idx: np.ndarray,
    zyx_um: np.ndarray,
    values: np.ndarray,
    min_distance_um: float,
    merge_distance_um: float,
    saddle: float,
    min_valley: float = 0.0,
) -> np.ndarray:
    """Indices of the maxima to keep (input sorted strongest first).

    Two maxima closer than ``merge_distance_um`` are one nucleus unless the response dips
    between them below ``saddle`` times the weaker one: a large or elongated nucleus has several
    maxima on one plateau, two touching nuclei have a valley. The valley must also be deeper
    than ``min_valley`` (a few noise SDs), so noise alone never splits a nucleus. Closer than
    ``min_distance_um`` they are always merged.
    """
    n = len(zyx_um)
    if n < 2:
        return np.arange(n)
    pairs = cKDTree(zyx_um).query_pairs(merge_distance_um, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(n)
    pairs = np.sort(pairs, axis=1)  # (stronger, weaker): inputs are sorted strongest first
    a, b = sub_idx[pairs[:, 0]], sub_idx[pairs[:, 1]]
    t = np.linspace(0.15, 0.85, 8)
    line = a[:, None, :] + (b - a)[:, None, :] * t[None, :, None]  # (pairs, samples, 3)
    along = ndimage.map_coordinates(response, line.reshape(-1, 3).T, order=1, mode="nearest")
    dip = along.reshape(len(pairs), len(t)).min(axis=1)
    weaker = np.minimum(values[pairs[:, 0]], values[pairs[:, 1]])
    dist = np.linalg.norm(zyx_um[pairs[:, 0]] - zyx_um[pairs[:, 1]], axis=1)
    same = (dip >= saddle * weaker) | (weaker - dip < min_valley) | (dist < min_distance_um)
    removed = np.zeros(n, dtype=bool)
    same_pairs = pairs[same]
    # Weaker maxima in order of strength: merged into a stronger one that is itself kept.
    for i, j in same_pairs[np.argsort(same_pairs[:, 1], kind="stable")]:
        if not removed[i]:
            removed[j] = True
    return np.flatnonzero(~removed)


def _ellipsoid_offsets(radius_um: float, voxel_size_zyx, inner_um: float = 0.0) -> np.ndarray:
    """Integer (dz, dy, dx) offsets of the voxels within ``inner_um < r <= radius_um``."""
    vox = np.asarray(voxel_size_zyx, dtype=float)
    reach = np.floor(radius_um / vox).astype(int)
    grid = np.stack(
        np.meshgrid(*(np.arange(-r, r + 1) for r in reach), indexing="ij"), axis=-1
    ).reshape(-1, 3)
    dist = np.sqrt((((grid * vox)) ** 2).sum(axis=1))
    keep = (dist <= radius_um + 1e-9) & (dist > inner_um)
    if not keep.any():
        keep = dist == dist.min()
    offsets = grid[keep]
    if len(offsets) > MAX_OFFSETS:  # fine voxels: an even subset reads the same percentile
        offsets = offsets[np.linspace(0, len(offsets) - 1, MAX_OFFSETS).astype(int)]
    return offsets


def _sample(channel: np.ndarray, centres_vox: np.ndarray, offsets: np.ndarray, q: float) -> np.ndarray:
    """q-th percentile of ``channel`` over ``offsets`` around each centre (clipped at the edges)."""
    base = np.rint(centres_vox).astype(int)
    pts = base[:, None, :] + offsets[None, :, :]
    for axis in range(3):
        np.clip(pts[..., axis], 0, channel.shape[axis] - 1, out=pts[..., axis])
    narrow = channel.dtype.itemsize <= 2 or channel.dtype == np.float32  # else float64: range, precision
    values = channel[pts[..., 0], pts[..., 1], pts[..., 2]].astype(np.float32 if narrow else np.float64)
    return np.percentile(values, q, axis=1)


def measure_colours(
    stack: Stack,
    xyz_um: np.ndarray,
    radius_um: float = 0.9,
    background: bool = True,
    zscore: bool = True,
    unmix: bool = True,
) -> dict[str, np.ndarray]:
    """Per-neuron intensity of each channel with a role, keyed by role.

    The 75th percentile in an ellipsoid of ``radius_um`` around each centre, minus the 20th
    percentile of a shell from 2 to 3 ``radius_um`` (local background: haze, gut, bleed from
    neighbours averaged out). With ``unmix`` (and a W channel), W's bleed-through is removed
    from R and G (:func:`w_bleed_slopes`). R, G, B, W are z-scored per volume (``zscore``);
    GFP stays in background-subtracted counts, which is what activity readouts need.
    """
    xyz_um = positions(xyz_um)
    vox = np.asarray(stack.voxel_size_zyx, dtype=float)
    centres = xyz_um[:, ::-1] / vox
    inner = _ellipsoid_offsets(radius_um, vox)
    shell = _ellipsoid_offsets(3.0 * radius_um, vox, inner_um=2.0 * radius_um)
    out: dict[str, np.ndarray] = {}
    for i, role in enumerate(stack.channel_roles):
        if role is None:
            continue
        if len(xyz_um) == 0:  # no nucleus: the channel's column is there, empty (as the docs list it)
            out[role] = np.zeros(0)
            continue
        ch = stack.channel(i)
        value = _sample(ch, centres, inner, 75)
        if background:
            value = value - _sample(ch, centres, shell, 20)
        out[role] = value.astype(np.float64)
    if unmix and "W" in out and len(xyz_um):
        for role, slope in w_bleed_slopes(out).items():
            out[role] = out[role] - slope * out["W"]
    if zscore:
        for role, value in out.items():
            if role != "GFP" and len(value):
                big = np.max(np.abs(value)) if len(value) else 0.0
                value = value / big if np.isfinite(big) and big > 0 else value  # counts near float64's range: std overflows
                sd = value.std()
                out[role] = (value - value.mean()) / sd if sd > 0 else np.zeros_like(value)
    return out


def w_bleed_slopes(raw: dict[str, np.ndarray], quantile: float = 0.1, min_neurons: int = 20) -> dict[str, float]:
    """How much of W (the pan-neuronal marker) R and G picked up, from one volume's
    background-subtracted readouts: the slope (≥ 0) of the ``quantile`` regression of the
    colour on W (a lower envelope). A NeuroPAL colour is off in most neurons, so their readout
    is a floor plus the bleed, proportional to W; a least-squares fit through all neurons would
    also remove real colour that happens to go with W. The pinball loss is convex in the slope
    (the intercept at each slope is a quantile), so a bounded scalar search finds it. Without
    ``min_neurons`` neurons, nothing is estimated (slope 0)."""
    from scipy.optimize import minimize_scalar

    w = raw["W"]
    slopes = {}
    # mTagBFP2 is excited at 405 nm, where TagRFP-T is not: its channel gets no W to remove
    # (estimating one there only took real blue that goes with W, measured on rendered stacks).
    for role in ("R", "G"):
        if role not in raw:
            continue
        colour = raw[role]
        if np.ptp(colour) == 0:  # a blank channel bleeds nothing (a search's 6e-6 z-scored to -W)
            slopes[role] = 0.0
            continue

        def pinball(slope):
            residual = colour - slope * w
            residual = residual - np.quantile(residual, quantile)
            return float(np.sum(np.maximum(quantile * residual, (quantile - 1.0) * residual)))

        if not (len(w) >= min_neurons and np.ptp(w) > 0):
            slopes[role] = 0.0
            continue
        # The search's tolerance is absolute (1e-5): a colour far dimmer than W in its units
        # (scaled to 0-1 beside W in counts: a slope of 1e-6) took several times its real bleed.
        # Tightened only then, so that every other fit stays as it was.
        ratio = np.ptp(colour) / np.ptp(w)
        slope = float(minimize_scalar(pinball, bounds=(0.0, 1.0), method="bounded",
                                      options={"xatol": 1e-5 * min(1.0, 100 * ratio)}).x)
        # A bleed fraction of at most 1 holds in light, not in counts: W imaged at a lower gain
        # than the colour bleeds more than 1 count per W count. Searched further (no slope can
        # exceed the colour's range over W's) only then, so that every other fit stays as it was.
        widest = 1.5 * ratio
        if slope > 1.0 - 1e-3 and widest > 1.0:
            slope = float(minimize_scalar(pinball, bounds=(0.0, widest), method="bounded").x)
        slopes[role] = slope
    return slopes


def segment_stack(stack: Stack, diameter_um: float = 3.0, progress: Progress | None = None, **options) -> NeuronTable:
    """Detect nuclei and read their colours: a neuron table in the stack's frame (µm).

    Columns: ``x_um, y_um, z_um``, ``R, G, B, W`` (per-volume z-scores; those with a channel),
    and extra columns ``GFP`` (background-subtracted counts, when there is a GFP channel),
    ``x_px, y_px, z_px`` (0-based voxel coordinates, as napari shows them) and ``score``
    (detection strength in noise SDs). ``progress(fraction, message)`` is called along the way.
    ``options``: ``threshold`` (6.0: minimum detection strength in noise SDs) and
    ``min_relative`` (0.08) of :func:`detect_nuclei`; ``unmix`` (True): remove W's
    bleed-through from R and G (see :func:`measure_colours`); ``colour_split`` (True): add the
    touching nuclei that only a colour channel separates (:func:`split_by_colour`).
    """
    _warn_without_w(stack)
    return _segment_volume(stack, diameter_um, progress, **options)


def segment_series(
    series: StackSeries,
    diameter_um: float = 3.0,
    progress: Callable[[int, int], None] | None = None,
    **options,
) -> list[NeuronTable]:
    """Every time point of a recording segmented alike (:func:`segment_stack`, whose
    ``options`` it takes), one volume in memory at a time: a neuron table per time point, in the
    recording's frame. ``progress(done, total)`` after each volume."""
    _warn_without_w(series)
    tables = []
    for t in range(len(series)):
        tables.append(_segment_volume(series.volume(t), diameter_um, **options))
        if progress is not None:
            progress(t + 1, len(series))
    return tables


def found_time_points(tables: list[NeuronTable], source: str, advice: str) -> list[int]:
    """The time points of a segmented recording where nuclei were found (the others are left out
    of tracking, with one warning); refused when there is none (``advice``: what to check)."""
    found = [t for t, table in enumerate(tables) if len(table)]
    if not found:
        raise FdlcError(f"{source}: no nuclei found; {advice}")
    empty = [t for t, table in enumerate(tables) if not len(table)]
    if empty:
        shown = ", ".join(map(str, empty[:5])) + (" …" if len(empty) > 5 else "")
        warn(f"{source}: no nuclei found at {len(empty)} time point(s) ({shown}); they are left out")
    return found


def _warn_without_w(stack: Stack | StackSeries) -> None:
    if "W" not in stack.channel_roles:
        warn(
            f"{stack.source}: no W (TagRFP-T) channel marked; detecting on the sum of channels"
            + ("" if any(stack.channel_roles) else " and writing no colours (give the channel roles)")
        )


def _segment_volume(
    stack: Stack,
    diameter_um: float = 3.0,
    progress: Progress | None = None,
    threshold: float = 6.0,
    min_relative: float = 0.08,
    unmix: bool = True,
    colour_split: bool = True,
) -> NeuronTable:
    _report(progress, 0.0, "loading")
    volume = detection_image(stack)
    zyx, score = detect_nuclei(
        volume, stack.voxel_size_zyx, diameter_um, threshold=threshold, min_relative=min_relative,
        progress=lambda f, m: _report(progress, 0.05 + 0.6 * f, m),
    )
    if colour_split:
        _report(progress, 0.7, "separating touching nuclei by colour")
        added, added_score = split_by_colour(stack, zyx, diameter_um, threshold, min_relative, w_volume=volume)
        zyx, score = np.vstack([zyx, added]), np.concatenate([score, added_score])
    _report(progress, 0.85, "reading colours")
    xyz = zyx[:, ::-1]
    colours = measure_colours(stack, xyz, radius_um=0.3 * diameter_um, unmix=unmix)
    gfp = colours.pop("GFP", None)
    vox = np.asarray(stack.voxel_size_zyx)
    extra = pd.DataFrame({"x_px": zyx[:, 2] / vox[2], "y_px": zyx[:, 1] / vox[1], "z_px": zyx[:, 0] / vox[0], "score": score})
    if gfp is not None:
        extra.insert(0, "GFP", gfp)
    table = NeuronTable(xyz=xyz, colours=colours, extra=extra, source=stack.source)
    _report(progress, 1.0, f"{len(table)} nuclei")
    return table


def score_detections(truth_xyz: np.ndarray, found_xyz: np.ndarray, max_distance_um: float = 1.5) -> dict:
    """Precision, recall, F1 and centre errors of detections against true centres (µm).

    One-to-one matching by minimum total distance (scipy ``linear_sum_assignment``); a pair
    counts when it is closer than ``max_distance_um`` (half a nucleus diameter by convention).
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    truth_xyz, found_xyz = positions(truth_xyz, "true positions"), positions(found_xyz, "detections")
    errors = np.zeros(0)
    pairs = np.zeros((0, 2), dtype=int)
    if len(truth_xyz) and len(found_xyz):
        d = cdist(truth_xyz, found_xyz)
        # Pairs beyond the radius cost the same as leaving both unmatched, so they never help.
        cost = np.where(d <= max_distance_um, d, 1e6)
        rows, cols = linear_sum_assignment(cost)
        ok = d[rows, cols] <= max_distance_um
        pairs = np.stack([rows[ok], cols[ok]], axis=1)
        errors = d[rows[ok], cols[ok]]
    tp = len(errors)
    precision = tp / len(found_xyz) if len(found_xyz) else 0.0
    recall = tp / len(truth_xyz) if len(truth_xyz) else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {
        "precision": precision, "recall": recall, "f1": f1, "tp": tp,
        "n_true": len(truth_xyz), "n_found": len(found_xyz),
        "median_error_um": float(np.median(errors)) if tp else float("nan"),
        "pairs": pairs,
    }
