"""NWB files in the NeuroPAL layout (ndx-multichannel-volume, as on DANDI), read with pynwb.

Where things are (``../shared/docs/neuropal_formats_and_tools.md``):

- image: ``acquisition['NeuroPALImageRaw'].data``, axes x, y, z, c; ``RGBW_channels`` holds the
  0-based channel indices of mNeptune2.5, CyOFP1.5, mTagBFP2, TagRFP-T;
- voxel size: ``imaging_planes['NeuroPALImVol'].grid_spacing`` (x, y, z, µm);
- channel names: ``imaging_planes['NeuroPALImVol'].order_optical_channels.channels``;
- neurons: ``processing['NeuroPAL']['NeuroPALSegmentation']['NeuroPALNeurons']``, ``voxel_mask``
  rows (x, y, z, weight) in voxels and ``ID_labels`` (names, sometimes ragged character arrays).

Files are opened with ``load_namespaces=True`` so the extension's classes come from the spec
cached in the file; the extension package itself is not used (its release caps pynwb < 3). Other
writers name things differently, so every lookup falls back to a search, and fields that pynwb
does not expose (an extension class whose spec is missing) are read from the HDF5 file directly.

:func:`write_nwb` writes the same layout with core pynwb types only (``ImageSeries`` for the
image, ``ImagingPlane`` for the grid spacing, ``PlaneSegmentation`` for the neurons) and adds
``RGBW_channels`` and ``order_optical_channels/channels`` with h5py afterwards, at the paths the
extension uses. It is meant for tests and round trips, not as a full ndx-multichannel-volume
writer.
"""

from __future__ import annotations

import os
import uuid
import warnings
from contextlib import contextmanager, suppress
from datetime import datetime, timezone
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import FdlcError, _followed
from ..table import NeuronTable, parse_name
from . import images
from .images import ImageError, Stack, _first_line, _to_um, finish_stack

IMAGE_NAME = "NeuroPALImageRaw"
VOLUME_NAME = "NeuroPALImVol"
MODULE_NAME = "NeuroPAL"
SEGMENTATION_NAME = "NeuroPALSegmentation"
NEURONS_NAME = "NeuroPALNeurons"
_RGBW = ("R", "G", "B", "W")


@contextmanager
def _open(path: str | os.PathLike):
    from pynwb import NWBHDF5IO

    source = str(path)
    if not Path(path).exists():
        raise ImageError(f"{source}: no such file")
    try:
        with warnings.catch_warnings():
            # Files written by other tools raise many harmless spec/version warnings.
            warnings.simplefilter("ignore")
            io = NWBHDF5IO(str(path), "r", load_namespaces=True)
            try:
                nwb = io.read()
            except BaseException:  # closed now: a refused file can be repaired or replaced at once
                io.close()
                raise
    except FdlcError:
        raise
    except Exception as exc:
        raise ImageError(f"{source}: not a readable NWB file ({_reason(exc)})") from None
    try:
        yield nwb
    finally:
        io.close()


def _reason(exc: BaseException) -> str:
    """pynwb's reason in a line: hdmf's construction errors begin with a dump of the whole
    file's builder tree (thousands of characters) and say why after 'due to:'."""
    text = str(exc)
    if "due to:" in text:
        text = text.rsplit("due to:", 1)[1]
    line = _first_line(Exception(text.strip())) or _first_line(exc)
    return line if len(line) <= 200 else line[:199] + "…"


def _children(container):
    """(name, object) of the data interfaces in an NWB container, tolerant of its type."""
    for attr in ("data_interfaces", "plane_segmentations", "containers"):
        mapping = getattr(container, attr, None)
        if mapping:
            return list(mapping.items())
    return []


def _find_image(nwb):
    if IMAGE_NAME in nwb.acquisition:
        return nwb.acquisition[IMAGE_NAME]
    candidates = list(nwb.acquisition.items())
    for module in nwb.processing.values():
        candidates += _children(module)
    with_data = [(n, o) for n, o in candidates if getattr(getattr(o, "data", None), "ndim", 0) in (3, 4)]
    for name, obj in with_data:  # NeuroPAL-named ones only (an image first)
        if "neuropal" in name.lower() and "image" in name.lower():
            return obj
    for name, obj in with_data:
        if "neuropal" in name.lower():
            return obj
    return None  # not any volume: a calcium recording (t, x, y, z) read as one was nonsense


