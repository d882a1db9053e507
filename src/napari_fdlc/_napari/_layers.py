"""Layer data for napari: stacks as R/G/B/W additive channels, neuron tables as Points.

Conventions (``../shared/docs/neuropal_formats_and_tools.md``): one image layer per channel with a
red/green/blue/gray colormap, additive blending, gamma 0.7 and contrast from the data; the voxel
size is the layers' ``scale``, so the world is in µm. Neurons are Points in *voxel* coordinates
with the image's scale (each neuron then sits on exactly one z plane, the one through its
centre); without a known voxel size they are in µm with scale 1.

Everything here returns napari "layer data tuples" ``(data, kwargs, layer_type)`` or plain
arrays: no napari import is needed, which keeps the readers light.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import FdlcError
from ..table import COLOUR_CHANNELS, NeuronTable

ROLE_COLORMAP = {"R": "red", "G": "green", "B": "blue", "W": "gray", "GFP": "green"}
ROLE_LONG = {"R": "mNeptune2.5", "G": "CyOFP1.5", "B": "mTagBFP2", "W": "TagRFP-T", "GFP": "GFP"}
GAMMA = 0.7
POINT_SIZE_UM = 3.0  # a nucleus across
META_KEY = "fdlc"  # layer.metadata[META_KEY]: what napari-fdlc knows about a layer

# Ring colour per status (faces stay transparent so the nucleus colour, the thing a NeuroPAL
# user reads, is never covered).
STATUS_COLOURS = {
    "auto": (1.0, 0.85, 0.1, 1.0),  # yellow: automatic name at or above the threshold
    "accepted": (0.2, 1.0, 0.2, 1.0),  # green
    "corrected": (0.2, 0.85, 1.0, 1.0),  # cyan
    "unsure": (1.0, 0.45, 0.0, 1.0),  # orange
    "hidden": (0.6, 0.6, 0.6, 0.55),  # grey: automatic name below the threshold, or none
}
STATUS_HEX = {k: "#%02x%02x%02x" % tuple(int(255 * c) for c in v[:3]) for k, v in STATUS_COLOURS.items()}


def contrast_limits(channel) -> tuple[float, float]:
    """Display range from the data: median (background) to the bright tail (99.95th
    percentile, at least mean + 4 SD), from a subsample so that big stacks stay quick."""
    if channel.ndim == 3 and not isinstance(channel, np.ndarray):
        # a lazy stack (over 1 GiB): a few planes, not every one of a NeuroPAL stack's ~30
        a = np.asarray(channel[np.unique(np.linspace(0, channel.shape[0] - 1, 8).round().astype(int))])
    else:
        a = np.asarray(channel[:: max(1, channel.shape[0] // 16)] if channel.ndim == 3 else channel)
    flat = a.ravel()
    if flat.size > 2_000_000:
        flat = flat[:: flat.size // 2_000_000 + 1]
    flat = flat[np.isfinite(flat)] if np.issubdtype(flat.dtype, np.floating) else flat
    if flat.size == 0:
        return (0.0, 1.0)
    lo = float(np.median(flat))
    hi = float(max(np.percentile(flat, 99.95), flat.mean() + 4 * flat.std()))
    hi = min(hi, float(flat.max()))
    if not hi > lo:
        hi = lo + 1.0
    return (lo, hi)


def stack_layers(stack, name: str | None = None, source_key: str | None = None, voxel_unknown: bool = False,
                 voxel_set: bool = False) -> list[tuple]:
    """One image layer per channel: R/G/B/W colormaps, additive, gamma 0.7, µm scale. A
    recording (:class:`~napari_fdlc.io.images.StackSeries`) gives t, z, y, x layers (time in
    volumes, scale 1), which the Track widget segments and tracks. With ``voxel_unknown`` (the
    file does not say it) the stack's voxel size is a stand-in, refused by
    :func:`stack_from_layers` until the layers' scale is set (Auto-label's *Voxel size*);
    ``voxel_set``: the voxel size is the one set in napari for this image (its saved session's)."""
    base = name or _short_name(stack.source)
    key = source_key or stack.source
    recording = stack.data.ndim == 5
    layers = []
    for i, role in enumerate(stack.channel_roles):
        channel = stack.data[:, i] if recording else stack.data[i]
        label = stack.channel_names[i] if stack.channel_names else (role or f"channel {i}")
        kwargs = {
            "name": f"{base} [{role or label}]",
            "scale": (1.0,) * recording + tuple(stack.voxel_size_zyx),
            "colormap": ROLE_COLORMAP.get(role, "gray"),
            "blending": "additive",
            "gamma": GAMMA,
            "contrast_limits": contrast_limits(channel[0] if recording else channel),
            "visible": role != "GFP",
            # the pan-neuronal W is in every nucleus: at half opacity the colour code stays readable
            "opacity": 0.5 if role == "W" else 1.0,
            "axis_labels": ("t",) * recording + ("z", "y", "x"),
            "metadata": {META_KEY: {"image": key, "role": role, "channel_name": label, "stack_name": base,
                                    **({"voxel_stand_in": list(stack.voxel_size_zyx)} if voxel_unknown else {}),
                                    **({"voxel_set": True} if voxel_set else {})}},
        }
        layers.append((channel, kwargs, "image"))
    return layers


def voxel_unknown(layer) -> bool:
    """True while an image layer's scale is still the stand-in its reader gave for a voxel size
    the file does not say (set since, in the widget or napari's console: known)."""
    stand_in = ((layer.metadata or {}).get(META_KEY) or {}).get("voxel_stand_in")
    return stand_in is not None and np.allclose(np.asarray(layer.scale[-3:], dtype=float), stand_in)


def is_image_layer(layer) -> bool:
    return type(layer).__name__ == "Image" and getattr(layer, "ndim", 0) >= 3 and not getattr(layer, "rgb", False)


def layer_role(layer, roles=("R", "G", "B", "W")) -> str | None:
    """The channel role of an image layer among ``roles``: from napari-fdlc's metadata, a
    ``[R]``-style tag or a fluorophore in its name, else its colormap."""
    meta = (layer.metadata or {}).get(META_KEY) or {}
    if "role" in meta:  # napari-fdlc read it: its role (None, GFP: no colour, not W) is known, whatever its colour
        return meta["role"] if meta["role"] in roles else None
    name = layer.name
    if name.endswith("]") and "[" in name:
        tag = name[name.rindex("[") + 1 : -1].strip().upper()
        if tag in roles:
            return tag
    from ..io.images import role_from_name

    role = role_from_name(name)
    if role in roles:
        return role
    cmap = getattr(getattr(layer, "colormap", None), "name", "")
    role = {"red": "R", "green": "G", "blue": "B", "gray": "W", "grey": "W"}.get(cmap)
    return role if role in roles else None


def stack_from_layers(images: dict, source: str, recording: bool = False):
    """A :class:`~napari_fdlc.io.images.Stack` from image layers, one per channel role
    (``{"W": layer, ...}``), which must share their shape and voxel size (layer scale); a layer
    with axes before z, y, x gives its first volume. With ``recording``, a
    :class:`~napari_fdlc.io.images.StackSeries` of t, z, y, x layers, lazy (dask): its volumes
    are read one at a time. Lazy layers stay lazy."""
    from ..io.images import ROLES, Stack, StackSeries

    if not images:
        raise FdlcError("no image chosen: pick the image layer of at least one channel (W to detect nuclei)")
    layers = list(images.values())
    axes = 4 if recording else 3
    for layer in layers:
        if moved_in_viewer(layer.rotate, layer.shear, layer.affine):  # its neurons would land off its nuclei
            raise FdlcError(f"the image layer '{layer.name}' is rotated, sheared or moved by an affine transform in "
                            "the viewer; neurons are placed in the image's own voxels: reset its transform first")
        if getattr(layer, "multiscale", False):
            raise FdlcError(f"the image layer '{layer.name}' is a multiscale pyramid; add its full-resolution level "
                            "(layer.data[0]) as an image layer of its own and choose that")
    if any(layer.data.ndim < axes for layer in layers):
        raise FdlcError("the chosen image layers must be recordings (t, z, y, x)" if recording
                        else "the chosen image layers must be 3D stacks (z, y, x)")
    shapes = {tuple(layer.data.shape[-axes:]) for layer in layers}
    if len(shapes) != 1:
        raise FdlcError(f"the chosen channels differ in shape ({', '.join(map(str, sorted(shapes)))}); choose channels of one stack")
    scales = {tuple(np.round(np.asarray(layer.scale[-3:], dtype=float), 9)) for layer in layers}
    if len(scales) != 1:
        raise FdlcError("the chosen channels have different voxel sizes (layer scale); choose channels of one stack")
    for layer in layers:
        if voxel_unknown(layer):
            raise FdlcError(f"'{layer.name}': its file does not say the voxel size; set it (µm) in Auto-label's "
                            "Voxel size row first")
    # Neurons are found and their colours read in the stack's own voxels, from 0: a layer moved
    # in the viewer would put the points, and the colours read under other points, off by that.
    for layer in layers:
        shift = np.asarray(layer.translate, dtype=float)[-3:]
        if np.any(shift != 0):
            raise FdlcError(f"the image layer '{layer.name}' is shifted in the viewer (translate z, y, x = "
                            f"{', '.join(f'{v:g}' for v in shift)}); neurons are placed in the image's own voxels: "
                            "set its translate to 0 (layer.translate = 0 in napari's console) or open the file again")
    arrays = [layer.data[(0,) * (layer.data.ndim - axes)] for layer in layers]
    if all(isinstance(a, np.ndarray) for a in arrays) and not recording:
        data = np.stack(arrays)
    else:  # a recording is read one time point at a time, never copied whole
        import dask.array as da

        chunks = (1,) * recording + tuple(arrays[0].shape[recording:])
        data = da.stack([da.from_array(a, chunks=chunks) if isinstance(a, np.ndarray) else da.asarray(a)
                         for a in arrays], axis=axes - 3)
    kind = StackSeries if recording else Stack
    roles = [role if role in ROLES else None for role in images]  # {"channel 0": ...}: no role
    return kind(data, tuple(float(v) for v in layers[0].scale[-3:]), roles, source=source,
                channel_names=[layer.name for layer in layers])


def _short_name(source: str) -> str:
    name = str(source).replace("\\", "/").rsplit("/", 1)[-1]
    for suffix in (".ome.tiff", ".ome.tif", ".tiff", ".tif", ".nwb", ".nd2", ".csv"):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def table_points(
    table: NeuronTable,
    voxel_size_zyx=None,
    name: str | None = None,
    visible: bool = True,
) -> tuple:
    """A neuron table as one Points layer (features = the table's columns, text = names)."""
    features = table.to_dataframe().drop(columns=["x_um", "y_um", "z_um"])
    features = _plain_features(features)
    coords, scale = points_coordinates(table.xyz, voxel_size_zyx)
    named = bool(table.named.any())
    kwargs = {
        "name": name or _short_name(table.source),
        "scale": scale,
        "size": point_size(scale),
        "features": features,
        # A point added by hand is a new neuron: no name, no colour (napari would copy the last row's)
        "feature_defaults": {c: _blank(features[c]) for c in features.columns},
        "face_color": "transparent",
        "border_color": "white",
        "border_width": 0.12,
        "border_width_is_relative": True,
        "visible": visible,
        "axis_labels": ("z", "y", "x"),
        "metadata": {META_KEY: {"table": table.source}},
    }
    # fdlc track writes the name its tracks carry as `name` (its input's own names stay `label`)
    shown = "label" if named else "name" if "name" in features and any(features["name"]) else None
    if shown:
        kwargs["text"] = {"string": f"{{{shown}}}", "size": 9, "color": "white", "anchor": "upper_left"}
    return (coords, kwargs, "points")


def points_coordinates(xyz_um: np.ndarray, voxel_size_zyx=None) -> tuple[np.ndarray, tuple]:
    """(N, 3) z, y, x data coordinates and the layer scale for positions in µm."""
    zyx = np.asarray(xyz_um, dtype=float).reshape(-1, 3)[:, ::-1]
    if voxel_size_zyx is None:
        return zyx.copy(), (1.0, 1.0, 1.0)
    vox = np.asarray(voxel_size_zyx, dtype=float)
    return zyx / vox, tuple(float(v) for v in vox)


def point_size(scale) -> float:
    """Points are sized in data units: one nucleus across in x/y."""
    return POINT_SIZE_UM / float(np.mean(np.asarray(scale)[-2:]))


def moved_in_viewer(rotate, shear, affine) -> bool:
    """Whether a layer is rotated, sheared or moved by an affine transform in the viewer (its
    positions then are not the image's: napari-fdlc reads scale and translate only)."""
    def matrix(value) -> np.ndarray:
        return np.atleast_1d(np.asarray(getattr(value, "affine_matrix", value), dtype=float))

    def identity(value) -> bool:
        m = matrix(value)
        return value is None or np.allclose(m, np.eye(len(m)) if m.ndim == 2 else 0.0)

    return not (identity(rotate) and identity(shear) and identity(affine))


def layer_xyz_um(layer) -> np.ndarray:
    """Positions of a Points layer in µm (world coordinates), x, y, z."""
    if moved_in_viewer(layer.rotate, layer.shear, layer.affine):
        raise FdlcError(f"layer '{layer.name}' is rotated, sheared or moved by an affine transform in the viewer; "
                        "reset its transform first (napari-fdlc reads its scale and translate)")
    data = np.asarray(layer.data, dtype=float)
    if data.ndim != 2 or data.shape[1] < 3:
        raise FdlcError(f"layer '{layer.name}': neurons need 3D points (z, y, x); this layer has {data.shape[1] if data.ndim == 2 else 0} dimensions")
    if data.shape[1] > 3 and len(data) and np.ptp(data[:, :-3], axis=0).max() > 0:
        # e.g. the Track widget's points: one worm is one time point
        raise FdlcError(f"layer '{layer.name}' holds points of several time points; neurons of one volume are needed")
    data = data[:, -3:]
    scale = np.asarray(layer.scale, dtype=float)[-3:]
    translate = np.asarray(layer.translate, dtype=float)[-3:]
    return (data * scale + translate)[:, ::-1]


def _plain_features(df: pd.DataFrame) -> pd.DataFrame:
    """napari features cannot hold pandas' nullable/arrow string dtypes reliably: use object."""
    out = pd.DataFrame(index=range(len(df)))
    for c in df.columns:
        col = df[c]
        if pd.api.types.is_integer_dtype(col) and c == "t":  # timestamps in ns exceed float64's 2**53
            out[str(c)] = col.to_numpy(dtype=np.int64)
        elif pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col):
            out[str(c)] = col.to_numpy(dtype=float, na_value=np.nan)
        elif pd.api.types.is_bool_dtype(col):
            out[str(c)] = col.to_numpy(dtype=bool)
        else:
            out[str(c)] = np.asarray(["" if _missing(v) else str(v) for v in col], dtype=object)
    return out


