"""Robustness of nuclei detection and colour readout on unusual input (defect hunt).

Each test asserts the behaviour the project promises: bad input is one line (FdlcError / exit 2),
results are sensible (positions in the stack, finite colours) whatever the pixel values.
Small arrays only; the CLI tests run ``fdlc`` in a subprocess so that Python warnings printed on
stderr are seen as a user would see them.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from contextlib import contextmanager

import numpy as np
import pytest
from scipy import ndimage

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.io.images import Stack, write_tiff
from napari_fdlc.render import random_worm, render_stack
from napari_fdlc.segment import detect_nuclei, measure_colours, score_detections, segment_stack
import warnings

VOX = (1.0, 0.25, 0.25)
ROLES = ["R", "G", "B", "W"]


@pytest.fixture(scope="module")
def small():
    """A small rendered worm: 4 x 16 x 96 x 138 uint16, 30 nuclei (segment_stack: F1 0.98)."""
    worm = random_worm(30, size_um=(20, 10, 8), min_spacing_um=2.6, seed=1)
    return render_stack(worm, seed=0, peak_photons=200)


@contextmanager
def time_limit(seconds: float):
    """Fail (instead of hanging the suite) when the block runs longer than ``seconds``."""

    def expired(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _fdlc(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "napari_fdlc.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


# ----- the noise estimate and constant regions -------------------------------------------------


def test_noise_with_a_blank_region_gives_almost_nothing():
    """NaN voxels (docs/image_formats.md: "read as their channel's median, background") over 40 %
    of a pure-noise volume: the noise SD was estimated from the lower half of the response,
    most of which was then the blank region's exact zero, so it collapsed and noise passed as
    nuclei (423). Like the whole noise volume (test_segment.test_pure_noise_gives_almost_nothing),
    it gives <= 1."""
    rng = np.random.default_rng(0)
    data = (100 + rng.poisson(30, (1, 16, 96, 96))).astype(np.float32)
    data[..., 58:] = np.nan
    found = segment_stack(Stack(data, VOX, ["W"]))
    assert len(found) <= 1, f"{len(found)} nuclei found in noise"


def test_noise_beside_a_margin_of_zeros_gives_almost_nothing():
    """A margin padded with zeros (a stack registered or cropped by another tool): the step from
    the background down to 0 is a ridge to a band-pass, which gave 49 nuclei along it."""
    rng = np.random.default_rng(0)
    data = (100 + rng.poisson(30, (1, 16, 96, 96))).astype(np.float32)
    data[..., 58:] = 0
    found = segment_stack(Stack(data, VOX, ["W"]))
    assert len(found) <= 1, f"{len(found)} nuclei found in noise"


@pytest.mark.parametrize("axis", ["x", "z"])
def test_a_stack_padded_with_zeros_gives_the_nuclei_it_gives_unpadded(small, axis):
    """Zero padding along x (20 voxels) or z (3 blank planes): the same nuclei, shifted by the
    padding (it gave one false nucleus for every few voxels of the step's edge)."""
    stack, _ = small
    data = np.asarray(stack.data)
    pad_shape = list(data.shape)
    if axis == "x":
        pad_shape[3] = 20
        padded, shift = np.concatenate([np.zeros(pad_shape, data.dtype), data], axis=3), [20 * VOX[2], 0, 0]
    else:
        pad_shape[1] = 3
        padded, shift = np.concatenate([data, np.zeros(pad_shape, data.dtype)], axis=1), [0, 0, 0]
    plain = segment_stack(stack)
    found = segment_stack(Stack(padded, stack.voxel_size_zyx, stack.channel_roles))
    assert len(found) == len(plain)
    np.testing.assert_allclose(np.sort(found.xyz - shift, axis=0), np.sort(plain.xyz, axis=0), atol=0.05)


def test_a_background_subtracted_stack_keeps_its_nuclei(small):
    """Clipped at 0 after subtracting the background, most of the stack is 0: the blank
    region's fill (_fill_blank) must not take the nuclei's contrast."""
    stack, truth = small
    data = np.asarray(stack.data).astype(np.int32)
    clipped = np.clip(data - np.percentile(data, 80, axis=(1, 2, 3), keepdims=True), 0, None).astype(np.uint16)
    found = segment_stack(Stack(clipped, stack.voxel_size_zyx, stack.channel_roles))
    assert score_detections(truth.xyz, found.xyz)["f1"] >= score_detections(truth.xyz, segment_stack(stack).xyz)["f1"] - 0.02


# ----- voxel sizes ---------------------------------------------------------------------------------


def test_a_voxel_size_in_mm_by_mistake_does_not_hang():
    """--voxel-size in mm instead of µm (0.001 for 1 µm): _bin loops over every offset of a
    500 x 500 x 500 block in Python (1.25e8 iterations, hours) on a stack far smaller than one
    block. It should answer at once: an ImageError (the stack is smaller than a nucleus) or no
    nuclei."""
    data = np.random.default_rng(0).poisson(30, (1, 8, 40, 40)).astype(np.uint16)
    with time_limit(10):
        try:
            found = segment_stack(Stack(data, (0.001, 0.001, 0.001), ["W"]))
        except FdlcError:
            return
    assert len(found) == 0


@pytest.mark.parametrize("voxel", [(0.0, 0.25, 0.25), (-1.0, 0.25, 0.25), (1.0, -0.25, -0.25)])
def test_detect_nuclei_refuses_a_voxel_size_that_is_not_positive(small, voxel):
    """detect_nuclei takes the voxel size itself (Stack checks it, detect_nuclei does not): 0
    raises OverflowError (a traceback), a negative size returns centres at negative µm,
    outside the volume. It should raise an FdlcError (ImageError) like Stack does."""
    volume = small[0].channel("W")
    with pytest.raises(FdlcError):
        detect_nuclei(volume, voxel)


# ----- pixel values: range and offset --------------------------------------------------------------


def test_float64_beyond_float32_range_is_read_like_any_other_scale(small):
    """Finite float64 pixels above float32's range (1e40 x the counts): the cast to float32
    makes them inf, so W finds no nuclei and a colour channel reads NaN (z-scored to all
    zeros, silently). Detection and z-scored colours do not depend on the scale of a channel:
    the same nuclei and colours as the unscaled stack."""
    stack, _ = small
    base = segment_stack(stack)
    scaled = segment_stack(Stack(stack.data.astype(np.float64) * 1e40, VOX, ROLES))
    assert len(scaled) == len(base)
    np.testing.assert_allclose(scaled.xyz, base.xyz, atol=0.01)
    for c in ROLES:
        np.testing.assert_allclose(scaled.colours[c], base.colours[c], atol=0.01)


def test_raw_colours_of_a_float64_channel_beyond_float32_range_are_finite(small):
    stack, truth = small
    data = stack.data.astype(np.float64)
    data[0] *= 1e40
    raw = measure_colours(Stack(data, VOX, ROLES), truth.xyz, zscore=False)
    assert np.isfinite(raw["R"]).all()


def test_a_large_constant_offset_does_not_change_detection(small):
    """float64 counts + 1e9 (a constant offset; a band-pass ignores it): the cast to float32
    keeps ~7 digits, so the counts are quantised in steps of 64 and the Gaussian filters add
    rounding noise: F1 falls from 0.98 to 0.62 (0.85 at +1e8, 0.95 at +1e7)."""
    stack, truth = small
    found = segment_stack(Stack(stack.data.astype(np.float64) + 1e9, VOX, ROLES))
    assert score_detections(truth.xyz, found.xyz)["f1"] >= 0.9


# ----- without a W channel: the sum of channels ----------------------------------------------------


def test_without_w_a_sparse_channel_does_not_swamp_the_sum(small):
    """No W: each channel is scaled by its 99.9th percentile minus its median (floor 1e-6).
    A background-subtracted channel that is zero but for one small spot has both at 0, so it is
    multiplied by 1e6 and the one spot is all that is found (1 nucleus instead of 34). "Equal
    weight per channel whatever its gain" should hold: the R and G nuclei are still found."""
    stack, truth = small
    data = stack.data[:3].astype(np.float32)
    data[2] = 0.0
    data[2, 6:9, 40:44, 60:64] = 500.0
    found = segment_stack(Stack(data, VOX, ["R", "G", "B"]))
    assert score_detections(truth.xyz, found.xyz)["f1"] >= 0.8, len(found)


def test_without_w_a_channel_marked_to_ignore_is_not_used_for_detection(small):
    """'-' (role None) is documented as "to ignore" a channel (cli --channels, docs), but when
    no channel is W the detection image sums every non-GFP channel, ignored ones included: a
    channel with other structures (here another worm's nuclei) adds detections (35 -> 39).
    With R, G, B given, an ignored channel should not change what is found."""
    stack, _ = small
    rgb = segment_stack(Stack(stack.data[:3], VOX, ["R", "G", "B"]))
    other = stack.data[3][:, ::-1, ::-1]
    with_ignored = segment_stack(Stack(np.concatenate([stack.data[:3], other[None]]), VOX, ["R", "G", "B", None]))
    assert len(with_ignored) == len(rgb)
    np.testing.assert_allclose(with_ignored.xyz, rgb.xyz)


# ----- fdlc segment: one line on stderr -----------------------------------------------------------


@pytest.mark.parametrize(
    "options, data",
    [
        (["--threshold", "1e300"], "counts"),  # RuntimeWarning: overflow encountered in cast
        (["--voxel-size", "0.05", "0.25", "0.25"], "counts"),  # 8 planes of 0.05 µm: binned to nothing
        ([], "float64 x 1e40"),  # RuntimeWarning: overflow encountered in cast (W -> float32)
    ],
    ids=["huge-threshold", "stack-thinner-than-a-bin", "float64-beyond-float32"],
)
def test_cli_segment_prints_no_python_warnings(tmp_path, small, options, data):
    """Odd but accepted options or pixels: numpy RuntimeWarnings (two lines each, with source
    code) reach stderr beside fdlc's own line. Whatever the outcome (a table, or exit 2 with
    one error line), stderr has only fdlc's lines."""
    stack, _ = small
    pixels = stack.data[:, 4:12]
    if data != "counts":
        pixels = pixels.astype(np.float64) * 1e40
    path = tmp_path / "worm.ome.tif"
    write_tiff(path, Stack(pixels, VOX, ROLES))
    out = tmp_path / "neurons.csv"
    result = _fdlc("segment", str(path), *options, "--quiet", "--out", str(out))
    lines = result.stderr.strip().splitlines()
    assert all(line.startswith("fdlc:") for line in lines), result.stderr
    if result.returncode != 0:
        assert result.returncode == 2 and len(lines) == 1 and not out.exists(), result.stderr


def test_a_stack_of_gfp_only_says_there_is_no_channel_for_nuclei(small):
    """A GFP-only stack found nothing, and the message pointed at the voxel size and threshold."""
    stack, _ = small
    with pytest.raises(FdlcError, match="no channel to find nuclei in"):
        segment_stack(Stack(stack.data[3:], VOX, ["GFP"]))


def test_colours_of_a_finely_sampled_stack_read_a_bounded_number_of_voxels(small):
    """At 0.05 µm voxels the background shell around each nucleus held ~460 000 voxels (about
    11 MB of offsets per neuron and channel: gigabytes for a head). It is now an even subset of
    at most MAX_OFFSETS, and the same colours are read where the shell is smaller."""
    from napari_fdlc.segment import MAX_OFFSETS, _ellipsoid_offsets

    assert len(_ellipsoid_offsets(2.7, (0.05, 0.05, 0.05), inner_um=1.8)) == MAX_OFFSETS
    assert len(_ellipsoid_offsets(2.7, VOX, inner_um=1.8)) < MAX_OFFSETS
    stack, truth = small
    colours = measure_colours(stack, truth.xyz)
    assert all(np.isfinite(v).all() for v in colours.values())


def _one_nucleus(radius_um: float, peak: float, shape=(16, 96, 96), noise: str = "poisson", seed: int = 0):
    """One ball nucleus at the centre, blurred by a NeuroPAL-like PSF (0.7 µm in z, 0.15 in x/y)."""
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    c = [s // 2 for s in shape]
    r = np.sqrt(((z - c[0]) * VOX[0]) ** 2 + ((y - c[1]) * VOX[1]) ** 2 + ((x - c[2]) * VOX[2]) ** 2)
    blob = ndimage.gaussian_filter((r <= radius_um).astype(float), (0.7 / VOX[0], 0.15 / VOX[1], 0.15 / VOX[2]))
    blob /= blob.max()
    rng = np.random.default_rng(seed)
    if noise == "poisson":
        return rng.poisson(100 + peak * blob).astype(float)
    return 100 + peak * blob + rng.normal(0, 1, shape)


def test_a_threshold_above_500_noise_sds_is_accepted_as_documented():
    """Every threshold up to 1000 noise SDs is taken: the finer scale runs at twice the
    threshold and checked that against the user's limit, so 500-1000 was refused once a nucleus
    was found, naming a value the user never gave."""
    volume = _one_nucleus(1.5, 10000, shape=(16, 128, 128), noise="gauss")
    stack = Stack(volume[None].astype(np.float32), VOX, ["W"])
    assert len(segment_stack(stack, threshold=400)) == 1
    found = segment_stack(stack, threshold=600)
    assert len(found) == 1


@pytest.mark.parametrize("radius_um, over", [(1.5, 5.0), (2.0, 3.0)], ids=["3um-5x", "4um-3x"])
def test_a_saturated_nucleus_is_one_nucleus(radius_um, over):
    """A W nucleus clipped by a 12-bit camera (core 3-5x over range) is one nucleus, as
    unclipped: its flat top band-passes to a ring, whose maxima were kept as 2-3 nuclei."""
    vox_peak = 3995 * over
    plain = _one_nucleus(radius_um, vox_peak)
    assert len(segment_stack(Stack(plain[None], VOX, ["W"]))) == 1  # not saturated: one
    clipped = np.minimum(plain, 4095).astype(np.uint16)
    found = segment_stack(Stack(clipped[None], VOX, ["W"]))
    assert len(found) == 1, np.round(found.xyz, 2).tolist()


def test_unmixed_colours_do_not_depend_on_the_gain_of_the_w_channel(small):
    """R and G after the bleed-through removal do not depend on W's gain (W 20x dimmer): the
    slope was bounded to 1 in counts, so part of W's bleed stayed in R (z-scores off by 0.2)."""
    stack, truth = small
    data = np.asarray(stack.data).astype(np.float32)
    ref = measure_colours(Stack(data, VOX, stack.channel_roles), truth.xyz)
    dim_w = data.copy()
    dim_w[3] *= 0.05
    got = measure_colours(Stack(dim_w, VOX, stack.channel_roles), truth.xyz)
    np.testing.assert_allclose(got["W"], ref["W"], atol=1e-4)  # W itself: z-scored, unchanged
    np.testing.assert_allclose(got["R"], ref["R"], atol=1e-2)
    np.testing.assert_allclose(got["G"], ref["G"], atol=1e-2)


def test_cli_segment_does_not_find_nuclei_in_a_channel_given_as_ignored(tmp_path, small, capsys):
    """`--channels GFP -` leaves nothing to find nuclei in: exit 2, one line. Nuclei were
    found in the channel given as '-' (taken as of unknown role)."""
    stack, _ = small
    data = np.asarray(stack.data)
    path = tmp_path / "two.ome.tif"
    write_tiff(path, Stack(data[[3, 0]], VOX, [None, None]))
    out = tmp_path / "neurons.csv"
    code = main(["segment", str(path), "--channels", "GFP", "-", "--quiet", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "no channel to find nuclei in" in err, (code, err)
    assert not out.exists()


@pytest.fixture(scope="module")
def worm():
    """20 well-spaced nuclei, 4 x 15 x 90 x 124 uint16 (segment_stack finds all 20)."""
    table = random_worm(20, size_um=(16, 8, 6), min_spacing_um=2.8, seed=1)
    return render_stack(table, seed=0, peak_photons=200, gut=False)


def _balls(centres_um, radius_um, peak, shape=(16, 96, 96), seed=0):
    """Ball nuclei blurred by a NeuroPAL-like PSF (0.7 µm in z, 0.15 in x/y), Poisson noise on
    a background of 100 (as test_segment_robustness._one_nucleus)."""
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    inside = np.zeros(shape, bool)
    for c in centres_um:
        c = np.asarray(c) / VOX
        r = np.sqrt(((z - c[0]) * VOX[0]) ** 2 + ((y - c[1]) * VOX[1]) ** 2 + ((x - c[2]) * VOX[2]) ** 2)
        inside |= r <= radius_um
    blob = ndimage.gaussian_filter(inside.astype(float), (0.7 / VOX[0], 0.15 / VOX[1], 0.15 / VOX[2]))
    blob /= blob.max()
    return np.random.default_rng(seed).poisson(100 + peak * blob).astype(float)


@pytest.mark.parametrize("value", [0, 100], ids=["zeros", "constant"])
def test_a_blank_colour_channel_reads_as_no_colour_not_as_minus_w(worm, value):
    """An R / G channel that holds one value (not acquired, written as 0 or the camera offset)
    has no colour: its z-scores should be 0 for every nucleus, as measure_colours gives for B
    or with unmix=False (sd 0 -> zeros). Instead the bleed-through removal subtracts
    slope * W with a slope of ~6e-6 (minimize_scalar never returns exactly 0), and the z-score
    blows that up to exactly -W: a fake colour, perfectly anti-correlated with W, which
    `fdlc label` then reads as a real R / G reading (it only drops columns of one value)."""
    stack, truth = worm
    data = np.asarray(stack.data).copy()
    data[0] = value  # R
    data[1] = value  # G
    colours = measure_colours(Stack(data, stack.voxel_size_zyx, stack.channel_roles), truth.xyz)
    assert np.allclose(colours["R"], 0), np.round(colours["R"][:5], 3).tolist()
    assert np.allclose(colours["G"], 0), np.round(colours["G"][:5], 3).tolist()


def test_two_saturated_nuclei_stacked_in_z_stay_two():
    """Two 2.6 µm nuclei 4 µm apart in z (one plane between their edges), W clipped by a 12-bit
    camera at 3x over range, as in test_a_saturated_nucleus_is_one_nucleus. Unclipped, both are
    found; docs/segmentation.md step 5: "two clipped neighbours have two plateaus and stay two".
    The z PSF joins their clipped regions into one plateau, and _one_per_saturated_nucleus
    merges every detection near one plateau whatever their distance (4 µm, more than a
    diameter and beyond the valley test's 0.8 diameter): one nucleus, placed midway between
    them where there is none."""
    centres = [(6.0, 12.0, 12.0), (10.0, 12.0, 12.0)]
    plain = _balls(centres, 1.3, 3 * 3995)
    assert len(segment_stack(Stack(plain[None], VOX, ["W"]))) == 2  # unclipped: two
    clipped = np.minimum(plain, 4095).astype(np.uint16)
    found = segment_stack(Stack(clipped[None], VOX, ["W"]))
    zyx = found.xyz[:, ::-1]
    assert len(found) == 2, np.round(zyx, 2).tolist()
    nearest = np.linalg.norm(zyx[:, None] - np.array(centres)[None], axis=2).min(axis=0)
    assert (nearest < 1.0).all(), nearest


@pytest.mark.parametrize("over", [5.0, 10.0])
def test_a_saturated_nucleus_is_placed_at_its_plateau_s_centre(over):
    """A 3 µm nucleus (the default diameter) clipped at 5-10x over a 12-bit range: docs step 5,
    "the maxima within a third of a diameter of one clipped plateau are one nucleus, at the
    plateau's centre". The ring's maxima are merged by the valley test first, so one detection
    is left on the ring; _one_per_saturated_nucleus only moves a plateau's detections when
    there are two or more (and returns at once for a volume with one detection), so the centre
    stays 0.7-0.9 µm off in z (the plateau's centre is within 0.02 µm), beyond the documented
    target of 0.5 µm."""
    centre = np.array([8.0, 12.1, 12.05])
    clipped = np.minimum(_balls([centre], 1.5, over * 3995), 4095).astype(np.uint16)
    found = segment_stack(Stack(clipped[None], VOX, ["W"]))
    assert len(found) == 1
    error = np.linalg.norm(found.xyz[0, ::-1] - centre)
    assert error < 0.3, f"centre {error:.2f} µm off"


def test_cli_segment_a_huge_voxel_size_is_one_line(tmp_path, worm, capsys):
    """`--voxel-size 1e160 1 1` (finite and positive, so accepted): the squared distances
    in _merge_without_valley overflow and cKDTree.query_pairs raises ValueError ("Encountering
    floating point overflow"), shown as a 30-line traceback with exit 1. Bad input should be
    one line on stderr with exit 2 (docs/segmentation.md)."""
    path = tmp_path / "worm.ome.tif"
    write_tiff(path, worm[0])
    out = tmp_path / "neurons.csv"
    try:
        code = main(["segment", str(path), "--voxel-size", "1e160", "1", "1", "--quiet", "--out", str(out)])
    except Exception as exc:  # what the user sees as a traceback
        pytest.fail(f"traceback: {type(exc).__name__}: {exc}")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, (code, err)


def test_cli_segment_voxel_size_in_nm_by_mistake_is_not_silent(tmp_path, worm, capsys):
    """x/y voxel size given in nm for µm (`--voxel-size 1 250 250`): a 3 µm nucleus is then
    1/80 of a voxel across, and the stack 31 mm wide. The opposite mistake (mm for µm) is
    refused in one line (docs/segmentation.md), and `fdlc label` warns about tables in nm;
    here `fdlc segment` silently writes 382 "nuclei" for a stack of 20, with nothing said on
    stderr. Expected: refused (exit 2, one line) or a warning about the voxel size."""
    path = tmp_path / "worm.ome.tif"
    write_tiff(path, worm[0])
    out = tmp_path / "neurons.csv"
    code = main(["segment", str(path), "--voxel-size", "1", "250", "250", "--quiet", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 or "voxel" in err.lower(), (code, err)


def test_detect_nuclei_two_voxel_sizes_is_a_clear_error():
    """A voxel size of two numbers should be refused as an ImageError ('give three positive
    numbers', as _detect_nuclei says). Instead the new voxel-size check in
    check_detection_options compares it with a 3-vector first: a numpy broadcasting ValueError
    traceback."""
    from napari_fdlc.io.images import ImageError
    from napari_fdlc.segment import detect_nuclei

    with pytest.raises(ImageError):
        detect_nuclei(np.zeros((4, 8, 8), np.float32), (1.0, 0.5), diameter_um=3.0)


def test_detect_nuclei_zero_diameter_blames_the_diameter():
    """A nucleus diameter of 0 (or negative) should be refused as a bad diameter ('nucleus
    diameter must be a number of µm above 0'). Instead the voxel-size check runs first and
    says that the (fine) voxel size 1 × 0.5 × 0.5 µm is 'coarser than a nucleus of 0 µm ...
    is it in µm (not nm)?', pointing at the wrong option."""
    from napari_fdlc.io.images import ImageError
    from napari_fdlc.segment import detect_nuclei

    with pytest.raises(ImageError, match="diameter"):
        detect_nuclei(np.zeros((4, 8, 8), np.float32), (1.0, 0.5, 0.5), diameter_um=0.0)


def _two_clipped_side_by_side(over: float):
    centres = [(8.0, 12.0, 10.0), (8.0, 12.0, 12.7)]  # 2.6 µm nuclei, 2.7 µm apart in x: touching
    plain = _balls(centres, 1.3, over * 3995)
    assert len(segment_stack(Stack(plain[None], VOX, ["W"]))) == 2  # unclipped: both found
    clipped = np.minimum(plain, 4095).astype(np.uint16)  # a 12-bit camera
    return centres, segment_stack(Stack(clipped[None], VOX, ["W"]))


def test_two_touching_saturated_nuclei_side_by_side_stay_two():
    """docs/segmentation.md step 5: "two clipped neighbours have two plateaus and stay two".
    Two touching 2.6 µm nuclei side by side in x (2.7 µm apart), W clipped at 3x over a 12-bit
    range: their clipped regions touch (the PSF), so segment._one_per_saturated_nucleus sees
    one plateau (4-5 µm long, under its 2-diameter limit) and merges both detections into one,
    placed midway (x 11.3 µm) where there is no nucleus. Expected: two, each within 1 µm."""
    centres, found = _two_clipped_side_by_side(3.0)
    zyx = found.xyz[:, ::-1]
    assert len(found) == 2, np.round(zyx, 2).tolist()
    nearest = np.linalg.norm(zyx[:, None] - np.array(centres)[None], axis=2).min(axis=0)
    assert (nearest < 1.0).all(), nearest


def test_two_touching_nuclei_clipped_hard_are_not_five():
    """The same two touching nuclei clipped at 5x over range: their joint plateau is longer
    than 2 diameters (6 µm), so _one_per_saturated_nucleus takes it for "neighbours blurred
    into one" and leaves every maximum of the band-pass's ring around it: 5 nuclei for 2.
    Expected: 2."""
    _, found = _two_clipped_side_by_side(5.0)
    assert len(found) == 2, np.round(found.xyz[:, ::-1], 2).tolist()


def _nucleus_near_the_first_plane(cz: float, vz: float, shape=(10, 64, 64)):
    """One 2.8 µm nucleus centred at z = ``cz`` µm (x = y = 8 µm), drawn on a 5x finer z grid
    that extends past the stack and sampled at ``vz`` µm planes from z = 0."""
    up, pad = 5, 15
    zf = (np.arange(-pad, shape[0] * up + pad) * vz / up)[:, None, None]
    y = (np.arange(shape[1]) * 0.25)[None, :, None]
    x = (np.arange(shape[2]) * 0.25)[None, None, :]
    ball = (np.sqrt((zf - cz) ** 2 + (y - 8) ** 2 + (x - 8) ** 2) <= 1.4).astype(float)
    blob = ndimage.gaussian_filter(ball, (0.7 / (vz / up), 0.15 / 0.25, 0.15 / 0.25))[pad::up][: shape[0]]
    img = np.random.default_rng(0).poisson(100 + 2000 * blob / blob.max())
    return Stack(img[None].astype(np.uint16), (vz, 0.25, 0.25), ["W"])


def test_a_nucleus_between_the_first_two_planes_gets_a_sub_voxel_centre():
    """docs step 4: "Sub-voxel centres: vertex of a parabola through the response along each
    axis". A nucleus centred 0.6 µm into a stack of 1.5 µm planes (between plane 0 and plane
    1) is placed at z = 0.0 exactly: _parabola_offsets skips every maximum in the first or
    last plane (no sample beyond it), so the centre snaps to the plane, 0.6 µm off (the
    documented target is 0.5 µm; away from the edge the same nucleus is placed within
    0.15 µm). Expected: within 0.3 µm."""
    inside = segment_stack(_nucleus_near_the_first_plane(4.0, 1.5))
    assert len(inside) == 1 and abs(inside.xyz[0, 2] - 4.0) < 0.3  # away from the edge: fine
    found = segment_stack(_nucleus_near_the_first_plane(0.6, 1.5))
    assert len(found) == 1
    assert abs(found.xyz[0, 2] - 0.6) < 0.3, f"z = {found.xyz[0, 2]:.2f} µm, truly 0.6"


def test_colours_of_float64_counts_near_float64_s_range_are_z_scored():
    """The z-scores do not depend on the scale of a channel (test_segment_robustness:
    float64 counts x 1e40 read as unscaled). At x 1e300 (finite float64) the nuclei are still
    found, but measure_colours' z-score takes value.std(), whose squares overflow to inf:
    RuntimeWarnings on stderr and every R, G, B, W written as 0 (no colour), silently.
    Expected: the same z-scores as the unscaled stack, without warnings."""
    centres = [(z, y, x) for z in (5.0, 10.0) for y in (5.0, 11.0, 17.0) for x in (5.0, 11.0)]
    w = _balls(centres, 1.3, 800, seed=1)
    brightness = np.linspace(200, 1200, len(centres))
    r = sum(_balls([c], 1.3, b, seed=2 + k) - 100 for k, (c, b) in enumerate(zip(centres, brightness))) + 100
    data = np.stack([r, w])
    base = segment_stack(Stack(data, VOX, ["R", "W"]))
    assert len(base) == 12
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scaled = segment_stack(Stack(data * 1e300, VOX, ["R", "W"]))
    assert len(scaled) == 12
    np.testing.assert_allclose(scaled.colours["R"], base.colours["R"], atol=0.01)
    np.testing.assert_allclose(scaled.colours["W"], base.colours["W"], atol=0.01)


def _clean_nuclei(peaks, shape=(16, 96, 96)):
    """12 nuclei (2.6 µm) of the given brightness over a flat background of 100, no noise."""
    centres = [(z, y, x) for z in (5.0, 10.0) for y in (5.0, 11.0, 17.0) for x in (5.0, 11.0)]
    z, y, x = np.ogrid[: shape[0], : shape[1], : shape[2]]
    img = np.zeros(shape)
    for c, p in zip(centres, peaks):
        img += p * (np.sqrt((z * 1.0 - c[0]) ** 2 + (y * 0.25 - c[1]) ** 2 + (x * 0.25 - c[2]) ** 2) <= 1.3)
    return 100 + ndimage.gaussian_filter(img, (0.7, 0.6, 0.6))


def _ball(shape, centre, radius):
    z, y, x = np.indices(shape)
    return (z - centre[0]) ** 2 + (y - centre[1]) ** 2 + (x - centre[2]) ** 2 <= radius**2


@pytest.mark.parametrize("cz, vz", [(0.0, 1.0), (0.4, 1.5)], ids=["on-the-first-plane", "0.4um-in-1.5um-planes"])
def test_a_nucleus_at_the_first_plane_is_not_put_outside_the_stack(cz, vz):
    """The new edge parabola of segment._parabola_offsets (through the first plane and the two
    inside it) extrapolates: for a nucleus centred on or just inside the first plane the
    response falls inward, the parabola's vertex lies outside, and the clip puts the centre
    half a plane outside the stack. Expected: a centre inside the stack (z >= 0) and no
    further off than before the change (0 and 0.4 µm: the centre snapped to the plane).
    Instead z = -0.5 µm for a nucleus at z = 0 (1 µm planes) and z = -0.75 µm for one at
    z = 0.4 µm (1.5 µm planes): 0.5 and 1.15 µm off, outside the image."""
    from test_segment_robustness import _nucleus_near_the_first_plane

    from napari_fdlc.segment import segment_stack

    found = segment_stack(_nucleus_near_the_first_plane(cz, vz))
    assert len(found) == 1
    z = float(found.xyz[0, 2])
    assert z >= 0 and abs(z - cz) <= max(cz, 0.3) + 1e-6, f"z = {z:.2f} µm, truly {cz} µm"


def test_only_the_plateaus_a_detection_lies_on_are_split(monkeypatch):
    """An 8-bit stack with 4 % of W clipped has about 20 000 plateaus (single voxels among
    them), and _one_per_saturated_nucleus cut every one into its nuclei with a distance
    transform and a maximum filter: 12.7 of detect_nuclei's 13 s. Only a plateau a detection
    lies on needs it (counted here, not timed)."""
    from scipy import ndimage as ndi

    from napari_fdlc import segment

    calls = []
    real = ndi.distance_transform_edt
    monkeypatch.setattr(segment.ndimage, "distance_transform_edt", lambda *a, **k: calls.append(1) or real(*a, **k))
    rng = np.random.default_rng(0)
    vol = rng.integers(0, 200, (16, 128, 128)).astype(np.uint8)
    vol.ravel()[rng.choice(vol.size, 4000, replace=False)] = 255
    vox = np.array([1.0, 0.25, 0.25])
    dets = rng.uniform(0, 1, (50, 3)) * np.array(vol.shape) * vox
    segment._one_per_saturated_nucleus(vol, vox, dets, np.arange(50.0)[::-1], 3.0)
    assert len(calls) <= 50, f"{len(calls)} plateaus cut for 50 detections"


def test_unmixed_colours_do_not_depend_on_colour_channels_scaled_to_one(small):
    """Colour channels normalised to [0, 1] (counts / 65535) beside W in counts: R and G are
    z-scored per volume, so their scale must not matter (the W-dimmer case is already handled,
    test_unmixed_colours_do_not_depend_on_the_gain_of_the_w_channel). Instead the bleed slope,
    now ~1e-6, is below minimize_scalar's absolute tolerance (xatol 1e-5) on [0, 1]: the
    search returns ~6e-6, several times the true slope, and R / G z-scores move by 0.7-0.8 SD."""
    stack, truth = small
    data = np.asarray(stack.data).astype(np.float32)
    ref = measure_colours(Stack(data, stack.voxel_size_zyx, ROLES), truth.xyz)
    scaled = data.copy()
    scaled[:3] /= 65535.0
    got = measure_colours(Stack(scaled, stack.voxel_size_zyx, ROLES), truth.xyz)
    np.testing.assert_allclose(got["B"], ref["B"], atol=1e-3)  # not unmixed: scale-free already
    np.testing.assert_allclose(got["R"], ref["R"], atol=0.05)
    np.testing.assert_allclose(got["G"], ref["G"], atol=0.05)


def test_float32_pixels_near_float32_s_maximum_are_detected(small):
    """float32 pixels up to 3.3e38 (finite float32; the docs' rescaling of wide pixels exists
    so that a channel's scale does not change detection). Expected: the nuclei of the unscaled
    stack. Instead _bin sums 2 x 2 blocks in float32 ('overflow encountered in add'), the
    band-pass turns inf into NaN ('invalid value encountered in subtract') and no nucleus is
    found, silently apart from the RuntimeWarnings."""
    stack, _ = small
    data = np.asarray(stack.data).astype(np.float32)
    base = segment_stack(Stack(data, stack.voxel_size_zyx, ROLES))
    huge = data * np.float32(3.3e38 / data.max())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        found = segment_stack(Stack(huge, stack.voxel_size_zyx, ROLES))
    assert len(found) == len(base), f"{len(found)} nuclei, unscaled {len(base)}"
    np.testing.assert_allclose(found.xyz, base.xyz, atol=0.05)


def test_a_stack_without_nuclei_keeps_its_colour_and_gfp_columns():
    """docs/segmentation.md: output columns R, G, B, W 'for the channels present' and GFP
    'when there is a GFP channel'. A stack where nothing is found (a blank volume) gives a
    table whose header lacks R, G, B, W and GFP (measure_colours skips every channel when
    there are no centres), so the CSV written has only x_um, y_um, z_um, label, x_px, y_px,
    z_px, score: a header that says the stack had no colour channels."""
    data = np.full((5, 5, 40, 40), 100, np.uint16)
    table = segment_stack(Stack(data, (1.0, 0.25, 0.25), [*ROLES, "GFP"]))
    assert len(table) == 0
    columns = list(table.to_dataframe().columns)
    for c in [*ROLES, "GFP"]:
        assert c in columns, columns