def _find_volume(nwb, image):
    vol = getattr(image, "imaging_volume", None) if image is not None else None
    if vol is not None:
        return vol
    planes = dict(nwb.imaging_planes)
    if VOLUME_NAME in planes:
        return planes[VOLUME_NAME]
    for name, plane in planes.items():
        gs = getattr(plane, "grid_spacing", None)
        if gs is not None and len(gs) == 3 and "neuropal" in name.lower():
            return plane
    for plane in planes.values():
        gs = getattr(plane, "grid_spacing", None)
        if gs is not None and len(gs) == 3:
            return plane
    return None


def _h5(obj, key: str):
    """A dataset or attribute of ``obj``'s HDF5 group that pynwb did not map to a field."""
    try:
        group = _h5_group_of(obj)
        if group is None:
            return None
        if key in group:
            return group[key][()]
        if key in group.attrs:
            return group.attrs[key]
    except Exception:
        return None
    return None


def _grid_spacing_um(volume) -> list[float | None] | None:
    """Voxel size Z, Y, X in µm from an imaging volume's grid spacing (x, y, z)."""
    if volume is None:
        return None
    gs = getattr(volume, "grid_spacing", None)
    if gs is None:
        return None
    gs = np.asarray(gs[()] if hasattr(gs, "shape") and not isinstance(gs, np.ndarray) else gs, dtype=float).ravel()
    if gs.size != 3:
        return None
    unit = getattr(volume, "grid_spacing_unit", None)
    # NWB's default grid unit is "meters", but NeuroPAL writers store µm values under it; trust the
    # magnitude: sub-millimetre numbers labelled metres are converted, others are taken as µm.
    metres = unit and _to_um(1.0, unit) == 1e6
    known = gs[np.isfinite(gs)]  # an axis not known (NaN) says nothing of the unit
    if metres and known.size and np.abs(known).max() < 1e-3:
        factor = 1e6
    elif unit and not metres:
        factor = _to_um(1.0, unit)
        if factor is None:  # 'pixels', or a unit we cannot convert: unknown, asked for (not taken as µm)
            return None
    else:
        factor = 1.0
    x, y, z = (float(v) * factor for v in gs)
    return [z, y, x]


def _volume_channel_names(volume, image) -> list[str] | None:
    for owner in (volume, image):
        if owner is None:
            continue
        order = getattr(owner, "order_optical_channels", None)
        if order is not None:
            chans = getattr(order, "channels", None)
            if chans is not None:
                return [_text(c) for c in chans[()]] if hasattr(chans, "shape") else [_text(c) for c in chans]
    if volume is not None:
        try:
            group = _h5_group_of(volume)
            if group is None and getattr(getattr(image, "data", None), "file", None) is not None:
                # a plane without grid spacing or origin (both optional): found by its path
                group = image.data.file.get(f"general/optophysiology/{volume.name}")
            if group is not None and "order_optical_channels" in group:
                return [_text(c) for c in group["order_optical_channels"]["channels"][()]]
        except Exception:
            pass
    return None


def _h5_group_of(container):
    """The h5py group behind a pynwb container (via any dataset it holds)."""
    for attr in ("grid_spacing", "data", "origin_coords"):
        ds = getattr(container, attr, None)
        if ds is not None and hasattr(ds, "parent"):
            return ds.parent
    return None


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, (list, tuple, np.ndarray)) and not isinstance(value, str):
        # Ragged character arrays (one char per element), as some MATLAB writers store names.
        return "".join(_text(v) for v in np.asarray(value, dtype=object).ravel())
    return "" if value is None else str(value)


def _rgbw(image, n_channels: int, names: list[str] | None = None) -> list[str | None] | None:
    """Channel roles from RGBW_channels. 1-based (MATLAB) when an index reaches the channel count;
    where both readings fit (a fifth channel, GCaMP), the one the channel names agree with."""
    raw = getattr(image, "RGBW_channels", None)
    if raw is None:
        raw = _h5(image, "RGBW_channels")
    if raw is None:
        return None
    idx = np.asarray(raw[()] if hasattr(raw, "shape") and not isinstance(raw, np.ndarray) else raw).astype(int).ravel()
    if idx.size < 3 or idx.size > 4:
        return None
    readings = [_placed(idx, n_channels), _placed(idx - 1, n_channels) if idx.min() >= 1 else None]
    if readings[0] is None or readings[1] is None:
        return readings[0] or readings[1]
    by_name = images.roles_from_names(names) if names and len(names) == n_channels else [None] * n_channels

    def agreement(roles):
        return sum(r is not None and r == n for r, n in zip(roles, by_name))

    return max(readings, key=agreement)  # ties: 0-based, as pynwb writers store them


