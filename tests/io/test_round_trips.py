"""Readers and writers on files as other tools write them, and round trips through our writers
(session 33's review: each docstring says what used to happen)."""

from __future__ import annotations

import uuid

import numpy as np
import pandas as pd
import pytest
import tifffile

from napari_fdlc.errors import FdlcError
from napari_fdlc.io import images
from napari_fdlc.io.images import Stack, read_series, read_stack, write_tiff
from napari_fdlc.io.nwb import write_nwb
from napari_fdlc.match import make_labelling
from napari_fdlc.review import ReviewSession
from napari_fdlc.table import NEUROPAL_ID_HEADER, NeuronTable, read_table, write_neuropal_id, write_table
from datetime import datetime, timezone
import h5py
from napari_fdlc.io.images import ImageError, VoxelSizeUnknown
from napari_fdlc.io.nwb import read_nwb_neurons

VOXEL = {"PhysicalSizeX": 0.25, "PhysicalSizeY": 0.25, "PhysicalSizeZ": 1.5}


def _data(shape, seed=0):
    return np.random.default_rng(seed).integers(0, 4000, shape).astype(np.uint16)


def test_imagej_round_trip_keeps_a_single_channels_name(tmp_path):
    """Expected: write_tiff(ome=False) of a one-channel stack (TagRFP-T, role W) reads back
    with its channel name and so its role, as docs/image_formats.md promises ("both read back
    with voxel size and channel names"; the OME-TIFF round trip does). Actual: the name comes
    back as 'channel 0' and the role as None: _tiff_metadata reads ImageJ Labels only when the
    file has more than one channel, although write_tiff wrote one label per plane."""
    stack = Stack(_data((1, 5, 16, 16)), (1.5, 0.25, 0.3), ["W"], channel_names=["TagRFP-T"])
    path = tmp_path / "w_only.tif"
    write_tiff(path, stack, ome=False)
    got = read_stack(path)
    assert got.channel_names == ["TagRFP-T"]
    assert got.channel_roles == ["W"]


def test_nwb_round_trip_keeps_roles_without_all_four_rgbw(tmp_path):
    """Expected: write_nwb then read_stack gives back the stack's channel roles (as the
    OME-TIFF round trip does, through Fluor). Actual: a stack whose roles are not all of R, G,
    B, W (here W and GFP, channels named by laser line) comes back with no role at all:
    write_nwb writes RGBW_channels only when all four are present, and the roles it stores in
    each OpticalChannel's description are never read back."""
    stack = Stack(_data((2, 5, 16, 16)), (1.5, 0.25, 0.3), ["W", "GFP"], channel_names=["561 nm", "488 nm"])
    ome = tmp_path / "w_gfp.ome.tif"
    write_tiff(ome, stack)
    assert read_stack(ome).channel_roles == ["W", "GFP"]  # the OME-TIFF round trip keeps them
    path = tmp_path / "w_gfp.nwb"
    write_nwb(path, stack)
    got = read_stack(path)
    assert got.channel_names == ["561 nm", "488 nm"]
    assert got.channel_roles == ["W", "GFP"]


def test_ome_fluor_given_twice_is_ambiguous_not_a_user_error(tmp_path):
    """Expected: an OME-TIFF whose two channels carry the same Fluor (two GFP channels) opens,
    the doubly claimed role dropped as ambiguous, as docs/image_formats.md says of names.
    Actual: ImageError 'channel role(s) GFP given more than once; give each role once', which
    blames roles the user never gave; the file cannot be opened without --channels. Cause:
    _ome_channels turns each Fluor into a role without the ambiguity check of
    roles_from_names, and finish_stack passes them to Stack, which refuses duplicates."""
    path = tmp_path / "two_gfp.ome.tif"
    tifffile.imwrite(path, _data((2, 5, 16, 16)), ome=True, metadata={
        "axes": "CZYX", **VOXEL, "Channel": {"Name": ["GCaMP 488", "GCaMP 470"], "Fluor": ["GFP", "GFP"]}})
    got = read_stack(path)
    assert got.channel_roles == [None, None]
    assert got.channel_names == ["GCaMP 488", "GCaMP 470"]


def _ome_with_an_unnamed_channel(path):
    data = _data((2, 5, 16, 16))
    scratch = path.with_name("named.ome.tif")
    tifffile.imwrite(scratch, data, ome=True, metadata={"axes": "CZYX", **VOXEL, "Channel": {"Name": ["TagRFP-T", "XXX"]}})
    xml = tifffile.TiffFile(scratch).ome_metadata.replace(' Name="XXX"', "")
    tifffile.imwrite(path, data, description=xml, metadata=None)  # OME lets a Channel go unnamed
    return data


