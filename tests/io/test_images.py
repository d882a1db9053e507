"""Image readers: round trips, metadata, channel roles and one-line errors for bad input."""

from __future__ import annotations

from datetime import datetime, timezone
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import tifffile

from napari_fdlc.errors import FdlcError
from napari_fdlc.io import images
from napari_fdlc.io.images import (
    ImageError,
    Stack,
    StackSeries,
    VoxelSizeUnknown,
    read_nd2,
    read_series,
    read_stack,
    role_from_name,
    write_tiff,
)
from napari_fdlc.io.nwb import _text, read_nwb_neurons, write_nwb
from napari_fdlc.table import NeuronTable
import gc
import warnings
import re
from napari_fdlc.io.images import AxesUnknown

NAMES = ["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"]


@pytest.fixture
def stack():
    rng = np.random.default_rng(0)
    data = rng.integers(0, 4000, (4, 5, 24, 32)).astype(np.uint16)
    return Stack(data, (1.5, 0.25, 0.3), ["R", "G", "B", "W"], channel_names=NAMES)


def one_line_error(exc_info, *words):
    message = str(exc_info.value)
    assert "\n" not in message and message.strip() == message and message
    for w in words:
        assert w.lower() in message.lower(), message
    return message


# ----- TIFF ----------------------------------------------------------------------------------


@pytest.mark.parametrize("ome", [True, False], ids=["ome-tiff", "imagej"])
def test_tiff_round_trip(tmp_path, stack, ome):
    path = tmp_path / ("s.ome.tif" if ome else "s.tif")
    write_tiff(path, stack, ome=ome)
    got = read_stack(path)
    np.testing.assert_array_equal(np.asarray(got.data), stack.data)
    assert got.voxel_size_zyx == pytest.approx(stack.voxel_size_zyx)
    assert got.channel_roles == ["R", "G", "B", "W"]
    assert got.channel_names == NAMES
    assert got.shape_zyx == (5, 24, 32) and got.n_channels == 4 and not got.is_lazy
    assert got.channel("W").shape == (5, 24, 32)


def test_ome_units_are_converted(tmp_path):
    data = np.zeros((3, 8, 8), np.uint16)
    path = tmp_path / "nm.ome.tif"
    tifffile.imwrite(path, data, ome=True, metadata={
        "axes": "ZYX", "PhysicalSizeX": 250, "PhysicalSizeXUnit": "nm", "PhysicalSizeY": 250,
        "PhysicalSizeYUnit": "nm", "PhysicalSizeZ": 0.001, "PhysicalSizeZUnit": "mm"})
    got = read_stack(path)
    assert got.voxel_size_zyx == pytest.approx((1.0, 0.25, 0.25))
    assert got.channel_roles == [None] and got.data.shape == (1, 3, 8, 8)


def test_user_values_override_the_file(tmp_path, stack):
    path = tmp_path / "s.ome.tif"
    write_tiff(path, stack)
    got = read_stack(path, voxel_size=(2, 0.5, 0.5), channels=["W", "-", "gcamp", "R"])
    assert got.voxel_size_zyx == (2.0, 0.5, 0.5)
    assert got.channel_roles == ["W", None, "GFP", "R"]


def test_tiff_without_voxel_size_asks_for_it(tmp_path):
    path = tmp_path / "plain.tif"
    tifffile.imwrite(path, np.zeros((2, 4, 8, 8), np.uint16), metadata={"axes": "CZYX"})
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, "voxel size", "--voxel-size")
    got = read_stack(path, voxel_size=(1, 0.3, 0.3), channels=["W", "R"])
    assert got.channel_roles == ["W", "R"]


def test_tiff_without_axes_asks_for_them(tmp_path):
    path = tmp_path / "pages.tif"
    with tifffile.TiffWriter(path) as tw:
        for _ in range(6):  # separate pages, no shape metadata: axes unknown
            tw.write(np.zeros((8, 8), np.uint16), metadata=None)
    with pytest.raises(FdlcError) as exc:
        read_stack(path, voxel_size=(1, 0.3, 0.3))
    one_line_error(exc, "axes")
    got = read_stack(path, voxel_size=(1, 0.3, 0.3), axes="ZYX")
    assert got.data.shape == (1, 6, 8, 8)
    with pytest.raises(FdlcError) as exc:
        read_stack(path, voxel_size=(1, 0.3, 0.3), axes="CZYX")
    one_line_error(exc, "axes")


def test_a_time_series_is_a_recording_not_a_stack(tmp_path):
    path = tmp_path / "movie.tif"
    data = np.arange(3 * 4 * 8 * 8, dtype=np.uint16).reshape(3, 4, 8, 8)
    tifffile.imwrite(path, data, imagej=True, metadata={"axes": "TZYX"})
    with pytest.raises(FdlcError) as exc:
        read_stack(path, voxel_size=(1, 0.3, 0.3))
    one_line_error(exc, "3 time points", "fdlc track")
    series = read_series(path, voxel_size=(1, 0.3, 0.3), channels=["W"])
    assert len(series) == 3 and series.data.shape == (3, 1, 4, 8, 8)
    np.testing.assert_array_equal(series.volume(2).data[0], data[2])


@pytest.mark.parametrize("ome", [True, False], ids=["ome-tiff", "imagej"])
@pytest.mark.parametrize("lazy", [False, True], ids=["in-memory", "lazy"])
def test_recording_round_trip(tmp_path, stack, ome, lazy, monkeypatch):
    rng = np.random.default_rng(1)
    data = rng.integers(0, 4000, (3,) + stack.data.shape).astype(np.uint16)
    path = tmp_path / ("rec.ome.tif" if ome else "rec.tif")
    write_tiff(path, StackSeries(data, stack.voxel_size_zyx, stack.channel_roles, channel_names=NAMES), ome=ome)
    if lazy:
        monkeypatch.setattr(images, "LAZY_BYTES", 0)
    series = read_series(path)
    assert len(series) == 3 and series.shape_zyx == stack.shape_zyx and series.n_channels == 4
    assert series.channel_roles == ["R", "G", "B", "W"]
    np.testing.assert_allclose(series.voxel_size_zyx, stack.voxel_size_zyx, rtol=1e-5)
    assert isinstance(series.data, np.ndarray) != lazy
    for t in range(3):
        volume = series.volume(t)
        assert isinstance(volume.data, np.ndarray) and volume.source.endswith(f"(t={t})")
        np.testing.assert_array_equal(volume.data, data[t])


