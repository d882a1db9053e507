"""3D NeuroPAL stacks: one :class:`Stack` type and readers for TIFF, OME-TIFF, NWB and ND2.

Every reader returns the image as C, Z, Y, X with the voxel size in µm (Z, Y, X) and a role per
channel (``'R'`` mNeptune2.5, ``'G'`` CyOFP1.5, ``'B'`` mTagBFP2, ``'W'`` TagRFP-T, ``'GFP'``
activity/reporter, ``None`` anything else). Files larger than :data:`LAZY_BYTES` stay on disk as a
dask array, so napari can show them without loading them whole.

Positions everywhere in the package follow one convention: the centre of voxel ``(z, y, x)``
(0-based) is at ``(z * dz, y * dy, x * dx)`` µm.

Every problem with the file is raised as an :class:`ImageError` whose message is one line that
says what to do (the CLI prints it, the napari widget shows it).
"""

from __future__ import annotations

import io
import os
import re
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import FdlcError, first_line as _first_line  # (nwb.py takes _first_line from here)

ROLES = ("R", "G", "B", "W", "GFP")
IMAGEJ_ROLES = "fdlc_roles"  # the ImageJ property write_tiff records each channel's role in
FLUOROPHORES = {"R": "mNeptune2.5", "G": "CyOFP1.5", "B": "mTagBFP2", "W": "TagRFP-T", "GFP": "GCaMP6s"}
# Files above this size are wrapped lazily (dask) instead of read into memory.
LAZY_BYTES = 1 << 30

# Fluorophore names as they appear in files, matched case-insensitively (order matters only for
# readability: no pattern matches another fluorophore's name).
_ROLE_PATTERNS = (
    ("R", re.compile(r"neptune|nep|n2\.5", re.I)),
    ("G", re.compile(r"cyofp|cyo", re.I)),
    ("B", re.compile(r"bfp", re.I)),
    ("W", re.compile(r"tagrfp|rfp", re.I)),
    ("GFP", re.compile(r"gfp|gcamp", re.I)),
)
_SKIP_WORDS = {"", "-", "_", "none", "skip", "x", "dic", "other"}

_TIFF_SUFFIXES = (".tif", ".tiff", ".btf", ".tf8", ".ome.tif", ".ome.tiff", ".ome.btf")
_UNIT_TO_UM = {
    "um": 1.0, "µm": 1.0, "μm": 1.0, "micron": 1.0, "microns": 1.0, "micrometer": 1.0,
    "micrometers": 1.0, "micrometre": 1.0, "micrometres": 1.0, "\\u00b5m": 1.0,
    "nm": 1e-3, "nanometer": 1e-3, "nanometers": 1e-3, "nanometre": 1e-3, "nanometres": 1e-3,
    "mm": 1e3, "millimeter": 1e3, "millimeters": 1e3, "millimetre": 1e3, "millimetres": 1e3,
    "cm": 1e4, "centimeter": 1e4, "centimeters": 1e4, "centimetre": 1e4, "centimetres": 1e4,
    "m": 1e6, "meter": 1e6, "meters": 1e6, "metre": 1e6, "metres": 1e6,
    "å": 1e-4, "angstrom": 1e-4, "pm": 1e-6,  # OME allows them (compared in lower case)
}


class ImageError(FdlcError, ValueError):
    """An image file (or image parameters) that cannot be used."""


class AxesUnknown(ImageError):
    """A plain TIFF that does not say which of its axes is z, c or t; ``shape`` is its data's."""

    def __init__(self, message: str, shape: tuple):
        super().__init__(message)
        self.shape = shape


class VoxelSizeUnknown(ImageError):
    """The file does not say its voxel size (or not on every axis); ``known`` holds what it
    says, z, y, x in µm (None where it is silent)."""

    def __init__(self, message: str, known: tuple):
        super().__init__(message)
        self.known = known


