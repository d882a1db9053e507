"""The correspondence transformer (fDLC, Yu et al. 2021), written to train on a CPU.

Template and test neurons are embedded from their positions alone (µm in the canonical frame of
:mod:`napari_fdlc.geometry`, divided by ``scale_um``); no positional encoding of the order, so
the model is permutation-equivariant. Each layer lets every neuron attend to the neurons of its
own worm (with a learned distance bias, so that relative geometry comes for free) and then to
the other worm (cross-attention, as in SuperGlue/LightGlue). A learned type embedding marks
template vs test, as the paper's constant offset does.

Scores between template neuron i and test neuron j are a residual on a geometric prior the model
keeps: ``s_ij = <u_i, v_j>/sqrt(d) - alpha * |p_i + dp_i - q_j - dq_j|^2`` where the dp, dq are
learned displacements (a soft non-rigid warp). Every test neuron also gets a "no match" logit.
Probabilities are a softmax per test neuron over the template neurons plus "no match".

Weights are stored as safetensors plus a JSON config; nothing is ever unpickled.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .colour import IDENTITY_CHANNELS
from .errors import ModelError, _followed, model_files, one_line, plain_permissions

DEFAULT_CONFIG = {
    "dim": 64,
    "heads": 4,
    "layers": 4,
    "fourier_bands": 6,
    "scale_um": 20.0,  # coordinates are divided by this before the network sees them
    "prior_sigma_um": 4.0,  # initial width of the geometric prior
    "colour_channels": 0,  # >0: per-neuron NeuroPAL colour (normal scores) is a model input too
}

WHOLE_BOUNDS = {"dim": (1, 4096), "heads": (1, 256), "layers": (1, 64), "fourier_bands": (0, 24), "colour_channels": (0, 3)}
LENGTH_BOUNDS = (1e-3, 1e4)  # µm


def model_config(config) -> dict:
    """``config`` over :data:`DEFAULT_CONFIG`, refused (ModelError) unless it names known sizes
    with sensible values: a whole dimension that the heads divide, whole positive counts,
    positive lengths."""
    if config is not None and not isinstance(config, dict):
        raise ModelError(f"a model configuration is a JSON object of sizes, not {type(config).__name__}")
    full = {**DEFAULT_CONFIG, **(config or {})}
    unknown = sorted(set(full) - set(DEFAULT_CONFIG))
    if unknown:
        raise ModelError(f"unknown model setting(s) {', '.join(unknown)} (known: {', '.join(DEFAULT_CONFIG)})")
    # Bounds far beyond any useful model, short of what cannot be built or run: 2**k of 128
    # Fourier bands overflows float32 (every score NaN), a width of 10**7 asks for terabytes,
    # a length of 1e-200 µm divides by zero.
    for key, (least, most) in WHOLE_BOUNDS.items():
        value = full[key]
        if isinstance(value, bool) or not isinstance(value, int) or not least <= value <= most:
            raise ModelError(f"model setting {key} must be a whole number from {least} to {most} (got {value!r})")
    for key in ("scale_um", "prior_sigma_um"):
        value = full[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not LENGTH_BOUNDS[0] <= value <= LENGTH_BOUNDS[1]:
            raise ModelError(f"model setting {key} must be a length from {LENGTH_BOUNDS[0]:g} to {LENGTH_BOUNDS[1]:g} µm "
                             f"(got {value!r})")
    if full["colour_channels"] not in (0, len(IDENTITY_CHANNELS)):  # what inference and training feed
        raise ModelError(f"model setting colour_channels must be 0 (positions only) or {len(IDENTITY_CHANNELS)} "
                         f"({', '.join(IDENTITY_CHANNELS)}) (got {full['colour_channels']})")
    if full["dim"] % full["heads"]:
        raise ModelError(f"model setting dim ({full['dim']}) must be a multiple of heads ({full['heads']})")
    return full


class FourierEmbedding(nn.Module):
    """xyz -> MLP([xyz, sin/cos(2^k xyz)]): lets a small network resolve µm-scale structure."""

    def __init__(self, dim: int, bands: int):
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(bands)) * math.pi / 4, persistent=False)
        width = 3 + 6 * bands
        self.mlp = nn.Sequential(nn.Linear(width, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        angles = xyz[..., None] * self.freqs  # B N 3 K
        feats = torch.cat([xyz, angles.sin().flatten(-2), angles.cos().flatten(-2)], dim=-1)
        return self.mlp(feats)


class Attention(nn.Module):
    """Multi-head attention with an optional additive bias and a key padding mask."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, x, context, key_mask=None, bias=None):
        """``key_mask`` (B, M) True = real neuron, or None when no key is padding; ``bias``
        (B or 1, heads, N, M) is added to the scores. A batch of 1 on either side is broadcast."""
        b, n, d = x.shape
        h = self.heads
        q = self.q(x).view(b, n, h, d // h).transpose(1, 2)
        k, v = self.kv(context).view(context.shape[0], -1, 2, h, d // h).permute(2, 0, 3, 1, 4)
        batch = max(b, k.shape[0])
        q, k, v = (t.expand(batch, -1, -1, -1) for t in (q, k, v))
        if key_mask is not None:
            fill = torch.zeros((), dtype=x.dtype, device=x.device) if bias is None else bias
            bias = fill.masked_fill(~key_mask[:, None, None, :], float("-inf"))
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        return self.out(out.transpose(1, 2).reshape(batch, n, d))


class Block(nn.Module):
    """Self-attention within each worm (distance-biased), then cross-attention between worms."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.self_attn = Attention(dim, heads)
        self.cross_attn = Attention(dim, heads)
        self.norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(3))
        self.ffn = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))
        # One learned locality per head: bias = -softplus(w_h) * |p_i - p_j|^2.
        self.locality = nn.Parameter(torch.linspace(-1.0, 4.0, heads))

    def forward(self, tmpl, test, tmpl_sq, test_sq, tmpl_mask=None, test_mask=None):
        """One layer on the template (B or 1, M, d) and the test (B, N, d) descriptors; the
        masks are None when a side has no padding (then no mask is built at all)."""
        locality = -F.softplus(self.locality)[None, :, None, None]
        x, y = self.norms[0](tmpl), self.norms[0](test)
        tmpl = tmpl + self.self_attn(x, x, tmpl_mask, locality * tmpl_sq[:, None])
        test = test + self.self_attn(y, y, test_mask, locality * test_sq[:, None])
        x, y = self.norms[1](tmpl), self.norms[1](test)
        tmpl, test = tmpl + self.cross_attn(x, y, test_mask), test + self.cross_attn(y, x, tmpl_mask)
        tmpl = tmpl + self.ffn(self.norms[2](tmpl))
        return tmpl, test + self.ffn(self.norms[2](test))


class CorrespondenceModel(nn.Module):
    """fDLC-style matcher: log p(test j ↔ template i), plus a "no match" column."""

    def __init__(self, config: dict | None = None):
        super().__init__()
        self.config = model_config(config)
        dim, heads = self.config["dim"], self.config["heads"]
        self.embed = FourierEmbedding(dim, self.config["fourier_bands"])
        self.role = nn.Parameter(torch.zeros(2, dim))  # marks template (0) and test (1)
        # Colour enters beside position, with a "colour present" flag so that the same weights
        # serve --no-color. Zero start: an untrained colour branch changes nothing.
        channels = self.config["colour_channels"]
        self.colour_embed = None
        if channels:
            self.colour_embed = nn.Sequential(nn.Linear(channels + 1, dim), nn.GELU(), nn.Linear(dim, dim))
            nn.init.zeros_(self.colour_embed[2].weight)
            nn.init.zeros_(self.colour_embed[2].bias)
        self.blocks = nn.ModuleList(Block(dim, heads) for _ in range(self.config["layers"]))
        self.project = nn.Linear(dim, dim)
        # Zero start: the first scores are the geometric prior alone (the non-learned floor),
        # so training on a CPU starts from a sensible matcher rather than from noise.
        nn.init.zeros_(self.project.weight)
        self.displace = nn.Linear(dim, 3)
        nn.init.zeros_(self.displace.weight)
        nn.init.zeros_(self.displace.bias)
        self.no_match = nn.Linear(dim, 1)
        sigma = self.config["prior_sigma_um"] / self.config["scale_um"]
        self.log_alpha = nn.Parameter(torch.tensor(math.log(1.0 / (2 * sigma**2))))

    def _colour(self, colour, xyz):
        if self.colour_embed is None:
            return 0.0
        b, n, _ = xyz.shape
        c = self.config["colour_channels"]
        if colour is None:  # no colour: zeros with the flag off
            feats = torch.zeros(b, n, c + 1, dtype=xyz.dtype, device=xyz.device)
        elif colour.shape[-1] == c + 1:  # the caller set the flag per neuron (training batches)
            feats = colour.to(xyz.dtype)
        else:
            flag = torch.ones(*colour.shape[:2], 1, dtype=xyz.dtype, device=xyz.device)
            feats = torch.cat([colour.to(xyz.dtype), flag], dim=-1)
        return self.colour_embed(feats)

    def forward(self, template_xyz, test_xyz, template_mask=None, test_mask=None, template_colour=None, test_colour=None):
        """template_xyz (B, M, 3) and test_xyz (B, N, 3) in µm, canonical frame.

        Returns log-probabilities (B, N, M + 1); column M is "no match". Padded template columns
        get -inf; padded test rows are garbage and must be ignored by the caller.

        A template of batch 1 is shared by all B tests: it is embedded and self-attended once
        (the result is the same as expanding it). Template and test are never padded to each
        other's size, and a mask with no padding is dropped, so unpadded inputs run without any
        attention mask.
        """
        b = test_xyz.shape[0]
        template_mask = real_mask(template_mask)
        test_mask = real_mask(test_mask)
        scale = self.config["scale_um"]
        p0, q0 = template_xyz / scale, test_xyz / scale
        tmpl = self.embed(p0) + self.role[0] + self._colour(template_colour, p0)
        test = self.embed(q0) + self.role[1] + self._colour(test_colour, q0)
        tmpl_sq = torch.cdist(p0, p0).square()  # within each worm, shared by all layers
        test_sq = torch.cdist(q0, q0).square()
        for block in self.blocks:
            tmpl, test = block(tmpl, test, tmpl_sq, test_sq, template_mask, test_mask)
        p = (p0 + self.displace(tmpl)).expand(b, -1, -1)
        q = q0 + self.displace(test)
        u = self.project(tmpl).expand(b, -1, -1)
        v = self.project(test)
        logits = torch.einsum("bnd,bmd->bnm", v, u) / math.sqrt(u.shape[-1])
        logits = logits - self.log_alpha.exp() * torch.cdist(q, p).square()
        if template_mask is not None:
            logits = logits.masked_fill(~template_mask[:, None, :], float("-inf"))
        no_match = self.no_match(test)
        return torch.cat([logits, no_match], dim=-1).log_softmax(dim=-1)


def trace_model(model: CorrespondenceModel, template_xyz, test_xyz, template_mask=None, test_mask=None,
                template_colour=None, test_colour=None):
    """A TorchScript trace of ``model`` for inputs like these, called with the given ones only:
    ``f(template, test, *[masks and colours that are not None])``.

    Neuron counts stay free; the batch sizes and which masks and colours are given are fixed by
    the example (a mask given must have padding: the masked path is what gets traced). Same
    numbers as the model; on a CPU a small pass spends much of its time in Python dispatch,
    which the trace skips (about 1 ms of 5 for one 130-neuron test)."""
    import warnings

    present = [x is not None for x in (template_mask, test_mask, template_colour, test_colour)]

    class Traced(nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, a, b, *given):
            it = iter(given)
            return self.model(a, b, *(next(it) if p else None for p in present))

    example = tuple(x for x in (template_xyz, test_xyz, template_mask, test_mask, template_colour, test_colour) if x is not None)
    with warnings.catch_warnings():  # the tracer warns about Python values it cannot follow: none matter here
        warnings.simplefilter("ignore")
        return torch.jit.trace(Traced().eval(), example, check_trace=False)


def real_mask(mask):
    """None when every entry is real (no padding): attention then needs no mask."""
    return None if mask is None or bool(mask.all()) else mask


def matching_loss(log_probs, target, negative=None, entropy_weight=0.0):
    """Cross-entropy toward each test neuron's template index (M = "no match", -1 = ignore).

    ``negative`` marks pairs shown in a wrong orientation: every neuron's target is "no match",
    which teaches the model to be unconfident when the worms are not aligned.
    """
    m = log_probs.shape[-1] - 1
    target = target.clone()
    if negative is not None:
        target[negative] = torch.where(target[negative] >= 0, m, target[negative])
    valid = target >= 0
    if not valid.any():
        return log_probs[..., -1].sum() * 0.0  # the no-match column is finite (padded columns are -inf)
    picked = log_probs.gather(-1, target.clamp(min=0)[..., None])[..., 0]
    return -(picked[valid]).mean()


# ----------------------------------------------------------------------------------------------
# Saving and loading: safetensors + JSON, never pickle.

def save_model(model: CorrespondenceModel, path: str | Path, card: dict | None = None) -> None:
    from safetensors.torch import save_file

    weights, config_path = (_followed(f) for f in model_files(path))  # links: the files they name
    weights.parent.mkdir(parents=True, exist_ok=True)
    # Both files are written in full before either replaces the old one: an interruption while
    # writing leaves the old pair whole.
    # short (a long file name leaves room for them) and each with its suffix: cut at 40 characters,
    # a long stem made the two one file, and the JSON was written over the weights
    tmp = weights.with_name(f".{weights.stem[:40]}{weights.suffix}.tmp")
    json_tmp = config_path.with_name(f".{config_path.stem[:40]}{config_path.suffix}.tmp")
    try:
        save_file({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}, str(tmp))
        plain_permissions(tmp)
        json_tmp.write_text(json.dumps({"config": model.config, **(card or {})}, indent=2))
        tmp.replace(weights)
        json_tmp.replace(config_path)
    finally:
        for left in (tmp, json_tmp):
            left.unlink(missing_ok=True)


def check_finite(state: dict, weights: Path) -> None:
    """Refuse weights that hold NaN or infinity (a corrupt copy, a run that diverged): they would
    load, and fail far later in the assignment."""
    bad = sorted(k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all()))
    if bad:
        raise ModelError(f"{weights}: weights that are not finite numbers ({', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''})")


def load_model(path: str | Path) -> CorrespondenceModel:
    """Load ``path.safetensors`` with its ``path.json`` config; refuse anything that does not fit."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    weights, config_path = model_files(path)
    for p in (weights, config_path):
        if not p.exists():
            raise ModelError(f"{p}: model file missing")
    try:
        meta = json.loads(config_path.read_text())
        config = meta["config"]
        model = CorrespondenceModel(config)
    except (ValueError, KeyError, TypeError, ArithmeticError, RuntimeError, ModelError) as exc:
        raise ModelError(f"{config_path}: not a valid model configuration ({one_line(exc)})") from None
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelError(f"{weights}: not a valid safetensors file ({str(exc).splitlines()[0]})") from None
    check_finite(state, weights)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError:
        raise ModelError(f"{weights}: the weights do not fit the configuration in {config_path.name}") from None
    model.eval()
    return model