def test_a_single_stack_is_a_recording_of_one(tmp_path, stack):
    path = tmp_path / "one.ome.tif"
    write_tiff(path, stack)
    series = read_series(path)
    assert len(series) == 1 and series.volume(0).source == str(path)
    np.testing.assert_array_equal(series.volume(0).data, stack.data)
    with pytest.raises(FdlcError) as exc:
        StackSeries(stack.data, stack.voxel_size_zyx, stack.channel_roles)
    one_line_error(exc, "T, C, Z, Y, X")


def test_2d_image_is_refused(tmp_path):
    path = tmp_path / "flat.ome.tif"
    tifffile.imwrite(path, np.zeros((2, 8, 8), np.uint16), ome=True, metadata={"axes": "CYX"})
    with pytest.raises(FdlcError) as exc:
        read_stack(path, voxel_size=(1, 0.3, 0.3))
    one_line_error(exc, "2D")


def test_truncated_tiff_is_refused(tmp_path, stack):
    path = tmp_path / "cut.ome.tif"
    write_tiff(path, stack, compression=None)
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, str(path))


@pytest.mark.parametrize("content", [b"", b"II*\x00garbage", b"not an image at all"], ids=["empty", "corrupt", "text"])
def test_bad_files_are_refused(tmp_path, content):
    path = tmp_path / "bad.tif"
    path.write_bytes(content)
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, str(path))


def test_missing_file_and_folder_and_unknown_format(tmp_path):
    with pytest.raises(FdlcError) as exc:
        read_stack(tmp_path / "nope.tif")
    one_line_error(exc, "no such file")
    with pytest.raises(FdlcError) as exc:
        read_stack(tmp_path)
    one_line_error(exc, "folder")
    other = tmp_path / "stack.czi"
    other.write_bytes(b"ZISRAWFILE" + bytes(100))
    with pytest.raises(FdlcError) as exc:
        read_stack(other)
    one_line_error(exc, "TIFF", "NWB", "ND2")


def test_channel_roles_that_do_not_fit(tmp_path, stack):
    path = tmp_path / "s.ome.tif"
    write_tiff(path, stack)
    with pytest.raises(FdlcError) as exc:
        read_stack(path, channels=["R", "G"])
    one_line_error(exc, "2 channel role(s)", "4 channel(s)")
    with pytest.raises(FdlcError) as exc:
        read_stack(path, channels=["R", "G", "B", "purple"])
    one_line_error(exc, "purple")
    with pytest.raises(FdlcError) as exc:
        read_stack(path, channels=["R", "R", "B", "W"])
    one_line_error(exc, "more than once")


def test_bad_voxel_size_is_refused(tmp_path, stack):
    path = tmp_path / "s.ome.tif"
    write_tiff(path, stack)
    with pytest.raises(FdlcError) as exc:
        read_stack(path, voxel_size=(1, 0, 0.3))
    one_line_error(exc, "voxel size")


@pytest.mark.parametrize(
    "name, role",
    [("mNeptune2.5", "R"), ("NEP", "R"), ("n2.5", "R"), ("CyOFP1.5", "G"), ("cyo", "G"),
     ("mTagBFP2", "B"), ("TagRFP-T", "W"), ("RFP", "W"), ("GCaMP6s", "GFP"), ("EGFP", "GFP"),
     ("w", "W"), ("DIC", None), ("", None), (None, None)],
)
def test_role_from_name(name, role):
    assert role_from_name(name) == role


def test_ambiguous_names_give_no_role(tmp_path):
    data = np.zeros((2, 3, 8, 8), np.uint16)
    stack = Stack(data, (1, 0.3, 0.3), [None, None], channel_names=["TagRFP", "RFP 2"])
    path = tmp_path / "two_rfp.ome.tif"
    write_tiff(path, stack)
    assert read_stack(path).channel_roles == [None, None]


def test_big_tiff_is_read_lazily(tmp_path, stack, monkeypatch):
    path = tmp_path / "s.ome.tif"
    write_tiff(path, stack)
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    got = read_stack(path)
    assert got.is_lazy
    np.testing.assert_array_equal(np.asarray(got.data), stack.data)
    np.testing.assert_array_equal(got.channel("B"), stack.data[2])


# ----- NWB -----------------------------------------------------------------------------------


@pytest.fixture
def neurons():
    return NeuronTable(
        xyz=[[3.0, 2.5, 1.5], [6.3, 4.0, 4.5], [1.2, 1.0, 3.0]], labels=["AVAL", "RMDDR?", ""]
    )


def test_nwb_round_trip(tmp_path, stack, neurons):
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, neurons)
    got = read_stack(path)
    np.testing.assert_array_equal(np.asarray(got.data), stack.data)
    assert got.voxel_size_zyx == pytest.approx(stack.voxel_size_zyx)
    assert got.channel_roles == ["R", "G", "B", "W"]
    assert got.channel_names == NAMES
    table = read_nwb_neurons(path)
    assert list(table.labels) == ["AVAL", "RMDDR", ""]
    assert list(table.label_conf) == [1.0, 0.5, 0.0]
    # voxel_mask stores whole voxels: positions come back on the grid (0.3, 0.25, 1.5 µm).
    np.testing.assert_allclose(table.xyz, neurons.xyz, atol=0.76)
    assert set(table.colours) == {"R", "G", "B", "W"}


def test_nwb_roles_without_rgbw_and_one_based(tmp_path, stack):
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack)
    with h5py.File(path, "a") as f:
        f["acquisition/NeuroPALImageRaw/RGBW_channels"][...] = [4, 1, 2, 3]  # 1-based, MATLAB style
    assert read_stack(path).channel_roles == ["G", "B", "W", "R"]
    with h5py.File(path, "a") as f:
        del f["acquisition/NeuroPALImageRaw/RGBW_channels"]
    assert read_stack(path).channel_roles == ["R", "G", "B", "W"]  # from the channel names


