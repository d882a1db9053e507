"""Identify the neurons of a test worm against one or more labelled templates.

test ──► registration onto the reference ──► model on each ──► choice ──► calibration, ──► names
         (register.py: the template, or          candidate pose               colour fusion    (match.name_probabilities,
          the atlas for the built-in panel)                                                     match.assign)

Registration finds candidate poses (any roll about the body axis, either head direction, both
chiralities); the model scores them, and the pose chosen is the one with the best sum of the
model's willingness to match and the registration's likelihood, with a prior that keeps the
reference's handedness unless the model, a name the user fixed or ``--chirality`` says
otherwise. The panel registers onto the atlas and keeps the likeliest pose per chirality.
A test that turns out to be the template's own worm (another volume of it) gets a second look
after a smooth warp onto the template (:meth:`Identifier._warp_refine`).

The model is loaded once; :meth:`Identifier.label` may be called for as many tests as needed.
torch is imported here only when an :class:`Identifier` is made, so ``import napari_fdlc`` and
napari's plugin discovery stay fast.
"""

from __future__ import annotations

import json
import math
import os
import threading
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from . import colour as colour_model
from ._blas import one_blas_thread
from .errors import FdlcError, ModelError, first_line, warn
from .geometry import (CHIRALITIES, apply_affine, canonical_frame, compose_affine, fit_affine, fit_warp,
                       mirrored_by_names, position_evidence, refuse_flat)
from .match import Labelling, assign_log, check_fixed, make_labelling, name_probabilities
from .register import (HEAD_WINDOW, Placement, body_reach, head_window, posterior, register, smaller_worm_factor,
                       template_mixture)
from .table import NeuronTable, check_named

if TYPE_CHECKING:
    from .reference import Atlas, Panel

WEIGHTS_NAME = "fdlc_model"
TRACKING_WEIGHTS_NAME = "fdlc_tracking"  # the small model fdlc track follows volumes with
# The prior against a mirrored placement that ships (see InferenceSettings.mirror_penalty), not
# fitted: on worms of labs it had not seen, the model's preference between the two placements
# is noise. Fitted on validation worms it came out 0.1-1.0 by fold, and trusting the model cost
# the EY fold 23 points of panel top-1 (45.6 vs 68.3 %); the demo worm was named mirrored.
MIRROR_PRIOR = 1.0
# Several recordings named in one call (Identifier.label_panel_many) share one handedness when a
# sign test over their evidence is this significant (set a priori, not tuned).
BATCH_HANDEDNESS_P = 0.01
# Starts of the registration onto a template kept per chirality (register.register's keep),
# twice as many for a test of fewer than SMALL_TEST neurons (Identifier.place).
KEPT_STARTS = 3
SMALL_TEST = 100
# The panel chooses the test's handedness on its first templates only (the atlas's mean worm and
# the first samples), then runs the others in that handedness: 15 model passes instead of 20.
# With 5, every choice on the corpus stayed the same (the shipped model and the five fold models,
# every worm of every lab, panel on auto); with 3 one SF worm of 36 flipped, with 2 three EY worms.
PANEL_HANDEDNESS_TEMPLATES = 5
# Recordings of one microscope named together with their colours adapted
# (Identifier.label_panel_many): from ADAPT_MIN_TESTS recordings, a name's colour is measured on
# them when given with confidence ADAPT_MIN_CONF or more in ADAPT_MIN_WORMS of them. Leave-one-lab-out
# (session 11; the panel on the lab's worms in one call), 0.3 / 0.5 / 0.7 and mean only or mean and
# spread all gained on every lab (+0.3 to +7.0 points); the middle setting ships.
ADAPT_MIN_TESTS = 3
ADAPT_MIN_CONF = 0.5
ADAPT_MIN_WORMS = 3
# The second look of InferenceSettings.warp_um. Matches of the first answer less likely than
# WARP_MIN_PROB do not shape the warp. A test is the template's own worm when the warp leaves the
# median of its matches within WARP_SAME_WORM_UM (RMS per axis) of their partners: measured
# 0.29-0.45 µm on held-out synthetic pairs, 0.42-0.59 on a simulated recording's volumes against
# its first, 0.87-3.2 µm between any two worms of a corpus lab (20 pairs per lab). The position
# likelihood is then WARP_RESIDUAL_SCALE times as wide as that residual, within WARP_WIDTH_UM
# (on fold models' pairs, 2.5 against 1-2 and fixed widths of 2-8 µm).
# A test of fewer than FEW_NEURONS neurons: beside a template the atlas's answer is left out. Its
# registration fits any handful of points, so its posterior is sharp whatever the truth (session
# 15, the shipped model, 3 pairs per corpus lab, random subsets of a worm's named neurons: 1-3
# neurons 0-7 % right at a mean confidence of 0.71-0.78 with it, 0.18-0.30 without it; 5-8
# neurons 13-18 % at 0.66-0.68 with it, 9-12 % at 0.28-0.34 without; 12 neurons 24 % either way).
# ``fdlc label`` says that names from so few neurons are guesses.
FEW_NEURONS = 10
WARP_MIN_PROB = 0.3
WARP_SAME_WORM_UM = 0.7
WARP_RESIDUAL_SCALE = 2.5
WARP_WIDTH_UM = (1.0, 10.0)
WARP_SMOOTHNESS = 1.0


TRACE_LOCK = threading.Lock()  # see Identifier._model_pass
WARM_UP_LOCK = threading.Lock()  # one warm-up at a time (several widgets may start one)


class AtlasView(NamedTuple):
    """A test placed in the atlas's frame in one handedness (:meth:`Identifier._atlas_views`),
    with the model's log p against the atlas's mean worm there (None: not asked)."""

    atlas: Atlas
    placement: Placement
    worm: NeuronTable | None = None
    worm_log_p: np.ndarray | None = None


def shipped_weights() -> Path:
    return Path(str(resources.files("napari_fdlc") / "data" / WEIGHTS_NAME))


# With a template, a test is cut to its head window (as the panel does) only when it also
# spreads along the body this many times further than every template: a template that names
# ventral-cord neurons (NP's) keeps them in reach. A test reaching 120 neurons over 250 µm
# into the body, named beside the next worm of its lab, the atlas without the lab beside it:
# NP 47.6 -> 79.8 % top-1, EY 15.8 -> 70.0, KK 15.3 -> 56.9, SF 0.4 -> 47.6, SK1 2.2 -> 49.4
# (shipped model; benchmarks/robustness.py --protocol pairs). At 1.0 or 1.15 NP's own tilted
# heads reached past their template's and lost 0.3-0.6 points; at 1.3 none moved.
TEMPLATE_REACH_MARGIN = 1.3


# (name, low, high, low excluded) of each numeric InferenceSettings field.
_SETTING_RANGES = (
    *((name, 0.0, math.inf, True) for name in ("temperature", "panel_temperature", "colour_sigma", "no_match_weight")),
    *((name, 0.0, math.inf, False) for name in (
        "colour_weight", "fallback_colour_weight", "mirror_penalty", "atlas_weight", "atlas_weight_position",
        "panel_atlas_weight", "panel_atlas_weight_position", "warp_um")),
    *((name, 0.0, 1.0, False) for name in (
        "chirality_doubt", "template_chirality_doubt", "atlas_worm_weight", "atlas_worm_weight_position")),
)