def _blank(column: pd.Series):
    """What a point added by hand holds in a feature column: nothing read (NaN, '', False)."""
    if pd.api.types.is_bool_dtype(column):
        return False
    if pd.api.types.is_integer_dtype(column):  # whole-number times (ns): NaN would make them floats;
        return int(column.iloc[0]) if len(column) else 0  # the writer takes a point's time from its frame
    return np.nan if pd.api.types.is_numeric_dtype(column) else ""


def _missing(v) -> bool:
    try:
        return v is None or bool(pd.isna(v))
    except (TypeError, ValueError):
        return False


def table_from_layer(layer, use_label: bool = False) -> NeuronTable:
    """A neuron table from any Points layer: positions in µm (world), colours from features
    R, G, B, W when present, names from feature ``label`` when ``use_label``."""
    xyz = layer_xyz_um(layer)
    n = len(xyz)
    if n == 0:
        raise FdlcError(f"layer '{layer.name}': no points")
    feats = layer.features if len(layer.features) == n else pd.DataFrame(index=range(n))
    colours = {}
    for c in COLOUR_CHANNELS:
        if c in feats.columns:
            v = pd.to_numeric(feats[c], errors="coerce").to_numpy(dtype=float, copy=True)
            if np.isfinite(v).any():  # an empty cell: the NeuronTable fills and remembers it
                colours[c] = v
    labels = None
    if use_label:
        for col in ("label", "user_id", "name"):
            if col in feats.columns:
                labels = np.asarray(["" if _missing(v) else str(v) for v in feats[col]], dtype=object)
                break
    from ..table import _drop_duplicate_names, parse_name

    label_conf = None
    if labels is not None:
        parsed = [parse_name(v) for v in labels]
        labels = np.array([p[0] for p in parsed], dtype=object)
        label_conf = np.array([p[1] for p in parsed])
        labels, label_conf = _drop_duplicate_names(labels, label_conf, f"layer '{layer.name}'")
    # the table's other columns (a detection score, an ID of the user's) go on to the export
    extra = feats[[c for c in feats.columns if not _layer_owned(c)]].reset_index(drop=True)
    return NeuronTable(xyz, colours, labels, label_conf, extra=extra, source=f"layer '{layer.name}'")