def test_nwb_without_voxel_size_or_image(tmp_path, stack):
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack)
    with h5py.File(path, "a") as f:
        del f["general/optophysiology/NeuroPALImVol/grid_spacing"]
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, "voxel size")
    assert read_stack(path, voxel_size=(1, 1, 1)).voxel_size_zyx == (1, 1, 1)
    with h5py.File(path, "a") as f:
        del f["acquisition/NeuroPALImageRaw"]
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, "no NeuroPAL image")
    with pytest.raises(FdlcError) as exc:
        read_nwb_neurons(path)
    one_line_error(exc, "no neuron segmentation")


def test_truncated_nwb_is_refused(tmp_path, stack):
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack)
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 3])
    with pytest.raises(FdlcError) as exc:
        read_stack(path)
    one_line_error(exc, str(path))


def test_ragged_character_labels_are_joined():
    assert _text(np.array([b"A", b"V", b"A", b"L"], dtype=object)) == "AVAL"
    assert _text(["R", "M", "D", "?"]) == "RMD?"
    assert _text(b"AVAR") == "AVAR"


@pytest.mark.parametrize("bad", ["mNeptune2.5/red", "TagRFP: 561 nm"])
def test_write_nwb_with_slash_or_colon_in_a_channel_name(tmp_path, stack, bad):
    """Channel names with '/' or ':' (legal in OME) are written: NWB object names cannot hold
    them, so the OpticalChannel names are sanitised and the names kept unchanged in
    order_optical_channels."""
    names = list(NAMES)
    names[0] = bad
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, channel_names=names)
    got = read_stack(path)
    assert got.channel_names == names
    assert got.channel_roles == ["R", "G", "B", "W"]


def test_write_nwb_refuses_nan_neuron_positions(tmp_path, stack):
    """A NaN neuron position is refused in one line, and nothing is left on disk."""
    path = tmp_path / "worm.nwb"
    neurons = NeuronTable([[3.0, 2.5, 1.5], [np.nan, 1.0, 3.0]], labels=["AVAL", "AVAR"])
    with pytest.raises(FdlcError) as exc:
        write_nwb(path, stack, neurons)
    one_line_error(exc)
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_write_nwb_with_a_neuron_left_of_the_image(tmp_path, stack):
    """A neuron outside the image (x < 0, which a uint32 voxel mask cannot hold) is refused in
    one line with nothing written, or written so that it reads back where it was."""
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
    """A place that cannot be written is one line naming the target, not the hidden temporary
    file nor a bare OSError."""
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    target = blocker / "sub" / "worm.nwb"
    with pytest.raises(FdlcError) as exc:
        write_nwb(target, stack)
    assert ".tmp" not in one_line_error(exc, str(target))


def test_write_nwb_refuses_a_recording(tmp_path, stack):
    """An NWB file here holds one volume: a recording (T, C, Z, Y, X) is refused in one line."""
    series = StackSeries(np.stack([stack.data, stack.data]), stack.voxel_size_zyx, stack.channel_roles,
                         channel_names=NAMES)
    with pytest.raises(FdlcError) as exc:
        write_nwb(tmp_path / "rec.nwb", series)
    one_line_error(exc)


@pytest.mark.parametrize("spacing", [[0.0, 0.0, 0.0], [0.3, 0.25, np.nan], [-0.3, -0.25, -1.5]],
                         ids=["zero", "nan", "negative"])
def test_read_nwb_neurons_refuses_a_bad_grid_spacing(tmp_path, stack, spacing):
    """A zero, NaN or negative grid spacing is refused by read_nwb_neurons as by read_stack,
    not turned into positions that are all 0, NaN or negative."""

    from napari_fdlc.io.images import ImageError

    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, NeuronTable([[3.0, 2.5, 1.5], [6.0, 1.0, 3.0]], labels=["AVAL", "AVAR"]))
    with h5py.File(path, "a") as f:
        f["general/optophysiology/NeuroPALImVol/grid_spacing"][...] = spacing
    with pytest.raises(ImageError) as exc:
        read_nwb_neurons(path, colours=False)
    one_line_error(exc)


def test_nwb_mask_centre_is_weighted_when_a_voxel_has_zero_weight(tmp_path):
    """Centres are the weighted mean of multi-voxel masks (docs/image_formats.md), also when a
    voxel weighs 0."""
    from pynwb import NWBHDF5IO, NWBFile
    from pynwb.ophys import ImageSegmentation, OpticalChannel


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


# ----- ND2 (cannot be written: a stand-in with ND2File's interface is injected) ---------------


class FakeND2:
    """The part of ``nd2.ND2File`` that the reader uses."""

    def __init__(self, data, sizes, voxel=(0.3, 0.3, 1.2), names=("mNeptune", "CyOFP", "mTagBFP", "TagRFP")):
        self._data = data
        self.sizes = sizes
        self.dtype = data.dtype
        self._voxel = voxel
        self.metadata = SimpleNamespace(
            channels=[SimpleNamespace(channel=SimpleNamespace(name=n)) for n in names]
        )
        self.closed = False

    def voxel_size(self, channel=0):
        x, y, z = self._voxel
        return SimpleNamespace(x=x, y=y, z=z)

    def asarray(self):
        return self._data

    def to_dask(self):
        import dask.array as da

        return da.from_array(self._data)

    def close(self):
        self.closed = True


def test_nd2_through_a_fake_file(tmp_path):
    data = np.arange(6 * 4 * 10 * 12, dtype=np.uint16).reshape(6, 4, 10, 12)  # Z, C, Y, X
    fake = FakeND2(data, {"Z": 6, "C": 4, "Y": 10, "X": 12})
    got = read_nd2(tmp_path / "w.nd2", opener=lambda p: fake)
    assert got.data.shape == (4, 6, 10, 12)
    np.testing.assert_array_equal(got.data[2], data[:, 2])
    assert got.voxel_size_zyx == pytest.approx((1.2, 0.3, 0.3))
    assert got.channel_roles == ["R", "G", "B", "W"]
    assert fake.closed