@dataclass
class Stack:
    """One 3D multichannel volume.

    ``data`` is C, Z, Y, X (numpy or dask); ``voxel_size_zyx`` in µm; ``channel_roles`` one entry
    per channel from :data:`ROLES` or ``None``; ``channel_names`` as written in the file.
    """

    data: Any
    voxel_size_zyx: tuple[float, float, float]
    channel_roles: list[str | None]
    source: str = "<memory>"
    channel_names: list[str] | None = None

    def __post_init__(self) -> None:
        if getattr(self.data, "ndim", None) != 4:
            raise ImageError(f"{self.source}: a stack must be C, Z, Y, X (got {getattr(self.data, 'shape', '?')})")
        self.voxel_size_zyx = _check_voxel_size(self.voxel_size_zyx, self.source)
        self.channel_roles = list(self.channel_roles)
        if len(self.channel_roles) != self.data.shape[0]:
            raise ImageError(
                f"{self.source}: {len(self.channel_roles)} channel roles for {self.data.shape[0]} channels"
            )
        unknown = [r for r in self.channel_roles if r is not None and r not in ROLES]
        if unknown:
            raise ImageError(f"{self.source}: unknown channel role {unknown[0]!r} (use {', '.join(ROLES)} or None)")
        _check_unique_roles(self.channel_roles, self.source)
        if self.channel_names is None:
            self.channel_names = [r or f"channel {i}" for i, r in enumerate(self.channel_roles)]
        elif len(self.channel_names) != self.data.shape[0]:
            raise ImageError(f"{self.source}: {len(self.channel_names)} channel names for {self.data.shape[0]} channels")

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape[1:])

    @property
    def n_channels(self) -> int:
        return int(self.data.shape[0])

    @property
    def is_lazy(self) -> bool:
        return not isinstance(self.data, np.ndarray)

    def role_index(self, role: str) -> int | None:
        """Index of the channel playing ``role`` ('R', 'G', 'B', 'W', 'GFP'), or None."""
        return self.channel_roles.index(role) if role in self.channel_roles else None

    def channel(self, key: str | int) -> np.ndarray:
        """One channel as an in-memory Z, Y, X numpy array (by role or index). Voxels that are
        not finite numbers (NaN outside a registered region, inf) read as the channel's median:
        background, instead of blanking every statistic taken over them."""
        index = self.role_index(key) if isinstance(key, str) else int(key)
        if index is None:
            raise ImageError(f"{self.source}: no {key} channel (roles: {self.channel_roles})")
        channel = np.asarray(self.data[index])
        if channel.dtype.kind == "f":
            finite = np.isfinite(channel)
            if not finite.all():
                fill = np.median(channel[finite]) if finite.any() else 0.0
                channel = np.where(finite, channel, fill).astype(channel.dtype)
        return channel

    def extent_um(self) -> np.ndarray:
        """Size of the volume in µm, Z, Y, X."""
        return np.asarray(self.shape_zyx) * np.asarray(self.voxel_size_zyx)


@dataclass
class StackSeries:
    """A recording: the same volume over time, T, C, Z, Y, X (numpy or dask: a long recording
    stays on disk and :meth:`volume` reads one time point at a time). Voxel size, roles and
    names as in :class:`Stack`, shared by every time point."""

    data: Any
    voxel_size_zyx: tuple[float, float, float]
    channel_roles: list[str | None]
    source: str = "<memory>"
    channel_names: list[str] | None = None

    def __post_init__(self) -> None:
        if getattr(self.data, "ndim", None) != 5:
            raise ImageError(f"{self.source}: a recording must be T, C, Z, Y, X (got {getattr(self.data, 'shape', '?')})")
        if self.data.shape[0] < 1:
            raise ImageError(f"{self.source}: the recording has no time point")
        first = Stack(self.data[0], self.voxel_size_zyx, self.channel_roles, self.source, self.channel_names)
        self.voxel_size_zyx, self.channel_roles, self.channel_names = (
            first.voxel_size_zyx, first.channel_roles, first.channel_names)

    def __len__(self) -> int:
        return int(self.data.shape[0])

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape[2:])

    @property
    def n_channels(self) -> int:
        return int(self.data.shape[1])

    def volume(self, t: int) -> Stack:
        """Time point ``t`` as an in-memory :class:`Stack` (its source says which time point)."""
        source = self.source if len(self) == 1 else f"{self.source} (t={t})"
        return Stack(np.asarray(self.data[t]), self.voxel_size_zyx, self.channel_roles, source, self.channel_names)


# ---------------------------------------------------------------------------------------------
# Channel roles


def role_from_name(name: str | None) -> str | None:
    """Channel role from a fluorophore / channel name ('mNeptune2.5' -> 'R'), None when unknown."""
    if not name:
        return None
    text = str(name).strip()
    upper = text.upper()
    if upper in ROLES:
        return upper
    for role, pattern in _ROLE_PATTERNS:
        if pattern.search(text):
            return role
    return None


def parse_channel_roles(channels: Sequence[str | None], n_channels: int, source: str) -> list[str | None]:
    """User-given roles (``['R', 'G', 'B', 'W']``, fluorophore names or '-' to skip) -> roles."""
    channels = list(channels)
    if len(channels) != n_channels:
        raise ImageError(
            f"{source}: {len(channels)} channel role(s) given ({' '.join(map(str, channels))}) "
            f"but the image has {n_channels} channel(s); give one role per channel, '-' for a channel to ignore"
        )
    roles: list[str | None] = []
    for c in channels:
        if c is None or str(c).strip().lower() in _SKIP_WORDS:
            roles.append(None)
            continue
        role = role_from_name(c)
        if role is None:
            raise ImageError(
                f"{source}: unknown channel role '{c}'; use R, G, B, W, GFP or '-' (or a fluorophore name)"
            )
        roles.append(role)
    _check_unique_roles(roles, source)
    return roles


