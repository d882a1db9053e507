"""Synthetic NeuroPAL stacks: geometry of the truth, determinism, channels, realism knobs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from napari_fdlc.errors import FdlcError
from napari_fdlc.io.images import ImageError
from napari_fdlc.render import align_worm, colour_intensities, random_worm, render_recording, render_stack, spread_apart
from napari_fdlc.table import NeuronTable
import subprocess
import sys
import textwrap

# Small, coarse stacks: a few thousand voxels each.
SMALL = dict(margin_um=(2.0, 3.0, 3.0), voxel_size_zyx=(1.0, 0.5, 0.5), gut=False)


def one_line(exc_info) -> str:
    message = str(exc_info.value)
    assert message and "\n" not in message, message
    return message


@pytest.fixture(scope="module")
def worm():
    return random_worm(40, size_um=(36, 14, 10), seed=3)


@pytest.fixture(scope="module")
def rendered(worm):
    return render_stack(worm, seed=5)


def test_stack_layout(rendered):
    stack, truth = rendered
    assert stack.data.dtype == np.uint16 and stack.data.ndim == 4
    assert stack.channel_roles == ["R", "G", "B", "W"]
    assert stack.channel_names[3] == "TagRFP-T"
    assert stack.voxel_size_zyx == (1.0, 0.25, 0.25)
    assert len(truth) == 40
    extent = stack.extent_um()[::-1]
    assert np.all(truth.xyz >= 0) and np.all(truth.xyz <= extent)
    for c in ("x_px", "y_px", "z_px", "radius_um", "R_int", "G_int", "B_int"):
        assert c in truth.extra.columns


def test_truth_keeps_the_worm_shape(worm, rendered):
    _, truth = rendered
    # A rotation and a shift only: all pairwise distances are kept (the worm's spacing is 2.6 µm,
    # above the renderer's minimum, so nothing was pushed apart).
    np.testing.assert_allclose(pdist(truth.xyz), pdist(worm.xyz), atol=1e-6)
    np.testing.assert_array_equal(truth.colours["R"], worm.colours["R"])


def test_nuclei_are_bright_in_w_and_background_is_dim(rendered):
    stack, truth = rendered
    w = stack.channel("W").astype(float)
    idx = np.rint(truth.xyz[:, ::-1] / stack.voxel_size_zyx).astype(int)
    at_nuclei = w[tuple(idx.T)]
    background = np.percentile(w, 20)
    assert np.median(at_nuclei) > background + 150
    assert np.all(at_nuclei > background + 40)


def test_colours_follow_the_table(rendered):
    stack, truth = rendered
    idx = tuple(np.rint(truth.xyz[:, ::-1] / stack.voxel_size_zyx).astype(int).T)
    for c in "RGB":
        seen = stack.channel(c).astype(float)[idx]
        r = np.corrcoef(seen, truth.extra[f"{c}_int"])[0, 1]
        assert r > 0.7, (c, r)


def test_deterministic_with_a_seed(worm, rendered):
    again, truth = render_stack(worm, seed=5)
    np.testing.assert_array_equal(again.data, rendered[0].data)
    np.testing.assert_array_equal(truth.xyz, rendered[1].xyz)
    other, _ = render_stack(worm, seed=6)
    assert not np.array_equal(other.data, rendered[0].data)


def test_noise_level_and_options(worm):
    quiet, _ = render_stack(worm, seed=1, peak_photons=2000, gut=False, shape_zyx=(12, 60, 120))
    noisy, _ = render_stack(worm, seed=1, peak_photons=50, gut=False, shape_zyx=(12, 60, 120))
    assert quiet.data.shape == (4, 12, 60, 120)

    def snr(stack):
        w = stack.channel("W").astype(float)
        return (np.percentile(w, 99.5) - np.median(w)) / np.std(w[w < np.median(w)])

    assert snr(quiet) > 2 * snr(noisy)
    with_gfp, truth = render_stack(worm, seed=1, gfp=True, shape_zyx=(12, 60, 90))
    assert with_gfp.channel_roles[-1] == "GFP" and with_gfp.data.shape[0] == 5
    # The shape cuts the worm: only centres inside the stack are in the truth.
    assert 0 < len(truth) < len(worm)
    assert np.all(truth.xyz[:, 0] <= 90 * 0.25)


def test_gut_autofluorescence_is_blue_green(worm):
    stack, truth = render_stack(worm, seed=2, gut_strength=2.0)
    plain, _ = render_stack(worm, seed=2, gut=False)
    posterior = slice(int(truth.xyz[:, 0].max() / 0.25) + 8, None)  # past the last neuron
    extra = {c: stack.channel(c)[..., posterior].mean() - plain.channel(c)[..., posterior].mean() for c in "RGBW"}
    assert extra["B"] > extra["W"] > 0 and extra["G"] > extra["R"] > 0


def test_positions_pushed_apart_and_alignment():
    xyz = np.array([[0.0, 0, 0], [0.5, 0, 0], [10, 0, 0], [10, 3, 0]])
    out = spread_apart(xyz, 2.0)
    assert np.linalg.norm(out[1] - out[0]) >= 1.99
    np.testing.assert_allclose(out[2:], xyz[2:])
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(200, 3)) * [2, 20, 5]  # long along y, thin along x
    aligned = align_worm(cloud)
    spread = aligned.std(axis=0)
    assert spread[0] > spread[1] > spread[2]  # long axis -> x, thinnest -> z
    np.testing.assert_allclose(np.sort(spread), np.sort(cloud.std(axis=0)), rtol=0.05)


def test_colour_mapping_is_positive_and_monotone():
    z = np.array([-1.5, -0.2, 0.0, 0.7, 2.5, 9.0])
    out = colour_intensities(z)
    assert np.all(out >= 0.05) and np.all(np.diff(out) >= 0)
    assert np.all(colour_intensities(np.ones(5)) == 0.5)


def test_random_colours_when_the_table_has_none(worm):
    bare = NeuronTable(worm.xyz)
    stack, truth = render_stack(bare, seed=0, shape_zyx=(16, 70, 170))
    assert set(truth.colours) == {"R", "G", "B", "W"}


def test_empty_table_is_refused():
    with pytest.raises(FdlcError):
        render_stack(NeuronTable(np.zeros((0, 3))))


@pytest.mark.parametrize("n", [1, 2])
def test_render_a_table_of_one_or_two_neurons(n):
    """Tables of one or two neurons render (the alignment's SVD has fewer than 3 rows for them)."""
    table = NeuronTable([[1.0, 2.0, 3.0], [6.0, 2.5, 3.0]][:n], {"R": [300.0, 900.0][:n]})
    stack, truth = render_stack(table, **SMALL)
    assert len(truth) == n
    assert stack.data.shape[0] == 4
    if n == 2:
        assert np.linalg.norm(truth.xyz[0] - truth.xyz[1]) == pytest.approx(np.linalg.norm([5.0, 0.5, 0.0]))


@pytest.mark.parametrize("what", ["nan_position", "inf_position"])
def test_render_refuses_non_finite_positions(what):
    """NaN or infinite positions are refused in one line."""
    worm = random_worm(8, size_um=(16, 8, 6), seed=1)
    xyz = worm.xyz.copy()
    xyz[1, 0] = np.nan if what == "nan_position" else np.inf
    with pytest.raises(FdlcError) as exc:
        render_stack(NeuronTable(xyz, worm.colours), **SMALL)
    one_line(exc)


def test_render_with_a_missing_colour_value():
    """A NaN colour (a neuron without a reading) renders as the channel's median, as
    read_table reads it, or is refused in one line; never a failed Poisson draw."""
    worm = random_worm(8, size_um=(16, 8, 6), seed=1)
    colours = {c: v.copy() for c, v in worm.colours.items()}
    colours["R"][2] = np.nan
    try:
        stack, truth = render_stack(NeuronTable(worm.xyz, colours), **SMALL)
    except FdlcError as exc:
        assert "\n" not in str(exc)
        return
    assert np.isfinite(truth.extra["R_int"].to_numpy(dtype=float)).all()
    assert stack.data.max() > 0


@pytest.mark.parametrize("overrides", [
    {"shape_zyx": (-3, 10, 10)},
    {"shape_zyx": (0, 10, 10)},
    {"peak_photons": float("nan")},
    {"peak_photons": 1e30},
    {"background_photons": -50.0},
], ids=["negative_shape", "zero_shape", "nan_photons", "absurd_photons", "negative_background"])
def test_render_refuses_absurd_parameters(overrides):
    """Negative or zero shapes, NaN or absurd photon counts and a negative background are
    refused in one line."""
    worm = random_worm(6, size_um=(16, 8, 6), seed=1)
    with pytest.raises(FdlcError) as exc:
        render_stack(worm, **{**SMALL, **overrides})
    one_line(exc)


def test_identity_properties_do_not_depend_on_the_other_neurons():
    """With ``identity``, a neuron keeps its own properties in every stack of a recording, also
    when another neuron (the highest identity) is missing from a volume."""
    worm = random_worm(6, size_um=(20, 8, 6), seed=1)
    no_colour = NeuronTable(worm.xyz)  # R, G, B drawn per neuron (NeuroPAL-like on/off)
    _, all_six = render_stack(no_colour, identity=np.arange(6), identity_seed=3, seed=1, align=False, **SMALL)
    _, first_four = render_stack(no_colour.subset(np.arange(4)), identity=np.arange(4), identity_seed=3, seed=2,
                                 align=False, **SMALL)
    for c in ("R", "G", "B"):
        np.testing.assert_allclose(first_four.colours[c], all_six.colours[c][:4], err_msg=c)


def test_identity_properties_are_independent_draws():
    """With ``identity``, each per-neuron property has its own random stream: R, G and B differ
    (no grey nuclei) and brightness does not follow the nucleus's size."""
    worm = random_worm(60, size_um=(50, 16, 12), seed=2)
    no_colour = NeuronTable(worm.xyz)
    _, truth = render_stack(no_colour, identity=np.arange(60), identity_seed=5, align=False, **SMALL)
    assert not np.allclose(truth.colours["R"], truth.colours["G"])
    assert not np.allclose(truth.colours["G"], truth.colours["B"])
    # Without identity the two are independent (r ~ -0.2 here); with it r ~ 0.83.
    r = np.corrcoef(np.log(truth.extra["radius_um"].to_numpy(float)), np.log(truth.colours["W"]))[0, 1]
    assert abs(r) < 0.5, r


def _small_worm(n: int = 12) -> NeuronTable:
    from napari_fdlc.reference import generate_worm

    return generate_worm(seed=1).subset(np.arange(n))


@pytest.mark.parametrize("settings", [
    {"background_photons": 1e20}, {"gut_strength": 1e20}, {"bleed": 1e20},  # numpy's "lam value too large"
    {"voxel_size_zyx": (1.0, 0.25)}, {"psf_sigma_um": (1.0, 0.25)}, {"margin_um": (1.0, 0.25)},  # unpacking errors
    {"identity": np.arange(5)},  # a reshape error
    {"identity": np.full(12, 10**13)},  # drew 1e13 values per property: MemoryError (1e9: 3 minutes, 70 GB)
    {"nucleus_radius_um": "two"},
], ids=["background", "gut", "bleed", "voxel size", "psf", "margin", "identity length", "identity size", "not a number"])
def test_settings_that_cannot_be_rendered_are_one_image_error(settings):
    with pytest.raises(ImageError):
        render_stack(_small_worm(), **settings)


def test_a_setting_given_as_text_of_a_number_is_used():
    """nucleus_radius_um="2" was checked as a number, then compared as text (TypeError)."""
    stack, truth = render_stack(_small_worm(), nucleus_radius_um="2")
    assert len(truth) == 12


def test_random_worm_that_cannot_be_made_is_an_fdlc_error():
    """500 neurons in a 10 µm ball, or 0 neurons: a plain ValueError (a broadcasting one for 0)."""
    from napari_fdlc.render import random_worm

    for args in ((500, (10, 10, 10)), (0,)):
        with pytest.raises(FdlcError):
            random_worm(*args)


ANTERIOR = ("I1", "I2", "I3", "MC", "M1", "M2", "M3", "M4", "M5", "MI", "NSM", "IL1", "IL2", "OLQ", "OLL",
            "URA", "URB", "URY", "CEP")


@pytest.mark.parametrize("given", ["R", "GB"])
def test_truth_carries_the_colours_that_were_rendered_for_a_partial_colour_table(given):
    """A table with some of R, G, B: the missing channels are drawn (NeuroPAL-like on/off) and
    the truth should carry every rendered colour, the given ones as they were in the input (the
    docstring: "the input colours"). render_stack only checks ``"R" not in table.colours``: with R
    alone the truth has no G or B at all (though they were rendered); with G and B but no R the
    input G and B are thrown away and replaced by rendered intensities."""
    worm = random_worm(10, size_um=(20, 8, 6), seed=1)
    table = NeuronTable(worm.xyz, {c: worm.colours[c] for c in given})
    _, truth = render_stack(table, seed=0, **SMALL)
    assert {"R", "G", "B"} <= set(truth.colours), sorted(truth.colours)
    for c in given:
        np.testing.assert_allclose(truth.colours[c], worm.colours[c], err_msg=f"input {c} not kept")


def _recording(frames=3, n=8):
    worm = random_worm(n, size_um=(16, 8, 6), seed=1)
    return [worm] * frames, [np.arange(n)] * frames


def test_recording_with_fewer_identity_arrays_than_volumes_is_refused():
    """render_recording(volumes, identities): one identity array per volume. With 3 volumes and
    2 identity arrays it silently renders a 2-time-point recording (``zip`` truncates), dropping
    a volume, instead of an ImageError."""
    volumes, identities = _recording(3)
    with pytest.raises(ImageError):
        series, truths = render_recording(volumes, identities[:2], **SMALL)
        pytest.fail(f"rendered {len(series)} time points for 3 volumes")


@pytest.mark.parametrize("settings", [{"voxel_size_zyx": (1.0, 0.5)}, {"margin_um": (2.0, 3.0)}],
                         ids=["voxel size", "margin"])
def test_recording_settings_that_cannot_be_rendered_are_one_image_error(settings):
    """render_stack refuses a 2-number voxel size or margin as an ImageError (tested in
    test_render.py); render_recording computes its shape from them before render_stack checks
    them and fails with numpy's bare ValueError 'operands could not be broadcast together'."""
    volumes, identities = _recording(2)
    with pytest.raises(ImageError):
        render_recording(volumes, identities, **{**SMALL, **settings})


def test_recording_with_an_empty_volume_is_one_image_error():
    """A recording with an empty volume (every neuron dropped at one time point): render_stack
    says "the neuron table is empty" (ImageError), but render_recording computes np.ptp over the
    empty volume first: ValueError 'zero-size array to reduction operation maximum'."""
    volumes, identities = _recording(1)
    volumes = volumes + [NeuronTable(np.zeros((0, 3)))]
    identities = identities + [np.zeros(0, dtype=int)]
    with pytest.raises(ImageError):
        render_recording(volumes, identities, **SMALL)


def _run_limited(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter with at most 3 GB of address space (a renderer that
    tries to allocate the stack fails there instead of swapping the machine)."""
    prelude = "import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))\n"
    return subprocess.run([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=120)


def test_a_huge_shape_is_refused_with_the_renderers_own_message():
    """shape_zyx=(2**21, 2**21, 2**22) is 2**64 voxels, far above MAX_VOXELS (5e8). The check
    ``shape.prod() > MAX_VOXELS`` wraps around in int64 (the product is 0) and passes; the stack
    allocation then fails with numpy's ValueError 'array is too big' (not an ImageError)."""
    proc = _run_limited("""
        from napari_fdlc.render import random_worm, render_stack
        from napari_fdlc.io.images import ImageError
        try:
            render_stack(random_worm(6, size_um=(16, 8, 6), seed=1), shape_zyx=(2**21, 2**21, 2**22), gut=False)
        except ImageError as exc:
            print("IMAGE_ERROR", exc)
        except Exception as exc:
            print("OTHER", type(exc).__name__, exc)
        else:
            print("RENDERED")
    """)
    assert "IMAGE_ERROR" in proc.stdout, proc.stdout + proc.stderr[-2000:]


def test_positions_far_too_large_are_refused_not_rendered_into_a_tiny_empty_stack():
    """Positions ~1e21 µm (a table in the wrong unit): the extent in voxels overflows int64 in
    ``np.ceil(extent / vox).astype(int)`` (to -2**63), ``np.maximum(..., 3)`` makes it 3, and the
    "are the positions in µm?" check never fires: a 4 x 3 x 3 x 3 stack of pure background with
    an empty truth is returned silently."""
    worm = random_worm(6, size_um=(16, 8, 6), seed=1)
    with pytest.raises(ImageError):
        stack, truth = render_stack(NeuronTable(worm.xyz * 1e20, worm.colours), **SMALL)
        pytest.fail(f"rendered a {stack.data.shape} stack with {len(truth)} of 6 neurons")


def test_render_truth_keeps_a_missing_colour_reading_missing():
    """Expected: a neuron without an R reading (NaN in the table, kept as a gap and written
    back empty by NeuronTable) is, in the rendered ground truth, still without an R reading:
    render_stack's docstring says the truth carries "the input colours", and make_sample writes
    that truth as the sample's neuron table.
    Instead: render_stack builds the truth from ``table.colours``, where the gap already holds
    the volume's median, so the truth's neuron has R = the median and ``to_dataframe`` /
    ``write_table`` write it as if it had been measured (the same defect was fixed in
    simulate_worm)."""
    worm = random_worm(8, size_um=(16, 8, 6), seed=1)
    r = worm.colours["R"].copy()
    r[2] = np.nan
    table = NeuronTable(worm.xyz, {**worm.colours, "R": r})
    assert np.isnan(table.to_dataframe()["R"].iloc[2])  # the source writes the gap back empty
    _, truth = render_stack(table, seed=0, align=False, **SMALL)
    assert len(truth) == 8
    written = truth.to_dataframe()["R"].iloc[2]
    assert np.isnan(written), f"the truth of the neuron without an R reading has R = {written} (the median)"


@pytest.mark.parametrize("shape", [5, ("a", "b", "c")], ids=["one number", "text"])
def test_render_shape_that_is_not_three_sizes_is_one_image_error(shape):
    """Expected: a ``shape_zyx`` that is not 3 positive sizes is refused with render's own
    ImageError ("shape_zyx must be 3 positive sizes ..."), as (0, 10, 10) and (-3, 10, 10) are.
    Instead: a single number fails while the error message is being built
    (``tuple(shape_zyx)``: TypeError 'int' object is not iterable), and text fails in
    ``np.asarray(shape_zyx, dtype=int)`` with numpy's bare ValueError."""
    worm = random_worm(6, size_um=(16, 8, 6), seed=1)
    with pytest.raises(ImageError):
        render_stack(worm, shape_zyx=shape, **SMALL)


def test_render_recording_without_margin_keeps_every_neuron_in_the_truth():
    """Expected: render_recording renders every volume into "one shape (the largest extent of
    any volume), each volume centred in it", so each time point's truth holds all of its
    neurons, row for row with the identities given (the truth carries no identity column, so a
    dropped row silently misaligns every later one). render_stack on the same volume with the
    same settings keeps all 4 neurons.
    Instead: render_recording sizes the stack from the positions *before* render_stack pushes
    close centres apart (spread_apart), so with ``margin_um=(0, 0, 0)`` the pushed neurons at
    the ends lie just outside and are left out of the truth: 2 of 4 per volume."""
    xyz = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [10.0, 0.0, 0.0], [5.0, 2.0, 1.0]])
    volume = NeuronTable(xyz, {"R": [1.0, 2.0, 3.0, 4.0]})
    settings = dict(margin_um=(0.0, 0.0, 0.0), voxel_size_zyx=(0.5, 0.25, 0.25), gut=False)
    _, alone = render_stack(volume, align=False, **settings)
    assert len(alone) == 4
    _, truths = render_recording([volume, volume], [np.arange(4)] * 2, **settings)
    assert [len(t) for t in truths] == [4, 4], f"truth sizes per time point: {[len(t) for t in truths]} of 4 neurons"