def test_nd2_via_read_stack(tmp_path, monkeypatch):
    import nd2

    data = np.zeros((1, 5, 3, 8, 8), np.uint16)  # T=1 is squeezed away
    fake = FakeND2(data, {"T": 1, "Z": 5, "C": 3, "Y": 8, "X": 8}, names=("TagRFP-T", "GCaMP", "DIC"))
    monkeypatch.setattr(nd2, "ND2File", lambda path: fake)
    path = tmp_path / "w.nd2"
    path.write_bytes(b"\xda\xce\xbe\x0a" + bytes(64))
    got = read_stack(path)
    assert got.channel_roles == ["W", "GFP", None]
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    assert read_stack(path).is_lazy


def test_nd2_problems(tmp_path):
    def broken(path):
        raise OSError("File not a valid ND2 file\nsecond line")

    with pytest.raises(FdlcError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=broken)
    one_line_error(exc, "not a readable ND2 file")
    movie = FakeND2(np.arange(3 * 5 * 8 * 8, dtype=np.uint16).reshape(3, 5, 8, 8), {"T": 3, "Z": 5, "Y": 8, "X": 8}, names=())
    with pytest.raises(FdlcError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=lambda p: movie)
    one_line_error(exc, "time points")
    series = read_nd2(tmp_path / "w.nd2", opener=lambda p: movie, time=True)
    assert len(series) == 3
    np.testing.assert_array_equal(series.volume(1).data[0], movie.asarray()[1])
    flat = FakeND2(np.zeros((2, 8, 8), np.uint16), {"C": 2, "Y": 8, "X": 8}, voxel=(1.0, 1.0, 1.0))
    with pytest.raises(FdlcError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=lambda p: flat)
    one_line_error(exc, "2D")
    uncalibrated = FakeND2(np.zeros((4, 8, 8), np.uint16), {"Z": 4, "Y": 8, "X": 8}, voxel=(1.0, 1.0, 1.0), names=())
    with pytest.raises(FdlcError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=lambda p: uncalibrated)
    one_line_error(exc, "voxel size")


def test_an_axis_of_unknown_meaning_is_asked_for_not_called_2d(tmp_path):
    """axes 'CQYX' (Q: tifffile's axis of unknown meaning, often a plain stack's Z) was refused
    as "a 2D image"; it is an unknown axis, and the message says how to name it."""
    path = tmp_path / "a.tif"
    tifffile.imwrite(path, np.zeros((2, 5, 16, 16), np.uint16))
    with pytest.raises(FdlcError, match="unknown image axes 'CQYX'"):
        read_stack(path, axes="CQYX")


# ----- Session 30's review -------------------------------------------------------------------


def _zcyx(nz=5, nc=2, ny=16, nx=16):
    return ((np.arange(nz * nc * ny * nx) * 7) % 4000 + 1).astype(np.uint16).reshape(nz, nc, ny, nx)


def test_an_imagej_file_over_4gb_read_lazily_has_all_its_planes(tmp_path, monkeypatch):
    """ImageJ writes no BigTIFF: over 4 GB its hyperstacks have one page header and the planes
    after it (tifffile's truncate=True). The lazy reader made one block per header and died in a
    reshape (ValueError traceback); it now maps the planes from the file."""
    data = _zcyx()
    path = tmp_path / "big_fiji.tif"
    tifffile.imwrite(path, data, imagej=True, truncate=True, resolution=(4.0, 4.0),
                     metadata={"axes": "ZCYX", "unit": "micron", "spacing": 1.5})
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    lazy = read_stack(path)
    assert lazy.is_lazy
    np.testing.assert_array_equal(np.asarray(lazy.data), data.transpose(1, 0, 2, 3))


def test_an_imagej_stack_with_a_1um_z_step_has_its_voxel_size(tmp_path):
    """ImageJ leaves `spacing` out of a calibrated stack whose z step is 1 (its unit) and reads
    it back as 1; such a stack was refused for want of a z voxel size."""
    path = tmp_path / "fiji_1um.tif"
    tifffile.imwrite(path, _zcyx(), imagej=True, resolution=(4.0, 4.0),
                     metadata={"axes": "ZCYX", "unit": "micron", "Labels": ["TagRFP-T", "mNeptune2.5"] * 5})
    assert "spacing" not in tifffile.TiffFile(path).imagej_metadata
    assert read_stack(path).voxel_size_zyx == pytest.approx((1.0, 0.25, 0.25))


def test_an_lzw_compressed_tiff_is_read(tmp_path):
    """LZW, the commonest TIFF compression of other software, needs imagecodecs (now a
    dependency): every LZW stack was refused as unreadable."""
    planes = _zcyx(nz=4, nc=1)[:, 0]
    path = tmp_path / "lzw.tif"
    tifffile.imwrite(path, planes, compression="lzw")
    stack = read_stack(path, axes="ZYX", voxel_size=(1.0, 0.25, 0.25), channels=["W"])
    np.testing.assert_array_equal(np.asarray(stack.data)[0], planes)


def test_a_multi_position_nd2_says_to_export_one_position(tmp_path):
    """An ND2 of several stage positions was refused as 'unknown image axes PZCYX; give them
    (--axes CZYX)', and --axes is not used for ND2: the advice could not help. One position
    (P of 1) reads as a volume."""
    several = FakeND2(np.zeros((2, 5, 2, 16, 16), np.uint16), {"P": 2, "Z": 5, "C": 2, "Y": 16, "X": 16}, names=("a", "b"))
    with pytest.raises(images.ImageError) as exc:
        read_nd2(tmp_path / "p.nd2", opener=lambda p: several, channels=["W", "R"])
    one_line_error(exc, "2 positions", "export each position")
    data = _zcyx()[None]
    one = FakeND2(data, {"P": 1, "Z": 5, "C": 2, "Y": 16, "X": 16}, names=("a", "b"))
    got = read_nd2(tmp_path / "p.nd2", opener=lambda p: one, channels=["W", "R"])
    np.testing.assert_array_equal(got.data, data[0].transpose(1, 0, 2, 3))


def test_axes_given_for_an_nd2_or_nwb_file_are_refused(tmp_path):
    """--axes names the axes of a TIFF that does not record them; for ND2 and NWB it was
    silently ignored."""
    path = tmp_path / "w.nd2"
    path.write_bytes(b"\xda\xce\xbe\x0a" + bytes(64))
    with pytest.raises(images.ImageError) as exc:
        read_stack(path, axes="CZYX")
    one_line_error(exc, "--axes", "ND2")