def _described_roles(volume, n_channels: int) -> list[str | None] | None:
    """Roles as write_nwb records them in each optical channel's description, for a file
    without RGBW_channels (written only when R, G, B and W are all there: a W + GFP stack lost
    its roles), None when no description is a role."""
    try:
        channels = list(getattr(volume, "optical_channel", None) or [])
    except Exception:
        return None
    roles = [str(getattr(c, "description", "") or "").strip() for c in channels]
    roles = [r if r in images.ROLES else None for r in roles]
    if len(roles) != n_channels or not any(roles) or len({r for r in roles if r}) != sum(1 for r in roles if r):
        return None
    return roles


def _placed(idx: np.ndarray, n_channels: int) -> list[str | None] | None:
    if idx.min() < 0 or idx.max() >= n_channels or len(set(idx.tolist())) != idx.size:
        return None
    roles: list[str | None] = [None] * n_channels
    for role, i in zip(_RGBW, idx):
        roles[i] = role
    return roles


def read_nwb(
    path: str | os.PathLike,
    voxel_size: Sequence[float] | None = None,
    channels: Sequence[str | None] | None = None,
) -> Stack:
    """The NeuroPAL image of an NWB file as a :class:`Stack`."""
    source = str(path)
    with _open(path) as nwb:
        image = _find_image(nwb)
        if image is None:
            raise ImageError(f"{source}: no NeuroPAL image in the NWB file (looked for acquisition['{IMAGE_NAME}'], "
                             "else a 3D or 4D volume with NeuroPAL in its name)")
        dset = image.data
        outside = list(getattr(image, "external_file", None) or [])
        if outside and 0 in tuple(getattr(dset, "shape", (0,))):  # its data: an empty stand-in
            raise ImageError(f"{source}: the NeuroPAL image is kept outside the NWB file, in "
                             f"{', '.join(_text(f) for f in outside)}; open that file instead")
        if dset.ndim == 3:  # x, y, z without a channel axis
            axes = "XYZ"
        else:
            axes = "XYZC"
        shape = tuple(dset.shape)
        volume = _find_volume(nwb, image)
        voxel = _grid_spacing_um(volume)
        names = _volume_channel_names(volume, image)
        n_channels = shape[3] if len(shape) == 4 else 1
        roles, described = _rgbw(image, n_channels, names), _described_roles(volume, n_channels)
        if roles and described:  # RGBW_channels says four; the descriptions may add GFP
            roles = [r or (d if d not in roles else None) for r, d in zip(roles, described)]
        roles = roles or described
        nbytes = int(np.prod(shape)) * np.dtype(dset.dtype).itemsize
        try:
            if nbytes > images.LAZY_BYTES:
                import dask.array as da
                import h5py

                # A separate h5py handle outlives the pynwb reader; dask reads chunks on demand.
                data = da.from_array(h5py.File(source, "r")[dset.name], chunks="auto")
            else:
                data = np.asarray(dset[()])
        except Exception as exc:
            raise ImageError(f"{source}: the NWB image data cannot be read ({_first_line(exc)})") from None
    return finish_stack(data, axes, source, voxel, names, voxel_size, channels, roles=roles)


def _find_neurons(nwb):
    candidates = []
    for mname, module in nwb.processing.items():
        for name, obj in _children(module):
            inner = _children(obj) if not hasattr(obj, "colnames") else []
            for sub_name, sub in inner or [(name, obj)]:
                # a column of the table (every pynwb PlaneSegmentation has the attribute: a
                # calcium segmentation of image masks has it empty)
                columns = getattr(sub, "colnames", None)
                if "voxel_mask" in (columns or ()) or (columns is None and getattr(sub, "voxel_mask", None) is not None):
                    candidates.append((f"{mname}/{name}/{sub_name}", sub_name, sub))
    for full, name, obj in candidates:
        if name == NEURONS_NAME:
            return obj
    for full, name, obj in candidates:
        if "neuropal" in full.lower() and "neuron" in name.lower():
            return obj
    return candidates[0][2] if candidates else None