def roles_from_names(names: Sequence[str | None]) -> list[str | None]:
    """Roles guessed from channel names; a role claimed twice is dropped (ambiguous)."""
    roles = [role_from_name(n) for n in names]
    for role in set(r for r in roles if r):
        if roles.count(role) > 1:
            roles = [None if r == role else r for r in roles]
    return roles


def _check_unique_roles(roles: Sequence[str | None], source: str) -> None:
    seen = [r for r in roles if r]
    dup = sorted({r for r in seen if seen.count(r) > 1})
    if dup:
        raise ImageError(f"{source}: channel role(s) {', '.join(dup)} given more than once; give each role once")


def _check_voxel_size(voxel_size, source: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in voxel_size)
    except (TypeError, ValueError):
        raise ImageError(f"{source}: voxel size must be three numbers Z Y X in µm (got {voxel_size!r})") from None
    if len(values) != 3 or not all(np.isfinite(values)) or min(values) <= 0:
        raise ImageError(f"{source}: voxel size must be three positive numbers Z Y X in µm (got {voxel_size!r})")
    return values  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------
# Reading


def read_stack(
    path: str | os.PathLike,
    voxel_size: Sequence[float] | None = None,
    channels: Sequence[str | None] | None = None,
    axes: str | None = None,
) -> Stack:
    """Read a TIFF / OME-TIFF / ImageJ TIFF, NWB (NeuroPAL layout) or ND2 stack.

    ``voxel_size`` (Z, Y, X µm) and ``channels`` (one role per channel) override what the file
    says; ``axes`` (e.g. ``'CZYX'``) names the axes of a TIFF that does not record them.
    """
    return _read(path, voxel_size, channels, axes, time=False)


def read_series(
    path: str | os.PathLike,
    voxel_size: Sequence[float] | None = None,
    channels: Sequence[str | None] | None = None,
    axes: str | None = None,
) -> StackSeries:
    """A recording over time (a T axis; TIFF, OME-TIFF, ImageJ TIFF or ND2) as a
    :class:`StackSeries`; a file of one volume is a series of one. Arguments as :func:`read_stack`.
    NWB files hold NeuroPAL's single annotated volume, so they are a series of one."""
    return _read(path, voxel_size, channels, axes, time=True)