def test_imagej_axes_with_units_of_their_own(tmp_path):
    """ImageJ writes `zunit=` / `yunit=` where an axis has its own unit: a 1500 nm z step under
    `unit=micron` was read as 1500 µm. And a stack calibrated to 1 µm pixels (resolution 1 with a
    length unit) was refused as uncalibrated: ImageJ marks that by its unit, not the resolution."""
    path = tmp_path / "zunit.tif"
    tifffile.imwrite(path, _zcyx(), imagej=True, resolution=(4.0, 4.0),
                     metadata={"axes": "ZCYX", "unit": "micron", "zunit": "nm", "spacing": 1500})
    assert read_stack(path).voxel_size_zyx == pytest.approx((1.5, 0.25, 0.25))
    tifffile.imwrite(path, _zcyx(), imagej=True, resolution=(1.0, 1.0), metadata={"axes": "ZCYX", "unit": "micron", "spacing": 2.0})
    assert read_stack(path).voxel_size_zyx == pytest.approx((2.0, 1.0, 1.0))
    tifffile.imwrite(path, _zcyx(), imagej=True, resolution=(1.0, 1.0), metadata={"axes": "ZCYX", "unit": "pixel", "spacing": 2.0})
    with pytest.raises(images.ImageError) as exc:
        read_stack(path)
    one_line_error(exc, "voxel size")


def test_a_multi_position_ome_tiff_is_refused_not_read_in_part(tmp_path):
    """An OME-TIFF of two Images (stage positions, as bfconvert writes them) was read as its
    first, the second worm dropped without a word; refused as a multi-position ND2 is."""
    path = tmp_path / "positions.ome.tif"
    data = _zcyx().transpose(1, 0, 2, 3)
    with tifffile.TiffWriter(path, ome=True) as tw:
        for name in ("pos1", "pos2"):
            tw.write(data, metadata={"axes": "CZYX", "Name": name, "PhysicalSizeX": 0.25, "PhysicalSizeY": 0.25, "PhysicalSizeZ": 1.5})
    with pytest.raises(images.ImageError) as exc:
        read_stack(path)
    one_line_error(exc, "2 images", "export each position")


def test_ome_channel_names_that_look_like_numbers_stay_text(tmp_path):
    """Channels named by laser line ('488') came back as numbers (tifffile's xml2dict converts
    attribute values; 'NaN' became nan), and write_nwb then died with a TypeError traceback."""
    path = tmp_path / "lasers.ome.tif"
    names = ["405", "488", "NaN", "640"]
    data = np.ones((4, 4, 16, 16), np.uint16)
    tifffile.imwrite(path, data, ome=True, metadata={"axes": "CZYX", "PhysicalSizeX": 0.25, "PhysicalSizeY": 0.25,
                                                     "PhysicalSizeZ": 1.5, "Channel": {"Name": names}})
    got = read_stack(path, channels=["R", "G", "B", "W"])
    assert got.channel_names == names
    write_nwb(tmp_path / "lasers.nwb", got)


def test_nwb_one_based_rgbw_beside_a_gcamp_channel(tmp_path, stack):
    """With a fifth channel both readings of RGBW_channels [1, 2, 3, 4] fit; the 0-based one was
    taken (GCaMP used as W, every colour shifted) although the channel names say otherwise. Now
    the reading the names agree with."""
    data = np.concatenate([stack.data, stack.data[:1]])
    five = Stack(data, stack.voxel_size_zyx, ["R", "G", "B", "W", "GFP"], channel_names=NAMES + ["GCaMP6s"])
    path = tmp_path / "worm.nwb"
    write_nwb(path, five)
    with h5py.File(path, "a") as f:
        f["acquisition/NeuroPALImageRaw/RGBW_channels"][...] = [1, 2, 3, 4]
    assert read_stack(path).channel_roles == ["R", "G", "B", "W", "GFP"]