def _mask_centre(entry) -> np.ndarray:
    rows = entry
    if isinstance(rows, (np.void, tuple)) and len(rows) >= 3 and np.isscalar(rows[0]):
        rows = [rows]
    arr = np.asarray([tuple(r)[:4] for r in rows], dtype=float)
    if arr.ndim != 2 or arr.shape[0] == 0:
        return np.full(3, np.nan)
    if arr.shape[1] >= 4 and arr.shape[0] > 1 and np.all(arr[:, 3] >= 0) and arr[:, 3].sum() > 0:
        return np.average(arr[:, :3], axis=0, weights=arr[:, 3])
    return arr[:, :3].mean(axis=0)


def read_nwb_neurons(path: str | os.PathLike, colours: bool = True,
                     voxel_size: Sequence[float] | None = None) -> NeuronTable:
    """The annotated neurons of a NeuroPAL NWB file as a :class:`NeuronTable` (µm, names).

    Voxel-mask coordinates are taken as 0-based voxel indices (x, y, z) and scaled by the grid
    spacing, or by ``voxel_size`` (z, y, x µm) when given: the size the image is shown at. With ``colours`` the R, G, B, W intensities are read out of the image at each neuron
    (per-volume z-scores, as :func:`napari_fdlc.segment.measure_colours` does).
    """
    source = str(path)
    with _open(path) as nwb:
        ps = _find_neurons(nwb)
        if ps is None:
            raise ImageError(
                f"{source}: no neuron segmentation in the NWB file "
                f"(looked for processing['{MODULE_NAME}']['{SEGMENTATION_NAME}']['{NEURONS_NAME}'])"
            )
        image = _find_image(nwb)
        volume = getattr(ps, "imaging_plane", None)
        if voxel_size is not None:
            voxel = list(voxel_size)
        else:
            voxel = _grid_spacing_um(volume) if volume is not None else None
            if voxel is None:
                voxel = _grid_spacing_um(_find_volume(nwb, image))
        if voxel is None or any(v is None for v in voxel):
            raise ImageError(f"{source}: the NWB file does not say the voxel size (grid_spacing of '{VOLUME_NAME}')")
        n = len(ps)
        if n == 0:
            raise ImageError(f"{source}: the NWB neuron segmentation is empty")
        try:
            col = ps["voxel_mask"]
            centres = np.array([_mask_centre(col[i]) for i in range(n)])
        except Exception as exc:
            raise ImageError(f"{source}: the NWB voxel_mask cannot be read ({_first_line(exc)})") from None
        labels = [""] * n
        label_col = next((c for c in ("ID_labels", "labels", "label") if c in ps.colnames), None)
        if label_col is not None:
            col = ps[label_col]
            labels = [_text(col[i]) for i in range(n)]
    if not np.isfinite(centres).all():
        raise ImageError(f"{source}: some NWB neurons have an empty voxel_mask")
    z, y, x = images._check_voxel_size(voxel, source)
    xyz = centres * np.array([x, y, z])
    parsed = [parse_name(s) for s in labels]
    table = NeuronTable(
        xyz=xyz,
        labels=np.array([p[0] for p in parsed], dtype=object),
        label_conf=np.array([p[1] for p in parsed]),
        source=source,
    )
    from ..table import _drop_duplicate_names

    table.labels, table.label_conf = _drop_duplicate_names(table.labels, table.label_conf, source)
    if colours:
        from ..segment import measure_colours

        stack = read_nwb(path, voxel_size=voxel_size)  # the colours read on the voxels the positions were put on
        table.colours = measure_colours(stack, table.xyz)
    return table