def is_image_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an existing file that the readers take (by its first bytes or suffix)."""
    path = Path(path)
    return path.is_file() and path.stat().st_size > 0 and _sniff(path) is not None


def _read(path, voxel_size, channels, axes, time: bool):
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise ImageError(f"{source}: no such file")
    if path.is_dir():
        raise ImageError(f"{source}: is a folder; give an image file (TIFF, OME-TIFF, NWB or ND2)")
    if path.stat().st_size == 0:
        raise ImageError(f"{source}: the file is empty")
    kind = _sniff(path)
    if axes and kind in ("nwb", "nd2"):
        raise ImageError(f"{source}: --axes is for TIFF files that do not record their axes; a {kind.upper()} file records them")
    if kind == "tiff":
        return read_tiff(path, voxel_size=voxel_size, channels=channels, axes=axes, time=time)
    if kind == "nwb":
        from .nwb import read_nwb

        stack = read_nwb(path, voxel_size=voxel_size, channels=channels)
        if not time:
            return stack
        return StackSeries(stack.data[None], stack.voxel_size_zyx, stack.channel_roles, stack.source, stack.channel_names)
    if kind == "nd2":
        return read_nd2(path, voxel_size=voxel_size, channels=channels, time=time)
    raise ImageError(f"{source}: not a supported image file; use TIFF, OME-TIFF, NWB (.nwb) or ND2 (.nd2)")


def _sniff(path: Path) -> str | None:
    """File kind from the first bytes (reliable) and then the suffix (for truncated headers)."""
    with open(path, "rb") as fh:
        head = fh.read(8)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head == b"\x89HDF\r\n\x1a\n":
        return "nwb"
    name = path.name.lower()
    if head[:4] == b"\xda\xce\xbe\x0a":  # ND2 chunk magic
        return "nd2"
    if head[:4] == b"\x00\x00\x00\x0c":  # a legacy ND2 is a JPEG 2000 file: only one named .nd2 is one
        return "nd2" if name.endswith(".nd2") else None
    if name.endswith(_TIFF_SUFFIXES):
        return "tiff"
    if name.endswith((".nwb", ".h5", ".hdf5")):
        return "nwb"
    if name.endswith(".nd2"):
        return "nd2"
    return None


def finish_stack(
    data,
    axes: str,
    source: str,
    voxel_size_zyx: Sequence[float | None] | None,
    names: Sequence[str | None] | None,
    user_voxel_size: Sequence[float] | None = None,
    user_channels: Sequence[str | None] | None = None,
    roles: Sequence[str | None] | None = None,
    time: bool = False,
) -> Stack | StackSeries:
    """Bring ``data`` with ``axes`` (letters T, Z, C, Y, X, S, ...) to C, Z, Y, X and validate;
    with ``time``, to T, C, Z, Y, X as a :class:`StackSeries` (no T axis: a series of one).

    ``voxel_size_zyx`` and ``names`` are what the file says (entries may be None); the user's
    values win. ``roles`` are roles the file states directly (NWB ``RGBW_channels``).
    """
    axes = axes.upper()
    if len(axes) != data.ndim:
        raise ImageError(f"{source}: axes '{axes}' do not fit an image with {data.ndim} dimensions")
    if len(set(axes)) != len(axes):
        raise ImageError(f"{source}: axes '{axes}' name an axis twice; give each once, e.g. --axes TZCYX")
    # Singleton axes we do not use (a time series of one, one position, one sample) go away.
    index = tuple(0 if (a not in "CZYX" and data.shape[i] == 1) else slice(None) for i, a in enumerate(axes))
    if any(isinstance(i, int) for i in index):
        data = data[index]
        axes = "".join(a for a, i in zip(axes, index) if not isinstance(i, int))
    if "S" in axes:  # RGB(A) samples are channels when the file has no channel axis
        if "C" in axes:
            raise ImageError(f"{source}: both channels and RGB samples (axes {axes}); export one channel axis")
        axes = axes.replace("S", "C")
    if "T" in axes and "Z" not in axes and set(axes) <= set("TCYX"):  # before the advice to track it
        raise ImageError(f"{source}: 2D images over time (axes {axes}), no Z planes; if its planes are z planes "
                         f"saved as time points, give --axes {axes.replace('T', 'Z')}")
    if "T" in axes:
        n = data.shape[axes.index("T")]
        if not time:
            raise ImageError(f"{source}: a recording of {n} time points; fdlc segment and fdlc track read it "
                             "(here one volume is needed: export a single time point)")
        data = data.transpose([axes.index("T")] + [i for i, a in enumerate(axes) if a != "T"])
        axes = axes.replace("T", "")
    elif time:
        data = data[None]
    lead = 1 if time else 0  # the T axis in front, kept through the steps below
    unknown = [a for a in axes if a not in "CZYX"]
    if "Z" not in axes and not unknown:  # (an axis of unknown meaning may be Z: asked for below)
        raise ImageError(f"{source}: a 2D image (axes {axes}); fdlc needs a 3D stack with several Z planes")
    if unknown or len(set(axes)) != len(axes) or "Y" not in axes or "X" not in axes:
        raise ImageError(
            f"{source}: unknown image axes '{axes}'; give them explicitly, e.g. axes='CZYX' (--axes CZYX)"
        )
    if "C" not in axes:
        data = data[:, None] if time else data[None]
        axes = "C" + axes
    data = data.transpose(list(range(lead)) + [lead + axes.index(a) for a in "CZYX"])
    n_channels, nz = int(data.shape[lead]), int(data.shape[lead + 1])
    if nz < 2:
        raise ImageError(f"{source}: a 2D image (one Z plane); fdlc needs a 3D stack with several Z planes")
    if min(data.shape[lead + 2:]) < 2:
        raise ImageError(f"{source}: image of shape {tuple(data.shape[lead:])} (C, Z, Y, X) is too small")
    if not (np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.floating)):
        raise ImageError(f"{source}: pixel type {data.dtype} is not supported; export integer or float pixels")

    if user_voxel_size is not None:
        voxel = _check_voxel_size(user_voxel_size, source)
    else:
        if voxel_size_zyx is not None:  # a size of 0 or NaN in a file says none (its writer did not know it)
            voxel_size_zyx = [None if v is None or not 0 < float(v) < np.inf else float(v) for v in voxel_size_zyx]
        if voxel_size_zyx is None or any(v is None for v in voxel_size_zyx):
            missing = "" if voxel_size_zyx is None else " ".join(
                a for a, v in zip("ZYX", voxel_size_zyx) if v is None
            )
            raise VoxelSizeUnknown(
                f"{source}: the file does not say the voxel size{' in ' + missing if missing else ''}; "
                "give it in µm as --voxel-size Z Y X (voxel_size=(z, y, x))",
                tuple(voxel_size_zyx) if voxel_size_zyx is not None else (None, None, None),
            )
        voxel = _check_voxel_size(voxel_size_zyx, source)

    names = list(names) if names is not None and len(names) == n_channels else None
    if user_channels is not None:
        channel_roles = parse_channel_roles(user_channels, n_channels, source)
    elif roles is not None and len(roles) == n_channels:  # (an RGB OME channel has one Fluor for 3)
        channel_roles = list(roles)
        if names is not None:  # fill channels the file did not type (e.g. GFP) from their names; ''
            guessed = roles_from_names(names)  # is a channel the file says has no role
            channel_roles = [r if r is not None else (g if g not in channel_roles else None)
                             for r, g in zip(channel_roles, guessed)]
        channel_roles = [r or None for r in channel_roles]
    elif names is not None:
        channel_roles = roles_from_names(names)
    else:
        channel_roles = [None] * n_channels
    if time:
        return StackSeries(data, voxel, channel_roles, source, names)
    return Stack(data, voxel, channel_roles, source, names)


# ----- TIFF ----------------------------------------------------------------------------------


def read_tiff(
    path: str | os.PathLike,
    voxel_size: Sequence[float] | None = None,
    channels: Sequence[str | None] | None = None,
    axes: str | None = None,
    time: bool = False,
) -> Stack | StackSeries:
    """TIFF, OME-TIFF or ImageJ hyperstack (tifffile); ``time``: as a :class:`StackSeries`."""
    import tifffile

    source = str(path)
    with _tifffile_log() as problems:
        try:
            tif = tifffile.TiffFile(path)
            series_list = tif.series
        except Exception as exc:  # tifffile raises many types for damaged files
            raise ImageError(f"{source}: not a readable TIFF file ({_first_line(exc)}); check or re-export it") from None
    try:
        if problems:
            # tifffile skips what it cannot parse and returns the rest (e.g. a 2D page of a
            # truncated stack); reading on would give a wrong image, so stop here.
            raise ImageError(f"{source}: the TIFF is damaged or truncated ({problems[0]}); re-export it")
        if not series_list:
            raise ImageError(f"{source}: the TIFF is damaged or holds no image; re-export it")
        if tif.is_ome and len(series_list) > 1:  # read as its first alone, the others would be lost silently
            raise ImageError(f"{source}: an OME-TIFF of {len(series_list)} images (stage positions or fields); fdlc "
                             "reads one volume per file: export each position to its own file")
        series = series_list[0]
        file_axes = series.axes
        shape = tuple(series.shape)
        with _tifffile_log() as problems:
            try:  # both read every page's header: a damaged file fails here, in many ways
                _check_tiff_complete(tif, series, source)
                voxel, names, roles = _tiff_metadata(tif)
            except ImageError:
                raise
            except Exception as exc:
                problems.append(_first_line(exc))
        if problems:
            raise ImageError(f"{source}: the TIFF is damaged or truncated ({problems[0]}); re-export it")
        nbytes = int(np.prod(shape)) * np.dtype(series.dtype).itemsize
        if nbytes > LAZY_BYTES:
            data = _lazy_tiff(tif, series, source)
        else:
            try:
                data = series.asarray()
            except Exception as exc:
                raise ImageError(f"{source}: the TIFF image data cannot be read ({_first_line(exc)}); the file "
                                 "is damaged: re-export it") from None
            tif.close()
    except BaseException:
        tif.close()
        raise
    with _closed_on_error(tif):  # lazy data keep the file open: a refusal below must not
        return _tiff_stack(data, file_axes, axes, source, voxel, names, voxel_size, channels, roles, time)


def _tiff_stack(data, file_axes, axes, source, voxel, names, voxel_size, channels, roles, time):
    """:func:`read_tiff`'s data as a Stack, on the axes given (``axes``) or recorded."""
    if axes is not None:
        axes = axes.upper()
        if len(axes) != data.ndim:
            # pages with no recorded shape (other software's page stacks) cannot be split: how
            # many are z, c or t is not written anywhere
            bare = len(axes) > data.ndim and re.fullmatch(r"[QI]YX", file_axes)
            raise ImageError(
                f"{source}: axes '{axes}' given for an image with {data.ndim} dimensions {tuple(data.shape)}"
                + (f"; its {data.shape[0]} pages do not record how they split into {axes[:-2]}: save it as an ImageJ "
                   "hyperstack or OME-TIFF (Fiji: Image > Hyperstacks > Stack to Hyperstack, then save)" if bare else "")
            )
        file_axes = axes  # letters used twice are refused by finish_stack
    elif re.search(r"[QI]", file_axes):
        # Plain TIFFs do not record which axis is Z and which is C; guessing would mix them up.
        unknown = [n for a, n in zip(file_axes, data.shape) if a in "QI" and n > 1]
        if unknown:
            example = {3: "ZYX", 4: "ZCYX", 5: "TZCYX"}.get(data.ndim, "ZCYX")
            if file_axes.endswith("S"):  # an RGB TIFF: its samples (last) are the channels
                example = {3: "YXC", 4: "ZYXC", 5: "TZYXC"}.get(data.ndim, "ZYXC")
            raise AxesUnknown(
                f"{source}: the TIFF does not say its axes (shape {tuple(data.shape)}); "
                f"give them, e.g. --axes {example} (axes='{example}')", tuple(data.shape)
            )
    return finish_stack(data, file_axes, source, voxel, names, voxel_size, channels, roles=roles, time=time)