def test_nwb_grid_spacing_in_pixels_asks_for_the_voxel_size(tmp_path, stack):
    """A grid_spacing unit that is no length ('pixels') was taken as µm: 1 µm voxels, silently."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack)
    with h5py.File(path, "a") as f:
        spacing = f["general/optophysiology/NeuroPALImVol/grid_spacing"]
        spacing[...] = [1.0, 1.0, 1.0]
        spacing.attrs["unit"] = "pixels"
    with pytest.raises(images.ImageError) as exc:
        read_stack(path)
    one_line_error(exc, "voxel size")


def test_nd2_with_uncalibrated_pixels_and_a_z_step_asks_for_the_voxel_size(tmp_path):
    """nd2 reports 1 µm for an uncalibrated axis; only all three at 1 were taken as unknown, so
    x = y = 1 with a 0.5 µm z loop read as (0.5, 1, 1) µm, silently."""
    fake = FakeND2(_zcyx(), {"Z": 5, "C": 2, "Y": 16, "X": 16}, voxel=(1.0, 1.0, 0.5), names=("TagRFP-T", "mNeptune2.5"))
    with pytest.raises(images.ImageError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=lambda p: fake)
    one_line_error(exc, "voxel size")


def _stack():
    data = np.random.default_rng(0).integers(0, 4000, (4, 5, 16, 24)).astype(np.uint16)
    return Stack(data, (1.5, 0.25, 0.3), ["R", "G", "B", "W"], channel_names=NAMES)


def _one_line(exc) -> str:
    message = str(exc)
    assert message and "\n" not in message, message
    return message


def test_nwb_without_a_neuropal_image_does_not_read_a_calcium_series_as_the_volume(tmp_path):
    """Expected (docs/image_formats.md: the image is acquisition['NeuroPALImageRaw'], "else any
    NeuroPAL-named 3/4-D volume in acquisition or processing"): an NWB file that holds only a
    GCaMP activity recording (a TwoPhotonSeries, data t, x, y, z) has no NeuroPAL image and is
    refused in one line. Actual: nwb._find_image falls back to the first 3/4-D series of any
    name, so the recording is read silently as a NeuroPAL volume x, y, z, c: 10 time points
    become X, the z planes become 5 'channels', and the voxel size is attached to the wrong
    axes."""
    from pynwb import NWBHDF5IO, NWBFile
    from pynwb.ophys import OpticalChannel, TwoPhotonSeries

    nwb = NWBFile(session_description="t", identifier="t", session_start_time=datetime.now(timezone.utc))
    device = nwb.create_device(name="scope")
    plane = nwb.create_imaging_plane(
        name="CalciumImVol", optical_channel=[OpticalChannel(name="GCaMP", description="", emission_lambda=np.nan)],
        description="", device=device, excitation_lambda=np.nan, indicator="GCaMP6s", location="head",
        grid_spacing=[0.3, 0.3, 1.5], grid_spacing_unit="micrometers")
    movie = np.random.default_rng(0).integers(0, 100, (10, 16, 12, 5)).astype(np.uint16)  # t, x, y, z
    nwb.add_acquisition(TwoPhotonSeries(name="CalciumImageSeries", data=movie, imaging_plane=plane, rate=2.0, unit="n/a"))
    path = tmp_path / "activity_only.nwb"
    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)
    with pytest.raises(ImageError) as exc:
        got = read_stack(path)
        pytest.fail(f"a GCaMP time series was read as a NeuroPAL volume: C, Z, Y, X = {got.data.shape}")
    _one_line(exc.value)


@pytest.mark.parametrize("spacing", [[0.3, 0.25, np.nan], [0.3, 0.25, 0.0]], ids=["nan-z", "zero-z"])
def test_nwb_grid_spacing_that_is_no_size_asks_for_the_voxel_size(tmp_path, spacing):
    """Expected: a grid_spacing whose z is NaN or 0 (the writer did not know it) is a missing
    voxel size, as a TIFF's PhysicalSizeZ="0" is: VoxelSizeUnknown, whose message says to give
    --voxel-size (and napari then opens the stack in pixels, _napari/_io.py). Actual: a plain
    ImageError "voxel size must be three positive numbers Z Y X in µm (got [nan, 0.25, 0.3])"
    that blames a voxel size the user never gave and does not say --voxel-size; napari cannot
    open the file at all. Cause: nwb._grid_spacing_um passes non-positive / NaN values through,
    and finish_stack's _check_voxel_size refuses them instead of treating them as unknown."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _stack())
    with h5py.File(path, "a") as f:
        f["general/optophysiology/NeuroPALImVol/grid_spacing"][...] = spacing
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    message = _one_line(exc.value)
    assert isinstance(exc.value, VoxelSizeUnknown), message
    assert "--voxel-size" in message, message


@pytest.mark.parametrize("unit, values", [("nanometres", [300.0, 250.0, 1500.0]), ("millimetres", [3e-4, 2.5e-4, 1.5e-3]),
                                          ("metres", [3e-7, 2.5e-7, 1.5e-6])])
def test_nwb_grid_spacing_in_british_spelled_units_is_read(tmp_path, unit, values):
    """Expected: grid_spacing_unit is free text in NWB; "micrometres" is understood
    (images._UNIT_TO_UM), so "nanometres", "millimetres" and "metres" are too and the voxel size
    reads as (1.5, 0.25, 0.3) µm. Actual: VoxelSizeUnknown "the file does not say the voxel
    size": _UNIT_TO_UM lists only the -er spellings of every unit but the micrometre (and
    nwb._grid_spacing_um's metre check knows only 'm', 'meter', 'meters')."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _stack())
    with h5py.File(path, "a") as f:
        spacing = f["general/optophysiology/NeuroPALImVol/grid_spacing"]
        spacing[...] = values
        spacing.attrs["unit"] = unit
    assert read_stack(path).voxel_size_zyx == pytest.approx((1.5, 0.25, 0.3))


@pytest.mark.parametrize("z", [0.0, float("nan")], ids=["zero", "nan"])
def test_nd2_without_a_z_step_asks_for_the_voxel_size(tmp_path, z):
    """Expected: an ND2 whose z step is 0 or NaN (no calibrated Z loop) is a missing voxel size:
    VoxelSizeUnknown with "--voxel-size" in its message, as for uncalibrated x/y. Actual: a plain
    ImageError "voxel size must be three positive numbers Z Y X in µm (got [0.0, 0.3, 0.3])",
    which does not say what to do and makes napari refuse the file instead of opening it in
    pixels. Cause: read_nd2 passes the reported z through; only x = y = 1 is taken as unknown."""
    data = np.ones((5, 2, 16, 16), np.uint16)
    fake = FakeND2(data, {"Z": 5, "C": 2, "Y": 16, "X": 16}, (0.3, 0.3, z), ("TagRFP-T", "mNeptune2.5"))
    with pytest.raises(ImageError) as exc:
        read_nd2(tmp_path / "w.nd2", opener=lambda p: fake)
    message = _one_line(exc.value)
    assert isinstance(exc.value, VoxelSizeUnknown), message
    assert "--voxel-size" in message, message


def test_a_movie_without_z_planes_is_not_sent_to_fdlc_segment(tmp_path):
    """Expected: each refusal says what to do, and doing it helps. An ImageJ file of 5 planes
    marked as time points (T, Y, X: a z-stack saved with frames for slices, a common Fiji
    slip, or a 2D movie) is refused by read_stack with advice that works (e.g. --axes ZYX, or
    "no Z planes"). Actual: read_stack says "a recording of 5 time points; fdlc segment and
    fdlc track read it", and fdlc segment (read_series) then refuses the same file as "a 2D
    image (axes YX)". Cause: finish_stack raises the time-series message before it checks
    that the volume left after T has a Z axis."""
    path = tmp_path / "frames.tif"
    tifffile.imwrite(path, np.ones((5, 16, 16), np.uint16), imagej=True, resolution=(4.0, 4.0),
                     metadata={"axes": "TYX", "unit": "micron"})
    with pytest.raises(ImageError) as as_recording:
        read_series(path, voxel_size=(1.0, 0.25, 0.25))  # what fdlc segment / fdlc track read
    assert "2D" in str(as_recording.value)
    with pytest.raises(ImageError) as exc:
        read_stack(path, voxel_size=(1.0, 0.25, 0.25))
    message = _one_line(exc.value)
    assert "fdlc segment" not in message, message


def test_a_jpeg2000_image_is_refused_as_an_unsupported_format(tmp_path):
    """Expected (docs/image_formats.md: unknown formats are refused with one line saying what to
    do): a JPEG 2000 image (photo.jp2) is "not a supported image file; use TIFF, OME-TIFF, NWB
    (.nwb) or ND2 (.nd2)", and is_image_file says False. Actual: images._sniff takes the JPEG 2000
    signature (00 00 00 0C, shared with legacy ND2) as ND2 whatever the suffix, so
    is_image_file('photo.jp2') is True and the error is "the ND2 file cannot be read (Not a
    legacy ND2 file)", about a format the user never had."""
    path = tmp_path / "photo.jp2"
    path.write_bytes(b"\x00\x00\x00\x0cjP  \r\n\x87\n" + bytes(200))
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    message = _one_line(exc.value)
    assert "ND2 file" not in message and "TIFF" in message, message
    assert not images.is_image_file(path)