def test_an_unnamed_ome_channel_can_be_written_again(tmp_path):
    """Expected: an OME-TIFF with a Channel that has no Name (valid OME; common for DIC or a
    channel nobody named) reads with a text name for every channel, and the stack can be
    written to NWB and to an ImageJ TIFF. Actual: channel_names holds None; write_nwb dies with
    h5py's TypeError "Can't implicitly convert non-string objects to strings", write_tiff
    (ome=False) with AttributeError 'NoneType' object has no attribute 'encode', and the
    OME-TIFF round trip names the channel 'None'. Cause: _ome_channels keeps None for a channel
    without Name or Fluor, and finish_stack passes the list through unchecked."""
    path = tmp_path / "unnamed.ome.tif"
    _ome_with_an_unnamed_channel(path)
    got = read_stack(path)
    assert all(isinstance(n, str) for n in got.channel_names), got.channel_names
    assert got.channel_roles == ["W", None]
    write_nwb(tmp_path / "unnamed.nwb", got)
    write_tiff(tmp_path / "unnamed_ij.tif", got, ome=False)
    write_tiff(tmp_path / "again.ome.tif", got)
    assert "None" not in read_stack(tmp_path / "again.ome.tif").channel_names


def test_write_tiff_imagej_of_float64_gives_an_image_error_or_writes(tmp_path):
    """Expected: write_tiff(ome=False) of a valid Stack of float64 (or int32) voxels either
    writes an ImageJ hyperstack that reads back (documented: "both read back with voxel size
    and channel names") or refuses with a one-line ImageError. Actual: tifffile's bare
    ValueError "the ImageJ format does not support data type 'd'" escapes (int64 / float16 with
    ome=True likewise raise tifffile's OmeXmlError). Cause: write_tiff passes any dtype to
    tifffile, whose ImageJ writer takes only uint8, uint16, int16 and float32."""
    stack = Stack(np.random.default_rng(0).random((2, 5, 16, 16)), (1.5, 0.25, 0.3), ["W", "R"])
    path = tmp_path / "f64.tif"
    try:
        write_tiff(path, stack, ome=False)
    except FdlcError as exc:
        assert "\n" not in str(exc)
        assert not path.exists()
        return
    got = read_stack(path)
    np.testing.assert_allclose(np.asarray(got.data), stack.data, rtol=1e-6)


def _multi_file_ome(folder, data, first_t):
    """An OME-TIFF dataset split over two files (Micro-Manager, bfconvert per time point): the
    first file holds the OME-XML and time points < first_t, the second the rest."""
    nt, nc, nz = data.shape[:3]
    u1, u2 = (f"urn:uuid:{uuid.uuid4()}" for _ in range(2))

    def tiffdata(ts, uid, name):
        planes = [(t, c, z) for t in ts for c in range(nc) for z in range(nz)]
        return "".join(f'<TiffData FirstZ="{z}" FirstC="{c}" FirstT="{t}" IFD="{i}" PlaneCount="1">'
                       f'<UUID FileName="{name}">{uid}</UUID></TiffData>' for i, (t, c, z) in enumerate(planes))

    xml = (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" '
           f'UUID="{u1}"><Image ID="Image:0"><Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" '
           f'SizeX="{data.shape[4]}" SizeY="{data.shape[3]}" SizeZ="{nz}" SizeC="{nc}" SizeT="{nt}" '
           f'PhysicalSizeX="0.25" PhysicalSizeY="0.25" PhysicalSizeZ="1.5">'
           f'<Channel ID="Channel:0:0" Name="TagRFP-T" SamplesPerPixel="1"/>'
           f'<Channel ID="Channel:0:1" Name="mNeptune2.5" SamplesPerPixel="1"/>'
           f'{tiffdata(range(first_t), u1, "rec.ome.tif")}{tiffdata(range(first_t, nt), u2, "rec_1.ome.tif")}'
           f'</Pixels></Image></OME>')
    binary = (f'<?xml version="1.0" encoding="UTF-8"?><OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06" '
              f'UUID="{u2}"><BinaryOnly MetadataFile="rec.ome.tif" UUID="{u1}"/></OME>')
    for name, ts, desc in (("rec.ome.tif", range(first_t), xml), ("rec_1.ome.tif", range(first_t, nt), binary)):
        with tifffile.TiffWriter(folder / name) as tw:
            for i, (t, c, z) in enumerate((t, c, z) for t in ts for c in range(nc) for z in range(nz)):
                tw.write(data[t, c, z], description=desc if i == 0 else None, metadata=None, contiguous=False)
    return folder / "rec.ome.tif"


