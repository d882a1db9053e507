"""npe2 readers, writer and sample data.

- stacks (TIFF / OME-TIFF / NWB / ND2) open as R/G/B/W additive channels with the voxel scale;
  an NWB file's annotated neurons come along as a Points layer, and a saved review session of
  the image comes back as its neuron-ID layer; a stack that does not say its voxel size opens
  in pixels (the widget's Voxel size row sets it), or with its saved session's;
- neuron tables (our CSV, NeuroPAL_ID CSV) open as one Points layer;
- the writer saves a Points layer as a neuron-ID CSV (µm and voxel coordinates + features);
- the sample is the bundled synthetic NeuroPAL head with its neuron table.

Every problem is an :class:`~napari_fdlc.errors.FdlcError`, raised with a one-line message;
napari shows it as a notification.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import os
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import FdlcError, warn, warnings_to
from ..review import ReviewSession, find_session
from ._layers import META_KEY, _short_name, moved_in_viewer, review_points, stack_layers, table_points

STACK_SUFFIXES = (".tif", ".tiff", ".ome.tif", ".ome.tiff", ".nwb", ".nd2")
RESULT_SUFFIX = " neuron IDs"


def _one_path(path):
    if isinstance(path, (list, tuple)):
        return str(path[0]) if len(path) == 1 else None
    return str(path)


def notify_warning(message: str) -> None:
    """A warning shown in napari (a notification)."""
    from napari.utils.notifications import show_warning

    show_warning(message)


def _warn_in_napari(message: str) -> None:
    """A warning the user sees in napari (and on stderr, where scripts see it)."""
    with warnings_to(notify_warning):
        warn(message)


# ----- stacks --------------------------------------------------------------------------------


def get_stack_reader(path):
    """npe2 reader contribution: TIFF / OME-TIFF / NWB / ND2 stacks."""
    p = _one_path(path)
    if p is None or not p.lower().endswith(STACK_SUFFIXES) or os.path.isdir(p):
        return None
    return read_stack_layers


@warnings_to(notify_warning)  # what the readers warn about reaches the user
def read_stack_layers(path) -> list[tuple]:
    """A stack's channels as image layers (a recording's as t, z, y, x layers), with the
    annotated neurons of an NWB file and a saved Auto-label session."""
    from ..io.images import AxesUnknown, ImageError, Stack, VoxelSizeUnknown, read_series

    p = _one_path(path)

    def read(axes=None):
        try:
            return read_series(p, axes=axes), False
        except VoxelSizeUnknown as exc:  # shown in pixels (the axes the file does say in µm) until set
            return read_series(p, voxel_size=[1.0 if v is None else v for v in exc.known], axes=axes), True

    try:
        series, unknown = read()
    except AxesUnknown as exc:  # napari's File > Open has no --axes: a plain 3D array is a z-stack
        if len(exc.shape) != 3:
            raise ImageError(f"{p}: the TIFF does not say its axes (shape {exc.shape}); save it as an ImageJ hyperstack "
                             "or OME-TIFF, which say them (Fiji: Image > Hyperstacks > Stack to Hyperstack)") from None
        series, unknown = read("ZYX")
        warn(f"{p}: the TIFF does not say its axes; opened as one channel of z, y, x planes")
    # A voxel size set in napari for this image (Auto-label's row) is kept by its session: the
    # file opened again takes it, whether the file says none or says another. The session is
    # read once, for this and to be restored below.
    session_file = _saved_session_file(series.source)
    saved, set_in_napari = _saved_voxel_size(session_file[1])
    use_saved = saved is not None and (unknown or (set_in_napari and not np.allclose(saved, series.voxel_size_zyx)))
    if use_saved:
        said = "says none" if unknown else f"says {' × '.join(f'{v:g}' for v in series.voxel_size_zyx)}"
        series = dataclasses.replace(series, voxel_size_zyx=saved)
        warn(f"{p}: voxel size {' × '.join(f'{v:g}' for v in saved)} µm (z, y, x) as set for this image in "
             f"napari (its saved session; the file {said})")
        unknown = False
    elif unknown:
        warn(f"{p}: the file does not say the voxel size; shown in pixels: set it (µm) in Auto-label's "
             "Voxel size row before labelling or tracking")
    if len(series) > 1:
        layers = stack_layers(series, voxel_unknown=unknown, voxel_set=use_saved)
    else:
        stack = Stack(series.data[0], series.voxel_size_zyx, series.channel_roles, series.source, series.channel_names)
        layers = stack_layers(stack, voxel_unknown=unknown, voxel_set=use_saved)
        if p.lower().endswith(".nwb"):
            neurons = _nwb_neurons(p, stack)
            if neurons is not None:
                layers.append(neurons)
    # Auto-label names a recording's first time point: its session is restored alike
    restored = restored_session_layer(series.source, tuple(series.data.shape[-3:]), voxel_zyx=series.voxel_size_zyx,
                                      session_file=session_file, time_axis=(1.0, 0.0) if len(series) > 1 else None)
    if restored is not None:
        layers.append(restored)
    return layers


def _saved_session_file(image_key: str) -> tuple:
    """(path, the session, or the FdlcError that refused it) of ``image_key``'s saved review
    session; (None, None) without one."""
    path = find_session(image_key)
    if path is None:
        return None, None
    try:
        return path, ReviewSession.load(path)
    except FdlcError as exc:
        return path, exc


def _saved_voxel_size(session) -> tuple[tuple | None, bool]:
    """The voxel size of a saved review session (None without one, or a session that could
    not be read: said when it is restored), and whether it was set in napari (Auto-label's
    Voxel size row) rather than read from the file."""
    if not isinstance(session, ReviewSession) or session.voxel_size_zyx is None:
        return None, False
    return tuple(float(v) for v in session.voxel_size_zyx), bool(session.settings.get("voxel_size_set"))


def _nwb_neurons(path: str, stack):
    from ..io.images import ImageError
    from ..io.nwb import read_nwb_neurons

    try:
        # on the image's voxels, whatever voxel size it was given (a stand-in, or one set in napari)
        table = read_nwb_neurons(path, colours=False, voxel_size=stack.voxel_size_zyx)
    except ImageError as exc:
        if "no neuron segmentation" in str(exc):
            return None
        warn(str(exc))
        return None
    try:
        from ..segment import measure_colours

        table.colours = {k: v for k, v in measure_colours(stack, table.xyz).items() if k != "GFP"}
    except Exception as exc:  # colours are a bonus here; the positions and names are what count
        warn(f"{path}: NWB neuron colours not read ({exc})")
    data, kwargs, kind = table_points(table, stack.voxel_size_zyx, name=f"{_short_name(path)} neurons")
    kwargs["metadata"][META_KEY]["image"] = stack.source  # on the image's voxels: rescaled with it
    return data, kwargs, kind


def restored_session_layer(image_key: str, shape_zyx=None, default_name: str | None = None, voxel_zyx=None,
                           session_file: tuple | None = None, time_axis=None):
    """The neuron-ID layer of a saved review session of ``image_key`` (None when there is none
    or it does not fit the image: its shape or voxel size), under the name it was saved with
    (else ``default_name``). ``session_file``: :func:`_saved_session_file`'s answer, when the
    caller has read it already; ``time_axis``: (scale, translate) in t of the recording the image
    is (its names are drawn at its first time point, also for a session saved without one)."""
    path, session = session_file or _saved_session_file(image_key)
    if path is None:
        return None
    if isinstance(session, FdlcError):
        _warn_in_napari(f"saved session not restored: {session}")
        return None
    saved_shape = session.settings.get("image_shape")
    if shape_zyx is not None and saved_shape is not None and list(saved_shape) != list(shape_zyx):
        _warn_in_napari(f"{path}: saved for an image of shape {saved_shape}, not {list(shape_zyx)}; not restored")
        return None
    saved_voxel = session.voxel_size_zyx
    if voxel_zyx is not None and saved_voxel is not None and not np.allclose(saved_voxel, voxel_zyx, rtol=1e-6):
        # its neurons, in µm, would lie on other voxels of the image
        _warn_in_napari(f"{path}: saved for voxels of {tuple(saved_voxel)} µm, not {tuple(voxel_zyx)}; not restored")
        return None
    name = session.settings.get("layer_name") or default_name or f"{_short_name(image_key)}{RESULT_SUFFIX}"
    return review_points(session, name, {"session": str(path), "image": image_key}, time_axis=time_axis)


# ----- neuron tables --------------------------------------------------------------------------


def get_table_reader(path):
    """npe2 reader contribution: our neuron-table CSV and NeuroPAL_ID CSV (as Points)."""
    p = _one_path(path)
    if p is None or not p.lower().endswith(".csv") or not os.path.isfile(p):
        return None
    try:
        with open(p, encoding="utf-8-sig", errors="replace") as fh:
            head = "".join(fh.readline() for _ in range(12))
    except OSError:
        return None
    from ..table import neuropal_id_header

    lines = head.splitlines()
    if lines and lines[0].strip().lower().startswith("sep="):  # Excel's separator line, skipped by the reader
        lines = lines[1:]
    # quoted names too (R's write.csv), a line break inside one (Excel's Alt+Enter) too
    rows = [[h.strip() for h in cells] for cells in csv.reader(io.StringIO("\n".join(lines)))]
    header = next((cells for cells in rows if any(cells)), [])  # blank lines and ',,,' above it, as the reader
    ours = all(c in header for c in ("x_um", "y_um", "z_um"))
    return read_table_layer if (ours or neuropal_id_header(lines) is not None) else None


@warnings_to(notify_warning)
def read_table_layer(path) -> list[tuple]:
    from ..table import read_table, with_unique_names

    p = _one_path(path)
    table = read_table(p, unique_names=False)  # a table over time names each neuron once per time point
    voxel = _voxel_from_columns(table)
    if "t" in table.extra.columns and table.extra["t"].nunique() > 1:
        return [_points_over_time(table, voxel)]
    return [table_points(with_unique_names(table), voxel)]


def _points_over_time(table, voxel) -> tuple:
    """A table of several time points (``fdlc segment`` of a recording, ``fdlc track``, this
    plugin's writer) as one (t, z, y, x) Points layer: each volume at its frame, as the Track
    widget places a sequence's volumes, its names its own."""
    from ..table import table_from_dataframe
    from ..track import join_by_time, split_by_time
    from .tracks import frames_of

    sequence = split_by_time(table)  # each volume's names made unique on their own
    frames = frames_of(sequence.times) or list(range(len(sequence)))
    whole = table_from_dataframe(join_by_time(sequence.volumes, sequence.times), table.source, unique_names=False)
    data, kwargs, kind = table_points(whole, voxel)
    t = np.repeat(np.asarray(frames, dtype=float), [len(v) for v in sequence.volumes])
    kwargs.update(scale=(1.0, *kwargs["scale"]), axis_labels=("t", "z", "y", "x"))
    return np.column_stack([t, data]), kwargs, kind


# Voxel coordinates written beside µm: ours (0-based), NeuroPAL_ID's (1-based, to 3 decimals:
# a neuron within 2 voxels of the first tells its size too roughly)
_VOXEL_COLUMNS = ((("x_px", "y_px", "z_px"), 0.0, 1e-6),
                  (("Internal X (px)", "Internal Y (px)", "Internal Z (slice)"), 1.0, 2.0))


def _voxel_from_columns(table) -> tuple | None:
    """Voxel size from voxel coordinates written beside µm (our ``x_px, y_px, z_px``,
    NeuroPAL_ID's ``Internal X (px)``): lets the points sit on image planes exactly like the
    stack's, and a point moved is saved with its voxel coordinates written anew."""
    for columns, first, nearest in _VOXEL_COLUMNS:
        size = _voxel_size_of(table, columns, first, nearest)
        if size is not None:
            return size
    return None


def _voxel_size_of(table, columns, first: float, nearest: float) -> tuple | None:
    if not all(c in table.extra.columns for c in columns):
        return None
    size = []
    for um, px in zip((2, 1, 0), columns[::-1]):
        v = pd.to_numeric(table.extra[px], errors="coerce").to_numpy(dtype=float) - first
        ok = np.isfinite(v) & (np.abs(v) >= nearest)
        if not ok.any():
            return None
        ratio = table.xyz[ok, um] / v[ok]
        if not (np.all(ratio > 0) and np.ptp(ratio) < 1e-3 * np.median(ratio)):
            return None
        size.append(float(f"{np.median(ratio):.6g}"))  # x_px is written to 6 digits: 1.1999993 is 1.2
    return tuple(size)


# ----- writer ---------------------------------------------------------------------------------


def _per_axis(values, dims: int, missing: float) -> np.ndarray:
    """A layer attribute (scale, translate) for the last ``dims`` axes, ``missing`` where absent."""
    v = np.asarray(values if values is not None else [], dtype=float).ravel()[-dims:]
    return np.concatenate([np.full(dims - len(v), missing), v])


def _times_of_frames(frames: np.ndarray, t: pd.Series) -> list:
    """Each point's time: the one read for the points of its frame; else its frame. A point
    added by hand holds none, or a copy of another frame's time (napari's copy of the last
    point's; a whole-number column's first time), which is not its frame's."""
    known: dict[float, object] = {}
    claimed: set[float] = set()
    numeric = pd.to_numeric(t, errors="coerce")
    for frame, value, raw in zip(frames, numeric, t):
        # the points read come first, so each frame's time is claimed before a copy of it
        if np.isfinite(value) and frame not in known and value not in claimed:
            known[frame] = raw
            claimed.add(value)
    return [known.get(frame, int(frame) if float(frame).is_integer() else frame) for frame in frames]


def _digits_read(world: np.ndarray, data: np.ndarray, scale: np.ndarray, translate: np.ndarray) -> np.ndarray:
    """Each world coordinate as the shortest text (15 to 17 significant digits) that the layer's
    data coordinate comes from again: 1.2 rather than 1.2000000000000002 for a value read as 1.2,
    and a position of 17 digits kept whole (15 cut it, also where nothing needed mending)."""
    out = world.copy()
    for index, value in np.ndenumerate(world):
        axis = index[-1]
        for digits in (15, 16):
            shorter = float(f"{value:.{digits}g}")
            if (shorter - translate[axis]) / scale[axis] == data[index]:
                out[index] = shorter
                break
    return out


def write_neuron_csv(path: str, data, attributes: dict) -> list[str]:
    """npe2 writer: a Points layer as a neuron-ID CSV (``x_um, y_um, z_um`` in the world frame,
    the layer's features, and ``x_px, y_px, z_px`` voxel coordinates when the layer is scaled).
    Points of a (t, z, y, x) layer at several time points get a ``t`` column (a sequence table,
    as ``fdlc track`` reads), unless a ``t`` feature already says their time."""
    from ..table import COLOUR_CHANNELS, PIXEL_COLUMNS, write_table

    data = np.asarray(data, dtype=float)
    if data.ndim != 2 or data.shape[1] < 3:
        raise FdlcError(f"{path}: neuron tables need 3D points (z, y, x)")
    if len(data) == 0:
        raise FdlcError(f"{path}: the layer has no points to save")
    dims = data.shape[1]
    if moved_in_viewer(attributes.get("rotate"), attributes.get("shear"), attributes.get("affine")):
        raise FdlcError(f"{path}: the layer is rotated, sheared or moved by an affine transform in the viewer, and a "
                        "neuron table is in the image's axes; reset its transform (layer.affine = identity) first")
    scale = _per_axis(attributes.get("scale"), dims, 1.0)
    translate = _per_axis(attributes.get("translate"), dims, 0.0)
    scaled = not np.allclose(scale[-3:], 1.0) or not np.allclose(translate[-3:], 0.0)
    world = data * scale + translate
    if scaled:  # µm divided by the voxel size and multiplied back: the digits read, not the last bits of that
        world = _digits_read(world, data, scale, translate)
    varying = [k for k in range(dims - 3) if np.ptp(world[:, k]) > 0]
    feats = attributes.get("features")
    has_t = feats is not None and "t" in pd.DataFrame(feats).columns
    if varying and (len(varying) > 1 or varying[0] != dims - 4) and not has_t:
        raise FdlcError(f"{path}: the points vary along {len(varying)} axes besides z, y, x; "
                        "a neuron table holds one volume, or volumes over time (t, z, y, x)")
    df = pd.DataFrame({"x_um": world[:, -1], "y_um": world[:, -2], "z_um": world[:, -3]})
    if varying and not has_t:
        df["t"] = world[:, -4]
    # The Track widget's points sit at their frames on the recording's time axis (a scale or an
    # offset in seconds): a point added on a frame none was found on takes the frame's number,
    # like the rest of the sequence, not its time in seconds
    meta = (attributes.get("metadata") or {}).get(META_KEY) or {}
    frames = data[:, -4] if dims >= 4 and meta.get("tracks") else world[:, -4] if dims >= 4 else None
    data = data[:, -3:]
    feats = pd.DataFrame(feats) if feats is not None else pd.DataFrame(index=range(len(df)))
    feats = feats.reset_index(drop=True)
    if has_t and dims >= 4:
        feats["t"] = _times_of_frames(frames, feats["t"])
    elif has_t:  # one volume with a t column: a point added by hand is at its time too
        blank = feats["t"].isna() | feats["t"].astype(str).str.strip().eq("")
        known = pd.unique(feats["t"][~blank])
        if blank.any() and len(known) == 1:
            feats["t"] = feats["t"].astype(object).where(~blank, known[0])
    if "label" not in feats.columns and "name" in feats.columns:  # the Track widget's points name their neurons so
        feats = feats.rename(columns={"name": "label"})
    for c in [c for c in COLOUR_CHANNELS if c in feats.columns] + ["label"]:
        df[c] = feats[c].to_numpy() if c in feats.columns else ""
    # the review layer's own columns ('neuron', 'shown'), and voxel coordinates written anew
    # below; a table's own columns of those names are kept
    review = "session" in meta
    # (NeuroPAL_ID's 'Internal X (px)' too: with x_px written anew, a moved point's would be stale)
    left_out = ({"neuron", "shown"} if review else set()) | (set(PIXEL_COLUMNS) if scaled else set())
    for c in feats.columns:
        if c not in df.columns and c not in left_out:
            df[c] = feats[c].to_numpy()
    if scaled:
        df["x_px"], df["y_px"], df["z_px"] = data[:, 2], data[:, 1], data[:, 0]
    path = str(path)
    if not path.lower().endswith(".csv"):
        path += ".csv"
    try:
        write_table(df, path)
    except OSError as exc:
        raise FdlcError(f"{path}: cannot be written ({exc.strerror or exc})") from None
    return [path]


# ----- sample ---------------------------------------------------------------------------------

SAMPLE_NAME = "NeuroPAL sample"


def make_sample_data() -> list[tuple]:
    """The bundled NeuroPAL-like head: R/G/B/W channels and its neuron table (ground truth,
    hidden, names as text), plus its saved review session if there is one."""
    from ..sample import load_sample

    stack, truth = load_sample()
    layers = stack_layers(stack, name=SAMPLE_NAME)
    truth.source = "sample neurons"
    layers.append(table_points(truth, stack.voxel_size_zyx, name="sample neurons (truth)", visible=False))
    restored = restored_session_layer(stack.source, stack.shape_zyx, default_name=f"{SAMPLE_NAME}{RESULT_SUFFIX}",
                                      voxel_zyx=stack.voxel_size_zyx)
    if restored is not None:
        layers.append(restored)
    return layers


def image_key_of(layer) -> str:
    """What identifies the image of a layer for its session: the file it was read from."""
    meta = (getattr(layer, "metadata", None) or {}).get(META_KEY) or {}
    if meta.get("image"):
        return str(meta["image"])
    source = getattr(layer, "source", None)
    if source is not None and getattr(source, "path", None):
        return str(Path(source.path))
    if source is not None and getattr(source, "sample", None):
        plugin, name = source.sample
        return f"sample:{plugin}:{name}"
    # An image made in napari (a script, the console, another plugin) has no file: its name and
    # a fingerprint of its data, so that another image that happens to share the name does not
    # get this one's session.
    return f"layer:{_fingerprint(layer.data)}:{layer.name}"


def _fingerprint(data) -> str:
    """A short hash of an array's shape, type and (in memory) a sparse grid of its values: at
    most ~17 per axis, quick even for a big array."""
    import hashlib

    digest = hashlib.sha1(repr((tuple(data.shape), str(data.dtype))).encode())
    if isinstance(data, np.ndarray):  # a lazy array's values are not read for this
        grid = tuple(slice(None, None, max(1, n // 16)) for n in data.shape)
        digest.update(np.ascontiguousarray(data[grid]).tobytes())
    return digest.hexdigest()[:10]
