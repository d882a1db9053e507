"""Defects found reviewing render.py, simulate.py, io/nwb.py and _napari/_io.py (each test fails
until its defect is fixed)."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.io.images import Stack, StackSeries, read_stack
from napari_fdlc.render import random_worm, render_stack
from napari_fdlc.table import NeuronTable

NAMES = ["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"]
# Small, coarse stacks: a few thousand voxels each.
SMALL = dict(margin_um=(2.0, 3.0, 3.0), voxel_size_zyx=(1.0, 0.5, 0.5), gut=False)


def one_line(exc_info) -> str:
    message = str(exc_info.value)
    assert message and "\n" not in message, message
    return message


@pytest.fixture
def stack():
    data = np.random.default_rng(0).integers(0, 4000, (4, 5, 24, 32)).astype(np.uint16)
    return Stack(data, (1.5, 0.25, 0.3), ["R", "G", "B", "W"], channel_names=NAMES)


# ----- render.py --------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2])
def test_render_a_table_of_one_or_two_neurons(n):
    """align_worm takes vt from a reduced SVD, which has fewer than 3 rows for < 3 neurons, and
    np.linalg.det(vt) raises LinAlgError: a valid (small) table cannot be rendered."""
    table = NeuronTable([[1.0, 2.0, 3.0], [6.0, 2.5, 3.0]][:n], {"R": [300.0, 900.0][:n]})
    stack, truth = render_stack(table, **SMALL)
    assert len(truth) == n
    assert stack.data.shape[0] == 4
    if n == 2:
        assert np.linalg.norm(truth.xyz[0] - truth.xyz[1]) == pytest.approx(np.linalg.norm([5.0, 0.5, 0.0]))


@pytest.mark.parametrize("what", ["nan_position", "inf_position"])
def test_render_refuses_non_finite_positions(what):
    """NaN/inf positions crash in the SVD (LinAlgError) instead of a one-line FdlcError."""
    worm = random_worm(8, size_um=(16, 8, 6), seed=1)
    xyz = worm.xyz.copy()
    xyz[1, 0] = np.nan if what == "nan_position" else np.inf
    with pytest.raises(FdlcError) as exc:
        render_stack(NeuronTable(xyz, worm.colours), **SMALL)
    one_line(exc)


def test_render_with_a_missing_colour_value():
    """One NaN colour (a neuron without a reading; NeuronTable allows it) makes the Poisson draw
    fail with 'ValueError: lam value too large'. Either render it (e.g. as the channel's median,
    as read_table does) or refuse it in one line."""
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
    """Now: ValueError (negative dimensions / lam value too large), or a stack with no Z plane
    (zero shape), or negative background silently clipped."""
    worm = random_worm(6, size_um=(16, 8, 6), seed=1)
    with pytest.raises(FdlcError) as exc:
        render_stack(worm, **{**SMALL, **overrides})
    one_line(exc)


def test_identity_properties_do_not_depend_on_the_other_neurons():
    """render_stack(identity=...) promises each neuron keeps its own properties in every stack
    of a recording. For the two-draw properties (on/off colour, GFP activity) the value drawn for
    an identity depends on how many identities there are (ids.max() + 1), so a neuron changes
    colour when another neuron (the highest id) is missing from a volume."""
    worm = random_worm(6, size_um=(20, 8, 6), seed=1)
    no_colour = NeuronTable(worm.xyz)  # R, G, B drawn per neuron (NeuroPAL-like on/off)
    _, all_six = render_stack(no_colour, identity=np.arange(6), identity_seed=3, seed=1, align=False, **SMALL)
    _, first_four = render_stack(no_colour.subset(np.arange(4)), identity=np.arange(4), identity_seed=3, seed=2,
                                 align=False, **SMALL)
    for c in ("R", "G", "B"):
        np.testing.assert_allclose(first_four.colours[c], all_six.colours[c][:4], err_msg=c)


def test_identity_properties_are_independent_draws():
    """Every per-neuron property is drawn from a fresh default_rng(identity_seed), so with
    ``identity`` all properties come from the same random numbers: R, G and B are identical in
    every neuron (grey nuclei, no NeuroPAL colour code) and the W brightness is a deterministic
    function of the nucleus radius (bigger nuclei always brighter)."""
    worm = random_worm(60, size_um=(50, 16, 12), seed=2)
    no_colour = NeuronTable(worm.xyz)
    _, truth = render_stack(no_colour, identity=np.arange(60), identity_seed=5, align=False, **SMALL)
    assert not np.allclose(truth.colours["R"], truth.colours["G"])
    assert not np.allclose(truth.colours["G"], truth.colours["B"])
    # Without identity the two are independent (r ~ -0.2 here); with it r ~ 0.83.
    r = np.corrcoef(np.log(truth.extra["radius_um"].to_numpy(float)), np.log(truth.colours["W"]))[0, 1]
    assert abs(r) < 0.5, r


# ----- simulate.py ------------------------------------------------------------------------------


@pytest.mark.parametrize("what", ["empty", "nan"])
def test_simulate_refuses_empty_or_non_finite_tables(what):
    """An empty table fails with 'ValueError: high <= 0', a NaN position with
    'LinAlgError: Eigenvalues did not converge'."""
    from napari_fdlc.simulate import simulate_worm

    if what == "empty":
        table = NeuronTable(np.zeros((0, 3)))
    else:
        xyz = np.random.default_rng(0).normal(size=(10, 3)) * [20, 5, 4]
        xyz[2, 1] = np.nan
        table = NeuronTable(xyz)
    with pytest.raises(FdlcError) as exc:
        simulate_worm(table, 0)
    one_line(exc)


# ----- io/nwb.py --------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", ["mNeptune2.5/red", "TagRFP: 561 nm"])
def test_write_nwb_with_slash_or_colon_in_a_channel_name(tmp_path, stack, bad):
    """write_nwb names each OpticalChannel '<i> <channel name>'; NWB names cannot hold '/' or ':'
    so a stack whose (legal, e.g. OME) channel names contain them cannot be written at all
    (ValueError from pynwb). The names belong in order_optical_channels, unchanged."""
    from napari_fdlc.io.nwb import write_nwb

    names = list(NAMES)
    names[0] = bad
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, channel_names=names)
    got = read_stack(path)
    assert got.channel_names == names
    assert got.channel_roles == ["R", "G", "B", "W"]


def test_write_nwb_refuses_nan_neuron_positions(tmp_path, stack):
    """int(round(nan)) raises a bare ValueError ('cannot convert float NaN to integer')."""
    from napari_fdlc.io.nwb import write_nwb

    path = tmp_path / "worm.nwb"
    neurons = NeuronTable([[3.0, 2.5, 1.5], [np.nan, 1.0, 3.0]], labels=["AVAL", "AVAR"])
    with pytest.raises(FdlcError) as exc:
        write_nwb(path, stack, neurons)
    one_line(exc)
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_write_nwb_with_a_neuron_left_of_the_image(tmp_path, stack):
    """A neuron at x = -2 µm (outside the image) gives voxel -7, which does not fit the uint32
    voxel_mask: 'OverflowError: Python integer -7 out of bounds for uint32'. Either refuse it in
    one line, or write it so that it reads back where it was (within a voxel)."""
    from napari_fdlc.io.nwb import read_nwb_neurons, write_nwb

    path = tmp_path / "worm.nwb"
    neurons = NeuronTable([[3.0, 2.5, 1.5], [-2.0, 1.0, 3.0]], labels=["AVAL", "AVAR"])
    try:
        write_nwb(path, stack, neurons)
    except FdlcError as exc:
        assert "\n" not in str(exc)
        assert not path.exists()
        return
    got = read_nwb_neurons(path, colours=False)
    np.testing.assert_allclose(got.xyz, neurons.xyz, atol=0.76)


def test_write_nwb_to_an_unwritable_place_names_the_target(tmp_path, stack):
    """An OSError named the hidden temporary file (.worm.1a2b3c4d.tmp.nwb) or came as a bare
    FileExistsError from mkdir; the error should be one FdlcError line naming the target."""
    from napari_fdlc.io.nwb import write_nwb

    blocker = tmp_path / "afile"
    blocker.write_text("x")
    target = blocker / "sub" / "worm.nwb"
    with pytest.raises(FdlcError) as exc:
        write_nwb(target, stack)
    assert str(target) in one_line(exc) and ".tmp" not in str(exc.value)


def test_write_nwb_refuses_a_recording(tmp_path, stack):
    """A StackSeries (T, C, Z, Y, X) fails in transpose with 'ValueError: axes don't match
    array'; an NWB file here holds one volume, so say so in one line."""
    from napari_fdlc.io.nwb import write_nwb

    series = StackSeries(np.stack([stack.data, stack.data]), stack.voxel_size_zyx, stack.channel_roles,
                         channel_names=NAMES)
    with pytest.raises(FdlcError) as exc:
        write_nwb(tmp_path / "rec.nwb", series)
    one_line(exc)