@pytest.mark.parametrize("lazy", [False, True], ids=["in-memory", "lazy"])
def test_a_multi_file_ome_tiff_recording_is_not_called_truncated(tmp_path, monkeypatch, lazy):
    """Expected: a recording written as a multi-file OME-TIFF (the OME-XML in the first file,
    later time points in a companion file, as Micro-Manager and bfconvert write long
    recordings; tifffile reads it whole and right) reads as a recording with every time
    point. Actual: ImageError "the TIFF is truncated (image data past the end of the file);
    re-export it" whenever the companion file is bigger than the first. Cause:
    images._check_tiff_complete compares every page's data offsets with the size of the first
    file (tif.filehandle.size), also for pages that live in the companion file; it should use
    each page's own file (page.parent.filehandle.size)."""
    data = _data((3, 2, 4, 16, 16))
    path = _multi_file_ome(tmp_path, data, first_t=1)  # the companion holds 2 of the 3 time points
    assert np.array_equal(tifffile.TiffFile(path).series[0].asarray(), data)  # a valid file
    if lazy:
        monkeypatch.setattr(images, "LAZY_BYTES", 0)
    series = read_series(path)
    assert len(series) == 3 and series.channel_roles == ["W", "R"]
    for t in range(3):
        np.testing.assert_array_equal(series.volume(t).data, data[t])


def test_a_stack_refuses_channel_names_that_do_not_fit_its_channels(tmp_path):
    """Expected: Stack validates channel_names as it validates channel_roles (one per channel,
    else an ImageError), so a bad stack is refused where it is made. Actual: Stack(two
    channels, channel_names=['TagRFP-T']) is accepted; write_tiff then dies with tifffile's
    IndexError 'list index out of range for attribute Name' (ImageJ: a bare IndexError) and
    write_nwb silently writes one channel name for two channels (read back as 'channel 0',
    'channel 1'). Cause: Stack.__post_init__ checks the number of roles but never the number
    of names."""
    with pytest.raises(FdlcError):
        Stack(_data((2, 5, 16, 16)), (1.5, 0.25, 0.3), ["W", "R"], channel_names=["TagRFP-T"])


VOXEL_h = (1.5, 0.25, 0.3)


def _stack(n_channels=4):
    roles = ["R", "G", "B", "W", "GFP"][:n_channels]
    return Stack(_data((n_channels, 4, 8, 8)), VOXEL_h, roles)


def test_write_nwb_through_a_symlink_writes_the_linked_file(tmp_path):
    """Expected: write_nwb to a path that is a symbolic link writes the file the link names and
    keeps the link, as every other writer does (errors.atomic_write follows links; check_output
    says "a link stands for the file it names"). Actual: the link itself is replaced by a new
    file and the linked file keeps its old content. Cause: io/nwb.py:write_nwb builds its
    temporary name from the link and os.replace()s it over the link, without errors._followed."""
    real = tmp_path / "real.nwb"
    real.write_bytes(b"old")
    link = tmp_path / "link.nwb"
    link.symlink_to(real)
    write_nwb(link, _stack())
    assert link.is_symlink()
    assert real.read_bytes() != b"old"
    assert read_stack(real).channel_roles == ["R", "G", "B", "W"]


def test_save_model_through_a_symlink_writes_the_linked_files(tmp_path):
    """Expected: save_model to weights that are a symbolic link (a shared 'current' model
    linked into a runs folder) writes the linked file and keeps the link, as atomic_write does
    for every other output. Actual: the link is replaced by a plain file; the linked weights
    stay the old ones. Cause: model.py:save_model renames its '.tmp' files over the paths given
    (Path.replace) without following a link."""
    import torch

    from napari_fdlc.model import CorrespondenceModel, load_model, save_model

    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 1, "dim": 32})
    real = tmp_path / "shared"
    save_model(model, real)
    old = (tmp_path / "shared.safetensors").read_bytes()
    (tmp_path / "mine.safetensors").symlink_to(tmp_path / "shared.safetensors")
    (tmp_path / "mine.json").symlink_to(tmp_path / "shared.json")
    torch.manual_seed(1)
    save_model(CorrespondenceModel({"layers": 1, "dim": 32}), tmp_path / "mine")
    assert (tmp_path / "mine.safetensors").is_symlink() and (tmp_path / "mine.json").is_symlink()
    assert (tmp_path / "shared.safetensors").read_bytes() != old
    load_model(tmp_path / "mine")


def _long_name(tmp_path, suffix):
    name = "w" * (245 - len(suffix)) + suffix  # 245 characters: below NAME_MAX (255)
    (tmp_path / name).write_text("")  # the file system takes it
    (tmp_path / name).unlink()
    return tmp_path / name