@contextmanager
def _closed_on_error(handle):
    """Close ``handle`` (a file lazy data read from) when the block fails: the error may be
    held for long (shown in napari), and an open file stays locked on Windows."""
    try:
        yield
    except BaseException:
        handle.close()
        raise


@contextmanager
def _tifffile_log():
    """Collect tifffile's logged errors instead of printing them (our errors are one line)."""
    import logging

    problems: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.levelno >= logging.ERROR:
                problems.append(_first_line(Exception(record.getMessage())))

    logger = logging.getLogger("tifffile")
    handler = Collect()
    saved = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield problems
    finally:
        logger.removeHandler(handler)
        logger.propagate = saved


def _check_tiff_complete(tif, series, source: str) -> None:
    """A truncated TIFF still parses; catch image data that points past the end of the file."""
    for page in series.pages:
        if page is None:
            raise ImageError(f"{source}: the TIFF is incomplete (missing pages); re-export the file")
        offsets = getattr(page, "dataoffsets", ()) or ()
        counts = getattr(page, "databytecounts", ()) or ()
        # each page against its own file: a recording split over several OME-TIFF files keeps
        # pages in companion files bigger than the first
        size = getattr(getattr(getattr(page, "parent", None), "filehandle", None), "size", None) or tif.filehandle.size
        if offsets and counts and max(o + c for o, c in zip(offsets, counts)) > size:
            raise ImageError(f"{source}: the TIFF is truncated (image data past the end of the file); re-export it")


