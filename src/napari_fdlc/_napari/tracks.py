"""The Track dock widget: neurons of a recording over time, as napari Tracks plus labelled Points.

Pick the neurons' source — a recording open in the viewer (t, z, y, x image layers, e.g. a
TIFF / OME-TIFF / ND2 file with a time axis opened with napari-fdlc: every time point is
segmented first, as ``fdlc segment`` does) or a sequence file (one neuron table with a ``t``
column, or a folder of neuron tables) — and, optionally, a reference volume (labelled: tracks
get its names; default: the first time point), then *Track*. The core
(:func:`napari_fdlc.segment.segment_series`, :func:`napari_fdlc.track.track`) runs in a
``thread_worker``; the progress bar follows it. Two layers come back, in µm (scale 1; a
recording's image layers have scale 1 in t and their voxel size in z, y, x, so they overlay),
with time as the first axis:

* ``<name> tracks`` — a Tracks layer, one track per reference neuron (track ID = its row);
* ``<name> neurons`` — a Points layer of every neuron at the current time point (napari slices
  the time axis), with features ``t, track_id, track_conf, name`` and the name (or track ID) as
  text.

The viewer is switched to 3D display, so that the whole volume of the current time point shows.

Scripting::

    w = TrackWidget(viewer); viewer.window.add_dock_widget(w)
    w.identifier = my_identifier         # default: the shipped model
    w.set_sequence("recording.csv"); w.set_reference("labelled_t0.csv")
    w.run()                               # returns when the layers are in (wait=False: at once)
    w.set_recording("recording.ome.tif")  # or the image layers of a recording (its file or layer name)
    w.run(wait=False); w.cancel()         # Cancel: stops after the current volume (w.cancelled)
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from qtpy.compat import isalive
from qtpy.QtCore import QObject, QTimer, Signal
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QProgressBar,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from ..errors import FdlcError, warnings_to
from ._io import image_key_of, notify_warning
from ._jobs import wait_until_idle
from ._layers import META_KEY, _blank, _plain_features, _short_name, is_image_layer, layer_role, stack_from_layers
from ._warm_up import start_warm_up

SEQUENCE_FILE = "the sequence file below"
RECORDING_ROLES = ("R", "G", "B", "W", "GFP")

if TYPE_CHECKING:  # pragma: no cover
    import napari


class _Cancelled(Exception):
    """Raised in the worker at its next volume when the user cancels (not an error)."""


class _Signals(QObject):
    # (what is being done, volumes done, of how many): emitted from the worker thread, delivered
    # on the GUI thread
    progress = Signal(str, int, int)
    idle = Signal()  # the job has ended (emitted on the GUI thread)


def track_layers(result, sequence, name: str = "sequence", frames: list[int] | None = None,
                 time_axis: tuple[float, float] = (1.0, 0.0), image_key: str | None = None) -> list[tuple]:
    """napari layer data tuples ``(data, kwargs, type)`` for a :class:`TrackResult`: Tracks of
    the tracked neurons (none when no neuron is tracked: napari cannot hold empty tracks) and
    Points of all neurons, time first, then z, y, x in µm. Time is ``frames`` (a recording's
    time points, a table sequence's frame numbers: :func:`frames_of`) or else each volume's
    index in ``sequence``, shown at ``time_axis`` (scale, translate: the recording's own, so
    that each frame lies over its image; ``image_key``: that recording's, kept in the metadata:
    its voxel size may not change under them). The points keep each neuron's other columns
    (colours, GFP, a folder's ``file``), so that they are saved as ``fdlc track`` writes them."""
    import pandas as pd

    from ..track import other_columns

    frames = list(range(len(sequence))) if frames is None else frames
    rows, points, feats = [], [], {"t": [], "track_id": [], "track_conf": [], "name": []}
    for k, (vol, tid, conf) in enumerate(zip(sequence.volumes, result.track_id, result.confidence)):
        zyx = vol.xyz[:, ::-1]
        points.append(np.column_stack([np.full(len(vol), frames[k]), zyx]))
        names = [result.names[i] if i >= 0 else "" for i in tid]
        feats["t"].extend([sequence.times[k]] * len(vol))
        feats["track_id"].extend(tid.tolist())
        feats["track_conf"].extend(conf.tolist())
        feats["name"].extend(names)
        tracked = tid >= 0
        rows.append(np.column_stack([tid[tracked], np.full(tracked.sum(), frames[k]), zyx[tracked]]))
    measured = other_columns(sequence)
    if any(sequence.sources):
        measured["file"] = np.repeat(np.asarray(sequence.sources, dtype=object), [len(v) for v in sequence.volumes])
    features = pd.concat([pd.DataFrame(feats), _plain_features(measured)], axis=1)
    data = np.vstack(rows) if rows else np.zeros((0, 5))
    data = data[np.lexsort((data[:, 1], data[:, 0]))]  # napari wants tracks sorted by ID, then time
    track_names = {int(i): n for i, n in enumerate(result.names)}
    labelled = any(result.names)
    ids = np.asarray(feats["track_id"])
    text = [n if n else (str(i) if i >= 0 else "") for n, i in zip(feats["name"], ids)]
    colours = _id_colours(ids)
    meta = {"fdlc": {"tracks": True, "times": list(sequence.times), "names": track_names if labelled else {},
                     **({"image": image_key} if image_key else {})}}
    placed = {"scale": (time_axis[0], 1.0, 1.0, 1.0), "translate": (time_axis[1], 0.0, 0.0, 0.0)}
    tracks = (data, {"name": f"{name} tracks", "tail_length": 10, "blending": "translucent",
                     "axis_labels": ("t", "z", "y", "x"), "metadata": meta, **placed}, "tracks")
    # a point added by hand is no track's (napari would copy the last point's track and name);
    # the writer takes its time from its frame
    defaults = {**{c: _blank(features[c]) for c in features.columns},
                "t": sequence.times[0], "track_id": -1, "track_conf": np.nan, "name": ""}
    pts = (np.vstack(points), {
        "name": f"{name} neurons", "features": features, "feature_defaults": defaults, "size": 3.0, "face_color": colours,
        "border_color": "white", "border_width": 0.05, "out_of_slice_display": False,
        "text": {"string": text, "size": 8, "color": "white", "anchor": "upper_left"},
        "axis_labels": ("t", "z", "y", "x"), "metadata": meta, **placed,
    }, "points")
    return [tracks, pts] if len(data) else [pts]


MAX_FRAME = 100_000  # whole-number t beyond this are timestamps, not frame numbers


def frames_of(times: list) -> list[int] | None:
    """The time points at which a table sequence's volumes are shown: their ``t`` when every t
    is a frame number (a whole number from 0 to ``MAX_FRAME``, as ``fdlc segment`` writes, so
    that a recording whose empty time points were left out still lies on its image's frames);
    otherwise None, each volume at its position in the sequence (t in seconds, timestamps)."""
    if all(isinstance(t, (int, np.integer)) and 0 <= t <= MAX_FRAME for t in times):
        return [int(t) for t in times]
    return None


def _id_colours(ids: np.ndarray) -> np.ndarray:
    """A stable colour per track ID (golden-ratio hues); grey for untracked neurons."""
    import colorsys

    out = np.empty((len(ids), 4))
    for k, i in enumerate(ids):
        if i < 0:
            out[k] = (0.6, 0.6, 0.6, 0.6)
        else:
            out[k] = (*colorsys.hsv_to_rgb((i * 0.618034) % 1.0, 0.75, 1.0), 1.0)
    return out


class TrackWidget(QWidget):
    """Track neurons through a sequence; see the module docstring."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer", parent: QWidget | None = None):
        super().__init__(parent)
        self.viewer = getattr(napari_viewer, "__wrapped__", napari_viewer)
        self.identifier = None  # None: the shipped model
        self.last_error: str | None = None
        self.result = None
        self.sequence = None
        self.layers: list = []
        self._shown: dict[str, list] = {}  # each input's layers (its image key, or its sequence file)
        self._worker = None
        self._busy = False
        self._cancel = threading.Event()  # set by Cancel; the running job stops at its next volume
        self.cancelled = False  # the last job was cancelled
        self._summary = ""  # what the last result shows, in the status line
        self._signals = _Signals()
        self._signals.progress.connect(self._on_progress)
        self._build_ui()
        self._warming: threading.Thread | None = None
        QTimer.singleShot(0, self._warm_up)

    def _warm_up(self) -> None:
        """Run both models once on a generated recording (:func:`napari_fdlc.track.warm_up`;
        torch's import and the weights' loads are ~1 s on two cores) in a thread while the user
        picks the files (see ``_warm_up.py``); a job joins it before tracking."""
        if self._busy or self._warming is not None:
            return
        identifier = self.identifier

        def warm():
            from ..track import warm_up

            warm_up(identifier)

        self._warming = start_warm_up(warm)

    # ------------------------------------------------------------------------------------------
    def _build_ui(self) -> None:
        layout = QVBoxLayout(self)
        form = QFormLayout()
        self.source_combo = QComboBox()
        self.source_combo.setToolTip("a recording open in the viewer (t, z, y, x image layers: segmented first), "
                                     "or the sequence of neuron tables chosen below")
        form.addRow("Neurons from", self.source_combo)
        self.diameter_spin = QDoubleSpinBox()
        self.diameter_spin.setRange(0.5, 20.0)
        self.diameter_spin.setSingleStep(0.25)
        self.diameter_spin.setValue(3.0)
        self.diameter_spin.setSuffix(" µm")
        self.diameter_spin.setToolTip("typical nucleus diameter, for segmenting a recording")
        form.addRow("Nucleus diameter", self.diameter_spin)
        self.sequence_edit = QLineEdit()
        self.sequence_edit.setPlaceholderText("CSV with a t column, or a folder of CSVs")
        # A path typed or pasted is the input, as one chosen with the browse button.
        self.sequence_edit.textEdited.connect(lambda text: text.strip() and self.source_combo.setCurrentText(SEQUENCE_FILE))
        form.addRow("Sequence", self._with_browse(self.sequence_edit, self._browse_sequence))
        self.reference_edit = QLineEdit()
        self.reference_edit.setPlaceholderText("optional; default: the first time point")
        form.addRow("Reference", self._with_browse(self.reference_edit, self._browse_reference))
        self.colour_check = QCheckBox("use colour when present")
        self.colour_check.setChecked(True)
        form.addRow("", self.colour_check)
        layout.addLayout(form)
        self.run_button = QPushButton("Track")
        self.run_button.clicked.connect(lambda: self.run(wait=False))
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setToolTip("stop after the volume being segmented or tracked; the layers shown stay")
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self.cancel)
        buttons = QHBoxLayout()
        buttons.addWidget(self.run_button)
        buttons.addWidget(self.cancel_button)
        layout.addLayout(buttons)
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 100)
        self.progress_bar.setValue(0)
        layout.addWidget(self.progress_bar)
        self.status = QLabel("")
        self.status.setWordWrap(True)
        layout.addWidget(self.status)
        layout.addStretch(1)
        self._refresh_recordings()
        for event in (self.viewer.layers.events.inserted, self.viewer.layers.events.removed):
            event.connect(self._on_layers_changed)
        for layer in self.viewer.layers:
            layer.events.name.connect(self._refresh_recordings)

    def _on_layers_changed(self, event) -> None:
        if event.type == "inserted":
            event.value.events.name.connect(self._refresh_recordings)  # a recording renamed
        self._refresh_recordings()

    def _recordings(self) -> dict[str, tuple[str, dict[str, object]]]:
        """The recordings in the viewer: {name shown: (image key, {role: layer})}, from t, z, y, x image
        layers grouped by the file they came from (a layer of its own without a known role is
        taken as W, the channel nuclei are found in; several without one, as channels of no role)."""
        groups: dict[str, list] = {}
        for layer in self.viewer.layers:
            if is_image_layer(layer) and layer.data.ndim == 4:
                groups.setdefault(image_key_of(layer), []).append(layer)
        out = {}
        for key, layers in groups.items():
            channels: dict[str, object] = {}
            for layer in layers:
                role = layer_role(layer, RECORDING_ROLES) or ("W" if len(layers) == 1 else None)
                if role is not None and role not in channels:
                    channels[role] = layer
            if not channels:  # a file that names none: nuclei found in their sum, as fdlc track does
                channels = {f"channel {k}": layer for k, layer in enumerate(layers)}
            if channels:
                meta = (layers[0].metadata or {}).get(META_KEY) or {}
                name = meta.get("stack_name") or (_short_name(key) if len(layers) > 1 else layers[0].name)
                shown, n = f"recording: {name}", 2
                while shown in out:  # two files of one name (day1/worm.tif, day2/worm.tif): both offered
                    shown, n = f"recording: {name} [{n}]", n + 1
                out[shown] = (key, channels)
        return out

    def _refresh_recordings(self, *_) -> None:
        """Offer the recordings in the viewer; the one chosen stays chosen (by its image, so
        also when it was renamed)."""
        current, current_key = self.source_combo.currentText(), self.source_combo.currentData()
        self.source_combo.blockSignals(True)
        self.source_combo.clear()
        for name, (key, _) in self._recordings().items():
            self.source_combo.addItem(name, key)
        self.source_combo.addItem(SEQUENCE_FILE)
        same = self.source_combo.findData(current_key) if current_key is not None else -1
        if same >= 0:
            self.source_combo.setCurrentIndex(same)
        elif self.source_combo.findText(current) >= 0 and not (current == SEQUENCE_FILE and not self.sequence_edit.text()):
            self.source_combo.setCurrentText(current)  # else a recording, when there is one, comes first
        self.source_combo.blockSignals(False)

    def _with_browse(self, edit: QLineEdit, browse) -> QWidget:
        box = QWidget()
        row = QHBoxLayout(box)
        row.setContentsMargins(0, 0, 0, 0)
        row.addWidget(edit)
        button = QPushButton("…")
        button.setMaximumWidth(30)
        button.clicked.connect(browse)
        row.addWidget(button)
        return box

    def _browse_sequence(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Sequence (CSV with a t column)", "", "CSV (*.csv)")
        if path:
            self.set_sequence(path)

    def _browse_reference(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Reference volume", "", "CSV (*.csv)")
        if path:
            self.set_reference(path)

    # ------------------------------------------------------------------------------------------
    # Scripting interface
    def set_sequence(self, path) -> None:
        """Track the neuron tables of ``path`` (a CSV with a t column, or a folder of CSVs)."""
        self.sequence_edit.setText(str(path))
        self.source_combo.setCurrentText(SEQUENCE_FILE)

    def set_recording(self, name: str) -> None:
        """Track the recording open in the viewer whose file (or layer) is ``name``."""
        self._refresh_recordings()
        recordings = self._recordings()
        # by the file first: day1/worm.ome.tif and day2/worm.ome.tif are both 'worm'
        def same_file(key: str) -> bool:
            try:
                return bool(name) and Path(key).resolve() == Path(name).resolve()
            except (OSError, ValueError):
                return False

        matches = [t for t, (k, _) in recordings.items() if same_file(k)] or [
            t for t in recordings if t == name or t == f"recording: {name}" or t == f"recording: {_short_name(str(name))}"] or [
            t for t, (_, channels) in recordings.items() if any(layer.name == name for layer in channels.values())]
        if not matches:
            raise FdlcError(f"no recording '{name}' in the viewer (open a stack with a time axis)")
        self.source_combo.setCurrentText(matches[0])

    def set_reference(self, path) -> None:
        self.reference_edit.setText("" if path is None else str(path))

    @property
    def busy(self) -> bool:
        return self._busy

    def run(self, wait: bool = True):
        """Read the inputs, track in a worker thread, then add the layers. With ``wait`` (the
        default, for scripts) returns the two layers when done (None after an error)."""
        from napari.qt.threading import thread_worker

        if self._busy:  # said, but not made the state of the job that is running
            notify_warning("a tracking job is still running")
            return None
        self.last_error = None
        self.cancelled = False
        cancel = self._cancel = threading.Event()  # this job's own: a late Cancel cannot stop the next
        sequence_path = self.sequence_edit.text().strip()
        reference_path = self.reference_edit.text().strip()
        use_colour = self.colour_check.isChecked()
        identifier = self.identifier
        signals, warming = self._signals, self._warming
        source = self.source_combo.currentText()
        channels = name = None
        if source != SEQUENCE_FILE:
            key, channels = self._recordings().get(source, (None, None))
            if channels is None:
                self._error(f"the recording '{source}' is no longer in the viewer")
                return None
            name = source[len("recording: "):]
            first = next(iter(channels.values()))
            time_axis = (float(first.scale[0]), float(first.translate[0]))
        else:
            key, time_axis = str(Path(sequence_path).resolve()) if sequence_path else "", (1.0, 0.0)
        diameter = float(self.diameter_spin.value())
        shown_as = name or Path(sequence_path).stem or "sequence"  # the layers' name

        warned: list[str] = []  # what the readers warn about, shown when the job ends

        def report(doing: str, done: int, total: int) -> None:  # in the worker, after each volume
            if cancel.is_set():
                raise _Cancelled
            signals.progress.emit(doing, done, total)

        def job():
            from ..table import read_volume, warn_implausible_scales
            from ..track import Sequence, TrackSettings, read_sequence, track

            references = [read_volume(reference_path, "a reference is one volume: give one time point")] if reference_path else None
            if channels is not None:
                from ..segment import found_time_points, segment_series

                # named in messages as the user knows it: its file, or its name in napari (not the key)
                recording = stack_from_layers(channels, name if key.startswith("layer:") else key, recording=True)
                tables = segment_series(recording, diameter,
                                        progress=lambda done, total: report("segmenting", done, total))
                frames = found_time_points(tables, recording.source, "check the nucleus diameter and the voxel size")
                sequence = Sequence([tables[t] for t in frames], frames, [""] * len(frames))
            else:
                if not sequence_path:
                    raise FdlcError("choose a recording or a sequence first (a CSV with a t column, or a folder of CSVs)")
                sequence = read_sequence([sequence_path])
                frames = frames_of(sequence.times)
            warn_implausible_scales([sequence.volumes[0], *(references or [])])  # as fdlc track: not in µm?
            if warming is not None:  # one model, used by one thread at a time
                warming.join()
            ident = identifier
            if ident is None:
                from ..identify import default_identifier

                ident = default_identifier()
            report("tracking", 0, len(sequence))
            result = track(sequence, references, ident, TrackSettings(use_colour=use_colour),
                           progress=lambda done, total: report("tracking", done, total))
            # the layers' data too (every neuron's columns over time), off the GUI thread
            return sequence, result, track_layers(result, sequence, shown_as, frames, time_axis, image_key=key)

        @thread_worker(start_thread=False, ignore_errors=True)
        def work():
            with warnings_to(warned.append):
                return job()

        worker = work()
        self._worker = worker
        self._set_busy(True)
        worker.returned.connect(lambda out: self._show(*out, shown_as, key))
        worker.errored.connect(self._on_error)
        worker.finished.connect(lambda: self._set_busy(False))
        def show_warnings():
            for message in warned:
                notify_warning(message)

        worker.finished.connect(show_warnings)
        worker.start()
        if wait:
            self.wait()
            return None if self.last_error or self.cancelled else self.layers
        return worker

    def cancel(self) -> None:
        """Stop the running job after the volume it is on (segmenting or tracking); the layers
        already shown stay as they were."""
        if self._busy:
            self._cancel.set()
            self.status.setText("cancelling…")

    def wait(self, timeout: float | None = None) -> bool:
        """Process GUI events until the running job is done; True when idle."""
        return wait_until_idle(lambda: self._busy, self._signals.idle, timeout)

    # ------------------------------------------------------------------------------------------
    def _closed(self) -> bool:
        """Whether napari was closed under the job (its widgets are gone: the result is dropped)."""
        return not isalive(self.run_button)

    def _show(self, sequence, result, made: list[tuple], name: str, key: str) -> None:
        if self._closed():
            return
        try:
            self._add_layers(sequence, result, made, name, key)
        except Exception as exc:  # on the GUI thread, after the worker: said, not a traceback
            self._on_error(exc)

    def _add_layers(self, sequence, result, made: list[tuple], name: str, key: str) -> None:
        """Show the layers ``made`` by :func:`track_layers` in the worker."""
        self.sequence, self.result = sequence, result
        # A run on the same input replaces its layers; another input's result stays beside it.
        for layer in self._shown.pop(key, []):
            if layer in self.viewer.layers:
                self.viewer.layers.remove(layer)
        self.layers = [getattr(self.viewer, f"add_{kind}")(data, **kwargs) for data, kwargs, kind in made]
        self._shown[key] = list(self.layers)
        # Neurons are spread in z: show the whole volume at the current time point (in a 2D slice
        # only the neurons of one z plane would show), starting at the first time point.
        self.viewer.dims.ndisplay = 3
        self.viewer.dims.set_current_step(0, 0)
        tracked = sum(int((t >= 0).sum()) for t in result.track_id) / max(sum(len(t) for t in result.track_id), 1)
        self._summary = (f"{len(sequence)} time point{'s' * (len(sequence) != 1)}, {len(result.names)} tracks; "
                         f"{100 * tracked:.0f} % of the neurons tracked")
        self.status.setText(self._summary)
        if len(made) == 1:
            notify_warning(f"{name}: no neuron could be tracked (shown untracked); check the reference")

    def _on_error(self, exc: Exception) -> None:
        if isinstance(exc, _Cancelled):
            self.cancelled = True
            if not self._closed():
                self.status.setText("cancelled; the layers shown are unchanged")
        elif isinstance(exc, FdlcError):
            self._error(str(exc))
        else:
            self._error(f"unexpected error ({type(exc).__name__}: {exc})")

    def _error(self, message: str) -> None:
        self.last_error = message
        if self._closed():
            return
        self.status.setText(message)
        self.progress_bar.setValue(0)
        try:
            from napari.utils.notifications import show_error

            show_error(message)
        except Exception:  # pragma: no cover - notification machinery unavailable
            pass

    def _set_busy(self, busy: bool) -> None:
        self._busy = busy
        if not self._closed():  # napari closed under the job: nothing to show it in
            self._show_busy(busy)
        if not busy:
            self._worker = None
            self._signals.idle.emit()

    def _show_busy(self, busy: bool) -> None:
        self.run_button.setEnabled(not busy)
        self.cancel_button.setEnabled(busy)
        if busy:
            self.progress_bar.setValue(0)
            self.status.setText("tracking…")
        elif self.last_error is None and not self.cancelled:
            self.progress_bar.setValue(100)
            if self._cancel.is_set():  # Cancel came after the result was in: said as it is
                self.status.setText(f"{self._summary} (done before it could be cancelled)")

    def _on_progress(self, doing: str, done: int, total: int) -> None:
        if self._closed():
            return
        self.progress_bar.setValue(int(round(100 * done / max(total, 1))))
        self.status.setText(f"{doing}… {done}/{total} volumes")