def test_a_stack_of_bare_pages_given_more_axes_says_how_to_save_it(tmp_path):
    """A TIFF of bare pages (other software's page stack, no shape recorded) read with --axes
    TZCYX was refused as 'axes given for an image with 3 dimensions', which does not say why or
    what to do (image_formats.md promised that --axes reads it): the pages do not record how
    they split into t, z and c."""
    path = tmp_path / "bare.tif"
    with tifffile.TiffWriter(path) as writer:
        for _ in range(12):
            writer.write(np.zeros((16, 16), np.uint16), metadata=None, contiguous=False)
    with pytest.raises(ImageError, match="12 pages do not record how they split into TZC: save it as an ImageJ hyperstack"):
        read_series(path, axes="TZCYX", voxel_size=(1.0, 0.3, 0.3))


def _recording_tczyx(t=3, c=2, z=4, y=16, x=16):
    return ((np.arange(t * c * z * y * x) * 7) % 4000 + 1).astype(np.uint16).reshape(t, c, z, y, x)


@pytest.mark.parametrize("axes", [None, "QCZYX"], ids=["recording-for-a-stack", "bad-axes"])
def test_a_lazily_read_tiff_that_is_refused_is_closed(tmp_path, monkeypatch, axes):
    """A TIFF over 1 GiB is wrapped lazily; when it is then refused (a recording given to
    read_stack, as napari / fdlc label users do with their long recordings, or axes that do
    not fit), the TIFF should be closed like every other refused TIFF (read_tiff closes it on
    its other errors). Instead it stays open until the garbage collector finds it: Python
    reports "ResourceWarning: unclosed file" (on Windows the file stays locked while the
    error is shown)."""
    path = tmp_path / "rec.ome.tif"
    tifffile.imwrite(path, _recording_tczyx(), ome=True,
                     metadata={"axes": "TCZYX", "PhysicalSizeZ": 1.5, "PhysicalSizeY": 0.25, "PhysicalSizeX": 0.25})
    monkeypatch.setattr(images, "LAZY_BYTES", 0)  # stands for a recording over 1 GiB
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResourceWarning)
        with pytest.raises(ImageError):
            read_stack(path, axes=axes)
        gc.collect()
    unclosed = [str(w.message) for w in caught if issubclass(w.category, ResourceWarning) and str(path) in str(w.message)]
    assert not unclosed, unclosed


def test_a_lazily_read_nd2_recording_refused_as_a_stack_is_closed(tmp_path, monkeypatch):
    """read_stack on an ND2 recording over 1 GiB (the usual size of a recording) refuses it
    ("a recording of 3 time points"); read_nd2 closes the file on every other refusal (and
    after an eager read), so this one should be closed too. Instead the ND2File is left open:
    read_nd2 keeps it open for the dask array and finish_stack's refusal skips the close."""
    data = _recording_tczyx().transpose(0, 2, 1, 3, 4)  # T, Z, C, Y, X as nd2 gives it
    fake = FakeND2(data, {"T": 3, "Z": 4, "C": 2, "Y": 16, "X": 16}, voxel=(0.25, 0.25, 1.5), names=("TagRFP-T", "GCaMP6s"))
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    with pytest.raises(ImageError, match="recording"):
        read_nd2(tmp_path / "rec.nd2", opener=lambda p: fake)
    assert fake.closed, "the refused ND2 file was left open"


def test_a_lazily_read_nd2_whose_data_do_not_fit_its_sizes_is_closed(tmp_path, monkeypatch):
    """An ND2 file whose data shape differs from its sizes is refused in one line; read
    lazily (over 1 GiB), the file should still be closed. Instead it is left open (the
    shape check raises after the lazy branch skipped ``f.close()``)."""
    data = _recording_tczyx()[0].transpose(1, 0, 2, 3)  # Z, C, Y, X
    fake = FakeND2(data, {"Z": 4, "C": 2, "Y": 16, "X": 17}, voxel=(0.25, 0.25, 1.5), names=("TagRFP-T", "GCaMP6s"))  # sizes say one more column
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    with pytest.raises(ImageError, match="does not match"):
        read_nd2(tmp_path / "w.nd2", opener=lambda p: fake)
    assert fake.closed, "the refused ND2 file was left open"



def test_the_axes_advice_for_an_rgb_tiff_gives_the_right_image(tmp_path):
    """Expected: a TIFF of RGB pages that does not record its axes (tifffile axes 'QYXS',
    shape (5, 16, 16, 3): 5 planes of 16 x 16 with 3 colour samples) is refused with advice
    that, followed, reads the image right: 3 channels of 5 x 16 x 16. Actual: the advice is
    '--axes ZCYX' (the 4D example, whatever the axes), and following it reads the file silently
    as 16 channels of 5 x 16 x 3 (Y as channels, the samples as X). Cause:
    images._tiff_stack picks the example from data.ndim alone ({3: ZYX, 4: ZCYX, 5: TZCYX});
    where tifffile names a sample axis S (last), the example should end in ...YXC (e.g. ZYXC)."""
    rgb = (np.arange(5 * 16 * 16 * 3) % 251).astype(np.uint8).reshape(5, 16, 16, 3)
    path = tmp_path / "rgb.tif"
    tifffile.imwrite(path, rgb, photometric="rgb")
    with pytest.raises(AxesUnknown) as exc:
        read_stack(path, voxel_size=(1.5, 0.25, 0.25))
    advised = re.search(r"--axes (\w+)", str(exc.value)).group(1)
    got = read_stack(path, voxel_size=(1.5, 0.25, 0.25), axes=advised)
    assert got.data.shape == (3, 5, 16, 16), (advised, got.data.shape)
    np.testing.assert_array_equal(np.asarray(got.data), rgb.transpose(3, 0, 1, 2))


