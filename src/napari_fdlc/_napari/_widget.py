"""The Auto-label dock widget: detect, name, review and export the neurons of a NeuroPAL stack.

The widget is a face: the review state lives in a Qt-free :class:`napari_fdlc.review.ReviewSession`
that this widget displays (one Points layer whose features, ring colours and text follow the
session) and forwards to. Every action is a plain method, usable from a script::

    _, w = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    w.auto_label()                 # returns when the result is in the layer
    w.set_threshold(0.4); w.accept(12); w.assign(3, "AVAL"); w.undo()
    w.export("ids.csv")

Heavy work (segmentation, identification) runs in a ``thread_worker``; the GUI never waits on
it (``auto_label(wait=True)``, the default for scripts, spins a local event loop). Errors from
the core are :class:`~napari_fdlc.errors.FdlcError`: they become napari notifications.

Tests (and users with their own model) inject the model and templates::

    w.identifier = Identifier(CorrespondenceModel(), ...)   # default: the shipped weights
    w.set_templates([labelled_table, ...])                   # default: built-in reference panel
"""

from __future__ import annotations

import itertools
import re
import sys
import threading
import traceback
import weakref
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import pandas as pd
from qtpy.QtCore import QEvent, QObject, Qt, QTimer, Signal
from qtpy.QtGui import QColor
from qtpy.QtWidgets import (
    QAbstractItemView,
    QCheckBox,
    QComboBox,
    QCompleter,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QLineEdit,
    QMessageBox,
    QProgressBar,
    QPushButton,
    QScrollArea,
    QSizePolicy,
    QSlider,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from ..errors import FdlcError, warn, warnings_to
from ..review import (
    DEFAULT_THRESHOLD,
    ReviewSession,
    carry_decisions,
    decisions_from_frame,
    find_session,
    load_preferences,
    save_preferences,
    session_file_for,
    set_aside,
    user_session_file,
)
from ..table import COLOUR_CHANNELS, NeuronTable
from ._io import RESULT_SUFFIX, image_key_of, notify_warning
from ._jobs import wait_until_idle
from ._layers import (
    META_KEY,
    STATUS_HEX,
    _short_name,
    is_image_layer,
    layer_role,
    layer_time_axis,
    named_count,
    point_size,
    review_colours,
    review_coordinates,
    review_defaults,
    review_features,
    review_points,
    session_time_axis,
    stack_from_layers,
    table_from_layer,
    voxel_unknown,
)
from ._warm_up import start_warm_up

if TYPE_CHECKING:
    import napari

ROLES = ("R", "G", "B", "W")
SEGMENT = "Detect nuclei in the image"
BUILTIN = "Built-in reference panel"
SCRIPTED = "Templates given by script"
FROM_FILE = "Labelled table file…"
NONE = "(none)"

# key, method name, help text. Bound on the neuron-ID layer (so they win over the Points layer's
# own 1/2/3/A keys) and on the viewer.
KEYS = (
    ("A", "accept", "accept the name of the selected neuron"),
    ("1", "pick_1", "give it candidate 1"),
    ("2", "pick_2", "give it candidate 2"),
    ("3", "pick_3", "give it candidate 3"),
    ("U", "unsure", "mark its name unsure (?, confidence 0.5)"),
    ("C", "clear", "clear your decision (the automatic name applies again)"),
    ("T", "type_name", "type a name (Enter commits)"),
    ("N", "next", "next neuron (lowest confidence first)"),
    ("Shift-N", "previous", "previous neuron"),
    ("Control-Z", "undo", "undo"),
    ("Control-Shift-Z", "redo", "redo"),
)


class _Failed:
    """What a job returns when the core raised an FdlcError."""

    def __init__(self, exc: FdlcError):
        self.exc = exc


class _Signals(QObject):
    progress = Signal(float, str)  # emitted from the worker thread, delivered on the GUI thread
    idle = Signal()  # the job has ended (emitted on the GUI thread)


def _shown_conf(conf: float) -> str:
    """A confidence to two decimals, rounded down: one shown as the threshold is not below it
    (0.8584 read "0.86" beside a threshold of 0.86, and its name was hidden as below it)."""
    return f"{np.floor(conf * 100 + 1e-9) / 100:.2f}"


class AutoLabelWidget(QWidget):
    """Auto-label dock widget; see the module docstring for the scripting interface."""

    def __init__(self, napari_viewer: "napari.viewer.Viewer", parent: QWidget | None = None):
        super().__init__(parent)
        # napari hands plugins a proxy of the viewer; layer identity (``is``) needs the real one
        self.viewer = getattr(napari_viewer, "__wrapped__", napari_viewer)
        self.session: ReviewSession | None = None
        self.layer = None  # the neuron-ID Points layer
        self._open_sessions = _sessions_shown_in(self.viewer)
        self.identifier = None  # None: the shipped model (napari_fdlc.identify.default_identifier)
        self.last_error: str | None = None
        self._job_error: str | None = None  # the running (or last) job's own failure
        self._script_templates: list[NeuronTable] | None = None
        self._file_templates: dict[str, NeuronTable] = {}
        self._file_template_paths: dict[str, Path] = {}
        self._template_before: tuple[str, object] = (BUILTIN, None)  # restored when a template file is not taken
        self._worker = None
        self._busy = False
        self._stack = None  # the Stack of the last run (colours of points added by hand)
        self._released = False  # closed (see _release_viewer)
        self._roles_off: set[str] = set()  # channels the user set to (none): never guessed again
        self._guard = 0  # > 0 while the widget itself changes layers / controls
        self._known_names: list[str] | None = None
        self._bound: list = []  # key-binding providers (the viewer, neuron-ID layers)
        self._signals = _Signals()
        self._signals.progress.connect(self._on_progress)
        self._build_ui()
        self._apply_preferences()
        self._connect_viewer()
        self._refresh_choices()
        self._adopt_existing()
        self._refresh_all()
        self._warming: threading.Thread | None = None
        QTimer.singleShot(0, self._warm_up)

    def _warm_up(self) -> None:
        """Name a generated worm as the user's will be (:func:`napari_fdlc.identify.warm_up`,
        ~1.5 s on two cores with torch's import, the panel's caches and the traces) in a thread
        (see ``_warm_up.py``); a job that starts first warms the model itself."""
        if self._busy or self._warming is not None:
            return
        identifier, chirality = self.identifier, self.chirality_combo.currentData()
        use_colour = self.colour_check.isChecked()
        try:
            templates = self._templates()[0]
        except FdlcError:
            templates = None

        def warm():
            from ..identify import warm_up

            warm_up(_with_chirality(identifier, chirality), templates, use_colour)

        self._warming = start_warm_up(warm)

    def _apply_preferences(self) -> None:
        """The handedness, nucleus diameter and colour choice of the last napari session: a
        microscope's handedness is set once, not every time napari opens (held-out SF, whose
        recordings are mostly mirrored: 12.0 % one worm at a time on `auto`, 63.1 % with the
        lab's handedness set; docs/leave_one_lab_out.md). Every later change is saved at once."""
        prefs = load_preferences()
        index = self.chirality_combo.findData(prefs.get("handedness"))
        if index >= 0:
            self.chirality_combo.setCurrentIndex(index)
        diameter = prefs.get("diameter_um")
        if isinstance(diameter, (int, float)) and self.diameter_spin.minimum() <= diameter <= self.diameter_spin.maximum():
            self.diameter_spin.setValue(float(diameter))
        if isinstance(prefs.get("colour"), bool):
            self.colour_check.setChecked(prefs["colour"])
        self.chirality_combo.currentIndexChanged.connect(self._save_preferences)
        self.diameter_spin.valueChanged.connect(self._save_preferences)
        self.colour_check.toggled.connect(self._save_preferences)

    def _save_preferences(self, *_) -> None:
        save_preferences({**load_preferences(), "handedness": self.chirality_combo.currentData(),
                          "diameter_um": float(self.diameter_spin.value()), "colour": self.colour_check.isChecked()})

    # =========================================================================================
    # UI
    def _build_ui(self) -> None:
        outer = QVBoxLayout(self)
        outer.setContentsMargins(0, 0, 0, 0)
        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        outer.addWidget(scroll)
        body = QWidget()
        scroll.setWidget(body)
        layout = QVBoxLayout(body)

        # --- input -----------------------------------------------------------------------------
        box = QGroupBox("Image and neurons")
        form = QFormLayout(box)
        self.role_combos: dict[str, QComboBox] = {}
        for role, text in zip(ROLES, ("R (mNeptune)", "G (CyOFP)", "B (BFP)", "W (TagRFP-T)")):
            combo = _combo()
            combo.setToolTip(f"image layer holding the {text} channel")
            self.role_combos[role] = combo
            combo.activated.connect(lambda _index, role=role: self._on_role_activated(role))
            form.addRow(text, combo)
        self.neurons_combo = _combo()
        self.neurons_combo.setToolTip("detect nuclei in the image, or use the points of an existing layer")
        form.addRow("Neurons", self.neurons_combo)
        self.diameter_spin = QDoubleSpinBox()
        self.diameter_spin.setRange(1.0, 10.0)
        self.diameter_spin.setSingleStep(0.5)
        self.diameter_spin.setValue(3.0)
        self.diameter_spin.setSuffix(" µm")
        form.addRow("Nucleus diameter", self.diameter_spin)
        self.voxel_edit = QLineEdit()
        self.voxel_edit.setToolTip("the chosen image's voxel size z, y, x in µm (its layers' scale): set it\n"
                                   "when the file does not say it, or says it wrong")
        self.voxel_edit.returnPressed.connect(lambda: self._gui(self._on_voxel_entered))
        voxel_button = QPushButton("Set")
        voxel_button.clicked.connect(lambda: self._gui(self._on_voxel_entered))
        voxel_row = QHBoxLayout()
        voxel_row.addWidget(self.voxel_edit)
        voxel_row.addWidget(voxel_button)
        form.addRow("Voxel size", voxel_row)
        layout.addWidget(box)

        box = QGroupBox("Template")
        form = QFormLayout(box)
        self.template_combo = _combo()
        self.template_combo.setToolTip("where names come from: the built-in reference panel, or a labelled worm")
        self.template_combo.activated.connect(self._on_template_activated)
        self.template_combo.currentIndexChanged.connect(self._on_template_changed)
        form.addRow("Names from", self.template_combo)
        self.colour_check = QCheckBox("use NeuroPAL colour")
        self.colour_check.setChecked(True)
        form.addRow("", self.colour_check)
        self.chirality_combo = QComboBox()
        for value, text in CHIRALITY_CHOICES:
            self.chirality_combo.addItem(text, value)
        self.chirality_combo.setToolTip(
            "a recording mirrored by its acquisition (flipped z) swaps every left/right pair, and the\n"
            "image cannot tell: set it if you know your microscope ('fdlc handedness' reads it from worms\n"
            "you have labelled), or fix one left/right neuron and Re-label")
        form.addRow("Handedness", self.chirality_combo)
        layout.addWidget(box)

        row = QHBoxLayout()
        self.run_button = QPushButton("Auto-label")
        self.run_button.setToolTip("detect (if asked) and name every neuron; your decisions are kept")
        self.run_button.clicked.connect(lambda: self._gui(self.auto_label, wait=False))
        self.relabel_button = QPushButton("Re-label")
        self.relabel_button.setToolTip("name the other neurons again, with your decisions fixed as constraints")
        self.relabel_button.clicked.connect(lambda: self._gui(self.relabel, wait=False))
        row.addWidget(self.run_button)
        row.addWidget(self.relabel_button)
        layout.addLayout(row)
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 100)
        self.progress_bar.setValue(0)
        self.progress_bar.setTextVisible(True)
        self.progress_bar.setFormat("")
        layout.addWidget(self.progress_bar)

        # --- threshold ---------------------------------------------------------------------------
        box = QGroupBox("Confidence threshold")
        grid = QGridLayout(box)
        self.threshold_slider = QSlider(Qt.Orientation.Horizontal)
        self.threshold_slider.setRange(0, 100)
        self.threshold_slider.setValue(int(round(DEFAULT_THRESHOLD * 100)))
        self.threshold_slider.valueChanged.connect(self._on_slider)
        self.threshold_slider.sliderReleased.connect(lambda: self.session.autosave() if self.session is not None else None)
        self.threshold_label = QLabel(f"{DEFAULT_THRESHOLD:.2f}")
        self.coverage_label = QLabel("")
        self.coverage_label.setWordWrap(True)
        self.hide_check = QCheckBox("hide points without a shown name")
        self.hide_check.toggled.connect(lambda _: self._refresh_layer())
        grid.addWidget(self.threshold_slider, 0, 0)
        grid.addWidget(self.threshold_label, 0, 1)
        grid.addWidget(self.coverage_label, 1, 0, 1, 2)
        grid.addWidget(self.hide_check, 2, 0, 1, 2)
        layout.addWidget(box)

        # --- review ------------------------------------------------------------------------------
        box = QGroupBox("Review")
        v = QVBoxLayout(box)
        self.current_label = QLabel("select a neuron")
        self.current_label.setWordWrap(True)
        v.addWidget(self.current_label)
        form = QFormLayout()
        self.candidate_combo = _combo()
        self.candidate_combo.setToolTip("top-3 candidates with probabilities: choose one to give it")
        self.candidate_combo.activated.connect(self._on_candidate_activated)
        form.addRow("Candidates", self.candidate_combo)
        self.name_edit = QLineEdit()
        self.name_edit.setPlaceholderText("type a name, Enter (AVAL? = unsure)")
        self.name_edit.returnPressed.connect(self._on_name_entered)
        self._completer = QCompleter([])
        self._completer.setCaseSensitivity(Qt.CaseSensitivity.CaseInsensitive)
        self._completer.setFilterMode(Qt.MatchFlag.MatchStartsWith)
        self.name_edit.setCompleter(self._completer)
        form.addRow("Name", self.name_edit)
        v.addLayout(form)
        grid = QGridLayout()
        self.accept_button = QPushButton("Accept (A)")
        self.unsure_button = QPushButton("Unsure (U)")
        self.clear_button = QPushButton("Clear (C)")
        self.prev_button = QPushButton("◀ Prev (⇧N)")
        self.next_button = QPushButton("Next (N) ▶")
        self.undo_button = QPushButton("Undo")
        self.redo_button = QPushButton("Redo")
        self.undo_button.setToolTip("Ctrl-Z")
        self.redo_button.setToolTip("Ctrl-Shift-Z")
        self.accept_button.clicked.connect(lambda: self._on_current(self.accept))
        self.unsure_button.clicked.connect(lambda: self._on_current(self.mark_unsure))
        self.clear_button.clicked.connect(lambda: self._on_current(self.clear))
        self.prev_button.clicked.connect(lambda: self._gui(self.previous_neuron))
        self.next_button.clicked.connect(lambda: self._gui(self.next_neuron))
        self.undo_button.clicked.connect(lambda: self._gui(self.undo))
        self.redo_button.clicked.connect(lambda: self._gui(self.redo))
        for k, b in enumerate((self.accept_button, self.unsure_button, self.clear_button)):
            grid.addWidget(b, 0, k)
        grid.addWidget(self.prev_button, 1, 0)
        grid.addWidget(self.next_button, 1, 1)
        grid.addWidget(self.undo_button, 2, 0)
        grid.addWidget(self.redo_button, 2, 1)
        v.addLayout(grid)
        self.neuron_table = QTableWidget(0, 4)
        self.neuron_table.setHorizontalHeaderLabels(["#", "name", "conf", "status"])
        self.neuron_table.verticalHeader().setVisible(False)
        self.neuron_table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.neuron_table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.neuron_table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.neuron_table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.Stretch)
        self.neuron_table.setMinimumHeight(180)
        self.neuron_table.setToolTip("neurons by confidence, lowest first: click one to go there")
        self.neuron_table.cellClicked.connect(self._on_table_clicked)
        v.addWidget(QLabel("Neurons, lowest confidence first"))
        v.addWidget(self.neuron_table)
        layout.addWidget(box)

        # --- export --------------------------------------------------------------------------------
        box = QGroupBox("Export")
        h = QHBoxLayout(box)
        self.export_button = QPushButton("CSV…")
        self.export_button.setToolTip("neuron table with final names, automatic and user columns, µm and voxel coordinates")
        self.export_npid_button = QPushButton("NeuroPAL_ID CSV…")
        self.export_button.clicked.connect(lambda: self._export_dialog("fdlc"))
        self.export_npid_button.clicked.connect(lambda: self._export_dialog("neuropal_id"))
        h.addWidget(self.export_button)
        h.addWidget(self.export_npid_button)
        layout.addWidget(box)
        self.session_label = QLabel("")
        self.session_label.setWordWrap(True)
        self.session_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        layout.addWidget(self.session_label)

        # --- help --------------------------------------------------------------------------------
        self.help_box = QGroupBox("Keys (with the neuron-ID layer selected)")
        self.help_box.setCheckable(True)
        self.help_box.setChecked(True)
        hv = QVBoxLayout(self.help_box)
        rows = "".join(f"<tr><td><b>{k.replace('Control', 'Ctrl')}</b></td><td>{text}</td></tr>" for k, _, text in KEYS)
        legend = " ".join(
            f"<span style='color:{STATUS_HEX[s]}'>●</span> {s}"
            for s in ("auto", "accepted", "corrected", "unsure", "hidden")
        )
        self.help_label = QLabel(
            f"<table>{rows}</table><p>Rings: {legend} (below threshold / no name).<br>"
            "Every edit is saved at once; reopening the image restores the session.</p>"
        )
        self.help_label.setWordWrap(True)
        hv.addWidget(self.help_label)
        self.help_box.toggled.connect(self.help_label.setVisible)
        layout.addWidget(self.help_box)
        layout.addStretch(1)
        self.setSizePolicy(QSizePolicy.Policy.Preferred, QSizePolicy.Policy.Expanding)
        self.setMinimumWidth(300)

    # =========================================================================================
    # viewer wiring
    def _connect_viewer(self) -> None:
        layers = self.viewer.layers
        layers.events.inserted.connect(self._on_layer_inserted)
        layers.events.removed.connect(self._on_layer_removed)
        layers.events.changed.connect(self._refresh_choices)
        for layer in layers:
            layer.events.name.connect(self._refresh_choices)
        self._bind_keys(self.viewer)

    def event(self, e) -> bool:
        # napari closes a dock by taking the widget out of it: then let go of the viewer
        if e.type() == QEvent.Type.ParentChange:
            if self.parent() is not None:
                self._docked = True
            elif getattr(self, "_docked", False):
                self._release_viewer()
        return super().event(e)

    def _release_viewer(self) -> None:
        """Unbind the keys and disconnect from the viewer (the widget was closed). A job still
        running is left to end, and its result is dropped: a widget docked again must not find
        a layer that the closed one links to itself."""
        self._released = True
        for provider in self._bound:
            for key, _action, _text in KEYS:
                try:
                    provider.bind_key(key, None)
                except (KeyError, ValueError, TypeError):
                    pass
        self._bound = []
        layers = self.viewer.layers
        pairs = [
            (layers.events.inserted, self._on_layer_inserted),
            (layers.events.removed, self._on_layer_removed),
            (layers.events.changed, self._refresh_choices),
        ] + [(layer.events.name, self._refresh_choices) for layer in layers]
        for signal, slot in pairs:
            try:
                signal.disconnect(slot)
            except (TypeError, RuntimeError, ValueError):
                pass
        if self.layer is not None:
            self._disconnect_layer(self.layer)
        if self.session is not None:
            self.session.disconnect(self._on_session)

    def _bind_keys(self, provider) -> None:
        actions: dict[str, Callable[[], object]] = {
            "accept": lambda: self._on_current(self.accept),
            "pick_1": lambda: self._on_current(lambda i: self.pick_candidate(i, 1)),
            "pick_2": lambda: self._on_current(lambda i: self.pick_candidate(i, 2)),
            "pick_3": lambda: self._on_current(lambda i: self.pick_candidate(i, 3)),
            "unsure": lambda: self._on_current(self.mark_unsure),
            "clear": lambda: self._on_current(self.clear),
            "type_name": self._focus_name,
            "next": lambda: self._gui(self.next_neuron),
            "previous": lambda: self._gui(self.previous_neuron),
            "undo": lambda: self._gui(self.undo),
            "redo": lambda: self._gui(self.redo),
        }
        for key, action, _ in KEYS:
            provider.bind_key(key, lambda obj=None, fn=actions[action]: self._on_key(obj, fn), overwrite=True)
        self._bound.append(provider)

    def _on_key(self, provider, action: Callable[[], object]) -> None:
        """A review key: pressed on the neuron-ID layer of another worm (one reviewed earlier
        in this viewer), it reviews that worm first, so the key acts on the neuron selected there."""
        meta = (getattr(provider, "metadata", None) or {}).get(META_KEY) or {}
        if _is_points(provider) and provider is not self.layer and meta.get("session"):
            if self._busy:
                self._gui(self._check_idle)
                return
            self._gui(self._adopt, provider)
            if self.layer is not provider:
                return
        action()

    def _focus_name(self) -> None:
        self.name_edit.setFocus()
        self.name_edit.selectAll()

    def _on_layer_inserted(self, event) -> None:
        layer = event.value
        layer.events.name.connect(self._refresh_choices)
        self._refresh_choices()
        if self._guard:
            return
        meta = (layer.metadata or {}).get(META_KEY) or {}
        if _is_points(layer) and meta.get("session"):
            if self._under_review(meta["session"]):
                # a copy of the neuron-ID layer (Duplicate Layer): a plain points layer, not a
                # second view of the session under review
                with self._guarded():
                    layer.metadata = {k: v for k, v in layer.metadata.items() if k != META_KEY}
                return
            self._gui(self._adopt, layer)
        elif is_image_layer(layer):
            # after the reader's other layers (a restored session layer comes right after)
            QTimer.singleShot(0, lambda: self._restore_for_image(layer))

    def _under_review(self, session_path: str) -> bool:
        """Whether the session of ``session_path`` is the one under review, in a layer that is
        still in the viewer."""
        return (self.session is not None and self.session.path is not None and str(self.session.path) == str(session_path)
                and self.layer is not None and self.layer in self.viewer.layers)

    def _on_layer_removed(self, event) -> None:
        if event.value is self.layer:
            self._unlink()
        if self._stack is not None and is_image_layer(event.value) and not any(
                is_image_layer(layer) and image_key_of(layer) == self._stack.source for layer in self.viewer.layers):
            self._stack = None  # its image is closed: do not keep a copy of it
        self._refresh_choices()

    def _adopt_existing(self) -> None:
        """Docked into a viewer with layers: review a neuron-ID layer there, or bring back the
        saved session of an image opened by another reader."""
        for layer in self.viewer.layers:
            meta = (layer.metadata or {}).get(META_KEY) or {}
            if _is_points(layer) and meta.get("session"):
                self._gui(self._adopt, layer)
        if self.layer is None:
            for layer in list(self.viewer.layers):
                if is_image_layer(layer):
                    self._restore_for_image(layer)

    def _restore_for_image(self, image_layer) -> None:
        """An image with a saved session but no neuron-ID layer (opened by another reader):
        bring the session back."""
        from ._io import restored_session_layer

        if self._busy or image_layer not in self.viewer.layers:
            return
        key = image_key_of(image_layer)
        for layer in self.viewer.layers:
            meta = (layer.metadata or {}).get(META_KEY) or {}
            if _is_points(layer) and meta.get("image") == key and meta.get("session"):
                return
        restored = restored_session_layer(key, tuple(image_layer.data.shape[-3:]),
                                          voxel_zyx=tuple(float(v) for v in image_layer.scale[-3:]),
                                          time_axis=layer_time_axis(image_layer))
        if restored is not None:
            data, kwargs, _ = restored
            layer = self.viewer.add_points(data, **kwargs)  # inserted -> adopted
            self._notify_info(f"restored the saved session of {_short_name(key)} ({kwargs['metadata'][META_KEY]['session']})")
            return layer

    # =========================================================================================
    # choices in the combo boxes
    def _refresh_choices(self, *_) -> None:
        """Rebuild the combo boxes from the viewer's layers. Each layer item carries its layer,
        so a choice follows the layer when it is renamed; a channel the user turned off stays
        off (``_roles_off``); one never chosen is guessed from the layers' roles."""
        images = [layer for layer in self.viewer.layers if is_image_layer(layer)]
        points = [layer for layer in self.viewer.layers if _is_points(layer)]
        with self._guarded():
            for role, combo in self.role_combos.items():
                chosen = combo.currentData()
                _fill(combo, [(NONE, None)] + [(layer.name, layer) for layer in images])
                if chosen is None and role not in self._roles_off:
                    chosen = next((layer for layer in images if layer_role(layer) == role), None)
                _choose(combo, chosen, NONE)
            chosen = self.neurons_combo.currentData()
            _fill(self.neurons_combo, [(SEGMENT, None)] + [(layer.name, layer) for layer in points])
            _choose(self.neurons_combo, chosen, SEGMENT)
            current, chosen = self.template_combo.currentText(), self.template_combo.currentData()
            items = [(SCRIPTED, None)] if self._script_templates is not None else []
            items += [(BUILTIN, None)]
            items += [(f"layer: {layer.name}", layer) for layer in points if layer is not self.layer and named_count(layer) > 0]
            items += [(name, None) for name in self._file_templates] + [(FROM_FILE, None)]
            _fill(self.template_combo, items)
            texts = [text for text, _ in items]
            fallback = (current if current in texts and current != FROM_FILE and not current.startswith("layer: ")
                        else SCRIPTED if self._script_templates is not None else BUILTIN)
            _choose(self.template_combo, chosen, fallback)
        self._show_voxel_size()

    def _on_role_activated(self, role: str) -> None:
        """The user chose a channel's layer, or turned the channel off."""
        if self.role_combos[role].currentText() == NONE:
            self._roles_off.add(role)
        else:
            self._roles_off.discard(role)
        self._show_voxel_size()

    def _show_voxel_size(self) -> None:
        images = self._chosen_images()
        layer = images.get("W") or next(iter(images.values()), None)
        unknown = layer is not None and voxel_unknown(layer)
        # every digit the file gave (Set on the text shown must not round the voxel size)
        self.voxel_edit.setText("" if layer is None or unknown else " ".join(f"{v:.12g}" for v in layer.scale[-3:]))
        self.voxel_edit.setPlaceholderText("not in the file: z y x (µm)" if unknown else "z y x (µm)")

    def _on_voxel_entered(self) -> None:
        text = self.voxel_edit.text().replace(",", " ").replace("×", " ").split()
        try:
            values = [float(v) for v in text]
        except ValueError:
            values = []
        if len(values) != 3:
            raise FdlcError(f"voxel size '{self.voxel_edit.text()}': give three numbers z y x in µm")
        self.set_voxel_size(*values)

    def _on_template_changed(self, index: int) -> None:
        """Remember the template chosen (not while the combo is refilled), for a file dialog left
        without a file."""
        if not self._guard and index >= 0 and self.template_combo.itemText(index) != FROM_FILE:
            self._template_before = (self.template_combo.itemText(index), self.template_combo.itemData(index))

    def _on_template_activated(self, index: int) -> None:
        if self.template_combo.itemText(index) != FROM_FILE:
            return
        text, data = self._template_before
        path, _ = QFileDialog.getOpenFileName(self, "Labelled neuron table", "", "CSV (*.csv);;All files (*)")
        if not path or self._gui(self.add_template_file, path) is None:
            # cancelled, or a file that cannot be a template: the template chosen before stays
            # (the built-in panel took its place, or 'Labelled table file…' stayed and ran as it)
            self._refresh_choices()
            with self._guarded():
                _choose(self.template_combo, data, text if self.template_combo.findText(text) >= 0 else BUILTIN)

    # =========================================================================================
    # scripting API: inputs
    def set_templates(self, templates) -> None:
        """Use these labelled worms as templates (NeuronTables or CSV paths); ``None`` goes back
        to the built-in reference panel."""
        from ..table import read_table

        if templates is None:
            self._script_templates = None
        else:
            tables = [read_table(t) if isinstance(t, (str, Path)) else t for t in templates]
            for t in tables:
                if not isinstance(t, NeuronTable):
                    raise FdlcError(f"template {t!r}: give a NeuronTable or a CSV path")
                if not t.named.any():
                    raise FdlcError(f"{t.source}: the template has no named neuron")
            from ..identify import harmonise

            self._script_templates = harmonise(tables, report=self._notify_warning)
        self._known_names = None
        self._refresh_choices()
        self._refresh_completer()  # their names offered at once, not after the next edit
        self.template_combo.setCurrentText(SCRIPTED if templates is not None else BUILTIN)

    def add_template_file(self, path) -> str:
        """Read a labelled neuron table and offer it as a template (and choose it)."""
        from ..table import implausible_scale, read_table

        with warnings_to(self._notify_warning):
            table = read_table(path)
        if not table.named.any():
            raise FdlcError(f"{path}: the table has no named neuron; a template needs names")
        reason = implausible_scale(table)
        if reason:  # a table in nm or mm is read, but names come out meaningless: say why
            self._notify_warning(reason)
        # by the file: two of one name in different folders (rig1/worm1.csv, rig2/worm1.csv) are two
        resolved, name = Path(path).resolve(), f"file: {Path(path).name}"
        if self._file_template_paths.get(name, resolved) != resolved:
            name = f"file: {Path(path).parent.name}/{Path(path).name}"
            for n in itertools.count(2):
                if self._file_template_paths.get(name, resolved) == resolved:
                    break
                name = f"file: {Path(path).parent.name}/{Path(path).name} [{n}]"
        self._file_templates[name] = table
        self._file_template_paths[name] = resolved
        self._known_names = None
        self._refresh_choices()
        self._refresh_completer()  # its names offered at once, not after the next edit
        self.template_combo.setCurrentText(name)
        return name

    def set_channels(self, **roles) -> None:
        """Choose the image layer of each role, e.g. ``set_channels(R='red', W='white')``."""
        for role, name in roles.items():
            if role not in self.role_combos:
                raise FdlcError(f"channel role {role}: use R, G, B or W")
            name = getattr(name, "name", name) or NONE
            if self.role_combos[role].findText(name) < 0:
                raise FdlcError(f"no image layer named '{name}'")
            self.role_combos[role].setCurrentText(name)
            self._on_role_activated(role)

    def set_voxel_size(self, z: float, y: float, x: float) -> None:
        """Set the chosen image's voxel size (µm): the scale of every layer of the chosen
        channels' files (and of the neurons an NWB file holds, on its voxels), e.g. when a file
        does not say it (shown in pixels until then) or says it wrong. Kept by the image's
        session, so that the file opened again takes it."""
        self._check_idle()  # a labelling running placed its neurons at the size it read
        values = np.array([z, y, x], dtype=float)
        if not (np.all(np.isfinite(values)) and np.all(values > 0)):
            raise FdlcError(f"voxel size {z} {y} {x}: give three positive numbers z y x in µm")
        images = self._chosen_images()
        if not images:
            raise FdlcError("no image chosen: pick its channel layers first, then set the voxel size")
        keys = {image_key_of(layer) for layer in images.values()}
        chosen = [layer for layer in self.viewer.layers if is_image_layer(layer) and image_key_of(layer) in keys]
        if all(np.allclose(layer.scale[-3:], values, rtol=1e-9, atol=0) and not voxel_unknown(layer) for layer in chosen):
            return  # as it is (Set pressed on what the row shows)
        placed = []  # neurons placed in µm at the current voxel size: a new one would move them off
        for layer in self.viewer.layers:
            meta = (layer.metadata or {}).get(META_KEY) or {}
            if meta.get("image") in keys and (meta.get("session") or meta.get("tracks")):
                raise FdlcError(f"'{layer.name}' holds neurons placed at this image's voxel size: a new one would "
                                "move them off their nuclei")
            if meta.get("image") in keys and _is_points(layer):
                placed.append(layer)  # in the image's voxels (an NWB file's neurons): moved with it
        for layer in chosen + placed:
            layer.scale = (*layer.scale[:-3], *values)
            meta = dict((layer.metadata or {}).get(META_KEY) or {})
            meta.pop("voxel_stand_in", None)
            layer.metadata = {**(layer.metadata or {}), META_KEY: {**meta, "voxel_set": True}}
        self._show_voxel_size()

    def set_neurons(self, source) -> None:
        """Where neurons come from: ``'segment'`` or a Points layer (or its name)."""
        name = SEGMENT if source in (None, "segment", SEGMENT) else getattr(source, "name", source)
        if self.neurons_combo.findText(name) < 0:
            raise FdlcError(f"no points layer named '{name}'")
        self.neurons_combo.setCurrentText(name)

    def set_template(self, choice: str) -> None:
        """Choose the template entry: 'builtin', 'script', a layer name, or a file entry."""
        text = {"builtin": BUILTIN, "script": SCRIPTED}.get(choice, choice)
        if self.template_combo.findText(text) < 0:
            text = f"layer: {choice}"
        if self.template_combo.findText(text) < 0:
            raise FdlcError(f"no template '{choice}'")
        self.template_combo.setCurrentText(text)

    def _chosen_images(self) -> dict[str, object]:
        out = {}
        for role, combo in self.role_combos.items():
            name = combo.currentText()
            if name and name != NONE and name in self.viewer.layers:
                out[role] = self.viewer.layers[name]
        return out

    def _make_stack(self, images: dict[str, object]):
        key_layer = images.get("W") or next(iter(images.values()), None)
        return stack_from_layers(images, image_key_of(key_layer) if key_layer is not None else "")

    def _templates(self):
        """(templates or None for the built-in panel, description)."""
        text = self.template_combo.currentText()
        if text == SCRIPTED and self._script_templates is not None:
            return self._script_templates, f"{len(self._script_templates)} template(s) given by script"
        if text.startswith("layer: "):
            name = text[len("layer: "):]
            if name not in self.viewer.layers:
                raise FdlcError(f"template layer '{name}' is gone; choose another template")
            return [table_from_layer(self.viewer.layers[name], use_label=True)], text
        if text in self._file_templates:
            return [self._file_templates[text]], text
        return None, BUILTIN

    # =========================================================================================
    # scripting API: running
    @property
    def busy(self) -> bool:
        return self._busy

    def auto_label(self, wait: bool = True):
        """Detect (or take) the neurons, name them, and show the result in one Points layer.

        User decisions already made on this image are kept and passed as constraints. With
        ``wait`` (default) returns the layer once it holds the result (None on error); without,
        returns at once (the Auto-label button) — call :meth:`wait` to block.
        """
        self._check_idle()
        images = self._chosen_images()
        source = self.neurons_combo.currentText()
        with warnings_to(self._notify_warning):  # a template layer's repeated name, said in napari
            templates, template_text = self._templates()
        use_colour = self.colour_check.isChecked()
        diameter = float(self.diameter_spin.value())
        identifier, chirality = self.identifier, self.chirality_combo.currentData()
        # The channels are stacked (a copy of every one) in the worker, not on the GUI thread.
        image_key = base_name = None
        voxel_set = False  # the voxel size set in the widget, not the file's: the session keeps it
        if images:
            key_layer = images.get("W") or next(iter(images.values()))
            voxel_set = bool(((key_layer.metadata or {}).get(META_KEY) or {}).get("voxel_set"))
            image_key = image_key_of(key_layer)
            # kept with the layer: an image made in napari is known by its name, which the user may change
            key_layer.metadata = {**(key_layer.metadata or {}),
                                  META_KEY: {**((key_layer.metadata or {}).get(META_KEY) or {}), "image": image_key}}
            base_name = ((key_layer.metadata or {}).get(META_KEY) or {}).get("stack_name")

        own = source != SEGMENT and self.layer is not None and source == self.layer.name and self.session is not None
        given_table = None
        decisions = {}
        if own:
            given_table = self.session.table
        elif source != SEGMENT:
            if source not in self.viewer.layers:
                raise FdlcError(f"no points layer '{source}'")
            points = self.viewer.layers[source]
            given_table = table_from_layer(points)
            _refuse_another_time_point(points, images)
            points_scale = tuple(float(v) for v in points.scale[-3:])
            decisions = decisions_from_frame(points.features) if len(points.features) == len(given_table) else {}
            if image_key is None:
                image_key = image_key_of(points)
        elif not images:
            flat = [layer.name for layer in self.viewer.layers if type(layer).__name__ == "Image" and not is_image_layer(layer)]
            if flat and not any(is_image_layer(layer) for layer in self.viewer.layers):
                raise FdlcError(f"Auto-label needs a 3D stack (z, y, x): '{flat[0]}' is a 2D image (a projection?); open the stack itself")
            raise FdlcError("no image chosen to detect nuclei in: pick the W (TagRFP-T) channel layer")
        previous = self.session if (self.session is not None and not own and self.session.image == image_key) else None
        unreadable = None  # why a saved session of this image could not be read
        if previous is None and not own and image_key is not None:
            previous, unreadable = _saved_session(image_key)  # e.g. the neuron-ID layer was deleted: keep its decisions
        # without an image: the voxels of the session, or of points of a table we exported
        voxel_without_image = self.session.voxel_size_zyx if own else None
        if voxel_without_image is None and source != SEGMENT and not own and not np.allclose(points_scale, 1.0):
            voxel_without_image = points_scale
        own_decisions = self.session.decisions() if own else None
        # snapshots: the worker thread never reads a session the user may be editing
        previous_snapshot = (previous.table.xyz.copy(), previous.decisions()) if previous is not None else None
        signals, warming = self._signals, self._warming

        def work():
            from ..identify import label_neurons
            from ..table import implausible_scale

            stack = stack_from_layers(images, image_key) if images else None
            table = given_table
            if table is None:
                from ..segment import segment_stack

                table = segment_stack(stack, diameter_um=diameter, progress=lambda f, m: signals.progress.emit(0.6 * f, m))
            elif stack is not None and not any(c in table.colours for c in ("R", "G", "B")):
                from ..segment import measure_colours

                signals.progress.emit(0.3, "reading colours")
                extent = (np.asarray(stack.shape_zyx) - 1) * np.asarray(stack.voxel_size_zyx)
                outside = int(np.sum(np.any((table.xyz[:, ::-1] < 0) | (table.xyz[:, ::-1] > extent), axis=1)))
                if outside:  # their colours would be read at the image's edge
                    warn(f"{outside} of the {len(table)} neurons of '{source}' lie outside the chosen image: their "
                         "colours are read at its edge; check that the points belong to this image")
                colours = {k: v for k, v in measure_colours(stack, table.xyz, radius_um=0.3 * diameter).items() if k in COLOUR_CHANNELS}
                table = NeuronTable(table.xyz, colours, extra=table.extra, source=table.source)
            if len(table) == 0:
                raise FdlcError("no nuclei found: check the W channel and the nucleus diameter")
            carried = dict(decisions)
            lost = 0  # earlier decisions the new detection lacks
            if previous_snapshot is not None and previous_snapshot[1]:
                from_previous = carry_decisions(previous_snapshot, table.xyz)
                lost = len(previous_snapshot[1]) - len(from_previous)
                carried.update(from_previous)
            if own_decisions is not None:
                carried = own_decisions
            fixed = {i: d.name for i, d in carried.items()}
            signals.progress.emit(0.65, f"naming {len(table)} neurons…")
            if warming is not None:  # one model, used by one thread at a time
                warming.join()
            labelling = label_neurons(table, templates, use_colour=use_colour, fixed=fixed or None,
                                      identifier=_with_chirality(identifier, chirality))
            signals.progress.emit(1.0, "done")
            return stack, table, labelling, carried, lost, implausible_scale(table)

        def done(result):
            stack, table, labelling, carried, lost, scale_warning = result
            if stack is not None:
                self._stack = stack
            voxel = stack.voxel_size_zyx if stack is not None else voxel_without_image
            settings = {"template": template_text, "colour": use_colour, "diameter_um": diameter}
            recording = next((layer for layer in images.values() if layer.data.ndim >= 4), None)
            if recording is not None:  # the names are drawn at the time point they name (the first)
                settings["time_axis"] = [float(recording.scale[-4]), float(recording.translate[-4])]
            if stack is not None:
                settings["voxel_size_set"] = voxel_set
            if own:
                if self.session is None or self.session.table is not given_table:
                    # the layer, or points of it, went while the job ran
                    raise FdlcError("the neurons changed while auto-labelling; run Auto-label again")
                self.session.settings.update(settings)
                self.session.set_labelling(labelling, "auto-label", fixed_rows=own_decisions or ())
            else:
                # The image's session as it is now: decisions made while the job ran are kept
                # too, also with its layer deleted meanwhile (then the snapshot's session)
                latest = self.session if self.session is not None and self.session.image == image_key else previous
                missing = 0
                if latest is not None:
                    during = carry_decisions(latest, table.xyz)
                    if latest is previous:  # the snapshot's session: its decisions as they are now
                        lost, carried = len(latest.decisions()) - len(during), {**decisions, **during}
                    else:
                        lost, carried = max(lost, len(latest.decisions()) - len(during)), {**carried, **during}
                    if given_table is None:  # neurons added or moved by hand, before or while the job ran
                        missing = _lacking(latest.table.xyz[latest.by_hand], table.xyz)
                self._new_session(table, labelling, carried, image_key, voxel, stack, settings, source, base_name,
                                  lost=lost, unreadable=unreadable, missing=missing, by_hand=given_table is not None)
            self._status(self._done_message(len(table), labelling))
            if scale_warning:  # e.g. a voxel size or points layer not in µm: names come out meaningless, say why
                self._notify_warning(scale_warning)

        return self._start(work, done, wait, "auto-label")

    def relabel(self, wait: bool = True):
        """Name the undecided neurons again with every user decision fixed as a constraint
        (``label_neurons(..., fixed=...)``); user decisions are never changed."""
        self._check_idle()
        session = self._need_session()
        with warnings_to(self._notify_warning):  # a template layer's repeated name, said in napari
            templates, template_text = self._templates()
        use_colour = self.colour_check.isChecked()
        identifier, chirality = self.identifier, self.chirality_combo.currentData()
        table = session.table
        fixed = session.fixed()
        signals, warming = self._signals, self._warming

        def work():
            from ..identify import label_neurons

            signals.progress.emit(0.1, f"re-labelling with {len(fixed)} fixed name(s)…")
            if warming is not None:
                warming.join()
            lab = label_neurons(table, templates, use_colour=use_colour, fixed=fixed or None,
                                identifier=_with_chirality(identifier, chirality))
            signals.progress.emit(1.0, "done")
            return lab

        def done(labelling):
            if self.session is not session or session.table is not table:  # (was a warning beside "done")
                raise FdlcError("the neurons changed while re-labelling; run Re-label again")
            session.settings.update({"template": template_text, "colour": use_colour})
            session.set_labelling(labelling, "re-label", fixed_rows=fixed)
            self._status(f"re-labelled ({len(fixed)} of your names fixed)")
            hint = self._handedness_hint(labelling, fixed, template_text, chirality)
            if hint:
                self._notify_info(hint)

        return self._start(work, done, wait, "re-label")

    @staticmethod
    def _done_message(neurons: int, labelling) -> str:
        """What Auto-label says when it is done: the neurons, and what the panel did with them."""
        beyond = neurons - labelling.info.get("head_window", neurons)
        taken_up = labelling.info.get("smaller_worm")
        return (f"done: {neurons} neurons" + (f"; {beyond} beyond the head get no name" if beyond else "")
                + (f"; named as a smaller worm than a young adult (positions ×{taken_up:.2f})" if taken_up else ""))

    def _handedness_hint(self, labelling, fixed: dict[int, str], template_text: str, chirality: str) -> str | None:
        """A hint when the user's left/right names placed the worm mirrored relative to the
        built-in atlas while Handedness is on auto: a microscope that mirrors z does so for
        every recording, and Handedness set once (it is kept) names the next ones right from
        the start (held-out SF: 12.0 % one worm at a time on auto, 63.1 % with it set)."""
        if template_text != BUILTIN or chirality != "auto" or not labelling.info.get("mirrored"):
            return None
        from ..reference import load_panel

        names = set(load_panel().atlas.names)
        swap = {"L": "R", "R": "L"}
        sided = [n for n in fixed.values() if n[-1:] in swap and n[:-1] + swap[n[-1]] in names]
        if not sided:
            return None
        return (f"your names ({', '.join(sorted(sided)[:3])}) put this recording mirrored relative to the "
                "atlas: if your microscope always mirrors z, set Handedness to 'mirrored' (it is kept "
                "for the next sessions); if you only corrected one neuron's side, Undo and decide a few "
                "more of its names first (one name cannot tell the two apart)")

    def wait(self, timeout: float | None = None) -> bool:
        """Block (processing GUI events) until the running job is done; True when idle."""
        return wait_until_idle(lambda: self._busy, self._signals.idle, timeout)

    def _check_idle(self) -> None:
        if self._busy:
            raise FdlcError("a job is still running; wait for it to finish")

    def _start(self, work, done, wait: bool, what: str):
        from napari.qt.threading import create_worker

        self.last_error = self._job_error = None
        warned: list[str] = []  # what the core warns about in the worker (stderr only), shown when it ends

        def guarded_work():
            with warnings_to(warned.append):
                try:
                    return work()
                except FdlcError as exc:  # shown as a one-line notification, not a traceback
                    return _Failed(exc)

        # _ignore_errors: an unexpected exception is shown by napari's notification (with its
        # traceback, it is a bug) instead of being re-raised in the GUI thread.
        worker = create_worker(guarded_work, _start_thread=False, _ignore_errors=True)
        self._worker = worker
        self._busy = True
        self._set_running(True, what)

        def on_returned(result):
            if self._released:  # the widget was closed while the job ran: its result is dropped
                return
            for message in dict.fromkeys(warned):  # e.g. "no W channel marked", once each
                self._notify_warning(message)
            if isinstance(result, _Failed):
                self._report_error(result.exc)
                self._job_error = self.last_error
                return
            try:
                done(result)
            except Exception as exc:  # noqa: BLE001 - shown in the widget, never a bare traceback
                self._report_error(exc)
                self._job_error = self.last_error

        def on_errored(exc):
            self.last_error = self._job_error = f"unexpected error ({type(exc).__name__}: {exc})"
            self._status(self.last_error)
            self._notify_warning(self.last_error)  # not on the progress bar alone

        def on_finished():
            self._busy = False
            self._worker = None
            self._set_running(False, what)
            self._signals.idle.emit()

        worker.returned.connect(on_returned)
        worker.errored.connect(on_errored)
        worker.finished.connect(on_finished)
        worker.start()
        if wait:
            self.wait()
            # the job's own outcome: an error said meanwhile (a mistyped voxel size) is not its failure
            return self.layer if self._job_error is None else None
        return worker

    def _set_running(self, running: bool, what: str) -> None:
        self.run_button.setEnabled(not running)
        self.relabel_button.setEnabled(not running and self.session is not None and self.session.labelled)
        if running:
            self.progress_bar.setValue(0)
            self.progress_bar.setFormat(f"{what}…")
        else:
            self.progress_bar.setValue(100 if self._job_error is None else 0)

    def _on_progress(self, fraction: float, message: str) -> None:
        self.progress_bar.setValue(int(round(100 * max(0.0, min(1.0, fraction)))))
        self.progress_bar.setFormat(f"{message} (%p%)")

    def _new_session(self, table, labelling, carried, image_key, voxel, stack, settings, source_name, base_name=None,
                     lost: int = 0, unreadable: str | None = None, missing: int = 0, by_hand: bool = False) -> None:
        """Show a new session; the session file it replaces is first set aside when it holds
        decisions the new one lacks (``lost`` of them could not be carried over), neurons it
        lacks (``missing``: added or moved by hand, none detected there now) or could not be read
        (``unreadable``): annotations are never lost. ``by_hand``: the neurons are the user's own
        (a points layer of theirs), not a detection."""
        key = image_key or f"layer:{source_name}"
        path = session_file_for(key)
        if lost or unreadable or missing:
            # the file the decisions live in (the user's folder, after a save beside the image
            # failed) and the one the new session will write
            kept = None
            for old in dict.fromkeys(p for p in (find_session(key), path) if p is not None):
                try:
                    aside = set_aside(old)
                    kept = kept or aside
                except FdlcError as exc:  # e.g. a read-only folder: the old file stays as it is
                    self._notify_warning(str(exc))
                    if old == path:
                        path = user_session_file(key)
            where = f"; the earlier session is kept in {kept}" if kept else ""
            if unreadable:
                self._notify_warning(f"the saved session of this image could not be read ({unreadable}){where}")
            if lost:
                self._notify_warning(f"{lost} of your decisions had no neuron within 1.5 µm in the new detection "
                                     f"and were not carried over{where}")
            if missing:
                self._notify_warning(f"{missing} neuron(s) you added, moved or brought in the earlier session have no "
                                     f"neuron within 1.5 µm in the new detection and are not in it{where}")
        session = ReviewSession(
            table, labelling, threshold=self.threshold, voxel_size_zyx=voxel, image=key, path=path, by_hand=by_hand
        )
        session.settings.update(settings)
        if stack is not None:
            session.settings["image_shape"] = list(stack.shape_zyx)
        # The image's neuron-ID layer is reused (also when another worm was reviewed since): one per image
        old_layer = next((layer for layer in self.viewer.layers
                          if type(layer).__name__ == "Points" and ((layer.metadata or {}).get(META_KEY) or {}).get("image") == key
                          and ((layer.metadata or {}).get(META_KEY) or {}).get("session")), None)
        name = old_layer.name if old_layer is not None else \
            f"{base_name or _short_name(key.split(':')[-1] if key.startswith('layer:') else key)}{RESULT_SUFFIX}"
        session.settings["layer_name"] = name
        if carried:
            session.seed_decisions(carried)
        session.autosave()
        self._link(session, old_layer)
        if source_name != SEGMENT and source_name in self.viewer.layers and self.viewer.layers[source_name] is not self.layer:
            self.viewer.layers[source_name].visible = False
        if session.last_save_error:
            self._notify_warning(session.last_save_error)
        elif session.path != path:  # its first save already went to the user's folder
            self._on_session("save_moved", None)

    # =========================================================================================
    # session <-> layer
    def _adopt(self, layer) -> None:
        meta = (layer.metadata or {}).get(META_KEY) or {}
        path = meta.get("session")
        if layer is self.layer:
            return
        # A session reviewed before in this napari is taken up with its undo history (it autosaved
        # every edit, so the file says the same); another is read from its file.
        session = self._open_sessions.get(str(path))
        if session is None:  # (one left with no neurons is still the one with the undo history)
            session = ReviewSession.load(path)
        self._link(session, layer, catch_up=True)
        self._status(f"restored {Path(path).name}")

    def _link(self, session: ReviewSession, layer=None, catch_up: bool = False) -> None:
        """Show ``session`` in ``layer`` (a new Points layer when None). ``catch_up``: ``layer``
        is this session's own, perhaps edited while no widget followed it (:meth:`_catch_up`)."""
        if self.session is not None:
            self.session.disconnect(self._on_session)
        if self.layer is not None:
            self._disconnect_layer(self.layer)
        self.session = session
        # the slider's step: a saved 0.555 applied while the slider showed 0.56 (the next run used 0.56)
        session.set_threshold(round(session.threshold, 2), save=False)
        if session.path is not None:
            self._open_sessions[str(session.path)] = session
        meta = {"session": str(session.path) if session.path else None, "image": session.image}
        if layer is None:
            data, kwargs, _ = review_points(session, session.settings.get("layer_name", "neuron IDs"), meta)
            with self._guarded():
                layer = self.viewer.add_points(data, **kwargs)
        else:
            with self._guarded():
                layer.metadata = {**(layer.metadata or {}), META_KEY: meta}
                wanted = session_time_axis(session)
                if wanted is not None and layer.ndim == 4 and not catch_up:  # a new labelling on the image's layer
                    layer.scale = (wanted[0], *layer.scale[1:])
                    layer.translate = (wanted[1], *layer.translate[1:])
        if layer_time_axis(layer) is not None:  # where the names are drawn (e.g. restored on a
            # recording opened again, or reused by a labelling from positions alone)
            session.settings["time_axis"] = list(layer_time_axis(layer))
        self.layer = layer
        session.connect(self._on_session)
        layer.events.data.connect(self._on_layer_data)
        layer.events.name.connect(_record_layer_name)  # stays connected: renamed with the dock closed too
        layer.selected_data.events.items_changed.connect(self._on_selection)
        self._bind_keys(layer)
        if catch_up:
            self._catch_up()
            _remember_layer_name(session, layer)  # renamed before any widget followed it
        self._refresh_layer(structure=True)
        with self._guarded():
            self.viewer.layers.selection.active = layer
            layer.mode = "select"
        with self._guarded():
            self.threshold_slider.setValue(int(round(session.threshold * 100)))
        self._known_names = None
        self._refresh_choices()
        self._refresh_all()

    def _disconnect_layer(self, layer) -> None:
        for signal, slot in ((layer.events.data, self._on_layer_data),
                             (layer.selected_data.events.items_changed, self._on_selection)):
            try:
                signal.disconnect(slot)
            except (TypeError, RuntimeError, ValueError):
                pass

    def _unlink(self) -> None:
        if self.session is not None:
            self.session.disconnect(self._on_session)
        if self.layer is not None:
            self._disconnect_layer(self.layer)
        self.session = None
        self.layer = None
        self._refresh_all()

    def _on_session(self, kind: str, rows) -> None:
        if kind == "save_error":
            self._notify_warning(self.session.last_save_error or "the session could not be saved")
            return
        if kind == "save_moved":
            # the layer and the sessions shown name the file it lives in now: a widget docked
            # again, or Duplicate Layer, read the old one (and lost the decisions made since)
            self._open_sessions[str(self.session.path)] = self.session
            if self.layer is not None:
                meta = (self.layer.metadata or {}).get(META_KEY) or {}
                with self._guarded():
                    self.layer.metadata = {**(self.layer.metadata or {}), META_KEY: {**meta, "session": str(self.session.path)}}
            self.session_label.setText(f"Session autosaved to {self.session.path}")  # (a save alone: the slider)
            self._notify_warning(f"the image's folder is no longer writable; the session is saved to {self.session.path}")
            return
        if kind == "current":
            if not self._guard:
                self._show_current(centre=True)
            return
        self._refresh_layer(structure=(kind == "structure"))
        self._refresh_all()

    def _refresh_layer(self, structure: bool = False) -> None:
        layer, session = self.layer, self.session
        if layer is None or session is None:
            return
        with self._guarded():
            if structure or len(layer.data) != len(session):
                coords, scale, _ = review_coordinates(session, layer.ndim, layer_time_axis(layer))
                if len(layer.scale) == len(scale) and not np.allclose(layer.scale, scale):
                    # a layer reused after the voxel size changed: its data are in the new voxels
                    layer.scale = scale
                    layer.size = point_size(scale)
                current = np.asarray(layer.data)
                if current.shape != coords.shape or not np.allclose(current, coords):
                    layer.selected_data = set()
                    layer.data = coords
            layer.features = review_features(session)
            layer.feature_defaults = review_defaults(layer.features)
            layer.border_color = review_colours(session)
            if self.hide_check.isChecked():
                layer.shown = np.asarray(layer.features["shown"], dtype=bool)
            else:
                layer.shown = np.ones(len(session), dtype=bool)
            layer.refresh_text()

    def _on_layer_data(self, event) -> None:
        """Points added, removed or moved by hand: the session follows (undoable)."""
        if self._guard or self.session is None or self.layer is None:
            return
        action = str(getattr(event, "action", ""))
        if action not in ("added", "removed", "changed", "ActionType.ADDED", "ActionType.REMOVED", "ActionType.CHANGED"):
            return
        try:
            self._sync_structure(action.rsplit(".", 1)[-1].lower(), getattr(event, "data_indices", ()))
        except FdlcError as exc:
            self._report_error(exc)

    def _sync_structure(self, action: str, indices) -> None:
        data = np.asarray(self.layer.data, dtype=float)
        if data.ndim == 2 and data.shape[1] == 4 and len(data) and np.any(data[:, 0] != 0):
            # a point added at another time point of the recording: the names are of the first
            self._refresh_layer(structure=True)
            raise FdlcError(f"'{self.layer.name}': {self._first_time_point_only()}")
        n_old, n_new = len(self.session), len(data)
        moved = []
        if action == "removed" or n_new < n_old:
            removed = {int(i) for i in np.atleast_1d(indices)} if n_old - n_new == len(np.atleast_1d(indices)) else None
            if removed is None:
                return self._refresh_layer(structure=True)
            kept = [i for i in range(n_old) if i not in removed]
            description = f"remove {len(removed)} neuron(s)"
        elif action == "added" or n_new > n_old:
            kept = list(range(n_old)) + [None] * (n_new - n_old)
            description = f"add {n_new - n_old} neuron(s)"
        else:
            kept = list(range(n_old))
            description = "move neuron(s)"
            moved = [int(i) for i in np.atleast_1d(indices) if 0 <= int(i) < n_new] if indices is not None else []
        self._take_layer(kept, moved, description)

    def _first_time_point_only(self) -> str:
        time_axis = layer_time_axis(self.layer)
        first = f" (t = {time_axis[1]:g})" if time_axis else ""
        return (f"it names the recording's first time point{first}: move the time slider there to add a neuron, "
                "or follow neurons over time with the Track widget")

    def _catch_up(self) -> None:
        """Points added, removed or moved in the session's own layer while no widget followed it
        (the dock closed, another worm under review): the session takes them now, as one
        undoable edit. They were overwritten by the session's table, and in no file. Each point
        carries its session row (feature ``neuron``; a point added has none)."""
        layer, session = self.layer, self.session
        coords, scale, _ = review_coordinates(session, layer.ndim, layer_time_axis(layer))
        data = np.asarray(layer.data, dtype=float)
        stray = np.flatnonzero(data[:, 0] != 0) if data.ndim == 2 and data.shape[1] == 4 else []
        if len(stray):  # points added at another time point of the recording: refused, the rest taken
            with self._guarded():
                layer.selected_data = set(int(i) for i in stray)
                layer.remove_selected()
            data = np.asarray(layer.data, dtype=float)
            self._notify_warning(f"{len(stray)} point(s) added to '{layer.name}' at another time point are left out: "
                                 f"{self._first_time_point_only()}")
        if "neuron" not in layer.features.columns or data.shape != (len(data), len(scale)) or \
                not np.allclose(np.asarray(layer.scale, dtype=float), scale):
            return  # not the layer as this session left it: shown afresh
        rows = pd.to_numeric(layer.features["neuron"], errors="coerce").to_numpy(dtype=float)
        kept, seen = [], set()
        for v in rows:
            o = int(v) if np.isfinite(v) and v == int(v) and 0 <= v < len(session) and int(v) not in seen else None
            seen.add(o)
            kept.append(o)
        moved = [j for j, o in enumerate(kept) if o is not None and not np.allclose(data[j], coords[o])]
        if kept == list(range(len(session))) and not moved:
            return
        added, removed = kept.count(None), len(session) - len(seen - {None})
        description = ", ".join(f"{verb} {n} neuron(s)" for verb, n in (("add", added), ("remove", removed), ("move", len(moved))) if n)
        try:
            self._take_layer(kept, moved, description)
        except FdlcError as exc:
            self._report_error(exc)
        else:
            self._notify_info(f"the edits made in '{layer.name}' while it was not followed are kept: {description}")

    def _take_layer(self, kept: list, moved: list[int], description: str) -> None:
        """The session takes the layer's points: ``kept[j]`` the session row of point j (None:
        a neuron added), ``moved`` the points dragged."""
        from ._layers import layer_xyz_um

        session = self.session
        old = session.table
        xyz = layer_xyz_um(self.layer)
        n_new = len(xyz)
        colours = {}
        for c, v in old.colours_as_read().items():
            col = np.full(n_new, np.nan)
            for j, o in enumerate(kept):
                if o is not None:
                    col[j] = v[o]
            colours[c] = col
        new_rows = [j for j, o in enumerate(kept) if o is None]
        if new_rows:
            self._fill_colours(colours, xyz, kept, new_rows)
        if moved:  # a point dragged onto another nucleus takes the colour there
            self._fill_colours(colours, xyz, kept, moved)
        extra = old.extra.iloc[[o for o in kept if o is not None]].reset_index(drop=True) if all(o is not None for o in kept) else None
        if extra is None:
            extra = old.extra.reindex([o if o is not None else -1 for o in kept]).reset_index(drop=True)
        table = NeuronTable(xyz, colours, extra=extra, source=old.source)
        session.replace_table(table, kept, description)

    def _fill_colours(self, colours: dict, xyz, kept, new_rows) -> None:
        """Colours of neurons added (or moved) by hand: measured in the image on the scale of the
        others (z-scores across all neurons, as the detector does). Without the image, one added
        has no reading (NaN: the NeuronTable fills the median and exports the cell empty) and one
        moved keeps its colour."""
        measured = None
        stack = self._stack
        image = self.session.image if self.session is not None else None
        if stack is None or stack.source != image:
            try:  # e.g. a session restored from its file: the channels chosen in the widget (kept
                # for the next point added: stacking copies every channel)
                stack = self._stack = self._make_stack(self._chosen_images())
            except FdlcError:
                stack = None
        if stack is not None and stack.source == image:
            try:
                from ..segment import measure_colours

                measured = measure_colours(stack, xyz)  # z-scored per volume, as the table's
            except (FdlcError, ValueError, IndexError):  # colours are a bonus: fall back to the median
                measured = None
        for c, col in colours.items():
            if measured is not None and c in measured:
                col[new_rows] = measured[c][new_rows]

    def _on_selection(self, *_) -> None:
        if self._guard or self.layer is None or self.session is None:
            return
        selected = list(self.layer.selected_data)
        if len(selected) == 1 and selected[0] < len(self.session):
            with self._guarded():
                self.session.select(int(selected[0]))
            self._show_current(centre=False)

    # =========================================================================================
    # scripting API: review
    @property
    def threshold(self) -> float:
        return self.threshold_slider.value() / 100.0

    def set_threshold(self, p: float) -> None:
        """Hide automatic names below confidence ``p`` (0-1); user decisions stay shown."""
        from ..review import _check_threshold

        p = round(_check_threshold(p), 2)  # the slider's steps: the threshold shown is the one applied
        with self._guarded():
            self.threshold_slider.setValue(int(round(p * 100)))
        self.threshold_label.setText(f"{p:.2f}")
        if self.session is not None:
            self.session.set_threshold(p, save=not self.threshold_slider.isSliderDown())
        self._refresh_all()

    def _on_slider(self, value: int) -> None:
        self.threshold_label.setText(f"{value / 100:.2f}")
        if not self._guard:
            self._gui(self.set_threshold, value / 100.0)

    def accept(self, i: int) -> bool:
        """Confirm the name of neuron ``i`` (row in the Points layer)."""
        return self._edit(lambda s: s.accept(i), i)

    def assign(self, i: int, name: str) -> bool:
        """Give neuron ``i`` the name ``name`` ('AVAL?' marks it unsure, '' clears); typed in
        another case, a name the widget knows (atlas, templates) is taken in its own spelling."""
        from ..table import parse_name

        typed = str(name).strip()
        clean, _ = parse_name(typed)
        known = self._names()
        same = [n for n in known if n.lower() == clean.lower()] if clean and clean not in known else []
        if len(same) == 1:
            name = same[0] + ("?" if typed.endswith("?") else "")
        return self._edit(lambda s: s.assign(i, name), i)

    def pick_candidate(self, i: int, k: int) -> bool:
        """Give neuron ``i`` its k-th candidate (1, 2, 3)."""
        return self._edit(lambda s: s.pick_candidate(i, k), i)

    def mark_unsure(self, i: int) -> bool:
        """Mark the name of neuron ``i`` unsure (?, confidence 0.5)."""
        return self._edit(lambda s: s.mark_unsure(i), i)

    def clear(self, i: int) -> bool:
        """Remove the user's decision on neuron ``i``."""
        return self._edit(lambda s: s.clear(i), i)

    def undo(self) -> str | None:
        """Undo the last edit (returns its description)."""
        desc = self._need_session().undo()
        self._status(f"undone: {desc}" if desc else "nothing to undo")
        return desc

    def redo(self) -> str | None:
        desc = self._need_session().redo()
        self._status(f"redone: {desc}" if desc else "nothing to redo")
        return desc

    def next_neuron(self) -> int | None:
        """Go to the next neuron, lowest confidence first: selects it and centres the view."""
        return self._need_session().next_neuron()

    def previous_neuron(self) -> int | None:
        return self._need_session().previous_neuron()

    def select_neuron(self, i: int) -> None:
        """Make neuron ``i`` the current one: select it and centre the view on it."""
        session = self._need_session()
        with self._guarded():
            session.select(i)
        self._show_current(centre=True)

    def export(self, path, format: str = "fdlc", overwrite: bool = False) -> Path:
        """Write the reviewed names: ``format='fdlc'`` (our CSV) or ``'neuropal_id'``."""
        out = self._need_session().export(path, format=format, overwrite=overwrite)
        self._status(f"exported {out}")
        return out

    @property
    def current(self) -> int | None:
        return None if self.session is None else self.session.current

    def _need_session(self) -> ReviewSession:
        if self.session is None:
            raise FdlcError("no neurons labelled yet: run Auto-label first")
        return self.session

    def _edit(self, action, i) -> bool:
        session = self._need_session()
        changed = action(session)
        if session.current != i:
            with self._guarded():
                session.select(i)
            self._show_current(centre=False)
        return changed

    def _current_row(self) -> int:
        session = self._need_session()
        if self.layer is not None and len(self.layer.selected_data) == 1:
            i = int(next(iter(self.layer.selected_data)))
            if i < len(session):
                return i
        if self.layer is not None and len(self.layer.selected_data) > 1:
            # not the neuron last shown, which may be none of them
            raise FdlcError(f"{len(self.layer.selected_data)} neurons are selected: click the one to name")
        if session.current is None:
            raise FdlcError("no neuron selected: click a point, or press N to go to the next one")
        return session.current

    # =========================================================================================
    # GUI-side handlers (errors become notifications)
    def _gui(self, fn, *args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except FdlcError as exc:
            self._report_error(exc)
            return None

    def _on_current(self, fn):
        return self._gui(lambda: fn(self._current_row()))

    def _on_candidate_activated(self, index: int) -> None:
        if self._guard or self.session is None or self.session.current is None:
            return
        self._on_current(lambda i: self.pick_candidate(i, index + 1))  # several selected: refused, as the keys are

    def _on_name_entered(self) -> None:
        text = self.name_edit.text().strip()
        if not text:
            return
        if self._gui(lambda: self.assign(self._current_row(), text)) is not None:
            self.name_edit.clear()
            try:  # back to the canvas, so that the review keys work again
                self.viewer.window._qt_viewer.canvas.native.setFocus()
            except Exception:
                pass

    def _on_table_clicked(self, row: int, _col: int) -> None:
        item = self.neuron_table.item(row, 0)
        if item is not None:
            self._gui(self.select_neuron, int(item.text()))

    def _export_dialog(self, format: str) -> None:
        if self.session is None:
            return self._report_error(FdlcError("nothing to export: run Auto-label first"))
        default = self._default_export_path(format)
        path, _ = QFileDialog.getSaveFileName(
            self, "Export neuron IDs", str(default), "CSV (*.csv)", options=QFileDialog.Option.DontConfirmOverwrite
        )
        if not path:
            return
        if not path.lower().endswith(".csv"):
            path += ".csv"
        overwrite = False
        if Path(path).exists():
            answer = QMessageBox.question(self, "Overwrite?", f"{path} exists. Replace it?")
            if answer != QMessageBox.StandardButton.Yes:
                return
            overwrite = True
        out = self._gui(self.export, path, format=format, overwrite=overwrite)
        if out is not None:
            self._notify_info(f"exported {out}")

    def _default_export_path(self, format: str) -> Path:
        key = self.session.image or "neurons"
        # an image made in napari is keyed 'layer:<hash>:<name>': its name, with what a file name
        # cannot hold (':' opens a stream on Windows) replaced
        stem = re.sub(r'[<>:"/\\|?*]+', "_", _short_name(key.rsplit(":", 1)[-1] if key.startswith("layer:") else key))
        folder = Path(key).parent if (not key.startswith(("sample:", "layer:", "<")) and Path(key).parent.is_dir()) else Path.home()
        from ..review import _writable_folder

        if not _writable_folder(folder):
            folder = Path.home()
        return folder / f"{stem}_{'ids' if format == 'fdlc' else 'neuropal_id'}.csv"

    def _report_error(self, exc: BaseException) -> None:
        if isinstance(exc, FdlcError):
            message = str(exc)
        else:
            message = f"unexpected error ({type(exc).__name__}: {exc}); please report it"
            traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
        self.last_error = message
        self._status(message)
        self.progress_bar.setValue(0)  # not the last run's full bar beside this run's error
        self._notify_error(message)

    def _notify_error(self, message: str) -> None:
        from napari.utils.notifications import show_error

        show_error(message)

    def _notify_warning(self, message: str) -> None:
        notify_warning(message)

    def _notify_info(self, message: str) -> None:
        from napari.utils.notifications import show_info

        show_info(message)

    def _status(self, message: str) -> None:
        self.progress_bar.setFormat(message[:120])

    # =========================================================================================
    # display
    def _coverage_text(self) -> str:
        s = self.session
        if s is None:
            return ""
        c = s.counts()
        return (
            f"{s.coverage():.0%} of {len(s)} neurons named — {c['accepted']} accepted, {c['corrected']} corrected, "
            f"{c['unsure']} unsure, {c['hidden']} below threshold"
        )

    def _refresh_all(self) -> None:
        s = self.session
        has = s is not None
        for b in (self.accept_button, self.unsure_button, self.clear_button, self.prev_button, self.next_button, self.export_button, self.export_npid_button):
            b.setEnabled(has)
        self.relabel_button.setEnabled(has and not self._busy and s.labelled)
        self.undo_button.setEnabled(has and s.can_undo)
        self.redo_button.setEnabled(has and s.can_redo)
        self.coverage_label.setText(self._coverage_text() if has else "no neurons labelled yet")
        self.session_label.setText(f"Session autosaved to {s.path}" if has and s.path else "")
        self._fill_table()
        self._show_current(centre=False)
        self._refresh_completer()

    def _refresh_completer(self) -> None:
        """The Name field offers every name known (the panel's, the templates', the session's)."""
        names = self._names()
        model = self._completer.model()
        if hasattr(model, "setStringList") and model.stringList() != names:
            model.setStringList(names)

    def _names(self) -> list[str]:
        if self._known_names is None:
            names = set()
            try:
                from ..reference import load_atlas

                names.update(str(n) for n in load_atlas().names)
            except Exception:
                pass
            if self.session is not None:
                names.update(self.session.vocabulary)
            for t in self._script_templates or []:
                names.update(t.names)
            for t in self._file_templates.values():
                names.update(t.names)
            self._known_names = sorted(n for n in names if n)
        return self._known_names

    def _fill_table(self) -> None:
        s = self.session
        table = self.neuron_table
        if s is None:
            table.setRowCount(0)
            return
        order = s.review_order()
        names = s.display_names()
        conf = s.review_confidence()
        status = s.status
        shown = s.auto_shown()
        with self._guarded():
            table.setUpdatesEnabled(False)
            table.setRowCount(len(order))
            for r, i in enumerate(order):
                name = names[i] or (f"({s.auto_id[i]})" if s.auto_id[i] else "—")
                key = status[i] if status[i] != "auto" else ("auto" if shown[i] else "hidden")
                for c, text in enumerate((str(i), name, _shown_conf(conf[i]), status[i])):
                    item = table.item(r, c)
                    if item is None:
                        item = QTableWidgetItem()
                        table.setItem(r, c, item)
                    item.setText(text)
                    if c == 3:
                        item.setForeground(QColor(STATUS_HEX[key]))
            if s.current is not None and s.current in order:
                table.selectRow(order.index(s.current))
            table.setUpdatesEnabled(True)

    def _show_current(self, centre: bool) -> None:
        s = self.session
        with self._guarded():
            self.candidate_combo.clear()
            if s is None or s.current is None or s.current >= len(s):
                self.current_label.setText("select a neuron (click a point, or press N)")
                return
            i = s.current
            name = s.display_names()[i] or "(no name shown)"
            auto = s.auto_id[i] or "no match"
            self.current_label.setText(
                f"<b>Neuron {i}</b>: {name} — {s.status[i]}; automatic: {auto} ({_shown_conf(s.auto_conf[i])})"
            )
            holders = s.user_names()
            for k, (cand, p) in enumerate(s.candidates(i), start=1):
                # a name another neuron has from the user would only be refused: said beside it
                held = f" — neuron {holders[cand]} has it" if holders.get(cand, i) != i else ""
                self.candidate_combo.addItem(f"{k}. {cand}  ({_shown_conf(p)}){held}")
            if self.layer is not None and set(self.layer.selected_data) != {i}:
                self.layer.selected_data = {i}
            order = s.review_order()
            if i in order:
                self.neuron_table.selectRow(order.index(i))
        if centre:
            self._centre_on(i)

    def _centre_on(self, i: int) -> None:
        layer = self.layer
        if layer is None or i >= len(layer.data):
            return
        point = np.asarray(layer.data[i], dtype=float)
        world = point * np.asarray(layer.scale) + np.asarray(layer.translate)
        ndim = self.viewer.dims.ndim
        full = np.asarray(self.viewer.dims.point, dtype=float).copy()
        full[ndim - len(world):] = world
        displayed = list(self.viewer.dims.displayed)
        for axis in range(ndim):
            if axis not in displayed:
                self.viewer.dims.set_point(axis, full[axis])
        camera(self.viewer).center = tuple(full[displayed])

    @contextmanager
    def _guarded(self):
        self._guard += 1
        try:
            yield
        finally:
            self._guard -= 1


def camera(viewer):
    """The viewer's camera (``viewer.scene.camera`` since napari 0.9, ``viewer.camera`` before)."""
    scene = getattr(viewer, "scene", None)
    return scene.camera if scene is not None and hasattr(scene, "camera") else viewer.camera


def _saved_session(image_key: str) -> tuple[ReviewSession | None, str | None]:
    """The saved session of ``image_key`` (None when there is none), and why it could not be
    read when it could not."""
    path = find_session(image_key)
    if path is None:
        return None, None
    try:
        return ReviewSession.load(path), None
    except FdlcError as exc:
        return None, str(exc)


# Every session shown in a viewer since napari started, by file path, for all the Auto-label
# widgets docked in it: a session taken up again keeps its undo history, also after the dock
# was closed and opened again (gui.md).
_SESSIONS_SHOWN: dict[int, dict[str, ReviewSession]] = {}


def _refuse_another_time_point(points, images: dict) -> None:
    """Auto-label names a recording's first time point: neurons placed at another one (a t, z,
    y, x points layer) had their colours read, and earlier decisions carried, in the first."""
    image = next(iter(images.values()), None)
    data = np.asarray(points.data, dtype=float)
    if image is None or image.data.ndim < 4 or data.ndim != 2 or data.shape[1] < 4 or not len(data):
        return
    t = data[0, -4] * float(points.scale[-4]) + float(points.translate[-4])  # (one time point: checked before)
    first = float(image.translate[-4])  # the world t of the recording's first frame
    if not np.isclose(t, first, rtol=0, atol=1e-6 * max(1.0, abs(float(image.scale[-4])))):
        raise FdlcError(f"'{points.name}' lies at t = {t:g}; Auto-label names the recording's first time point "
                        f"(t = {first:g}): place the neurons there, or follow them over time with the Track widget")


def _lacking(hand_made: np.ndarray, detected: np.ndarray) -> int:
    """How many neurons the user added or moved (µm) a new detection lacks (none within 1.5 µm):
    work lost. A detected neuron the new detection lacks is its answer (another diameter, say)."""
    if not len(hand_made):
        return 0
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(detected).query(hand_made, distance_upper_bound=np.nextafter(1.5, 2))
    return int(np.sum(~np.isfinite(gap)))


def _record_layer_name(event) -> None:
    """A neuron-ID layer renamed, a widget following it or not (the dock closed, another worm
    under review): reopening the image brings it back under that name."""
    layer = event.source
    path = ((getattr(layer, "metadata", None) or {}).get(META_KEY) or {}).get("session")
    session = next((shown[path] for shown in _SESSIONS_SHOWN.values() if path in shown), None) if path else None
    if session is not None:
        _remember_layer_name(session, layer)


def _remember_layer_name(session: ReviewSession, layer) -> None:
    if session.settings.get("layer_name") != layer.name:
        session.settings["layer_name"] = layer.name
        session.autosave()


def _sessions_shown_in(viewer) -> dict[str, ReviewSession]:
    key = id(viewer)
    if key not in _SESSIONS_SHOWN:
        _SESSIONS_SHOWN[key] = {}
        weakref.finalize(viewer, _SESSIONS_SHOWN.pop, key, None)  # a viewer closed takes its sessions along
    return _SESSIONS_SHOWN[key]


CHIRALITY_CHOICES = (("auto", "auto"), ("same", "as the template / atlas"), ("mirrored", "mirrored"))


def _with_chirality(identifier, chirality: str):
    """The identifier to use (None: the shipped one) with the handedness the user chose."""
    from ..identify import default_identifier

    identifier = identifier or default_identifier()
    if not hasattr(identifier, "with_chirality"):  # scripts may inject their own matcher
        return identifier
    return identifier.with_chirality(chirality)


def _fill(combo: QComboBox, items: list[tuple[str, object]]) -> None:
    """Replace a combo box's items by (text, layer or None)."""
    combo.clear()
    for text, layer in items:
        combo.addItem(text, layer)


def _choose(combo: QComboBox, layer, fallback: str) -> None:
    """Select ``layer``'s item (under whatever name it has now), else the item ``fallback``."""
    index = next((i for i in range(combo.count()) if layer is not None and combo.itemData(i) is layer), -1)
    if index >= 0:
        combo.setCurrentIndex(index)
    else:
        combo.setCurrentText(fallback)


def _combo() -> QComboBox:
    combo = QComboBox()
    combo.setSizeAdjustPolicy(QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
    combo.setMinimumContentsLength(12)
    return combo


def _is_points(layer) -> bool:
    return type(layer).__name__ == "Points"
