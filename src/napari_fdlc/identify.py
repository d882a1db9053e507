"""Identify the neurons of a test worm against one or more labelled templates.

model (positions) ──► orientation search ──► affine refinement ──► colour fusion ──► names
                                                                          │
                                                     match.name_probabilities / assign

The model is loaded once; :meth:`Identifier.label` may be called for as many tests as needed.
torch is imported here only when an :class:`Identifier` is made, so ``import napari_fdlc`` and
napari's plugin discovery stay fast.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from . import colour as colour_model
from .errors import FdlcError, ModelError, warn
from .geometry import ORIENTATIONS, apply_affine, canonical_frame, fit_affine
from .match import Labelling, make_labelling, name_probabilities
from .table import NeuronTable

WEIGHTS_NAME = "fdlc_model"


def shipped_weights() -> Path:
    return Path(str(resources.files("napari_fdlc") / "data" / WEIGHTS_NAME))


@dataclass
class InferenceSettings:
    refine_steps: int = 2  # affine re-alignment passes after the orientation search
    colour_weight: float = 1.0  # λ: exponent of the colour likelihood ratio
    colour_sigma: float = 0.6  # width of the colour likelihood in normal-score units
    temperature: float = 1.0  # divides the log-probabilities (calibration, fitted on training labs)
    chirality_search: bool = True  # also try the z-mirrored recording convention
    no_match_weight: float = 0.2  # see match.assign

    @classmethod
    def from_dict(cls, d: dict | None) -> "InferenceSettings":
        known = {k: v for k, v in (d or {}).items() if k in cls.__dataclass_fields__}
        return cls(**known)


class Identifier:
    """The trained model plus everything needed to turn its output into names."""

    def __init__(self, model=None, settings: InferenceSettings | None = None, device: str | None = None):
        import torch

        self.torch = torch
        self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
        self.model = model.to(self.device).eval() if model is not None else None
        self.settings = settings or InferenceSettings()

    @classmethod
    def load(cls, path: str | Path | None = None, device: str | None = None) -> "Identifier":
        """Load weights (``path`` without suffix; default: the weights shipped in the package)."""
        from .model import load_model

        path = Path(path) if path else shipped_weights()
        if not path.with_suffix(".safetensors").exists():
            raise ModelError(
                f"no trained weights at {path.with_suffix('.safetensors')}: train them with 'fdlc train'"
            )
        model = load_model(path)
        meta = json.loads(path.with_suffix(".json").read_text())
        return cls(model, InferenceSettings.from_dict(meta.get("inference")), device)

    # ------------------------------------------------------------------------------------------
    def _forward(self, template_xyz: np.ndarray, test_batch: np.ndarray) -> np.ndarray:
        """log p for a batch of oriented copies of the test (K, N, 3) against one template."""
        torch = self.torch
        k = len(test_batch)
        tmpl = torch.as_tensor(template_xyz, dtype=torch.float32, device=self.device)
        tests = torch.as_tensor(test_batch, dtype=torch.float32, device=self.device)
        # Chunk so that 2000-neuron worms fit in memory.
        chunk = max(1, int(4e6 // max(1, tests.shape[1] * max(tmpl.shape[0], tests.shape[1]))))
        out = []
        with torch.inference_mode():
            for s in range(0, k, chunk):
                t = tests[s : s + chunk]
                out.append(self.model(tmpl.expand(len(t), -1, -1), t).float().cpu().numpy())
        return np.concatenate(out)

    def match_pair(self, template: NeuronTable, test: NeuronTable, use_colour: bool = True) -> tuple[np.ndarray, dict]:
        """Probabilities (N_test, M_template + 1) that each test neuron is each template neuron
        (last column: no match), with the chosen orientation in the info dict."""
        a, _, _ = canonical_frame(template.xyz)
        b, _, _ = canonical_frame(test.xyz)
        orientations = ORIENTATIONS if self.settings.chirality_search else ORIENTATIONS[:4]
        candidates = np.einsum("kij,nj->kni", orientations, b)
        log_p = self._forward(a, candidates)
        # Trained with wrongly oriented pairs as negatives, the model puts its mass on "no match"
        # when the worms are not aligned: the orientation it is most willing to match wins.
        m = a.shape[0]
        willingness = np.log1p(-np.exp(np.minimum(log_p[:, :, m], -1e-6))).mean(axis=1)
        best = int(np.argmax(willingness))
        moved, lp = candidates[best], log_p[best]
        for _ in range(self.settings.refine_steps):
            p = np.exp(lp[:, :m])
            weight = p.max(axis=1)
            targets = (p @ a) / np.maximum(p.sum(axis=1, keepdims=True), 1e-9)
            affine = fit_affine(moved, targets, weight**2)
            moved = apply_affine(moved, affine)
            lp = self._forward(a, moved[None])[0]
        # Calibration (fitted on training labs) applies to the final answer only, not to the
        # orientation search or the refinement weights.
        lp = lp / self.settings.temperature
        lp = lp - np.logaddexp.reduce(lp, axis=1, keepdims=True)
        if use_colour:
            lp = self._fuse_colour(lp, template, test)
        info = {"orientation": best, "mirrored": best >= 4, "willingness": willingness.tolist()}
        return np.exp(lp), info

    def _fuse_colour(self, log_p: np.ndarray, template: NeuronTable, test: NeuronTable) -> np.ndarray:
        channels = colour_model.shared_channels(template, test)
        if not channels:
            return log_p
        f = colour_model.normal_scores(template, channels)
        g = colour_model.normal_scores(test, channels)
        sigma = self.settings.colour_sigma
        # Likelihood ratio against the population (normal scores are N(0,1) by construction),
        # so "no match" keeps ratio 1 and colour only reorders real candidates.
        llr = colour_model.colour_log_likelihood(f, g, sigma) - len(channels) * np.log(sigma)
        llr = llr + 0.5 * (g**2).sum(axis=1, keepdims=True)
        fused = log_p.copy()
        fused[:, :-1] += self.settings.colour_weight * llr
        fused -= fused.max(axis=1, keepdims=True)
        return fused - np.log(np.exp(fused).sum(axis=1, keepdims=True))

    def label(
        self,
        test: NeuronTable,
        templates: list[NeuronTable],
        use_colour: bool = True,
        fixed: dict[int, str] | None = None,
    ) -> Labelling:
        """Names for every test neuron from one or several labelled templates."""
        if self.model is None:
            raise ModelError("no model loaded")
        if not templates:
            raise FdlcError("no template given")
        if use_colour and not any(colour_model.shared_channels(t, test) for t in templates):
            if any(c in test.colours for c in colour_model.IDENTITY_CHANNELS):
                warn("no colour channel in common with the template(s): identifying by position only")
            use_colour = False
        per_template, infos = [], []
        for template in templates:
            probs, info = self.match_pair(template, test, use_colour)
            per_template.append((probs[:, :-1], template.labels))
            infos.append(info)
        names, probs = name_probabilities(per_template)
        info = {"templates": infos, "colour": use_colour}
        return make_labelling(names, probs, fixed, info, self.settings.no_match_weight)


_DEFAULT: dict = {}


def default_identifier() -> Identifier:
    """The shipped model, loaded once per process."""
    if "identifier" not in _DEFAULT:
        _DEFAULT["identifier"] = Identifier.load()
    return _DEFAULT["identifier"]


def label_neurons(
    test: NeuronTable,
    templates: list[NeuronTable] | None = None,
    use_colour: bool = True,
    fixed: dict[int, str] | None = None,
    identifier: Identifier | None = None,
) -> Labelling:
    """Name the neurons of ``test``. Without templates the built-in reference panel is used
    (what Auto-label does). ``fixed`` maps row indices to names the user decided: they are kept
    and their names are not given to anyone else."""
    from .reference import load_panel

    identifier = identifier or default_identifier()
    templates = templates if templates else load_panel()
    for t in templates:
        if not t.named.any():
            raise FdlcError(f"{t.source}: the template has no named neuron")
    return identifier.label(test, templates, use_colour=use_colour, fixed=fixed)