def _lazy_tiff(tif, series, source: str):
    """Dask array reading one TIFF page per chunk (tifffile's zarr store needs zarr, not a dependency)."""
    import dask
    import dask.array as da

    pages = series.pages
    lock = threading.Lock()
    page_shape = tuple(pages[0].shape)
    lead = tuple(series.shape[: len(series.shape) - len(page_shape)])
    if len(pages) * int(np.prod(page_shape)) != int(np.prod(series.shape)):
        return _lazy_contiguous(tif, series, page_shape, source)

    def load(i: int) -> np.ndarray:
        with lock:  # one file handle shared by all chunks
            try:
                return pages[i].asarray()
            except Exception as exc:  # read when a volume is needed: damaged data shows only now
                raise ImageError(f"{source}: page {i} of the TIFF cannot be read ({_first_line(exc)}); "
                                 "the file is damaged, re-export it") from None

    blocks = [
        da.from_delayed(dask.delayed(load)(i), shape=page_shape, dtype=series.dtype) for i in range(len(pages))
    ]
    # ``tif`` stays referenced by ``pages`` (and so stays open) for as long as the array lives.
    return da.stack(blocks).reshape(lead + page_shape)


def _lazy_contiguous(tif, series, page_shape: tuple, source: str):
    """A series whose planes follow one header uncompressed (ImageJ's files over 4 GB: ImageJ
    writes no BigTIFF, so one IFD and the rest after it), as a dask array of its planes mapped
    from the file."""
    import dask.array as da

    offset = getattr(series, "dataoffset", None)
    if offset is None:  # compressed or scattered: no page to read a plane from
        raise ImageError(f"{source}: the TIFF holds more planes than page headers and cannot be read piece by "
                         "piece; save it as OME-TIFF (or BigTIFF)")
    try:
        planes = np.memmap(tif.filehandle.path, dtype=np.dtype(series.dtype).newbyteorder(tif.byteorder), mode="r",
                           offset=offset, shape=tuple(series.shape))
    except (ValueError, OSError) as exc:  # data past the end of the file
        raise ImageError(f"{source}: the TIFF is truncated ({_first_line(exc)}); re-export it") from None
    lead = len(series.shape) - len(page_shape)
    tif.close()  # the planes are mapped from the file: nothing else reads it (it was left open)
    return da.from_array(planes, chunks=(1,) * lead + page_shape)


def _to_um(value, unit) -> float | None:
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    if not np.isfinite(value) or value <= 0:
        return None
    if unit is None:
        return value  # OME's default unit is µm
    factor = _UNIT_TO_UM.get(str(unit).strip().lower().replace("\\u00b5", "µ"))
    return None if factor is None else value * factor