@pytest.mark.parametrize("what", ["write_table", "write_nwb"])
def test_a_long_valid_file_name_can_be_written(tmp_path, what):
    """Expected: an output of a 245-character name (valid: Linux allows 255) is written.
    Actual: OSError [Errno 36] 'File name too long' (write_table; write_nwb: ImageError
    'cannot be written (Unable to synchronously create file ... File name too long ...)'): the temporary file beside it is named
    '.<name>.<random>.tmp' (errors.atomic_write: mkstemp prefix) or
    '.<stem>.<8 hex>.tmp.nwb' (io/nwb.py:write_nwb), 10-20 characters longer than the name
    asked for, which passes the limit. Every writer through atomic_write (tables, NeuroPAL_ID
    CSV, TIFF, atlas, session) has the same limit."""
    if what == "write_table":
        path = _long_name(tmp_path, ".csv")
        write_table(NeuronTable([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], labels=["AVAL", "AVAR"]), path)
        assert list(read_table(path).labels) == ["AVAL", "AVAR"]
    else:
        path = _long_name(tmp_path, ".nwb")
        write_nwb(path, _stack())
        assert read_stack(path).channel_roles == ["R", "G", "B", "W"]


def test_imagej_round_trip_keeps_the_channel_roles(tmp_path):
    """Expected: write_tiff(ome=False) then read_stack gives back the stack's channel roles, as
    the OME-TIFF and NWB round trips do (the stack says channel 0, named after its laser line
    'GFP', is the TagRFP-T W channel and channel 1 is ignored). Actual: the roles come back
    guessed from the names alone: ['GFP', 'W'], the W channel now called GCaMP and the ignored
    channel W (and R, G, B, W stacks with names such as 'ch0' come back with no role at all).
    Cause: io/images.py:write_tiff records only ImageJ Labels (names), nothing of the roles,
    and _tiff_metadata returns no roles for ImageJ files."""
    stack = Stack(_data((2, 4, 8, 8)), VOXEL_h, ["W", None], channel_names=["GFP", "TagRFP"])
    write_tiff(tmp_path / "s.ome.tif", stack)
    assert read_stack(tmp_path / "s.ome.tif").channel_roles == ["W", None]  # OME keeps them
    write_tiff(tmp_path / "s.tif", stack, ome=False)
    assert read_stack(tmp_path / "s.tif").channel_roles == ["W", None]


def test_nwb_round_trip_keeps_a_gfp_role_beside_rgbw(tmp_path):
    """Expected: a five-channel stack (R, G, B, W and GFP, the GCaMP channel named by its laser
    line '488') written with write_nwb reads back with all five roles, as the OME-TIFF round
    trip does. Actual: roles [None, 'R', 'G', 'B', 'W']: the GFP role is lost. Cause:
    io/nwb.py:read_nwb takes RGBW_channels (R, G, B, W only) when present and reads the roles
    write_nwb put in the optical channels' descriptions (_described_roles) only when
    RGBW_channels is missing; the channels it leaves None are then guessed from names only."""
    stack = Stack(_data((5, 4, 8, 8)), VOXEL_h, ["GFP", "R", "G", "B", "W"],
                  channel_names=["488", "561a", "561b", "405", "561c"])
    write_tiff(tmp_path / "s.ome.tif", stack)
    assert read_stack(tmp_path / "s.ome.tif").channel_roles == ["GFP", "R", "G", "B", "W"]
    write_nwb(tmp_path / "s.nwb", stack)
    assert read_stack(tmp_path / "s.nwb").channel_roles == ["GFP", "R", "G", "B", "W"]


def test_write_nwb_refuses_channel_names_that_do_not_fit_the_channels(tmp_path):
    """Expected: write_nwb(channel_names=...) with one name for four channels is refused with
    an ImageError, as write_tiff refuses it ('1 channel names for 4 channels'). Actual: the
    file is written with one optical channel and one name for a four-channel image; read back,
    the names given are silently dropped (the channels named after their roles). Cause:
    io/nwb.py:write_nwb takes ``channel_names`` without checking its length."""
    stack = _stack()
    with pytest.raises(FdlcError):
        write_tiff(tmp_path / "s.ome.tif", stack, channel_names=["a"])
    with pytest.raises(FdlcError):
        write_nwb(tmp_path / "s.nwb", stack, channel_names=["a"])