@pytest.mark.parametrize("spacing", [[0.0, 0.0, 0.0], [0.3, 0.25, np.nan], [-0.3, -0.25, -1.5]],
                         ids=["zero", "nan", "negative"])
def test_read_nwb_neurons_refuses_a_bad_grid_spacing(tmp_path, stack, spacing):
    """read_stack refuses these voxel sizes, but read_nwb_neurons only checks for None and
    returns positions that are all 0, NaN or negative."""
    import h5py

    from napari_fdlc.io.images import ImageError
    from napari_fdlc.io.nwb import read_nwb_neurons, write_nwb

    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, NeuronTable([[3.0, 2.5, 1.5], [6.0, 1.0, 3.0]], labels=["AVAL", "AVAR"]))
    with h5py.File(path, "a") as f:
        f["general/optophysiology/NeuroPALImVol/grid_spacing"][...] = spacing
    with pytest.raises(ImageError) as exc:
        read_nwb_neurons(path, colours=False)
    one_line(exc)


def test_nwb_mask_centre_is_weighted_when_a_voxel_has_zero_weight(tmp_path):
    """docs/image_formats.md: centres are the weighted mean of multi-voxel masks. _mask_centre
    weighs only when *every* weight is > 0, so a mask with a zero-weight voxel gets the plain
    mean (here x = 15 voxels instead of 10)."""
    from pynwb import NWBHDF5IO, NWBFile
    from pynwb.ophys import ImageSegmentation, OpticalChannel

    from napari_fdlc.io.nwb import read_nwb_neurons

    nwb = NWBFile(session_description="t", identifier="t", session_start_time=datetime.now(timezone.utc))
    device = nwb.create_device(name="Microscope")
    plane = nwb.create_imaging_plane(
        name="NeuroPALImVol", optical_channel=[OpticalChannel(name="W", description="", emission_lambda=np.nan)],
        description="", device=device, excitation_lambda=np.nan, indicator="NeuroPAL", location="head",
        grid_spacing=[0.5, 0.5, 1.0], grid_spacing_unit="micrometers",
    )
    module = nwb.create_processing_module(name="NeuroPAL", description="")
    seg = ImageSegmentation(name="NeuroPALSegmentation")
    module.add(seg)
    ps = seg.create_plane_segmentation(name="NeuroPALNeurons", description="", imaging_plane=plane)
    ps.add_column(name="ID_labels", description="")
    ps.add_roi(voxel_mask=[(10, 10, 2, 1.0), (20, 10, 2, 0.0)], ID_labels="AVAL")
    ps.add_roi(voxel_mask=[(4, 6, 3, 1.0)], ID_labels="AVAR")
    path = tmp_path / "masks.nwb"
    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)
    got = read_nwb_neurons(path, colours=False)
    np.testing.assert_allclose(got.xyz[0], [5.0, 5.0, 2.0])
    np.testing.assert_allclose(got.xyz[1], [2.0, 3.0, 3.0])