def _ome_channels(xml: str) -> tuple[list[str | None] | None, list[str | None] | None]:
    """The first image's channel names (Name, else Fluor) as the file writes them (xml2dict would
    turn a name like '488' or 'NaN' into a number), and the roles their fluorophores (Fluor)
    give, None when none does: what write_tiff records of a stack's roles."""
    from xml.etree import ElementTree

    def children(element, tag):
        return [e for e in element if e.tag.rsplit("}", 1)[-1] == tag]

    try:
        image = children(ElementTree.fromstring(xml), "Image")[0]
        channels = children(children(image, "Pixels")[0], "Channel")
    except (ElementTree.ParseError, IndexError):
        return None, None
    names = [c.get("Name") or c.get("Fluor") for c in channels]
    if any(names):  # a channel OME leaves unnamed gets a name of its place (None broke every writer)
        names = [name or f"channel {i}" for i, name in enumerate(names)]
    fluors = [c.get("Fluor") for c in channels]
    roles = roles_from_names(fluors)  # a Fluor given twice: ambiguous, dropped
    # an empty Fluor (write_tiff's channel of no role) says none: '' is not guessed from its name
    roles = [r if r is not None or f != "" else "" for r, f in zip(roles, fluors)]
    return names if any(names) else None, roles if any(roles) else None


def _tiff_metadata(tif) -> tuple[list[float | None] | None, list[str] | None, list[str | None] | None]:
    """Voxel size (Z, Y, X µm, None where unknown), channel names and the roles the file types
    (OME's Fluor) from OME or ImageJ metadata."""
    import tifffile

    if tif.is_ome and tif.ome_metadata:
        try:
            ome = tifffile.xml2dict(tif.ome_metadata)["OME"]
            image = ome["Image"][0] if isinstance(ome["Image"], list) else ome["Image"]
            pixels = image["Pixels"]
        except Exception:
            pixels = None
        if pixels is not None:
            voxel = [
                _to_um(pixels.get(f"PhysicalSize{a}"), pixels.get(f"PhysicalSize{a}Unit")) if f"PhysicalSize{a}" in pixels else None
                for a in "ZYX"
            ]
            names, roles = _ome_channels(tif.ome_metadata)
            return voxel, names, roles
    if tif.is_imagej and tif.imagej_metadata is not None:
        meta = tif.imagej_metadata
        unit = meta.get("unit")
        page = tif.pages.first
        xres = yres = None
        try:
            xres, yres = page.get_resolution()
        except Exception:
            pass
        # ImageJ marks an uncalibrated stack by its unit ('pixel', or none), not by a resolution
        # of 1, and writes yunit / zunit where an axis has a unit of its own.
        y_unit, z_unit = meta.get("yunit", unit), meta.get("zunit", unit)
        x = _to_um(1.0 / xres, unit) if unit is not None and xres else None
        y = _to_um(1.0 / yres, y_unit) if y_unit is not None and yres else None
        # ImageJ leaves spacing out when the z step is 1 (its unit) and reads it back as 1.
        spacing = meta.get("spacing", 1.0 if int(meta.get("slices", 1) or 1) > 1 else None)
        z = _to_um(spacing, z_unit) if z_unit is not None and spacing else None
        names = None
        labels = meta.get("Labels")
        n_c = int(meta.get("channels", 1) or 1)
        if isinstance(labels, list) and n_c > 1 and len(labels) >= n_c:
            names = list(labels[:n_c])  # ImageJ stores one label per plane, channel fastest
        elif isinstance(labels, list) and n_c == 1 and labels and len(set(labels)) == 1:
            names = [labels[0]]  # one channel: every plane carries its name (as write_tiff writes it)
        written = [r.strip() for r in str((meta.get("Properties") or {}).get(IMAGEJ_ROLES, "")).split(",")]
        # an empty entry: no role, as written ('' is not guessed from the channel's name)
        roles = [r if r in ROLES else ("" if r == "" else None) for r in written] if len(written) == n_c else None
        return [z, y, x], names, roles if roles and any(roles) else None
    return None, None, None


# ----- ND2 -----------------------------------------------------------------------------------