def test_read_nwb_neurons_voxel_size_reads_colours_at_the_same_voxels(tmp_path):
    """read_nwb_neurons(path, voxel_size=...) places the neurons on the image's voxels at the
    given size ('the size the image is shown at'); the colours, read out of the image at each
    neuron, should be the same whatever the size (the same voxels). Instead the colours are
    measured in a stack read at the file's own voxel size, at positions scaled by the given
    one: with a size twice the file's, every neuron's colour is read at twice its voxel index
    (another place, or the image's edge)."""
    from napari_fdlc.io.images import Stack
    from napari_fdlc.io.nwb import read_nwb_neurons, write_nwb
    from napari_fdlc.table import NeuronTable

    data = np.full((4, 6, 16, 16), 100, np.uint16)
    centres = [(1, 3, 3), (4, 12, 12), (2, 12, 3), (3, 3, 12)]  # z, y, x voxels
    for k, (z, y, x) in enumerate(centres):
        data[k % 4, z, y - 1:y + 2, x - 1:x + 2] = 3000  # each neuron bright in one channel
        data[3, z, y - 1:y + 2, x - 1:x + 2] = 3000
    stack = Stack(data, (1.0, 0.5, 0.5), ["R", "G", "B", "W"],
                  channel_names=["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"])
    vox = np.array([0.5, 0.5, 1.0])  # x, y, z
    neurons = NeuronTable(xyz=np.array([[x, y, z] for z, y, x in centres], float) * vox)
    path = tmp_path / "worm.nwb"
    write_nwb(path, stack, neurons)
    own = read_nwb_neurons(path)
    given = read_nwb_neurons(path, voxel_size=(2.0, 1.0, 1.0))
    np.testing.assert_allclose(given.xyz, own.xyz * 2)  # the positions follow the size given
    for c in ("R", "G", "B"):
        np.testing.assert_allclose(given.colours[c], own.colours[c], atol=1e-6)


_PREAMBLE = ("Version,1.0\nGFP,0\nZ-Score Means,100,200,300,400\nZ-Score SDs,10,20,30,40\n"
             "Neuron Count,3\nComment,x\n\n")


_ROWS = [
    # user, conf, emph, auto, aconf, x, y, z, ix, iy, iz, R, G, B, W, GFP
    ("AVAL", 1, 1, "AVAL", 0.9, 1.25, 2.5, 3.0, 6, 11, 4, 1.5, 0.25, -0.75, 2.0, 12.5),
    ("AVAR", 0.5, 0, "AVAR", 0.8, 4.5, 5.5, 6.0, 19, 23, 7, 0.5, 1.75, 0.25, 1.0, 11.0),
    ("", 0, 0, "RIAL", 0.4, 7.5, 8.5, 9.0, 31, 35, 10, 2.5, 0.75, 1.25, 0.5, 10.0),
]


def _neuropal_id_file(path):
    lines = [",".join(NEUROPAL_ID_HEADER)]
    for u, c, e, a, ac, x, y, z, ix, iy, iz, r, g, b, w, gfp in _ROWS:
        lines.append(f"{u},{c},{e},{a},{ac},,{x},{y},{z},,{ix},{iy},{iz},,{r},{g},{b},{w},,{gfp},{gfp},{gfp}")
    path.write_text(_PREAMBLE + "\n".join(lines) + "\n", encoding="utf-8")
    return path


def _read_npid(path) -> pd.DataFrame:
    return pd.read_csv(path, skiprows=6, dtype=str, keep_default_na=False)


@pytest.fixture(autouse=True)
def _session_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("FDLC_SESSION_DIR", str(tmp_path / "user-data"))


def test_a_neuropal_id_export_read_and_written_back_keeps_gfp_and_emphasis(tmp_path):
    """NeuroPAL_ID's own columns that a table read from its export carries (``extra``:
    'Emphasized?', 'Estimated GFP', 'Max GFP', 'Normalized GFP') should be written back by
    write_neuropal_id into the same columns. Instead the GFP columns are written empty and
    'Emphasized?' is 0 on every neuron: the reporter measurements are lost on a read/write."""
    table = read_table(_neuropal_id_file(tmp_path / "npid.csv"))
    out = tmp_path / "back.csv"
    write_neuropal_id(table, out)
    back = _read_npid(out)
    assert back["Emphasized?"].tolist() == ["1", "0", "0"]
    for column in ("Estimated GFP", "Max GFP", "Normalized GFP"):
        assert back[column].astype(float).tolist() == pytest.approx([r[15] for r in _ROWS]), column