# features a layer holds that are not the table's own columns: positions, names, colours, and
# what a review or a tracking result adds (made again from the session)
_OWNED = {"label", "user_id", "name", "neuron", "auto_id", "auto_conf", "user_conf", "status", "shown", "t",
          "track_id", "track_conf", "x_um", "y_um", "z_um", "x_px", "y_px", "z_px", *COLOUR_CHANNELS}


def _layer_owned(column) -> bool:
    return str(column) in _OWNED or str(column).startswith(("cand_", "prob_"))


def named_count(layer) -> int:
    """Number of named points in a Points layer (feature ``label``)."""
    feats = getattr(layer, "features", None)
    if feats is None or "label" not in feats.columns:
        return 0
    return int(sum(1 for v in feats["label"] if not _missing(v) and str(v).strip() not in ("", "?")))


def review_features(session) -> pd.DataFrame:
    """The features of the result layer: what a user (or a script) reads per neuron."""
    df = pd.DataFrame(index=range(len(session)))
    df["neuron"] = np.arange(len(session))
    df["label"] = np.asarray(session.display_names(), dtype=object)
    df["auto_id"] = np.asarray(session.auto_id, dtype=object)
    df["auto_conf"] = session.auto_conf
    cands = [session.candidates(i) + [("", 0.0)] * 3 for i in range(len(session))]
    for k in range(3):
        df[f"cand_{k + 1}"] = np.asarray([c[k][0] for c in cands], dtype=object)
        df[f"prob_{k + 1}"] = np.asarray([c[k][1] for c in cands], dtype=float)
    df["user_id"] = np.asarray(session.user_id, dtype=object)
    df["user_conf"] = session.user_conf
    df["status"] = np.asarray(session.status, dtype=object)
    df["shown"] = np.asarray([bool(x) for x in session.final_names()], dtype=bool)
    colours = session.table.colours_as_read()  # a neuron without a reading is saved without one
    for c in COLOUR_CHANNELS:
        if c in colours:
            df[c] = colours[c]
    return df