@pytest.mark.parametrize("ome", [True, False], ids=["ome-tiff", "imagej"])
def test_a_channel_without_role_keeps_none_on_a_tiff_round_trip(tmp_path, ome):
    """Expected (docs/image_formats.md, Writing: OME-TIFF and ImageJ files "both read back
    with voxel size, channel names and roles"): a stack whose TagRFP-T channel the user set to
    be ignored (roles R, G, B, None, as --channels R G B - gives) reads back with roles R, G, B,
    None. Actual: R, G, B, W: the ignored channel is used as W again. Cause:
    images.finish_stack fills every channel the file leaves untyped from its name
    (roles_from_names), also for the files write_tiff wrote, whose roles are complete (OME
    Fluor '' / the ImageJ fdlc_roles property say "no role"); the fill should be skipped when
    the file records a role for every channel (e.g. the fdlc_roles property, or a Fluor
    attribute on every OME Channel)."""
    data = np.stack([_zcyx(nc=1)[:, 0]] * 4)
    stack = Stack(data, (1.5, 0.25, 0.25), ["R", "G", "B", None], channel_names=NAMES)
    path = tmp_path / ("s.ome.tif" if ome else "s.tif")
    write_tiff(path, stack, ome=ome)
    assert read_stack(path).channel_roles == ["R", "G", "B", None]


def test_a_lazily_read_imagej_file_over_4gb_leaves_no_file_open(tmp_path, monkeypatch):
    """Expected (the brief's contract: files closed): reading an ImageJ hyperstack over 4 GB
    (one page header, the planes after it) lazily keeps no stray open file: the planes are
    memory-mapped, so the TiffFile is no longer needed. Actual: the TiffFile is left open and
    unreferenced; Python reports "ResourceWarning: unclosed file" at the next garbage
    collection, while the stack is still in use (on Windows the file stays locked). Cause:
    images._lazy_contiguous maps the planes with np.memmap(tif.filehandle.path) and read_tiff
    never closes ``tif`` on this path (only _lazy_tiff's page-by-page array keeps it in use);
    close it after the memmap is made."""
    data = _zcyx()
    path = tmp_path / "big_fiji.tif"
    tifffile.imwrite(path, data, imagej=True, truncate=True, resolution=(4.0, 4.0),
                     metadata={"axes": "ZCYX", "unit": "micron", "spacing": 1.5})
    monkeypatch.setattr(images, "LAZY_BYTES", 0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ResourceWarning)
        stack = read_stack(path)
        gc.collect()
        np.testing.assert_array_equal(np.asarray(stack.data), data.transpose(1, 0, 2, 3))
    unclosed = [str(w.message) for w in caught if issubclass(w.category, ResourceWarning) and str(path) in str(w.message)]
    assert not unclosed, unclosed


def test_damaged_tiff_data_read_in_memory_says_what_to_do(tmp_path):
    """Expected (docs/image_formats.md: damaged files are refused "each with one line saying
    what to do"; the lazy reader says "the file is damaged, re-export it"): a TIFF whose
    compressed data are damaged, read into memory (under 1 GiB), is refused with advice.
    Actual: "...: the TIFF image data cannot be read (libdeflate_zlib_decompress returned
    LIBDEFLATE_BAD_DATA)", no word of what to do. Cause: read_tiff's eager branch
    (series.asarray() failing) words its ImageError without the advice the other refusals of
    damaged TIFFs carry."""
    path = tmp_path / "damaged.ome.tif"
    tifffile.imwrite(path, _zcyx(), ome=True, compression="zlib",
                     metadata={"axes": "ZCYX", "PhysicalSizeZ": 1.5, "PhysicalSizeY": 0.25, "PhysicalSizeX": 0.25})
    with tifffile.TiffFile(path) as tif:
        page = tif.series[0].pages[3]
        offset, count = page.dataoffsets[0], page.databytecounts[0]
    raw = bytearray(path.read_bytes())
    raw[offset:offset + count] = bytes(count)
    path.write_bytes(bytes(raw))
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    message = str(exc.value)
    assert "\n" not in message
    assert re.search(r"re-export|export|re-save|save it", message), message


def test_an_rgb_ome_tiff_whose_channel_has_a_fluor_opens(tmp_path):
    """Expected: a valid OME-TIFF of RGB planes (SizeC 3 as one Channel of SamplesPerPixel 3,
    which carries a Name and a Fluor) opens as 3 channels; the one Fluor cannot type three
    channels, so it is dropped as the one Name is. Actual: ImageError "1 channel roles for 3
    channels", blaming roles the user never gave; the file does not open. Cause:
    images.finish_stack drops file names whose count does not fit the channels but passes the
    file's roles (_ome_channels, one per Channel element) on to Stack unchecked; roles of the
    wrong length should be dropped like the names."""
    rgb = (np.arange(5 * 16 * 16 * 3) % 251).astype(np.uint8).reshape(5, 16, 16, 3)
    path = tmp_path / "rgb.ome.tif"
    tifffile.imwrite(path, rgb, photometric="rgb", ome=True, metadata={
        "axes": "ZYXS", "PhysicalSizeZ": 1.5, "PhysicalSizeY": 0.25, "PhysicalSizeX": 0.25,
        "Channel": {"Name": ["TagRFP-T"], "Fluor": ["TagRFP-T"]}})
    got = read_stack(path)
    assert got.data.shape == (3, 5, 16, 16)
    np.testing.assert_array_equal(np.asarray(got.data), rgb.transpose(3, 0, 1, 2))