@dataclass
class InferenceSettings:
    refine_steps: int = 0  # affine re-alignment passes after the placement (measured: no gain yet)
    colour_weight: float = 1.0  # λ: exponent of the colour likelihood ratio
    colour_sigma: float = 0.6  # width of the colour likelihood in normal-score units
    temperature: float = 1.0  # divides the log-probabilities (calibration, fitted on training labs)
    # Handedness of the test relative to the template (or the atlas): "auto" tries both, "same"
    # assumes the template's, "mirrored" the other (a z axis flipped by the acquisition).
    # Positions and colours barely tell (bilateral symmetry); a user who knows the microscope does.
    chirality: str = "auto"
    # Prior against a mirrored placement (relative to the template or the atlas). The head is
    # bilaterally symmetric and the model's preference between the two placements of a worm
    # from a lab it has not seen was measured to be noise, so the value that ships (MIRROR_PRIOR,
    # not fitted) keeps the reference's handedness unless the user says otherwise.
    mirror_penalty: float = MIRROR_PRIOR
    # Late colour fusion when the model got no colour input (only some of R, G, B shared):
    # weight 1 took a position-only model from 18 to 32 % top-1 on validation pairs (stage 1).
    fallback_colour_weight: float = 1.0
    chirality_doubt: float = 0.0  # panel: weight of the other chirality's answer
    # With a template: the same, for the probabilities reported (the names stay the chosen
    # chirality's). A whole worm named in the wrong handedness has its left/right pairs swapped
    # and came out as confident as a right one (KK, SK1 pairs: 5-10 % top-1 at confidence 0.7-0.8).
    # Counted, not fitted: how often two worms of a training lab differ in handedness
    # (train.mixed_handedness_rate).
    template_chirality_doubt: float = 0.0
    panel_temperature: float = 1.0  # panel: on the averaged answer (fitted on training labs)
    # With a template: the weight of the atlas's own answer (registration posterior, no model)
    # multiplied into the template's, with colour and position only; 0 = the template alone.
    # Fitted on training labs, each scored with an atlas built without it.
    atlas_weight: float = 0.0
    atlas_weight_position: float = 0.0
    # With a template: the weight of the model's answer against the atlas's mean worm (the
    # panel's first template, the test placed in the atlas's frame in the handedness the
    # template's names give) in an average with the template's answer, before the atlas's own
    # answer is multiplied in; with colour and position only. One worm is a noisy reference
    # (every name sits ~5 µm from its atlas mean); the mean worm averages the corpus.
    # Fitted on training labs, each scored with an atlas built without it; 0 = the template alone.
    atlas_worm_weight: float = 0.0
    atlas_worm_weight_position: float = 0.0
    # The panel: the same, the atlas's answer at the test's placement in the atlas frame
    # multiplied into the panel's average (its templates are samples of the atlas, the
    # posterior weighs every name's own spread and colour), with colour and position only.
    # Fitted on training labs; 0 = off.
    panel_atlas_weight: float = 0.0
    panel_atlas_weight_position: float = 0.0
    # With a template, when the test is the template's own worm (another volume, a simulated
    # copy): a smooth warp (geometry.fit_warp, Gaussian basis of this width in µm) fitted on the
    # first answer's confident matches carries the test onto the template's pose, and where it
    # leaves them within WARP_SAME_WORM_UM, the model looks again there, fused with a position
    # likelihood. Registration is rigid; a worm's pose bends it, which the model alone leaves
    # to its top-3 (held-out synthetic pairs 96.1 -> 99.3 % top-1). Between two worms the warp
    # leaves 0.9-3 µm (every corpus pair measured): they keep the first answer. 0 = off.
    warp_um: float = 12.0
    no_match_weight: float = 0.2  # see match.assign

    @classmethod
    def from_dict(cls, d: dict | None) -> "InferenceSettings":
        d = dict(d or {})
        if d.pop("chirality_search", True) is False:  # older model cards
            d.setdefault("chirality", "same")
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)

    def __post_init__(self):
        if self.chirality not in CHIRALITIES:
            raise FdlcError(f"unknown chirality '{self.chirality}' (use {', '.join(CHIRALITIES)})")
        # A value out of range fails far from here (a temperature of 0 made every probability
        # NaN, silently; a colour width of 0 divided by zero): refused where it is given.
        steps = self.refine_steps
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
            raise FdlcError(f"inference setting refine_steps must be a whole number of 0 or more (got {steps!r})")
        for name, low, high, open_low in _SETTING_RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or \
                    not math.isfinite(value) or not (low < value if open_low else low <= value) or not value <= high:
                what = f"from {low} to {high}" if high < math.inf else ("above 0" if open_low else "0 or more")
                raise FdlcError(f"inference setting {name} must be a number {what} (got {value!r})")