# ----- _napari/_io.py (no viewer needed) ---------------------------------------------------------


def test_writer_does_not_merge_time_points(tmp_path):
    """write_neuron_csv keeps only the last 3 coordinates: a t, z, y, x Points layer with
    points at two time points (no 't' feature) is written as one worm, the time lost, although
    layer_xyz_um refuses such a layer. Refuse it in one line, or write a 't' column."""
    from napari_fdlc._napari._io import write_neuron_csv

    data = np.array([[0, 1, 2, 3], [1, 1, 2, 3], [1, 4, 5, 6]], dtype=float)
    path = tmp_path / "points.csv"
    try:
        written = write_neuron_csv(str(path), data, {"scale": (1, 1, 1, 1)})
    except FdlcError as exc:
        assert "\n" not in str(exc)
        assert not path.exists()
        return
    import pandas as pd

    df = pd.read_csv(written[0])
    assert "t" in df.columns and list(df["t"]) == [0, 1, 1]


def test_writer_refuses_an_empty_layer(tmp_path):
    """An empty Points layer is written as a header-only CSV that read_table then refuses
    ('the table has no rows'): a file that cannot be opened again."""
    from napari_fdlc._napari._io import write_neuron_csv

    path = tmp_path / "empty.csv"
    with pytest.raises(FdlcError) as exc:
        write_neuron_csv(str(path), np.zeros((0, 3)), {})
    one_line(exc)
    assert not path.exists()


def test_writer_unwritable_path_is_an_fdlc_error(tmp_path):
    """_io's contract: every problem is an FdlcError with one line. A path under a file raises
    a bare NotADirectoryError/FileExistsError (OSError) from atomic_write."""
    from napari_fdlc._napari._io import write_neuron_csv

    blocker = tmp_path / "afile"
    blocker.write_text("x")
    with pytest.raises(FdlcError) as exc:
        write_neuron_csv(str(blocker / "points.csv"), np.zeros((2, 3)), {})
    one_line(exc)