def write_nwb(
    path: str | os.PathLike,
    stack: Stack,
    neurons: NeuronTable | None = None,
    channel_names: Sequence[str] | None = None,
    session_description: str = "NeuroPAL volume written by napari-fdlc",
) -> None:
    """Write ``stack`` (and optionally ``neurons``) in the NeuroPAL NWB layout, atomically.

    Core pynwb types only; see the module docstring for what is added with h5py.
    """
    import h5py
    from pynwb import NWBHDF5IO, NWBFile
    from pynwb.image import ImageSeries
    from pynwb.ophys import ImageSegmentation, OpticalChannel

    data = np.asarray(stack.data)
    if data.ndim != 4:
        raise ImageError(f"NWB: one volume (C, Z, Y, X) is written per file, not an array of {data.ndim} axes "
                         "(a recording: write each time point to its own file)")
    z, y, x = stack.voxel_size_zyx
    if neurons is not None:
        vox = neurons.xyz / np.array([x, y, z])
        if not np.isfinite(vox).all():
            raise ImageError("NWB: some neuron positions are not finite numbers")
        if (np.round(vox) < 0).any():
            raise ImageError("NWB: some neurons lie before the image's first voxel (negative x, y or z); "
                             "voxel masks hold voxels of the image")
    names = list(channel_names or stack.channel_names or [r or f"channel {i}" for i, r in enumerate(stack.channel_roles)])
    if len(names) != data.shape[0]:  # one name for 4 channels wrote 1 optical channel, read back as none
        raise ImageError(f"NWB: {len(names)} channel name(s) for {data.shape[0]} channels; give one per channel")
    nwb = NWBFile(
        session_description=session_description,
        identifier=str(uuid.uuid4()),
        session_start_time=datetime.now(timezone.utc),
    )
    device = nwb.create_device(name="Microscope")
    optical = [
        # NWB names cannot hold '/' or ':'; the names themselves are in order_optical_channels.
        OpticalChannel(name=f"{i:02d} {n}".replace("/", "_").replace(":", "_"),
                       description=str(stack.channel_roles[i] or ""), emission_lambda=np.nan)
        for i, n in enumerate(names)
    ]
    plane = nwb.create_imaging_plane(
        name=VOLUME_NAME, optical_channel=optical, description="NeuroPAL imaging volume",
        device=device, excitation_lambda=np.nan, indicator="NeuroPAL", location="head",
        grid_spacing=[x, y, z], grid_spacing_unit="micrometers",
        origin_coords=[0.0, 0.0, 0.0], origin_coords_unit="micrometers",
    )
    # NeuroPAL layout: x, y, z, c.
    image = ImageSeries(
        name=IMAGE_NAME, data=np.ascontiguousarray(data.transpose(3, 2, 1, 0)), unit="n/a", rate=1.0,
        description="NeuroPAL raw volume, axes x, y, z, c",
    )
    nwb.add_acquisition(image)
    if neurons is not None and len(neurons):  # (none: hdmf cannot type an empty name column)
        module = nwb.create_processing_module(name=MODULE_NAME, description="NeuroPAL neurons")
        seg = ImageSegmentation(name=SEGMENTATION_NAME)
        module.add(seg)
        ps = seg.create_plane_segmentation(name=NEURONS_NAME, description="neuron centres", imaging_plane=plane)
        ps.add_column(name="ID_labels", description="neuron names ('?' = unsure)")
        for (vx, vy, vz), label in zip(vox, neurons.label_strings()):
            # voxel_mask holds integer voxels in the core spec: centres are rounded to the grid.
            ps.add_roi(voxel_mask=[(int(round(vx)), int(round(vy)), int(round(vz)), 1.0)], ID_labels=label)
    roles = stack.channel_roles
    rgbw = [roles.index(r) for r in _RGBW if r in roles]
    path = _followed(Path(path))  # a link: the file it names is written, the link kept
    # pynwb needs a path, not a handle: write beside the target, then rename (atomic); a short
    # name, which a file name of 245 characters still leaves room for
    tmp = path.with_name(f".fdlc-{uuid.uuid4().hex[:8]}.tmp.nwb")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with NWBHDF5IO(str(tmp), "w") as io:
            io.write(nwb)
        with h5py.File(tmp, "a") as f:
            if len(rgbw) == 4:
                f[f"acquisition/{IMAGE_NAME}"].create_dataset("RGBW_channels", data=np.asarray(rgbw, dtype=np.int64))
            group = f[f"general/optophysiology/{VOLUME_NAME}"].create_group("order_optical_channels")
            group.create_dataset("channels", data=np.asarray(names, dtype=object), dtype=h5py.string_dtype())
        os.replace(tmp, path)
    except BaseException as exc:
        with suppress(OSError):  # (a folder that cannot be made has no temporary file either)
            tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):  # named by the target, not the hidden temporary file
            raise ImageError(f"{path}: cannot be written ({exc.strerror or _first_line(exc)})") from None
        raise