class Identifier:
    """The trained model plus everything needed to turn its output into names."""

    def __init__(self, model=None, settings: InferenceSettings | None = None, device: str | None = None):
        import torch

        self.torch = torch
        self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
        if isinstance(model, (str, os.PathLike)):
            raise TypeError(f"Identifier takes a loaded model; for weights on disk use Identifier.load({str(model)!r})")
        try:
            self.model = model.to(self.device).eval() if model is not None else None
        except (RuntimeError, ValueError, AssertionError) as exc:  # e.g. device="tpu", or "cuda" on a machine without one
            raise ModelError(f"device '{self.device}' cannot run the model ({first_line(exc)}); use cpu or cuda") from None
        self.settings = settings or InferenceSettings()
        self._traced: dict = {}  # see _model_pass; shared with copies made by with_settings
        self._mean_worm: tuple = (None, None)  # (atlas, its mean worm) for _atlas_worm_answer
        self._template_handedness: tuple = (None, None, None)  # (atlas, template's positions and names, mirrored): _atlas_placement

    @classmethod
    def load(cls, path: str | Path | None = None, device: str | None = None, identifies: bool = False) -> "Identifier":
        """Load weights (``path`` without suffix; default: the weights shipped in the package).
        ``identifies``: refuse a model trained to track (its training config's "task": "track"), which
        follows a worm from volume to volume but cannot name one from another."""
        from .model import load_model, model_files

        weights, config_path = model_files(path or shipped_weights())
        if not weights.exists():
            raise ModelError(f"no trained weights at {weights}: train them with 'fdlc train'")
        model = load_model(weights)
        recorded = json.loads(config_path.read_text())
        trained = recorded.get("train_config")
        if identifies and isinstance(trained, dict) and trained.get("task") == "track":
            raise ModelError(f"{path}: a model trained to track (task 'track'), which cannot name neurons; give an "
                             "identification model (default: the shipped one)")
        inference = recorded.get("inference")
        try:
            settings = InferenceSettings.from_dict(inference)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"{config_path}: 'inference' is not a set of inference settings ({exc})") from None
        return cls(model, settings, device)

    def with_settings(self, **changes) -> "Identifier":
        """The same model with some inference settings changed (the original is left alone)."""
        copy = Identifier(self.model, replace(self.settings, **changes), self.device)
        copy._traced = self._traced
        return copy

    def with_chirality(self, chirality: str) -> "Identifier":
        """This identifier, or a copy told the tests' handedness (see InferenceSettings.chirality)."""
        return self if chirality == self.settings.chirality else self.with_settings(chirality=chirality)

    # ------------------------------------------------------------------------------------------
    def _forward_many(
        self,
        template_xyz: np.ndarray,
        tests: list[np.ndarray],
        template_colour: np.ndarray | None = None,
        test_colours: list[np.ndarray] | None = None,
    ) -> list[np.ndarray]:
        """log p (N_v, M + 1) for each placed test (N_v, 3) against one template, batched."""
        colours = None if template_colour is None else [template_colour]
        return self._forward_grid([template_xyz], tests, colours, test_colours)[0]

    def _forward_grid(
        self,
        templates: list[np.ndarray],
        tests: list[np.ndarray],
        template_colours: list[np.ndarray] | None = None,
        test_colours: list[np.ndarray] | None = None,
    ) -> list[list[np.ndarray]]:
        """log p (N_v, M_t + 1) of every placed test against every template, ``[t][v]``, as
        one batch of template × test pairs (on two threads, 20 small passes take twice as long
        as one batch of 20). Sizes that differ are padded to a common size with a mask. A
        single template goes to the model with batch 1, so it is embedded once."""
        torch = self.torch
        if not tests or not templates:
            return [[] for _ in templates]
        with_colour = template_colours is not None and test_colours is not None
        tmpl, tmpl_mask, tmpl_c = self._padded(templates, template_colours if with_colour else None)
        test, test_mask, test_c = self._padded(tests, test_colours if with_colour else None)
        n_t, n_v = len(templates), len(tests)
        if n_t > 1:  # pair k is template k // n_v with test k % n_v
            tmpl, tmpl_mask, tmpl_c = (None if x is None else x.repeat_interleave(n_v, 0) for x in (tmpl, tmpl_mask, tmpl_c))
            test, test_mask, test_c = (None if x is None else x.repeat(n_t, *[1] * (x.dim() - 1)) for x in (test, test_mask, test_c))
        # Chunk so that 2000-neuron worms fit in memory.
        m, n = tmpl.shape[1], test.shape[1]
        chunk = max(1, int(4e6 // max(1, n * max(m, n))))
        shared = n_t == 1  # a single template stays batch 1 for every chunk
        out = []
        with torch.inference_mode():
            for s in range(0, len(test), chunk):
                part = slice(s, s + chunk)
                a = [x if shared or x is None else x[part] for x in (tmpl, tmpl_mask, tmpl_c)]
                b = [None if x is None else x[part] for x in (test, test_mask, test_c)]
                out.extend(self._model_pass(a[0], b[0], a[1], b[1], a[2], b[2]).float().cpu().numpy())

        def real(lp, rows, cols):  # without the padded rows and padded template columns
            return lp[:rows] if cols == m else np.concatenate([lp[:rows, :cols], lp[:rows, -1:]], axis=1)
        return [[real(out[t * n_v + v], len(tests[v]), len(templates[t])) for v in range(n_v)] for t in range(n_t)]

    def _model_pass(self, tmpl, test, tmpl_mask, test_mask, tmpl_c, test_c):
        """The model on one batch. On the CPU it goes through a trace of the model
        (:func:`model.trace_model`, one per batch shape and pattern of masks and colours, made on
        first use in ~0.1 s): the same numbers, 10-20 % less time."""
        if self.device != "cpu" or (tmpl_c is None) != (test_c is None):
            return self.model(tmpl, test, tmpl_mask, test_mask, tmpl_c, test_c)
        from .model import real_mask, trace_model

        # A mask without padding (a chunk of tests of one size) is no mask: the model drops it,
        # so a trace made on it follows the unmasked path, and must not serve padded batches.
        tmpl_mask, test_mask = real_mask(tmpl_mask), real_mask(test_mask)
        inputs = (tmpl, test, tmpl_mask, test_mask, tmpl_c, test_c)
        key = (tmpl.shape[0], test.shape[0], *(x is not None for x in inputs[2:]))
        traced = self._traced.get(key)
        if traced is None:
            # One trace at a time in the process: a widget's warm-up thread and a job may meet
            # here, and neither torch.jit.trace nor the warnings filter around it is thread-safe.
            with TRACE_LOCK:
                traced = self._traced.get(key)
                if traced is None:
                    if len(self._traced) >= 16:  # batch shapes seen are few; never let them pile up
                        self._traced.clear()
                    traced = self._traced[key] = trace_model(self.model, *inputs)
        return traced(*(x for x in inputs if x is not None))

    def _padded(self, points: list[np.ndarray], colours: list[np.ndarray] | None):
        """(B, size, 3) tensor, its (B, size) mask of real rows (None without padding) and the
        colours padded alike (None when not given)."""
        torch = self.torch
        sizes = np.array([len(p) for p in points])
        size = int(sizes.max())
        xyz = np.zeros((len(points), size, 3), dtype=np.float32)
        for i, p in enumerate(points):
            xyz[i, : len(p)] = p
        mask = None
        if (sizes < size).any():
            mask = torch.as_tensor(np.arange(size)[None, :] < sizes[:, None], device=self.device)
        col = None
        if colours is not None:
            c = np.zeros((len(points), size, colours[0].shape[1]), dtype=np.float32)
            for i, v in enumerate(colours):
                c[i, : len(v)] = v
            col = torch.as_tensor(c, device=self.device)
        return torch.as_tensor(xyz, device=self.device), mask, col

    def _align(
        self,
        template_xyz: np.ndarray,
        starts: list[np.ndarray],
        refine_steps: int | None = None,
        template_colour: np.ndarray | None = None,
        test_colours: list[np.ndarray] | None = None,
        prior: list[np.ndarray] | None = None,
    ) -> list[dict]:
        """Placement choice and affine refinement for many tests at once.

        ``starts[v]`` (K_v, N_v, 3) holds K_v candidate placements of test v in the template's
        frame (the registration's poses, see :meth:`place`; 1 when tracking from the previous
        volume), ``prior[v]`` (K_v,) a log-score added to the model's willingness to match each.
        All candidates of all tests go through the model in one batch; the best wins; then
        ``refine_steps`` affine passes, batched over tests.
        Returns per test: ``log_p`` (N_v, M + 1), ``best`` (candidate index), ``willingness``
        (per candidate), ``all_log_p``, ``affine`` (4×3: winning candidate -> final placement), ``moved``.
        """
        steps = self.settings.refine_steps if refine_steps is None else refine_steps
        a = np.asarray(template_xyz, dtype=np.float64)
        m = a.shape[0]
        flat = [c for cands in starts for c in cands]
        flat_colours = None
        if test_colours is not None:
            flat_colours = [col for cands, col in zip(starts, test_colours) for _ in cands]
        log_p = self._forward_many(a, flat, template_colour, flat_colours)
        results, k0 = [], 0
        for v, cands in enumerate(starts):
            lps = np.stack(log_p[k0 : k0 + len(cands)])
            k0 += len(cands)
            willingness = _willingness(lps, m)
            if prior is not None:
                willingness = willingness + prior[v]
            best = int(np.argmax(willingness))
            results.append({"best": best, "willingness": willingness, "log_p": lps[best], "all_log_p": lps,
                            "candidates": cands, "moved": cands[best], "affine": np.vstack([np.eye(3), np.zeros((1, 3))])})
        self._refine(a, results, steps, template_colour, test_colours)
        return results

    def _refine(self, a: np.ndarray, results: list[dict], steps: int, template_colour, test_colours) -> None:
        """``steps`` affine passes of :meth:`_align`'s ``results`` (in place) onto the template ``a``."""
        m = a.shape[0]
        for _ in range(steps):
            for r in results:
                p = np.exp(r["log_p"][:, :m])
                weight = p.max(axis=1)
                targets = (p @ a) / np.maximum(p.sum(axis=1, keepdims=True), 1e-9)
                affine = fit_affine(r["moved"], targets, weight**2)
                r["moved"] = apply_affine(r["moved"], affine)
                r["affine"] = compose_affine(r["affine"], affine)
            moved = [r["moved"] for r in results]
            for r, lp in zip(results, self._forward_many(a, moved, template_colour, test_colours)):
                r["log_p"] = lp

    @one_blas_thread
    def place(self, template: NeuronTable, tests: list[NeuronTable], use_colour: bool = True):
        """The template in its canonical frame, and each test registered onto it
        (:func:`napari_fdlc.register.register`) from every kept start, in the chiralities the
        settings allow: (template xyz, candidate placements (K_v, N_v, 3), mirrored flags (K_v,)
        and priors (K_v,) per test). The prior of a placement is its registration log-likelihood
        per neuron minus ``mirror_penalty`` if mirrored: the candidate chosen is the one where
        the model's willingness to match plus that prior is highest. Neither alone is reliable
        from detections: keeping only the likeliest pose collapsed 2 of 8 NP worms named from
        rendered images (74 → 18 %, 72 → 8 % top-1), the willingness alone lost other worms."""
        mixture = template_mixture(template)
        starts, mirrored, priors = [], [], []
        for test in tests:
            # A small test (SF's partial views: 46-95 neurons) ranks its starts less reliably
            # and costs the model little: twice the starts are kept. Leave-one-lab-out SF
            # pairs with colour 69.9 -> 73.9 %; keeping 6 for every test moved the others by
            # -2.1 to +0.6 points (NP position only lost).
            keep = 2 * KEPT_STARTS if len(test) < SMALL_TEST else KEPT_STARTS
            placements = register(test, mixture, use_colour, keep=keep, chiralities=self._chiralities(), every_start=True)
            starts.append(np.stack([p.xyz for p in placements]))
            mirrored.append(np.array([p.mirrored for p in placements]))
            priors.append(np.array([p.score - self.settings.mirror_penalty * p.mirrored for p in placements]))
        return mixture.mean, starts, mirrored, priors

    def _chiralities(self) -> tuple[bool, ...]:
        """The placements the chirality setting lets be tried: mirrored or not."""
        return {"auto": (False, True), "same": (False,), "mirrored": (True,)}[self.settings.chirality]

    def match_pair(
        self, template: NeuronTable, test: NeuronTable, use_colour: bool = True, fixed: dict[int, str] | None = None,
    ) -> tuple[np.ndarray, dict]:
        """Probabilities (N_test, M_template + 1) that each test neuron is each template neuron
        (last column: no match), with the chosen chirality in the info dict; names the user
        ``fixed`` (row -> name) choose the chirality that agrees with them."""
        return self.match_many(template, [test], use_colour, fixed)[0]

    @one_blas_thread
    def match_many(
        self, template: NeuronTable, tests: list[NeuronTable], use_colour: bool = True, fixed: dict[int, str] | None = None,
    ) -> list[tuple[np.ndarray, dict]]:
        """:meth:`match_pair` for many tests against one template, batched through the model
        (many volumes per second instead of one forward pass per volume). ``info["assign_probs"]``
        is the same answer without the temperature: what the names are assigned on."""
        if tests:  # checked (rows, names as read) as label does: a row past a test's end was an IndexError
            fixed = check_fixed(fixed, min(len(t) for t in tests)) or None
        split = self._alike_in_colour_input(template, tests, use_colour,
                                            lambda part: self.match_many(template, part, use_colour, fixed))
        if split is not None:
            return split
        found, model_saw_colour = self.search(template, tests, use_colour)
        colours = [self._colour_evidence(template, test, saw) if use_colour else None
                   for test, saw in zip(tests, model_saw_colour)]
        agreements, rechosen = [], []
        for k, f in enumerate(found):
            agreements.append(_agreement_with_fixed([f["all_log_p"]], [template], fixed))
            best = f["best"] if agreements[-1] is None else _best_given_fixed(f["willingness"], f["mirrored"], agreements[-1])
            if best != f["best"]:
                f["best"], f["log_p"], f["moved"] = best, f["all_log_p"][best], f["candidates"][best]
                f["affine"] = np.vstack([np.eye(3), np.zeros((1, 3))])
                rechosen.append(k)
        if rechosen and self.settings.refine_steps:  # refined again, from the placement the fixed names chose
            tc, sc = self._model_colours(template, [tests[k] for k in rechosen], use_colour)
            self._refine(found[0]["template_xyz"], [found[k] for k in rechosen], self.settings.refine_steps, tc, sc)
        self._warp_refine(template, tests, found, colours, use_colour)
        out = []
        for f, colour, agreement in zip(found, colours, agreements):
            info = {"mirrored": bool(f["mirrored"][f["best"]]), "willingness": f["willingness"].tolist(),
                    "warp_rms_um": f.get("warp_rms_um"), "same_worm": f.get("same_worm", False),
                    "assign_probs": self._answer(f["log_p"], colour, calibrated=False)}
            # No doubt about the handedness of the template's own worm: a warp that brings it
            # within WARP_SAME_WORM_UM of the template settled it (the other handedness swaps
            # left/right partners micrometres apart). Synthetic pairs: ECE 0.184 -> 0.025.
            doubt = self.settings.template_chirality_doubt and not info["same_worm"]
            other = _other_handedness(f) if agreement is None and doubt else None
            if other is not None:  # the other chirality's answer, for label_many's doubt
                info["other_handedness"] = self._answer(f["all_log_p"][other], colour)
            out.append((self._answer(f["log_p"], colour), info))
        return out

    def _warp_refine(self, template: NeuronTable, tests: list[NeuronTable], found: list[dict],
                     colours: list[np.ndarray | None], use_colour: bool) -> None:
        """The second look of ``warp_um`` (InferenceSettings) for a test that is the template's
        own worm: each test's chosen placement carried by a warp fitted on its answer's
        confident matches; where that leaves the matches within WARP_SAME_WORM_UM of their
        partners, one more model pass (all such tests in one batch), fused with the position
        likelihood there. Updates ``log_p`` and ``moved`` of ``found`` in place, sets
        ``same_worm`` on those and records ``warp_rms_um`` (NaN: fewer than 8 confident
        matches)."""
        if self.settings.warp_um <= 0 or not found:
            return
        a = found[0]["template_xyz"]  # the template in the frame the tests were placed in
        refined, warped, widths = [], [], []
        for k, (f, colour) in enumerate(zip(found, colours)):
            lp = _add_evidence(f["log_p"], colour)
            choice = assign_log(lp, self.settings.no_match_weight)
            partner = np.maximum(choice, 0)
            p = np.exp(lp[np.arange(len(lp)), partner])
            weight = np.where((choice >= 0) & (p >= WARP_MIN_PROB), p, 0.0)
            f["warp_rms_um"] = float("nan")
            if (weight > 0).sum() < 8:
                continue
            placed = fit_warp(f["moved"], a[partner], weight, self.settings.warp_um, WARP_SMOOTHNESS)(f["moved"])
            f["warp_rms_um"] = rms = float(np.sqrt(np.median(((placed - a[partner]) ** 2).sum(axis=1)[weight > 0]) / 3))
            if rms <= WARP_SAME_WORM_UM:
                refined.append(k)
                warped.append(placed)
                widths.append(float(np.clip(WARP_RESIDUAL_SCALE * rms, *WARP_WIDTH_UM)))
        if not refined:
            return
        tc, sc = self._model_colours(template, [tests[k] for k in refined], use_colour)
        for k, lp, placed, width in zip(refined, self._forward_many(a, warped, tc, sc), warped, widths):
            found[k].update(log_p=_add_evidence(lp, position_evidence(placed, a, width)), moved=placed, same_worm=True)

    @one_blas_thread
    def search(self, template: NeuronTable, tests: list[NeuronTable], use_colour: bool = True, refine_steps: int | None = None):
        """The full search for many tests against one template: registration (:meth:`place`),
        every candidate pose through the model in one batch, the choice, ``refine_steps``
        refinements. Returns the per-test results of :meth:`_align` (plus ``mirrored``, the
        candidates' flags, and ``template_xyz``, the template in the frame they were placed in) and whether the model took colour. ``fdlc label`` and the first
        volume of ``fdlc track`` both start here. Whether the model took colour, per test."""
        split = self._alike_in_colour_input(template, tests, use_colour,
                                            lambda part: list(zip(*self.search(template, part, use_colour, refine_steps))))
        if split is not None:
            return [f for f, _ in split], [saw for _, saw in split]
        a, starts, mirrored, priors = self.place(template, tests, use_colour)
        tc, sc = self._model_colours(template, tests, use_colour)
        found = self._align(a, starts, refine_steps, tc, sc, prior=priors)
        for f, flags in zip(found, mirrored):
            f["mirrored"], f["template_xyz"] = flags, a
        return found, [tc is not None] * len(tests)

    def _alike_in_colour_input(self, template: NeuronTable, tests: list[NeuronTable], use_colour: bool, run):
        """None when the model takes colour for every test or for none (one batch); else the
        answers of ``run`` (tests -> one answer each) on each kind of test apart, in the tests'
        order: one test without B took the colour input from all of them."""
        takes = [self._takes_colour([template, test], use_colour) for test in tests]
        if len(set(takes)) < 2:
            return None
        out: list = [None] * len(tests)
        for kind in (True, False):
            rows = [k for k, t in enumerate(takes) if t == kind]
            for k, answer in zip(rows, run([tests[k] for k in rows])):
                out[k] = answer
        return out

    def _answer(self, log_p: np.ndarray, colour: np.ndarray | None, calibrated: bool = True) -> np.ndarray:
        """The model's log p for one placement -> probabilities (N, M + 1), fused with the
        ``colour`` evidence (:meth:`_colour_evidence`, None: position only); ``calibrated``: with
        the temperature. The names are assigned on the answer without it (the weights of colour
        and of "no match" were chosen for top-1 at temperature 1), so that calibration changes
        the confidences reported, not the names."""
        return np.exp(self._calibrate(log_p, colour) if calibrated else _add_evidence(log_p, colour))

    def _model_colours(self, template: NeuronTable, tests: list[NeuronTable], use_colour: bool):
        """Colour inputs for a model trained with colour (normal scores of R, G, B), or Nones
        when the model has no colour branch, colour is off, or a table lacks a channel."""
        tables = [template, *tests]
        if not self._takes_colour(tables, use_colour):
            return None, None
        scores = [colour_model.normal_scores(t, colour_model.IDENTITY_CHANNELS) for t in tables]
        return scores[0], scores[1:]

    def _takes_colour(self, tables: list[NeuronTable], use_colour: bool) -> bool:
        """Whether the model gets colour as an input for these tables (see _model_colours)."""
        return bool(use_colour and self.model.config.get("colour_channels")) and all(
            colour_model.has_colour(t) for t in tables)

    def _calibrate(self, log_p: np.ndarray, evidence: np.ndarray | None = None) -> np.ndarray:
        """Temperature (fitted on training labs) on the final answer only — not on the
        placement choice or the refinement weights — then ``evidence`` as :func:`_add_evidence`
        adds it. One renormalisation does for both: the tempered rows' own would cancel in it."""
        if evidence is None and self.settings.temperature == 1.0:
            return log_p
        tempered = log_p / self.settings.temperature
        if evidence is not None:
            tempered[:, :-1] += evidence
        return _log_softmax_rows(tempered)

    def _colour_evidence(self, template: NeuronTable, test: NeuronTable, model_saw_colour: bool) -> np.ndarray | None:
        """(N_test, M_template) weighted colour log-likelihood ratios, added to the positional
        log-probabilities by :func:`_add_evidence` (None: no channel in common, or weight 0). It
        depends on the two tables only, not on the placement: computed once per pair. When the model itself
        could not take colour (a table lacks one of R, G, B), the channels the two tables share
        are still used, with the weight of a position-only model."""
        weight = self.settings.colour_weight if model_saw_colour else self.settings.fallback_colour_weight
        channels = colour_model.shared_channels(template, test)
        if not channels or weight == 0:
            return None
        f = colour_model.normal_scores(template, channels)
        g = colour_model.normal_scores(test, channels)
        sigma = self.settings.colour_sigma
        # Likelihood ratio against the population (normal scores are N(0,1) by construction),
        # so "no match" keeps ratio 1 and colour only reorders real candidates.
        llr = colour_model.colour_log_likelihood(f, g, sigma)
        llr += 0.5 * (g**2).sum(axis=1, keepdims=True) - len(channels) * np.log(sigma)
        llr *= weight
        return llr

    def label(
        self,
        test: NeuronTable,
        templates: list[NeuronTable],
        use_colour: bool = True,
        fixed: dict[int, str] | None = None,
        atlas: Atlas | None = None,
    ) -> Labelling:
        """Names for every test neuron from one or several labelled templates, each matched in
        its own registration. ``fixed`` maps rows to names the user decided. With an ``atlas``
        (and atlas weights in the settings), the templates' answer is joined by the atlas's
        answers (:meth:`_join_atlas`)."""
        return self.label_many([test], templates, use_colour, atlas, fixed)[0]

    @one_blas_thread
    def label_many(
        self,
        tests: list[NeuronTable],
        templates: list[NeuronTable],
        use_colour: bool = True,
        atlas: Atlas | None = None,
        fixed: dict[int, str] | None = None,
    ) -> list[Labelling]:
        """:meth:`label` for several tests, each template's matches batched over the tests
        (:meth:`match_many`: many volumes per second instead of one pass per volume); the same
        answers. ``fixed`` applies to every test (give it with one test). With an ``atlas``, a
        test that spreads along the body further than a head and than every template is named
        in its head window only (:func:`napari_fdlc.register.head_window`), as the panel does."""
        checked = {}
        for test in tests:
            self._check(test, templates, use_colour)
            checked = check_fixed(fixed, len(test))
        fixed = checked or None  # as a table's names are read: ' ADAL ' and 'ADAL?' are ADAL
        windows = [None] * len(tests)
        if atlas is not None:
            mixture = atlas.mixture()
            reach = max([HEAD_WINDOW] + [TEMPLATE_REACH_MARGIN * body_reach(t, mixture) for t in templates])
            windows = [head_window(test, mixture, use_colour, reach) for test in tests]
        if all(w is None for w in windows):
            return self._label_many(tests, templates, use_colour, atlas, fixed)
        return [self._label_many([test], templates, use_colour, atlas, fixed)[0] if w is None else
                _widened(self._label_many([test.subset(w)], templates, use_colour, atlas, _fixed_in(fixed, w),
                                          _fixed_outside(fixed, w))[0], w, len(test), fixed)
                for test, w in zip(tests, windows)]

    def _label_many(self, tests: list[NeuronTable], templates: list[NeuronTable], use_colour: bool,
                    atlas: Atlas | None, fixed: dict[int, str] | None, taken: set[str] = frozenset()) -> list[Labelling]:
        """:meth:`label_many` for tests of a head's extent; ``taken``: names the user gave neurons
        outside them (not given inside)."""
        if not tests:
            return []
        flags = [self._check(test, templates, use_colour) for test in tests]
        # A test without a colour channel in common goes position only, and the model takes
        # colour for a batch only when every test has R, G and B: tests that differ in either are
        # named apart (a test beside one without B lost the model's colour input: 84 of 152 names)
        kinds = [(flag, all(self._takes_colour([t, test], flag) for t in templates)) for test, flag in zip(tests, flags)]
        if len(set(kinds)) > 1:
            return [self._label_many([test], templates, flag, atlas, fixed, taken)[0] for test, flag in zip(tests, flags)]
        use_colour = flags[0]
        matches = [self.match_many(template, tests, use_colour, fixed) for template in templates]
        infos = [[found[k][1] for found in matches] for k in range(len(tests))]  # per test, per template
        wanted = []  # per test, the handedness (relative to the template) the atlas joins in
        for info in infos:
            mirrored = info[0]["mirrored"]
            # The template's own worm (a second look after a warp, :meth:`_warp_refine`) needs
            # no atlas beside the handedness chosen: it cost held-out synthetic pairs 0.5 points.
            chosen = () if all(i["same_worm"] for i in info) else (mirrored,)
            # The other handedness's answer (below) is joined with the atlas in that handedness.
            other = (not mirrored,) if all("other_handedness" in i for i in info) else ()
            wanted.append(chosen + other)
        views = self._atlas_views(tests, templates[0], wanted, use_colour, atlas)
        out = []
        for k, (test, info, view) in enumerate(zip(tests, infos, views)):
            per_template, to_assign = [], []
            for template, found, i in zip(templates, matches, info):
                per_template.append((found[k][0][:, :-1], template.labels))
                to_assign.append((i.pop("assign_probs")[:, :-1], template.labels))
            names, probs = name_probabilities(per_template)
            assign_probs = name_probabilities(to_assign)[1]
            mirrored = info[0]["mirrored"]
            probs, assign_probs, joined = self._join_atlas(test, names, probs, assign_probs, use_colour, view.get(mirrored))
            others = [i.pop("other_handedness", None) for i in info]
            if all(o is not None for o in others):
                # The probabilities reported with a template: the chosen chirality's answer
                # mixed with the other chirality's (each template's best placement in the other
                # handedness, joined with the atlas in that handedness), at
                # ``template_chirality_doubt``. Positions and colours barely tell a worm from its
                # mirror image, so a name is trusted only as much as the handedness it was given in.
                other = name_probabilities([(o[:, :-1], t.labels) for o, t in zip(others, templates)])[1]
                other = self._join_atlas(test, names, other, other, use_colour, view.get(not mirrored))[0]
                doubt = self.settings.template_chirality_doubt
                probs = (1 - doubt) * probs + doubt * other
            probs, assign_probs = _without(names, taken, probs, assign_probs)
            out.append(make_labelling(names, probs, fixed, {"templates": info, "colour": use_colour, "atlas": joined},
                                      self.settings.no_match_weight, assign_probs=assign_probs))
        return out

    def _join_atlas(self, test: NeuronTable, names: list[str], probs: np.ndarray, assign_probs: np.ndarray,
                    use_colour: bool, view: AtlasView | None):
        """(probs, assign_probs, joined): the templates' answer over ``names``, averaged with the
        model's answer against the atlas's mean worm (:meth:`_atlas_worm_answer`, at
        ``atlas_worm_weight``), times the atlas's own posterior at the test's placement there
        (:func:`napari_fdlc.register.posterior`, in the template's names, see :func:`_in_names`)
        raised to ``atlas_weight``; ``view`` is the test's from :meth:`_atlas_views`; unchanged
        (joined False) without one."""
        if view is None:
            return probs, assign_probs, False
        atlas = view.atlas
        weight = self.settings.atlas_weight if use_colour else self.settings.atlas_weight_position
        worm_weight = self.settings.atlas_worm_weight if use_colour else self.settings.atlas_worm_weight_position
        if view.worm_log_p is not None:
            worm_probs, worm_assign = self._atlas_worm_answer(test, view, names, probs, assign_probs, use_colour)
            probs = (1 - worm_weight) * probs + worm_weight * worm_probs
            assign_probs = (1 - worm_weight) * assign_probs + worm_weight * worm_assign
        if weight > 0:
            resp, none = posterior(test, atlas.mixture(), view.placement.xyz, use_colour)
            prior = _in_names(resp, none, atlas.names, names)
            # Names on the product itself; the probabilities reported temper the atlas's part
            # like the model's (the temperature divides the whole log-answer).
            probs, assign_probs = _times(probs, prior, weight / self.settings.temperature), _times(assign_probs, prior, weight)
        return probs, assign_probs, True

    def _atlas_views(self, tests: list[NeuronTable], template: NeuronTable, wanted: list[tuple[bool, ...]],
                     use_colour: bool, atlas: Atlas | None) -> list[dict[bool, AtlasView]]:
        """For each test, {mirrored_to_template: :class:`AtlasView`} in each handedness
        of ``wanted`` (relative to the template): the test placed in the atlas's frame
        (:meth:`_atlas_placement`, both handedness in one registration) and the model's log p
        against the atlas's mean worm there (None when ``atlas_worm_weight`` is 0 or the test is
        a partial view: SF's ~60-neuron recordings sit on the whole-head mean worm at one of
        several offsets, a weaker placement than on a template of its own lab). Every test's
        passes go to the model as one batch. Empty without an atlas, at atlas weights 0, when
        the template cannot place the atlas, or for a test of fewer than FEW_NEURONS neurons."""
        weight = self.settings.atlas_weight if use_colour else self.settings.atlas_weight_position
        worm_weight = self.settings.atlas_worm_weight if use_colour else self.settings.atlas_worm_weight_position
        views: list[dict] = [{} for _ in tests]
        if atlas is None or (weight <= 0 and worm_weight <= 0):
            return views
        passes = []  # (test index, handedness, placement) for the mean worm
        for k, (test, handedness) in enumerate(zip(tests, wanted)):
            if not handedness or len(test) < FEW_NEURONS:
                continue
            placements = self._atlas_placement(test, template, handedness, atlas, use_colour)
            for mirrored, placement in zip(handedness, placements or ()):
                views[k][mirrored] = AtlasView(atlas, placement)
                if worm_weight > 0 and not placement.partial_view:
                    passes.append((k, mirrored, placement))
        if passes:
            from .reference import atlas_worm

            if self._mean_worm[0] is not atlas:
                self._mean_worm = (atlas, atlas_worm(atlas))
            worm = self._mean_worm[1]
            # One batch for the tests that give the model colour and one for those that do not.
            for takes in (True, False):
                group = [p for p in passes if self._takes_colour([worm, tests[p[0]]], use_colour) == takes]
                if not group:
                    continue
                tc, sc = self._model_colours(worm, [tests[k] for k, _, _ in group], use_colour)
                log_ps = self._forward_grid([worm.xyz], [p.xyz for _, _, p in group], None if tc is None else [tc], sc)[0]
                for (k, mirrored, placement), log_p in zip(group, log_ps):
                    views[k][mirrored] = AtlasView(atlas, placement, worm, log_p)
        return views

    def _atlas_placement(self, test: NeuronTable, template: NeuronTable, handedness: tuple[bool, ...], atlas: Atlas,
                         use_colour: bool) -> list[Placement] | None:
        """The test placed in the atlas's frame, once for each handedness relative to the
        template (``handedness``: mirrored to the template or not) in one registration: a
        template is labelled, so its names give its handedness relative to the atlas, and with
        the test's relative to the template, the test's (None when the template shares fewer
        than 4 names with the atlas)."""
        # The template's handedness relative to the atlas, once per template (2 ms a time)
        # (by the template's content: a table changed in place is another template)
        cached_atlas, cached_template, _ = self._template_handedness
        key = (template.xyz.tobytes(), tuple(template.label_strings()))
        if cached_atlas is not atlas or cached_template != key:
            self._template_handedness = (atlas, key, mirrored_by_names(atlas.names, atlas.mean, template, min_names=4))
        template_mirrored = self._template_handedness[2]
        if template_mirrored is None:
            return None
        chiralities = tuple(bool(template_mirrored) != bool(m) for m in handedness)
        # Without the z stretch of the panel's registration: beside a template it took pairs
        # with colour up 0.1-2.3 points but, the settings refitted, SF's position-only pairs
        # below the non-learned floor (held out, 32.9 -> 23.2 %; docs/benchmarks.md).
        return atlas.register(test, use_colour, chiralities=chiralities, stretch_z=False)

    def _atlas_worm_answer(self, test: NeuronTable, view: AtlasView, names: list[str], probs: np.ndarray,
                           assign_probs: np.ndarray, use_colour: bool):
        """The model's answer (reported, and without the temperature for the assignment) for
        the test placed in the atlas's frame against the atlas's mean worm (``view``, from
        :meth:`_atlas_views`), in the template's ``names`` (N, names): a name the atlas lacks
        keeps the template's own probability (no opinion); what the atlas gives names the
        template lacks is "no named match". The atlas's part shares what the names it lacks
        leave of each row, so that the answer stays a probability (the two side by side summed
        up to ~2: averaged in, a neuron's "no named match" share was gone)."""
        worm, log_p = view.worm, view.worm_log_p
        colour = self._colour_evidence(worm, test, self._takes_colour([worm, test], use_colour)) if use_colour else None
        column = {n: i for i, n in enumerate(worm.labels)}
        known = np.array([n in column for n in names], dtype=bool)
        rows = [column[n] for n, k in zip(names, known) if k]
        out = []
        for calibrated, own in ((True, probs), (False, assign_probs)):
            answer = own.copy()
            left = np.clip(1 - own[:, ~known].sum(axis=1, keepdims=True), 0, 1)
            answer[:, known] = left * self._answer(log_p, colour, calibrated)[:, rows]
            out.append(answer)
        return out

    @one_blas_thread
    def label_panel(self, test: NeuronTable, panel: Panel, use_colour: bool = True, fixed: dict[int, str] | None = None) -> Labelling:
        """Names from the built-in panel. The test is placed in the atlas frame once per
        chirality (:meth:`Atlas.register`); the panel's templates share that frame, so one
        chirality is chosen for all of them: the one agreeing with the user's ``fixed`` names
        when there are any, else the one the model is most willing to match, minus the fixed
        prior against a mirrored placement (``mirror_penalty``). The choice is made on the first
        ``PANEL_HANDEDNESS_TEMPLATES`` templates (their willingness scaled to the whole panel, so
        that the prior keeps its weight); the other templates run in the chosen chirality only.
        A test that shows much of the body beyond the head is named in its head only
        (:func:`napari_fdlc.register.head_window`); the rest get no name."""
        from .reference import Panel  # (not at the top: reference imports this module's neighbours)

        if not isinstance(panel, Panel):
            raise TypeError(f"label_panel takes the built-in panel (napari_fdlc.reference.load_panel()), not a "
                            f"{type(panel).__name__}; for templates use label()")
        use_colour = self._check(test, panel.templates, use_colour)
        fixed = check_fixed(fixed, len(test)) or None  # as a table's names are read: ' ADAL ' and 'ADAL?' are ADAL
        window = head_window(test, panel.atlas.mixture(), use_colour)
        if window is None:
            result = self._label_panel(test, panel, use_colour, fixed)
        else:
            result = _widened(self._label_panel(test.subset(window), panel, use_colour, _fixed_in(fixed, window),
                                                _fixed_outside(fixed, window)), window, len(test), fixed)
        taken_up = smaller_worm_factor(test.xyz)
        if taken_up > 1.0:  # registered as a smaller worm (napari_fdlc.register.YOUNG_ADULT_SPACING_UM)
            result.info["smaller_worm"] = taken_up
        return result

    def _label_panel(self, test: NeuronTable, panel: Panel, use_colour: bool, fixed: dict[int, str] | None,
                     taken: set[str] = frozenset()) -> Labelling:
        """:meth:`label_panel` for a test of a head's extent, colour checked; ``taken`` as in
        :meth:`_label_many`."""
        placements = panel.atlas.register(test, use_colour, self._chiralities())
        templates = panel.templates
        tc_sc = [self._model_colours(t, [test], use_colour) for t in templates]
        with_colour = all(tc is not None for tc, _ in tc_sc)

        def passes(indices, chosen):  # per template: (placements, N, M + 1), all from one batch
            return [np.stack(lps) for lps in self._forward_grid(
                [templates[i].xyz for i in indices], [p.xyz for p in chosen],
                [tc_sc[i][0] for i in indices] if with_colour else None,
                tc_sc[0][1] * len(chosen) if with_colour else None)]

        deciders = range(min(PANEL_HANDEDNESS_TEMPLATES, len(templates)) if len(placements) == 2 else len(templates))
        first = passes(deciders, placements)
        willingness = sum(_willingness(lps, len(templates[i])) for lps, i in zip(first, deciders))
        willingness = willingness * len(templates) / len(deciders)
        willingness = willingness - self.settings.mirror_penalty * np.array([p.mirrored for p in placements])
        agreement = _agreement_with_fixed(first, [templates[i] for i in deciders], fixed)
        best = int(np.argmax(willingness)) if agreement is None else \
            _best_given_fixed(willingness, [p.mirrored for p in placements], agreement)
        others = range(len(deciders), len(templates))
        rest = passes(others, [placements[best]]) if len(others) else []
        answers = [lps[best] for lps in first] + [lps[0] for lps in rest]  # per template, chosen placement
        colours = [self._colour_evidence(t, test, tc is not None) if use_colour else None
                   for t, (tc, _) in zip(templates, tc_sc)]

        def names_and_probs(per_template, calibrated=True):  # the panel's answer: (names, (N, names))
            return name_probabilities([
                (self._answer(lp, colours[i], calibrated)[:, :-1], templates[i].labels)
                for i, lp in enumerate(per_template)
            ])

        # The names are assigned on the chosen placement's answer without the temperatures.
        # The probabilities reported keep some weight on the other chirality (its answer from
        # the deciding templates; none once a fixed name decided: its answer is mostly the same
        # names with left and right swapped, so the doubt lands on the partner) and get the
        # panel's temperature; both fitted for calibration.
        weight = self.settings.panel_atlas_weight if use_colour else self.settings.panel_atlas_weight_position
        atlas_answers = {}  # placement index -> the atlas's posterior there, computed once

        def with_atlas(names, probs, k):  # times the atlas's answer at placement k
            if weight <= 0:
                return probs
            if k not in atlas_answers:
                atlas_answers[k] = posterior(test, panel.atlas.mixture(), placements[k].xyz, use_colour)
            return _times(probs, _in_names(*atlas_answers[k], panel.atlas.names, names), weight)

        names, chosen = names_and_probs(answers)
        probs = chosen = with_atlas(names, chosen, best)
        doubt = self.settings.chirality_doubt if agreement is None and len(placements) == 2 else 0.0
        if doubt:
            other_names, other_probs = names_and_probs([lps[1 - best] for lps in first])
            other_probs = with_atlas(other_names, other_probs, 1 - best)
            other = {n: other_probs[:, i] for i, n in enumerate(other_names)}
            probs = (1 - doubt) * chosen + doubt * np.stack([other.get(n, np.zeros(len(test))) for n in names], axis=1)
        probs = _sharpen(probs, self.settings.panel_temperature)
        info = {"colour": use_colour, "mirrored": placements[best].mirrored, "willingness": willingness.tolist(),
                "registration": [p.score for p in placements]}
        probs, assign_probs = _without(names, taken, probs,
                                       with_atlas(names, names_and_probs(answers, calibrated=False)[1], best))
        return make_labelling(names, probs, fixed, info, self.settings.no_match_weight, assign_probs=assign_probs)

    @one_blas_thread
    def label_panel_many(self, tests: list[NeuronTable], panel: Panel, use_colour: bool = True,
                         first: list[Labelling] | None = None, share_handedness: bool = True,
                         adapt_colours: bool = False) -> list[Labelling]:
        """:meth:`label_panel` for several recordings of one microscope, which can decide
        together what one worm cannot show. ``first``: the tests' :meth:`label_panel` answers
        when already made.

        ``share_handedness``: on ``auto``, one handedness for all of them when their evidence
        clearly agrees (:func:`decide_handedness`; handedness is a property of the microscope),
        else each keeps its own choice. ``info["batch_handedness"]`` says what was decided.

        ``adapt_colours`` (with colour, from ``ADAPT_MIN_TESTS`` tests): then the atlas's colour
        per name is measured on the tests themselves, from the names given with confidence
        ``ADAPT_MIN_CONF`` or more in at least ``ADAPT_MIN_WORMS`` of them
        (:meth:`Atlas.with_colours_of`), and the tests are named again with a panel drawn from
        that atlas. ``info["adapted_colours"]`` counts the names whose colour was measured."""
        if first is not None and len(first) != len(tests):
            raise FdlcError(f"label_panel_many: {len(first)} first answers for {len(tests)} tests (one each)")
        results = list(first) if first is not None else [self.label_panel(t, panel, use_colour) for t in tests]
        if share_handedness:
            results = self._shared_handedness(tests, panel, use_colour, results)
        if not (adapt_colours and can_adapt_colours(tests, use_colour)):
            return results
        from .reference import panel_on

        counted = _counted_recordings(tests)  # a tiny test or a copy measures nothing of its own
        names = [np.where((np.asarray(r.auto_conf) >= ADAPT_MIN_CONF) & c, np.asarray(r.auto_id, dtype=object), "")
                 for r, c in zip(results, counted)]
        atlas = panel.atlas.with_colours_of(tests, names, ADAPT_MIN_WORMS)
        adapted = int((atlas.colour != panel.atlas.colour).any(axis=1).sum())
        # The handedness the tests decided together stands: the colours were measured on names
        # given in it, and a second vote can fall short of significance (7 of 7 decides, 6 of 6
        # does not) and leave every worm to its own, wrong, choice
        batch = results[0].info.get("batch_handedness") if results else None
        decided = batch["decided"] if batch else None
        again = self.with_chirality(decided) if decided else self
        results = again.label_panel_many(tests, panel_on(panel, atlas), use_colour, share_handedness=share_handedness)
        for r in results:
            r.info["adapted_colours"] = adapted
            if decided:
                r.info["batch_handedness"] = batch
        return results

    def _shared_handedness(self, tests: list[NeuronTable], panel: Panel, use_colour: bool,
                           results: list[Labelling]) -> list[Labelling]:
        """The sign test of :meth:`label_panel_many` over the tests' answers ``results``."""
        if self.settings.chirality != "auto" or len(tests) < 2:
            return results
        evidence = np.array([handedness_evidence(r, self.settings.mirror_penalty) if c else (0.0, 0.0)
                             for r, c in zip(results, _counted_recordings(tests))])  # (0, 0): abstains
        decided, k, n = decide_handedness(evidence[:, 0], evidence[:, 1])
        for i, r in enumerate(results):
            if decided and r.info["mirrored"] != (decided == "mirrored"):
                results[i] = self.with_chirality(decided).label_panel(tests[i], panel, use_colour)
            # a new Labelling: the caller's own answers (``first``) are left as they were
            results[i] = replace(results[i], info={**results[i].info, "batch_handedness": {
                "decided": decided, "lean_mirrored": k, "votes": n, "tests": len(tests)}})
        return results

    def _check(self, test: NeuronTable, templates: list[NeuronTable], use_colour: bool) -> bool:
        """Refuse a missing model or template; returns whether colour can be used."""
        if self.model is None:
            raise ModelError("no model loaded")
        if not templates:
            raise FdlcError("no template given")
        _need_tables(test, templates)
        check_named(templates)
        if len(test) == 0:
            raise FdlcError(f"{test.source or 'the test'}: no neurons to name")
        if not all(np.isfinite(t.xyz).all() for t in (test, *templates)):
            raise FdlcError("a neuron position is not a finite number")
        refuse_flat(test.xyz, test.source, FEW_NEURONS)
        return use_colour and any(colour_model.shared_channels(t, test) for t in templates)


def colour_note(test: NeuronTable, references: list[NeuronTable], use_colour: bool = True) -> str | None:
    """The line to say when colour was asked for but ``test`` shares no colour channel with the
    ``references`` (templates, or the panel's), so it is named by position only; else None."""
    if not use_colour or any(colour_model.shared_channels(t, test) for t in references):
        return None
    flat = [c for c in colour_model.IDENTITY_CHANNELS if c in test.colours and c not in colour_model.read_channels(test)]
    if flat:
        return (f"{test.source}: {', '.join(flat)} {'has' if len(flat) == 1 else 'have'} no reading that differs "
                "between neurons (empty, or one value for every neuron): identifying by position only")
    if any(c in test.colours for c in colour_model.IDENTITY_CHANNELS):
        return f"{test.source}: no colour channel in common with the template(s): identifying by position only"
    return f"{test.source}: no colour column (R, G, B): identifying by position only (--no-color says it is meant)"


def smaller_worm_note(test: NeuronTable, result: Labelling) -> str | None:
    """The line to say when the panel named ``test`` as a smaller worm than a young adult
    (its neurons lie closer together than in a complete head), else None."""
    taken_up = result.info.get("smaller_worm")
    if not taken_up:
        return None
    return (f"{test.source}: its neurons lie closer together than in a young adult's head, so it is named as a "
            f"smaller worm (its positions taken {taken_up:.2f}x larger); if it is not, check that x_um, y_um, z_um are µm")


def can_adapt_colours(tests: list[NeuronTable], use_colour: bool = True) -> bool:
    """Whether :meth:`Identifier.label_panel_many` can measure the panel's colours on these
    tests: with colour, and ``ADAPT_MIN_TESTS`` of them or more having R, G and B."""
    coloured = [t for t, c in zip(tests, _counted_recordings(tests)) if c and colour_model.has_colour(t)]
    return use_colour and len(coloured) >= ADAPT_MIN_TESTS


def _counted_recordings(tests: list[NeuronTable]) -> list[bool]:
    """Which tests count as recordings of their own where several decide together (the shared
    handedness, the colours measured on them): not one of fewer than ``FEW_NEURONS`` neurons (3
    points always lie in a plane, their mirror image is themselves: a vote by chance; 2 have
    normal scores of +-0.67 whatever was measured) nor a copy of an earlier one (a file given
    twice was two votes, and three copies of one worm measured its colours on itself)."""
    seen, out = set(), []
    for t in tests:
        rows = np.column_stack([t.xyz, *(v for _, v in sorted(t.colours.items()))])
        rows = rows[np.lexsort(rows.T[::-1])]  # a copy with its rows in another order is a copy
        key = hash((rows.tobytes(), tuple(sorted(t.colours))))
        out.append(len(t) >= FEW_NEURONS and key not in seen)
        seen.add(key)
    return out


def handedness_evidence(result: Labelling, mirror_penalty: float) -> tuple[float, float]:
    """Of a :meth:`Identifier.label_panel` answer made on ``auto``: its mirrored placement's
    score minus the other's, by the model's willingness to match (without the prior) and by
    the registration's likelihood."""
    willingness, registration = result.info.get("willingness") or (), result.info.get("registration") or ()
    if len(willingness) < 2 or len(registration) < 2:  # made in one handedness (given, or a template's): abstains
        return 0.0, 0.0
    return willingness[1] - willingness[0] + mirror_penalty, registration[1] - registration[0]


def decide_handedness(willingness, registration=None) -> tuple[str | None, int, int]:
    """One handedness for several recordings from their evidence (:func:`handedness_evidence`):
    a recording votes for the side its two pieces of evidence lean to, and abstains when they
    disagree (``registration`` None: the willingness alone votes); "mirrored" or "same" when
    significantly many votes go one way (one-sided sign test, p < ``BATCH_HANDEDNESS_P``), else
    None. Returns (decided, votes for mirrored, votes).

    Per worm either piece is weak (right for 22-89 % of the worms of a lab the model never
    saw), and a lab can lean the wrong way on one: with an atlas built without KK, the shipped
    model's willingness leans mirrored on 6 of KK's 9 worms (2 are), its registration on 1.
    On batches of 30 recordings resampled from each corpus lab, the willingness alone decided
    50 of 2000 wrongly (KK's), the two together 1 (benchmarks/handedness.py, handedness.md)."""
    from scipy.stats import binomtest

    willingness = np.asarray(willingness, dtype=float)
    registration = willingness if registration is None else np.asarray(registration, dtype=float)
    votes = (np.sign(willingness) == np.sign(registration)) & (willingness != 0)
    k, n = int((votes & (willingness > 0)).sum()), int(votes.sum())
    for decided, side in (("mirrored", "greater"), ("same", "less")):
        if n and binomtest(k, n, 0.5, alternative=side).pvalue < BATCH_HANDEDNESS_P:
            return decided, k, n
    return None, k, n


def _need_tables(test, templates) -> None:
    """A script's test and templates are neuron tables (a DataFrame or an array ended in an
    AttributeError deep inside)."""
    for what, table in (("the test", test), *(("a template", t) for t in templates)):
        if not isinstance(table, NeuronTable):
            raise TypeError(f"{what} must be a NeuronTable (napari_fdlc.table.read_table, or NeuronTable(xyz)), "
                            f"not a {type(table).__name__}")


def _fixed_in(fixed: dict[int, str] | None, rows: np.ndarray) -> dict[int, str] | None:
    """The user's ``fixed`` names (by row of a test) by row of the test's ``rows``."""
    inside = {k: fixed[row] for k, row in enumerate(rows.tolist()) if row in (fixed or {})}
    return inside or None


def _fixed_outside(fixed: dict[int, str] | None, rows: np.ndarray) -> set[str]:
    """The names the user fixed on neurons outside ``rows``: not given to a neuron inside."""
    inside = set(rows.tolist())
    return {name for row, name in (fixed or {}).items() if row not in inside}


def _without(names: list[str], taken: set[str], *probs: np.ndarray) -> list[np.ndarray]:
    """``probs`` (N, names) with the ``taken`` names' columns emptied (their share goes to "no
    named match"), before the names are assigned: the reported and the assigned answers alike."""
    columns = [i for i, name in enumerate(names) if name in taken]
    if not columns:
        return list(probs)
    out = [p.copy() for p in probs]
    for p in out:
        p[:, columns] = 0.0
    return out


def _widened(part: Labelling, rows: np.ndarray, n: int, fixed: dict[int, str] | None) -> Labelling:
    """``part``, the answer for ``rows`` of a test of ``n`` neurons (named without the names
    fixed outside them, :func:`_fixed_outside`), as the answer for the whole test: the other
    neurons get no name (certainly no named match), or the name the user fixed."""
    inside = set(rows.tolist())
    probs = np.zeros((n, len(part.names)))
    probs[rows] = part.probs
    auto_id, auto_conf = [""] * n, np.ones(n)
    for k, row in enumerate(rows):
        auto_id[row], auto_conf[row] = part.auto_id[k], part.auto_conf[k]
    for row, name in (fixed or {}).items():
        if row not in inside:
            auto_id[row], auto_conf[row] = name, 0.0
    return Labelling(part.names, probs, auto_id, auto_conf, {**part.info, "head_window": len(rows)})


def _add_evidence(log_p: np.ndarray, evidence: np.ndarray | None) -> np.ndarray:
    """log p (N, M + 1) with evidence (N, M; log likelihood ratios such as colour's) added to
    the real columns ("no match" keeps ratio 1: evidence only reorders real candidates),
    renormalised."""
    if evidence is None:
        return log_p
    fused = log_p.copy()
    fused[:, :-1] += evidence
    return _log_softmax_rows(fused)


def _log_softmax_rows(x: np.ndarray) -> np.ndarray:
    """``scipy.special.log_softmax(x, axis=1)`` for rows with a finite entry, in a third of the
    time (its overhead showed in every tracked volume)."""
    top = x.max(axis=1, keepdims=True)
    return x - (top + np.log(np.exp(x - top).sum(axis=1, keepdims=True)))


def _in_names(resp: np.ndarray, none: np.ndarray, atlas_names, names: list[str]) -> np.ndarray:
    """The atlas's answer (N, atlas names) and (N,) none as (N, names + 1), the last column
    "none". A name the atlas lacks gets the neuron's mean over the names it knows: no opinion."""
    column = {n: i for i, n in enumerate(atlas_names)}
    known = np.array([n in column for n in names], dtype=bool)
    out = np.empty((len(resp), len(names) + 1))
    out[:, :-1][:, known] = resp[:, [column[n] for n, k in zip(names, known) if k]]
    out[:, :-1][:, ~known] = out[:, :-1][:, known].mean(axis=1, keepdims=True) if known.any() else 1.0
    out[:, -1] = none
    return out


def _times(probs: np.ndarray, answer: np.ndarray, weight: float) -> np.ndarray:
    """``probs`` (N, names; the rest of each row is "no match") times another ``answer`` (N,
    names + 1, the last column "none") raised to ``weight``, renormalised: a product of
    experts. The small floor keeps one expert from vetoing a name outright."""
    return _renormalised(_with_no_match(probs) * (answer + 1e-4) ** weight)


def _sharpen(probs: np.ndarray, temperature: float) -> np.ndarray:
    """``probs`` (N, names; the rest of each row is "no match") raised to 1/temperature and
    renormalised with the no-match share. Averaging the templates' answers leaves the panel
    under-confident; a temperature fitted on the training labs undoes it."""
    if temperature == 1.0:
        return probs
    return _renormalised(np.maximum(_with_no_match(probs), 1e-300) ** (1 / temperature))


def _with_no_match(probs: np.ndarray) -> np.ndarray:
    """(N, names) -> (N, names + 1): the rest of each row as an explicit "no match" column."""
    return np.hstack([probs, np.clip(1 - probs.sum(axis=1, keepdims=True), 0, None)])


def _renormalised(full: np.ndarray) -> np.ndarray:
    """Rows of (N, names + 1) scaled to sum 1, then without the "no match" column."""
    return (full / full.sum(axis=1, keepdims=True))[:, :-1]


def _other_handedness(found: dict) -> int | None:
    """Index of the likeliest candidate placement in the chirality not chosen (None: none tried)."""
    other = np.flatnonzero(found["mirrored"] != found["mirrored"][found["best"]])
    return int(other[np.argmax(found["willingness"][other])]) if len(other) else None


def _willingness(log_ps: np.ndarray, m: int) -> np.ndarray:
    """Per candidate placement (K, N, M + 1): mean log-probability of *having* a match. Trained
    with wrongly oriented pairs as negatives, the model puts its mass on "no match" when the
    worms are not aligned, so the placement it is most willing to match is the likeliest."""
    return np.log1p(-np.exp(np.minimum(log_ps[:, :, m], -1e-6))).mean(axis=1)


def _agreement_with_fixed(per_candidate, templates: list[NeuronTable], fixed: dict[int, str] | None) -> np.ndarray | None:
    """Per candidate placement: summed log-probability of the names the user fixed (over
    templates); None when no fixed name is in any template. One confirmed left/right neuron is
    enough to settle a chirality that positions and colours cannot (bilateral symmetry)."""
    total = None
    for lps, template in zip(per_candidate, templates):
        index = {n: i for i, n in enumerate(template.labels) if n}
        rows = [(j, index[n]) for j, n in (fixed or {}).items() if n in index]
        if rows:
            j, i = np.array(rows).T
            score = np.array([lp[j, i].sum() for lp in lps])
            total = score if total is None else total + score
    return total


def _best_given_fixed(willingness: np.ndarray, mirrored, agreement: np.ndarray) -> int:
    """The placement the user's fixed names point to: each handedness's likeliest placement
    (willingness and registration prior, as without fixed names), then of those the one the
    fixed names agree with more. They settle the handedness, not the pose: over every
    placement, one fixed neuron's log p chose among poses by its noise (a wrong mirrored start
    won, and a template's answer fell from 73 to 9 % top-1 once one right name was confirmed).
    One name cannot tell a worm named the wrong way round from one neuron given its partner's
    name, and is taken as the first (benchmarks/fixed_names.py, docs/benchmarks.md)."""
    mirrored = np.asarray(mirrored, bool)
    willingness = np.asarray(willingness, float)
    winners = [int(np.flatnonzero(mirrored == m)[np.argmax(willingness[mirrored == m])])
               for m in (False, True) if (mirrored == m).any()]
    return max(winners, key=lambda k: agreement[k])


_DEFAULT: dict = {}
_DEFAULT_LOCK = threading.Lock()


def default_identifier() -> Identifier:
    """The shipped model, loaded once per process (a widget's warm-up thread and a job may ask
    at the same time)."""
    with _DEFAULT_LOCK:
        if "identifier" not in _DEFAULT:
            _DEFAULT["identifier"] = Identifier.load()
        return _DEFAULT["identifier"]


def shipped_tracking_weights() -> Path:
    return shipped_weights().with_name(TRACKING_WEIGHTS_NAME)


def default_tracker(device: str | None = None) -> Identifier:
    """The shipped tracking model (what ``fdlc track`` runs on volumes placed from the one
    before; docs/model_card.md), loaded once per process and device (None: the one
    :class:`Identifier` would choose, so that it is not loaded twice)."""
    if device is None:
        import torch

        device = "cuda" if torch.cuda.is_available() else "cpu"
    key = ("tracker", device)
    with _DEFAULT_LOCK:
        if key not in _DEFAULT:
            _DEFAULT[key] = Identifier.load(shipped_tracking_weights(), device)
        return _DEFAULT[key]


def harmonised_templates(templates: list[NeuronTable]) -> tuple[list[NeuronTable], list[int]]:
    """The templates in the first one's handedness, and the indices of those mirrored back:
    a template whose names fit the first better mirrored (at least 6 names in common) comes
    from a recording mirrored relative to it, and would name the test's left/right pairs the
    other way round than the first; its z is flipped (a mirror image, positions only), which
    its names then fit. Each template is matched in its own registration and their answers
    are averaged, so mixed handedness would average contradictions. On the corpus's KK, SF and
    SK1, whose worms mix both, 2-3 templates of any handedness gained up to 1.0 point of top-1
    this way (held out, benchmarks/templates.py; what is left there is the test's own
    handedness). With ``--chirality same`` their top-3 lost 2-7 points: a template of the
    other handedness had kept the left/right partner among the candidates."""
    if len(templates) < 2:
        return list(templates), []
    first = canonical_frame(templates[0].xyz)[0]
    out, flipped = [templates[0]], []
    for k, template in enumerate(templates[1:], 1):
        if mirrored_by_names(templates[0].labels, first, template, min_names=6):
            template = replace(template, xyz=template.xyz * np.array([1.0, 1.0, -1.0]))
            flipped.append(k)
        out.append(template)
    return out, flipped


def harmonise(templates: list[NeuronTable], report=warn) -> list[NeuronTable]:
    """:func:`harmonised_templates`, saying in one line which were mirrored back (``report``:
    stderr by default; the napari widget shows a notification)."""
    templates, flipped = harmonised_templates(templates)
    if flipped:
        report(f"{', '.join(templates[k].source for k in flipped)}: mirrored relative to {templates[0].source} "
               "(their names say so); used mirrored back, so that every template has one handedness")
    return templates


def label_neurons(
    test: NeuronTable,
    templates: list[NeuronTable] | None = None,
    use_colour: bool = True,
    fixed: dict[int, str] | None = None,
    identifier: Identifier | None = None,
    use_atlas: bool = True,
) -> Labelling:
    """Name the neurons of ``test``. Without templates the built-in reference panel is used
    (what Auto-label does); with templates, they are joined by the built-in atlas's own answer
    (unless ``use_atlas`` is False; see :meth:`Identifier.label`). ``fixed`` maps row indices to
    names the user decided: they are kept and their names are not given to anyone else.
    Several templates are used as given: :func:`harmonise` them first, once (``fdlc label`` and
    the widget do), if they may come from recordings of different handedness."""
    from .reference import load_panel

    identifier = identifier or default_identifier()
    templates = None if templates is None else list(templates)  # a generator, read once (it was used up by the check)
    _need_tables(test, templates or [])
    if not templates:
        return identifier.label_panel(test, load_panel(), use_colour=use_colour, fixed=fixed)
    for t in templates:
        if not t.named.any():
            raise FdlcError(f"{t.source}: the template has no named neuron")
    atlas = load_panel().atlas if use_atlas else None  # the panel is cached; its atlas with it
    return identifier.label(test, templates, use_colour=use_colour, fixed=fixed, atlas=atlas)


def warm_up(identifier: Identifier | None = None, templates: list[NeuronTable] | None = None,
            use_colour: bool = True) -> None:
    """Name one generated worm the way :func:`label_neurons` will name the user's, and throw
    the answer away: the first real call then pays neither torch's import, the model's load,
    the panel's caches nor the model's traces (about 1.4 s on two cores, session 19). The
    widget runs it beside the segmentation that comes first. Errors are left to the real call."""
    from .reference import generate_worm

    try:
        worm = generate_worm(seed=0)
        test = NeuronTable(worm.xyz, worm.colours, source="warm-up")  # no names: a test
        with WARM_UP_LOCK:
            label_neurons(test, templates, use_colour=use_colour, identifier=identifier)
    except FdlcError:
        pass