def review_defaults(features: pd.DataFrame) -> dict:
    """What a point added to the result layer holds: a new neuron, no session row. Where no
    widget follows the layer (restored, the dock closed) napari copied the last row's name and
    the user's decision on it (and set again with the features, napari's own come back)."""
    return {**{c: _blank(features[c]) for c in features.columns}, "neuron": -1}


def review_colours(session) -> np.ndarray:
    """(N, 4) ring colours: status for user decisions, yellow/grey for automatic names."""
    shown = session.auto_shown()
    out = np.empty((len(session), 4))
    for i, st in enumerate(session.status):
        key = st if st != "auto" else ("auto" if shown[i] else "hidden")
        out[i] = STATUS_COLOURS[key]
    return out


def session_time_axis(session) -> tuple[float, float] | None:
    """(scale, translate) of the time axis of the recording a session names a time point of
    (its first frame, data t = 0), None for a stack or a file that says nothing usable."""
    return _time_axis((getattr(session, "settings", None) or {}).get("time_axis"))


def layer_time_axis(layer) -> tuple[float, float] | None:
    """(scale, translate) of a t, z, y, x layer's time axis; None for a 3D layer."""
    if getattr(layer, "ndim", 3) < 4:
        return None
    return _time_axis((layer.scale[-4], layer.translate[-4]))