def read_nd2(
    path: str | os.PathLike,
    voxel_size: Sequence[float] | None = None,
    channels: Sequence[str | None] | None = None,
    opener: Callable[[str], Any] | None = None,
    time: bool = False,
) -> Stack | StackSeries:
    """Nikon ND2 through the ``nd2`` package (``time``: as a :class:`StackSeries`).

    ``opener`` (default ``nd2.ND2File``) can be any callable returning an object with ND2File's
    interface (``sizes``, ``voxel_size()``, ``metadata.channels``, ``asarray()``/``to_dask()``,
    ``close()``): nd2 files cannot be written, so the tests inject one.
    """
    source = str(path)
    if opener is None:
        import nd2

        opener = nd2.ND2File
    try:
        f = opener(str(path))
    except Exception as exc:
        raise ImageError(f"{source}: not a readable ND2 file ({_first_line(exc)})") from None
    try:
        sizes = dict(f.sizes)
        if sizes.get("P", 1) > 1:  # stage positions: several worms (or fields), not one volume
            raise ImageError(f"{source}: a multi-position ND2 ({sizes['P']} positions); fdlc reads one position at a "
                             "time: export each position to its own file")
        axes = "".join(k.upper()[0] for k in sizes)
        shape = tuple(int(v) for v in sizes.values())
        try:
            vs = f.voxel_size()
            voxel = [float(vs.z), float(vs.y), float(vs.x)]
            # nd2 reports 1.0 for an uncalibrated axis; NeuroPAL pixels are 0.1-0.4 µm, never
            # exactly 1 in x and y, so those are "unknown" (the z loop may still have its step).
            if voxel[1:] == [1.0, 1.0]:
                voxel = None
        except Exception:
            voxel = None
        names = _nd2_channel_names(f)
        itemsize = np.dtype(getattr(f, "dtype", np.uint16)).itemsize
        if int(np.prod(shape)) * itemsize > LAZY_BYTES:
            data = f.to_dask()
            lazy = True
        else:
            data = np.asarray(f.asarray())
            lazy = False
    except FdlcError:
        f.close()
        raise
    except Exception as exc:
        f.close()
        raise ImageError(f"{source}: the ND2 file cannot be read ({_first_line(exc)})") from None
    if not lazy:
        f.close()
    with _closed_on_error(f):  # lazy data keep the file open: a refusal below must not
        if tuple(data.shape) != shape:
            raise ImageError(f"{source}: ND2 data shape {tuple(data.shape)} does not match its sizes {sizes}")
        if "P" in axes:  # one position
            data, axes = data[tuple(0 if a == "P" else slice(None) for a in axes)], axes.replace("P", "")
        return finish_stack(data, axes, source, voxel, names, voxel_size, channels, time=time)


def _nd2_channel_names(f) -> list[str] | None:
    try:
        chans = f.metadata.channels or []
        names = [c.channel.name for c in chans]
        return names or None
    except Exception:
        return None


# ---------------------------------------------------------------------------------------------
# Writing (test fixtures, the bundled sample, exports)


def write_tiff(
    path: str | os.PathLike,
    stack: Stack | StackSeries,
    ome: bool = True,
    compression: str | None = "zlib",
    channel_names: Sequence[str] | None = None,
) -> None:
    """Write a stack (or a recording, with its time axis) as OME-TIFF (``ome=True``) or as an
    ImageJ hyperstack, atomically.

    ImageJ files carry voxel size via resolution + ``spacing``; they are written uncompressed
    because ImageJ itself cannot open compressed hyperstacks.
    """
    import tifffile

    from ..errors import atomic_write

    data = np.asarray(stack.data)
    time = "T" if data.ndim == 5 else ""
    names = list(channel_names or stack.channel_names or [r or "" for r in stack.channel_roles])
    n_channels = data.shape[-4]
    if len(names) != n_channels:
        raise ImageError(f"{path}: {len(names)} channel names for {n_channels} channels")
    writable = {"uint8", "uint16", "int16", "float32"} if not ome else \
        {"uint8", "uint16", "uint32", "int8", "int16", "int32", "float32", "float64"}
    if data.dtype.name not in writable:  # tifffile's own error was a bare ValueError / OmeXmlError
        raise ImageError(f"{path}: {'ImageJ' if not ome else 'OME-TIFF'} cannot hold pixels of type {data.dtype} "
                         f"({', '.join(sorted(writable))}); convert them first"
                         + ("" if ome else ", or write OME-TIFF"))
    z, y, x = stack.voxel_size_zyx
    buffer = io.BytesIO()  # tifffile wants a named file or a seekable buffer, not a bare fd
    if ome:
        metadata = {
            "axes": time + "CZYX",
            "PhysicalSizeZ": z, "PhysicalSizeZUnit": "µm",
            "PhysicalSizeY": y, "PhysicalSizeYUnit": "µm",
            "PhysicalSizeX": x, "PhysicalSizeXUnit": "µm",
            # each channel's role as its fluorophore (OME's Fluor): read back whatever its name
            "Channel": {"Name": names, "Fluor": [FLUOROPHORES.get(r, "") for r in stack.channel_roles]},
        }
        tifffile.imwrite(buffer, data, ome=True, metadata=metadata, compression=compression)
    else:
        hyper = np.ascontiguousarray(np.swapaxes(data, -4, -3))  # ImageJ wants (T,) Z, C, Y, X
        planes = int(np.prod(hyper.shape[:-3]))
        labels = [names[c] for _ in range(planes) for c in range(hyper.shape[-3])]
        tifffile.imwrite(
            buffer, hyper, imagej=True, resolution=(1.0 / x, 1.0 / y),
            # the roles too (ImageJ has no fluorophore field: read from names alone, they came back
            # lost or wrong), as a property ImageJ shows in Image > Show Info
            metadata={"axes": time + "ZCYX", "spacing": z, "unit": "um", "Labels": labels,
                      "Properties": {IMAGEJ_ROLES: ",".join(r or "" for r in stack.channel_roles)}},
        )
    with atomic_write(path, "wb") as out:
        out.write(buffer.getbuffer())