def test_review_neuropal_id_export_of_a_neuropal_id_table_keeps_its_gfp(tmp_path):
    """A NeuroPAL_ID export reviewed (its table the session's neurons, as Auto-label on a
    NeuroPAL_ID CSV opened as Points does) and exported again as NeuroPAL_ID should keep each
    neuron's GFP readings (its fdlc export keeps them, as 'Estimated GFP' ...). Instead
    ReviewSession.export builds a NeuronTable of positions, colours and names only (no extra
    columns) for write_neuropal_id: 'Estimated GFP', 'Max GFP', 'Normalized GFP' come out empty."""
    table = read_table(_neuropal_id_file(tmp_path / "npid.csv"))
    labelling = make_labelling(["AVAL", "AVAR", "RIAL"], np.array([[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]))
    session = ReviewSession(table, labelling, voxel_size_zyx=(1.0, 0.25, 0.25))
    session.accept(0)
    fdlc = pd.read_csv(session.export(tmp_path / "ids.csv"), dtype=str, keep_default_na=False)
    assert fdlc["Estimated GFP"].astype(float).tolist() == [12.5, 11.0, 10.0]  # kept in our layout
    back = _read_npid(session.export(tmp_path / "again_npid.csv", format="neuropal_id"))
    written = back["Estimated GFP"].tolist()
    assert written != ["", "", ""] and [float(v) for v in written] == [12.5, 11.0, 10.0], f"Estimated GFP written {written}"


def test_a_moved_neuron_of_a_neuropal_id_table_is_exported_without_its_old_voxel_coordinates(tmp_path):
    """A session of a NeuroPAL_ID table with a neuron moved: its export writes x_px, y_px, z_px
    anew and leaves NeuroPAL_ID's 'Internal X (px)' out. Those were copied unchanged beside the
    new position: the file contradicted itself."""
    table = read_table(_neuropal_id_file(tmp_path / "npid.csv"))
    session = ReviewSession(table, voxel_size_zyx=(1.5, 0.25, 0.25))
    xyz = table.xyz.copy()
    xyz[0, 0] += 10.0
    moved = NeuronTable(xyz, table.colours_as_read(), extra=table.extra, source=table.source)
    session.replace_table(moved, list(range(len(table))), "move")
    df = session.to_dataframe()
    assert not {"Internal X (px)", "Internal Y (px)", "Internal Z (slice)"} & set(df.columns), list(df.columns)
    assert df["x_px"][0] == pytest.approx(moved.xyz[0, 0] / 0.25)


def test_a_neuropal_id_export_says_the_mean_and_sd_its_colours_were_z_scored_with(tmp_path):
    """The colours are z-scored over the neurons: the preamble's 'Z-Score Means' and 'SDs' are
    the mean and SD used, so the values written can be undone to those given. It said 0 and 1,
    which they were not (a NeuroPAL_ID table read and exported came back with other colours and
    no way back)."""
    table = read_table(_neuropal_id_file(tmp_path / "npid.csv"))
    write_neuropal_id(table, tmp_path / "out.csv")
    lines = (tmp_path / "out.csv").read_text().splitlines()
    means = [float(v) for v in lines[2].split(",")[1:]]
    sds = [float(v) for v in lines[3].split(",")[1:]]
    out = _read_npid(tmp_path / "out.csv")
    for k, (ours, theirs) in enumerate([("R", "Z-Scored Red"), ("G", "Z-Scored Green"), ("B", "Z-Scored Blue"),
                                         ("W", "Z-Scored White")]):
        undone = out[theirs].astype(float).to_numpy() * sds[k] + means[k]
        np.testing.assert_allclose(undone, table.colours[ours], atol=1e-3 * max(1.0, sds[k]))


NAMES = ["mNeptune2.5", "CyOFP1.5", "mTagBFP2", "TagRFP-T"]


def _named_stack(shape=(4, 5, 16, 24)):
    data = np.random.default_rng(0).integers(0, 4000, shape).astype(np.uint16)
    return Stack(data, (1.5, 0.25, 0.3), ["R", "G", "B", "W"], channel_names=NAMES)


def _nwb_with_plane():
    from pynwb import NWBFile
    from pynwb.image import ImageSeries
    from pynwb.ophys import OpticalChannel

    nwb = NWBFile(session_description="t", identifier="t", session_start_time=datetime.now(timezone.utc))
    device = nwb.create_device(name="Microscope")
    plane = nwb.create_imaging_plane(
        name="NeuroPALImVol", optical_channel=[OpticalChannel(name=f"c{i}", description="", emission_lambda=np.nan)
                                               for i in range(4)],
        description="", device=device, excitation_lambda=np.nan, indicator="NeuroPAL", location="head",
        grid_spacing=[0.3, 0.25, 1.5], grid_spacing_unit="micrometers")
    xyzc = np.random.default_rng(0).integers(0, 4000, (24, 16, 5, 4)).astype(np.uint16)
    nwb.add_acquisition(ImageSeries(name="NeuroPALImageRaw", data=xyzc, unit="n/a", rate=1.0))
    return nwb, plane


def _save(nwb, path):
    from pynwb import NWBHDF5IO

    with NWBHDF5IO(str(path), "w") as io:
        io.write(nwb)


def _calcium_rois(seg, plane):
    """A calcium segmentation as ophys files hold it: ROIs as 3D image masks, no voxel_mask."""
    ps = seg.create_plane_segmentation(name="CalciumROIs", description="", imaging_plane=plane)
    mask = np.zeros((24, 16, 5))
    mask[3:5, 3:5, 2] = 1
    ps.add_roi(image_mask=mask)
    ps.add_roi(image_mask=mask[::-1])


def test_read_nwb_neurons_finds_the_voxel_mask_segmentation_beside_a_calcium_one(tmp_path):
    """Expected (docs/image_formats.md: the neurons of NeuroPALNeurons "else any segmentation
    with a voxel_mask"): a file whose ImageSegmentation holds a calcium PlaneSegmentation
    (image_mask ROIs) and the annotated neurons (voxel_mask, ID_labels) under another name reads
    those neurons. Actual: ImageError "the NWB voxel_mask cannot be read ('voxel_mask')".
    Cause: nwb._find_neurons takes any object with ``hasattr(sub, 'voxel_mask')`` as a candidate,
    and every pynwb PlaneSegmentation has that attribute (a predefined optional column), so the
    calcium ROIs, listed first, are chosen and their missing voxel_mask column fails."""
    from pynwb.ophys import ImageSegmentation

    nwb, plane = _nwb_with_plane()
    module = nwb.create_processing_module(name="ophys", description="")
    seg = ImageSegmentation(name="ImageSegmentation")
    module.add(seg)
    _calcium_rois(seg, plane)
    somata = seg.create_plane_segmentation(name="Somata", description="", imaging_plane=plane)
    somata.add_column(name="ID_labels", description="")
    somata.add_roi(voxel_mask=[(10, 10, 2, 1.0)], ID_labels="AVAL")
    somata.add_roi(voxel_mask=[(4, 6, 3, 1.0)], ID_labels="AVAR")
    path = tmp_path / "two_segmentations.nwb"
    _save(nwb, path)
    table = read_nwb_neurons(path, colours=False)
    assert list(table.labels) == ["AVAL", "AVAR"]
    np.testing.assert_allclose(table.xyz, [[3.0, 2.5, 3.0], [1.2, 1.5, 4.5]])


def test_nwb_with_only_a_calcium_segmentation_has_no_neurons_to_read(tmp_path):
    """Expected: a file with a NeuroPAL image and a calcium segmentation of image masks only
    (no voxel_mask anywhere) has no annotated neurons: read_nwb_neurons says "no neuron
    segmentation", which napari's reader (_napari/_io.py:_nwb_neurons) takes silently as a file
    without neurons. Actual: "the NWB voxel_mask cannot be read ('voxel_mask')", and napari
    shows that as a warning on every open of the file. Cause: nwb._find_neurons' hasattr test
    (every PlaneSegmentation has a voxel_mask attribute) instead of the table's colnames."""
    from pynwb.ophys import ImageSegmentation

    nwb, plane = _nwb_with_plane()
    module = nwb.create_processing_module(name="ophys", description="")
    seg = ImageSegmentation(name="ImageSegmentation")
    module.add(seg)
    _calcium_rois(seg, plane)
    path = tmp_path / "calcium_only.nwb"
    _save(nwb, path)
    with pytest.raises(ImageError) as exc:
        read_nwb_neurons(path, colours=False)
    assert "no neuron segmentation" in str(exc.value), str(exc.value)


def test_nwb_grid_spacing_in_metres_with_one_unknown_axis_keeps_the_others_in_um(tmp_path):
    """Expected: grid_spacing [3e-7, 2.5e-7, NaN] labelled 'meters' (z not known) is 0.3 and
    0.25 µm in x and y with z asked for: VoxelSizeUnknown.known == (None, 0.25, 0.3), which
    napari's reader uses as the layers' scale until z is set. Actual: known == (None, 2.5e-07,
    3e-07): the x, y layers are shown a million times too small. Cause:
    nwb._grid_spacing_um decides metres-vs-µm with ``gs.max() < 1e-3``, and the max of an
    array holding NaN is NaN (the comparison False), so the metre values are taken as µm."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _named_stack())
    with h5py.File(path, "a") as f:
        spacing = f["general/optophysiology/NeuroPALImVol/grid_spacing"]
        spacing[...] = [3e-7, 2.5e-7, np.nan]
        spacing.attrs["unit"] = "meters"
    with pytest.raises(VoxelSizeUnknown) as exc:
        read_stack(path)
    known = exc.value.known
    assert known[0] is None
    assert known[1:] == pytest.approx((0.25, 0.3)), known


def test_nwb_channel_names_are_read_without_grid_spacing_or_origin(tmp_path):
    """Expected: order_optical_channels/channels names the channels whatever else the imaging
    plane holds; grid_spacing and origin_coords are optional in NWB's ImagingPlane, and without
    grid_spacing the voxel size is given by the user. Actual: the names come back as
    ['R', 'G', 'B', 'W'] (the names are lost; a file without RGBW_channels loses its roles with
    them). Cause: nwb._volume_channel_names finds the plane's HDF5 group through
    _h5_group_of, which only looks at the grid_spacing, data and origin_coords datasets."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _named_stack())
    with h5py.File(path, "a") as f:
        del f["general/optophysiology/NeuroPALImVol/grid_spacing"]
        del f["general/optophysiology/NeuroPALImVol/origin_coords"]
    got = read_stack(path, voxel_size=(1.5, 0.25, 0.3))
    assert got.channel_names == NAMES


def test_an_nwb_file_pynwb_cannot_read_is_not_left_open(tmp_path):
    """Expected: a file refused as "not a readable NWB file" is closed again, so that it can be
    repaired (or replaced) from the same session, e.g. napari's console. Actual: the HDF5 file
    stays open read-only while the error lives (napari keeps it for its notification), and
    h5py.File(path, 'a') fails with "file is already open for read-only". Cause: nwb._open
    closes the NWBHDF5IO only after a successful io.read(); when read() raises, the reader is
    left open (referenced from the exception's context)."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _named_stack())
    with h5py.File(path, "a") as f:
        del f["session_start_time"]  # a required field missing: pynwb cannot build the NWBFile
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    assert exc.value is not None  # the error is still held, as napari holds it
    with h5py.File(path, "a") as f:  # a repair
        f["session_start_time"] = "2020-01-01T00:00:00+00:00"


def test_an_nwb_file_pynwb_cannot_build_is_refused_in_a_short_line(tmp_path):
    """Expected: a file that pynwb cannot build (here its required 'identifier' is missing) is
    refused with one readable line. Actual: a one-"line" message of several thousand
    characters, pynwb's dump of the whole file's builder tree (every group, dataset and
    attribute), ending in "missing argument 'identifier'". Cause: nwb._open puts
    _first_line(exc) of hdmf's ConstructError in the message, and that error's first line is
    the repr of the root GroupBuilder."""
    path = tmp_path / "worm.nwb"
    write_nwb(path, _named_stack())
    with h5py.File(path, "a") as f:
        del f["identifier"]
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    message = str(exc.value)
    assert "\n" not in message
    assert len(message) < 400, f"{len(message)} characters: {message[:300]}..."


def test_nwb_image_stored_in_an_external_file_is_not_called_2d(tmp_path):
    """Expected: an ImageSeries 'NeuroPALImageRaw' whose frames are in an external file
    (external_file + format='external', valid NWB; its data is an empty placeholder) is refused
    with a line that says the image is not in the NWB file (naming the external file). Actual:
    "a 2D image (one Z plane); fdlc needs a 3D stack with several Z planes", which is not true
    of anything in the file. Cause: nwb.read_nwb reads the empty (0, 0, 0) placeholder as an
    x, y, z volume and finish_stack judges its shape."""
    from pynwb.image import ImageSeries

    nwb, plane = _nwb_with_plane()
    nwb.acquisition.pop("NeuroPALImageRaw")
    nwb.add_acquisition(ImageSeries(name="NeuroPALImageRaw", external_file=["worm.tif"], format="external",
                                    starting_frame=[0], timestamps=[0.0], unit="n/a"))
    path = tmp_path / "external.nwb"
    _save(nwb, path)
    with pytest.raises(ImageError) as exc:
        read_stack(path)
    message = str(exc.value)
    assert "2D" not in message and "worm.tif" in message, message


def test_write_nwb_with_an_empty_neuron_table(tmp_path):
    """Expected: write_nwb(path, stack, neurons) with a table of no neurons (an empty Points
    layer or segmentation) either writes the image with an empty segmentation or is refused in
    one line (an FdlcError), nothing left on disk. Actual: a bare hdmf ``Exception`` "could not
    resolve dtype for VectorData 'ID_labels': Cannot infer dtype of empty list or tuple",
    which fdlc's error handling does not catch (a traceback). Cause: write_nwb adds the
    ID_labels column without a dtype and no row, so hdmf cannot infer its type on write."""
    path = tmp_path / "worm.nwb"
    try:
        write_nwb(path, _named_stack(), NeuronTable(np.zeros((0, 3))))
    except FdlcError as exc:
        assert "\n" not in str(exc)
        assert list(tmp_path.iterdir()) == []
        return
    except Exception as exc:  # noqa: BLE001 - the defect
        pytest.fail(f"{type(exc).__module__}.{type(exc).__name__}: {exc}")
    assert read_stack(path).data.shape == (4, 5, 16, 24)