def _time_axis(value) -> tuple[float, float] | None:
    try:
        step, first = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return (step, first) if np.isfinite(step) and step > 0 and np.isfinite(first) else None


def review_coordinates(session, ndim: int | None = None, time_axis=None) -> tuple[np.ndarray, tuple, tuple]:
    """Data coordinates, scale and translate of a session's neuron-ID layer: z, y, x, with a
    leading t (the named time point) for a recording, so that napari draws the names at that
    time point only. ``ndim``: an existing layer's dimensions (one made before names had a time
    axis stays 3D); ``time_axis``: (scale, translate) of the recording as shown now, instead of
    the one the session was made on (a recording opened again starts where its file says)."""
    coords, scale = points_coordinates(session.table.xyz, session.voxel_size_zyx)
    time_axis = _time_axis(time_axis) or session_time_axis(session)
    if time_axis is None or ndim == 3:
        return coords, scale, (0.0,) * 3
    coords = np.column_stack([np.zeros(len(coords)), coords])
    return coords, (time_axis[0], *scale), (time_axis[1], 0.0, 0.0, 0.0)


def review_points(session, name: str, metadata: dict | None = None, time_axis=None) -> tuple:
    """Layer data tuple of the result layer for a review session (``time_axis``: of the
    recording it names a time point of, as shown now; see :func:`review_coordinates`)."""
    coords, scale, translate = review_coordinates(session, time_axis=time_axis)
    features = review_features(session)
    kwargs = {
        "name": name,
        "scale": scale,
        "translate": translate,
        "size": point_size(scale),
        "features": features,
        "feature_defaults": review_defaults(features),
        "face_color": "transparent",
        "border_color": review_colours(session),
        "border_width": 0.14,
        "border_width_is_relative": True,
        "text": review_text(),
        "axis_labels": ("t", "z", "y", "x")[-coords.shape[1]:],
        "metadata": {META_KEY: dict(metadata or {})},
    }
    return (coords, kwargs, "points")


def review_text() -> dict:
    return {"string": "{label}", "size": 10, "color": "white", "anchor": "upper_left"}
