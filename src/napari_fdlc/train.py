"""Training: real cross-worm pairs of the annotated corpus mixed with synthetic pairs.

Real pairs carry true biological variability (names give the correspondence; unnamed neurons
are ignored or count as unmatched). Synthetic pairs (:mod:`napari_fdlc.simulate`) add
deformations the corpus lacks. Every pair is put in the canonical frame; the true orientation
(one of 16) is found from the names. Kinds of examples:

* coarse: the test in its true orientation;
* aligned: the test affinely aligned on the true matches, then perturbed a little — what the
  refinement passes see;
* negative: the test in a wrong orientation, every target "no match" — what makes the model's
  willingness to match a test of whether two worms are aligned (see ``docs/model_card.md``);
* registered (``registered_fraction``): the test registered onto the template, exactly what
  inference shows the model (:mod:`napari_fdlc.register`);
* panel (``panel_fraction``): a real worm registered onto an atlas of the training worms,
  against a worm sampled from that atlas — what the built-in panel shows the model.

Validation runs the real inference path (:class:`napari_fdlc.identify.Identifier`) per lab.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from .colour import IDENTITY_CHANNELS, has_colour, normal_scores
from .corpus import LABS, Worm, load_corpus
from .errors import FdlcError, ModelError, atomic_write
from .evaluate import Scores, mirrored_relative_to
from .geometry import N_PROPER, ORIENTATIONS, apply_affine, canonical_frame, fit_affine, fit_warp, true_orientation
from .reference import atlas_worm, build_atlas
from .register import register, template_mixture
from .simulate import SimulationParams, simulate_worm
from .table import NeuronTable


TASKS = ("identify", "track")
MAX_THREADS = 1024  # threads and workers a configuration may ask for


@dataclass
class TrainConfig:
    corpus: str | None = None
    train_labs: tuple[str, ...] = LABS
    val_labs: tuple[str, ...] = LABS
    val_worms_per_lab: int = 2  # worms of each training lab kept out for validation
    steps: int = 3000
    batch_size: int = 16
    lr: float = 5e-4
    weight_decay: float = 1e-4
    synthetic_fraction: float = 0.2
    aligned_fraction: float = 0.1
    negative_fraction: float = 0.15
    # Placed by registration as inference places them (napari_fdlc.register), in the true
    # chirality: real pairs registered onto the template, and real worms registered onto an
    # atlas of the training worms against a worm sampled from it (the built-in panel's case).
    registered_fraction: float = 0.0
    panel_fraction: float = 0.0
    colour_dropout: float = 0.3  # pairs shown without colour, so --no-color uses the same weights
    # Real worms' augmentation (what differs between labs): scale per axis (± fraction), and
    # colour as another lab's filters and readout might give it: each channel's z-scores mixed
    # with the others' (bleed-through, off-diagonal weights uniform in 0..colour_mixing) plus
    # noise (SD in z-score units). The shipped recipe uses 0.08, 0 and 0.
    scale_jitter: float = 0.08
    colour_mixing: float = 0.0
    colour_noise: float = 0.0
    max_neurons: int = 112  # crop bigger worms to a window along the body axis (CPU cost ~ N^2)
    seed: int = 0
    # Which worms of each training lab are held out (and which validation pairs are drawn): the
    # same for every stage of a recipe whatever its example seed, so that a stage warm-started
    # from another validates and calibrates on worms neither trained on.
    split_seed: int = 0
    eval_every: int = 250
    val_pairs_per_lab: int = 24
    time_limit_min: float | None = None
    stop_at: int | None = None  # stop after this step (the schedule still spans ``steps``)
    # One thread: on a shared 2-core machine, two torch threads fighting another process made a
    # step 25x slower (7.4 s vs 0.29 s measured); small matrices gain little from threads anyway.
    threads: int | None = 1
    # Processes that make training examples beside the one that steps the model: with a GPU the
    # step is cheap and making the examples (crops, simulator, registration) is what takes the time.
    # 0 makes them in the training process. The stream of examples depends on ``seed`` and this.
    workers: int = 0
    device: str | None = None
    model: dict = field(default_factory=dict)
    out: str = "runs/model"
    init_from: str | None = None  # start from these weights (keys that fit; new branches start at zero)
    resume: bool = False  # continue from the checkpoint at ``out`` (weights and step count)
    calibrate: bool = True  # fit colour weight and temperature on training-lab validation pairs
    # "identify": pairs of worms as ``fdlc label`` shows them to the model (the kinds above).
    # "track": the tracking model (track.py): a volume of a simulated recording of one worm,
    # placed onto the recording's first volume by the tracker's geometric chain, exactly as
    # ``fdlc track`` shows it to the model; validated by tracking accuracy per lab.
    task: str = "identify"
    motion: tuple[float, float] = (0.5, 3.5)  # track: recordings' motion, × SequenceParams' (uniform)
    frames_apart: int = 30  # track: the volume is 1..this many volumes after the reference
    stale_warp: int = 3  # track: placed with the warp of one of the 1..this many volumes before

    def to_json(self) -> dict:
        return asdict(self)

    def check(self) -> None:
        self._check_types()
        if self.task not in TASKS:
            raise FdlcError(f"unknown training task '{self.task}' (use {' or '.join(TASKS)})")
        for name in ("steps", "batch_size", "eval_every", "val_pairs_per_lab", "stop_at", "threads"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise FdlcError(f"--{name.replace('_', '-')} must be at least 1 (got {value})")
        if self.workers < 0:
            raise FdlcError(f"--workers must be 0 or more (got {self.workers})")
        for name in ("threads", "workers"):  # torch's own refusal of 2**31 was a traceback
            value = getattr(self, name)
            if value is not None and value > MAX_THREADS:
                raise FdlcError(f"--{name} must be at most {MAX_THREADS} (got {value})")
        if not 0 <= self.seed < 2**32:
            raise FdlcError(f"--seed must be a whole number from 0 to 2**32 - 1 (got {self.seed})")
        if not 0 <= self.split_seed < 2**32:
            raise FdlcError(f"split_seed must be a whole number from 0 to 2**32 - 1 (got {self.split_seed})")
        if self.time_limit_min is not None and not 0 < self.time_limit_min < math.inf:
            raise FdlcError(f"--minutes must be a positive number (got {self.time_limit_min})")
        self._check_ranges()
        if self.device:
            self._check_device()
        from .model import model_config

        model_config(self.model)

    def _check_ranges(self) -> None:
        """Numbers a run can use: a configuration file can hold a negative rate or NaN, which
        torch or numpy would only refuse with a traceback (or, for sizes, a misleading error)."""
        def fail(name, what):
            raise FdlcError(f"training setting {name} must be {what} (got {getattr(self, name)!r})")

        if not 0 < self.lr < math.inf:
            fail("lr", "a positive number")
        for name in ("weight_decay", "colour_mixing", "colour_noise"):
            if not 0 <= getattr(self, name) < math.inf:
                fail(name, "a number of 0 or more")
        for name in ("synthetic_fraction", "aligned_fraction", "negative_fraction", "registered_fraction",
                     "panel_fraction", "colour_dropout"):
            if not 0 <= getattr(self, name) <= 1:
                fail(name, "a fraction from 0 to 1")
        if not 0 <= self.scale_jitter < 1:
            fail("scale_jitter", "a fraction from 0 to below 1")
        for name in ("max_neurons", "frames_apart", "stale_warp"):
            if getattr(self, name) < 1:
                fail(name, "at least 1")
        if self.task == "identify" and self.max_neurons < 4:  # else no example could ever be made
            fail("max_neurons", "at least 4 (a training pair needs 4 matched neurons)")
        if self.val_worms_per_lab < 0:
            fail("val_worms_per_lab", "0 or more")
        low, high = self.motion
        if not 0 <= low <= high < math.inf:
            fail("motion", "two numbers, 0 <= low <= high")

    def _check_device(self) -> None:
        """A device torch can put a tensor on: the name must parse, and the device be there."""
        import torch

        try:
            device = torch.device(self.device)
        except RuntimeError:
            raise FdlcError(f"--device {self.device}: not a torch device (use cpu or cuda)") from None
        if device.type == "cuda" and not torch.cuda.is_available():
            raise FdlcError(f"--device {self.device}: no CUDA device here (torch sees none); use --device cpu")
        try:
            torch.empty(0, device=device)
        except (RuntimeError, AssertionError) as exc:
            raise FdlcError(f"--device {self.device}: torch cannot use it here ({str(exc).splitlines()[0]})") from None

    def _check_types(self) -> None:
        """Each setting of the kind it must be (a configuration file can hold anything)."""
        def fail(name, kind):
            raise FdlcError(f"training setting {name} must be {kind} (got {getattr(self, name)!r})")

        for f in fields(self):
            value = getattr(self, f.name)
            kind = f.type.replace(" | None", "")
            if value is None and "None" in f.type:
                continue
            if kind == "int" and (isinstance(value, bool) or not isinstance(value, int)):
                fail(f.name, "a whole number")
            if kind == "float" and (isinstance(value, bool) or not isinstance(value, (int, float))):
                fail(f.name, "a number")
            if kind in ("str", "bool", "dict") and not isinstance(value, {"str": str, "bool": bool, "dict": dict}[kind]):
                fail(f.name, {"str": "a string", "bool": "true or false", "dict": "a JSON object"}[kind])
            if kind == "tuple[str, ...]" and not all(isinstance(v, str) for v in value):
                fail(f.name, "a list of lab names")
            if kind == "tuple[float, float]" and (len(value) != 2 or not all(isinstance(v, (int, float)) for v in value)):
                fail(f.name, "two numbers")

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> "TrainConfig":
        """The configuration a checkpoint's JSON records it was trained with (its ``out``: here)."""
        path = Path(path)
        try:
            recorded = "train_config" in json.loads(path.read_text())
        except (OSError, ValueError, TypeError) as exc:
            raise FdlcError(f"{path}: no checkpoint record to go on from ({exc}); give --out, or --config") from None
        if not recorded:
            raise FdlcError(f"{path}: the checkpoint records no training configuration; give --config")
        cfg = cls.from_json(path)
        cfg.out = str(path.with_suffix(""))
        return cfg

    @classmethod
    def from_json(cls, path: str | Path) -> "TrainConfig":
        """A configuration from a JSON file: a bare config, or a checkpoint's JSON (train_config)."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise FdlcError(f"{path}: not a readable JSON training configuration ({exc})") from None
        if isinstance(data, dict) and "train_config" in data:
            data = data["train_config"]
            if isinstance(data, dict):  # when that run was told to stop, where it ran, and whether it
                # went on from another, are not its recipe
                data = {**data, "stop_at": None, "time_limit_min": None, "device": None, "resume": False}
        if not isinstance(data, dict):
            raise FdlcError(f"{path}: a training configuration is a JSON object of settings")
        unknown = set(data) - set(cls.__dataclass_fields__)
        if unknown:
            raise FdlcError(f"{path}: unknown training setting(s) {', '.join(sorted(unknown))}")
        for key in ("train_labs", "val_labs", "motion"):
            if key in data:
                if not isinstance(data[key], list):
                    raise FdlcError(f"{path}: {key} must be a list (got {data[key]!r})")
                data[key] = tuple(data[key])
        return cls(**data)


# Training-time simulator: the published magnitudes, except a smaller transverse roll — the
# canonical frame plus the 180° flips already cover which side the worm lies on, and a ±81°
# roll would show the model poses that the corpus (worms lie on their side) never has.
TRAIN_SIM = SimulationParams(transverse_rotation=0.15 * np.pi)


def _augment(table: NeuronTable, rng: np.random.Generator, cfg: TrainConfig | None = None) -> NeuronTable:
    """Field-of-view crop along the body axis, drops, noise, scale, colour mixing: what differs
    between labs (``cfg``'s magnitudes; defaults without it)."""
    cfg = cfg or TrainConfig()
    canon, _, _ = canonical_frame(table.xyz)
    keep = np.ones(len(table), bool)
    if rng.random() < 0.4:
        x = canon[:, 0]
        lo, hi = np.quantile(x, [rng.uniform(0, 0.3), 1 - rng.uniform(0, 0.3)])
        keep &= (x >= lo) & (x <= hi)
    keep &= rng.random(len(table)) >= rng.uniform(0, 0.15)
    if keep.sum() < 8:
        keep[:] = True
    t = table.subset(np.flatnonzero(keep))
    xyz = t.xyz * (1 + rng.uniform(-cfg.scale_jitter, cfg.scale_jitter, 3)) + rng.normal(0, 0.4, t.xyz.shape)
    colours = t.colours
    if (cfg.colour_mixing or cfg.colour_noise) and all(c in colours for c in IDENTITY_CHANNELS):
        rgb = np.column_stack([colours[c] for c in IDENTITY_CHANNELS]).astype(float)
        rgb = (rgb - rgb.mean(axis=0)) / (rgb.std(axis=0) + 1e-9)
        mixing = np.eye(3) + rng.uniform(0, cfg.colour_mixing, (3, 3)) * (1 - np.eye(3))
        rgb = rgb @ mixing.T + rng.normal(0, cfg.colour_noise, rgb.shape)
        colours = {**colours, **dict(zip(IDENTITY_CHANNELS, rgb.T))}
    return NeuronTable(xyz, colours, t.labels, t.label_conf, source=t.source)


def _crop(table: NeuronTable, max_neurons: int, rng) -> NeuronTable:
    """A contiguous window of at most ``max_neurons`` along the body axis: a smaller field of
    view, as other labs record, and attention cost that fits a CPU."""
    if len(table) <= max_neurons:
        return table
    x = canonical_frame(table.xyz)[0][:, 0]
    order = np.argsort(x)
    start = rng.integers(0, len(table) - max_neurons + 1)
    return table.subset(np.sort(order[start : start + max_neurons]))


def _targets(template: NeuronTable, test: NeuronTable) -> np.ndarray:
    """Template index per test neuron; M = no match; -1 = unknown (ignored by the loss)."""
    m = len(template)
    index = {n: i for i, n in enumerate(template.labels) if n}
    template_complete = (template.labels == "").mean() < 0.1
    target = np.full(len(test), -1, dtype=np.int64)
    for j, name in enumerate(test.labels):
        if name in index:
            target[j] = index[name]
        elif name and template_complete and not (name + "L" in index or name + "R" in index) \
                and not (name[-1:] in ("L", "R") and name[:-1] in index):
            # a named neuron the (fully named) template does not have; a name written without
            # its side (a few SF worms' "AIB"), in the test or in the template, has its partner
            # there, which one unknown
            target[j] = m
    return target


def make_example(template: NeuronTable, test: NeuronTable, target: np.ndarray, rng, cfg: TrainConfig, atlas=None, registered: bool = False):
    """Coordinates for one training pair as the model sees them, or None when too few matches.

    By default both worms are in their canonical frames and the test is turned by the true
    orientation (or a wrong one: a negative). With ``registered`` the test is registered onto
    the template as :meth:`Identifier.place` does; with ``atlas`` (the template was sampled from
    it, in its frame) onto the atlas as the built-in panel does; either way in the chirality the
    names say is right."""
    a = template.xyz if atlas is not None else canonical_frame(template.xyz)[0]
    b, _, _ = canonical_frame(test.xyz)
    m = len(template)
    matched = np.flatnonzero((target >= 0) & (target < m))
    if len(matched) < 4:
        return None
    pairs = np.column_stack([target[matched], matched])
    true = true_orientation(a, b, pairs)
    negative = False
    if atlas is not None or registered:
        mixture = atlas.mixture() if atlas is not None else template_mixture(template)
        b = register(test, mixture, chiralities=(bool(true >= N_PROPER),))[0].xyz
        return _example(a, b, target, negative, template, test)
    u = rng.random()
    if u < cfg.negative_fraction:
        wrong = rng.choice([k for k in range(len(ORIENTATIONS)) if k != true])
        b = b @ ORIENTATIONS[wrong].T
        negative = True
    else:
        b = b @ ORIENTATIONS[true].T
        if u < cfg.negative_fraction + cfg.aligned_fraction:
            b = apply_affine(b, fit_affine(b[matched], a[target[matched]]))
            angle = rng.normal(0, 0.08)
            c, s = math.cos(angle), math.sin(angle)
            jitter = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * (1 + rng.normal(0, 0.03, 3))
            b = b @ jitter.T + rng.normal(0, 3.0, 3)
    return _example(a, b, target, negative, template, test)


def _example(a, b, target, negative, template, test):
    return a.astype(np.float32), b.astype(np.float32), target, negative, _colour_features(template), _colour_features(test)


def _colour_features(table: NeuronTable) -> np.ndarray | None:
    if not has_colour(table):
        return None
    return normal_scores(table, IDENTITY_CHANNELS).astype(np.float32)


MAX_DRAWS = 1000  # draws without a usable example before the worms are declared unusable


def sample_example(worms: list[Worm], rng, cfg: TrainConfig, atlas=None):
    """One training example: a synthetic pair, a real cross-worm pair, or (with ``atlas``, the
    atlas of the training worms) a real worm against a worm sampled from the atlas; with
    ``cfg.task == "track"``, a tracking example (:func:`tracking_example`)."""
    if cfg.task == "track":
        return tracking_example(worms, rng, cfg)
    for _ in range(MAX_DRAWS):
        u = rng.random()
        placement = {}
        if u < cfg.synthetic_fraction:
            template = _crop(worms[rng.integers(len(worms))].table, cfg.max_neurons, rng)
            synth = simulate_worm(template, rng, TRAIN_SIM)
            m = len(template)
            target = np.where(synth.origin >= 0, synth.origin, m)
            test = synth.table
        elif atlas is not None and u < cfg.synthetic_fraction + cfg.panel_fraction:
            template = atlas_worm(atlas, rng)  # whole, like the panel's templates
            test = _crop(_augment(worms[rng.integers(len(worms))].table, rng, cfg), cfg.max_neurons, rng)
            target = _targets(template, test)
            placement = {"atlas": atlas}
        else:
            i, j = rng.choice(len(worms), 2, replace=False)
            template = _crop(_augment(worms[i].table, rng, cfg), cfg.max_neurons, rng)
            test = _crop(_augment(worms[j].table, rng, cfg), cfg.max_neurons, rng)
            target = _targets(template, test)
            placement = {"registered": rng.random() < cfg.registered_fraction}
        example = make_example(template, test, target, rng, cfg, **placement)
        if example is not None:
            return example
    raise FdlcError(f"no training example in {MAX_DRAWS} draws: the training worms share too few named neurons "
                    "(a pair needs 4 names in common)")


def tracking_example(worms: list[Worm], rng, cfg: TrainConfig):
    """A volume of a simulated recording of one training worm (``track.simulate_sequence`` at a
    random motion) placed as ``fdlc track`` places it: the warp of a volume before (fitted on
    that volume's true partners, as a chain on track has it) carried into the geometric step.
    That volume is 1 to ``stale_warp`` volumes back, so that the model also sees the larger
    residuals of a chain that lags. The template is the recording's first volume, the
    reference; targets are its rows."""
    from .track import SequenceParams, TrackSettings, _geometric_step, _Reference, simulate_sequence

    table = _crop(worms[rng.integers(len(worms))].table, cfg.max_neurons, rng)
    t = int(rng.integers(1, cfg.frames_apart + 1))
    lag = int(rng.integers(1, min(cfg.stale_warp, t) + 1))
    params = SequenceParams(frames=t + 1).scaled(rng.uniform(*cfg.motion))
    volumes, origins = simulate_sequence(table, rng, params, only=(0, t - lag, t))
    if t == lag:  # the volume the warp comes from is the reference itself
        volumes, origins = [volumes[0], *volumes], [origins[0], *origins]
    ref = _Reference(volumes[0], np.arange(len(volumes[0])))
    row = np.full(len(table), -1)
    row[origins[0][origins[0] >= 0]] = np.flatnonzero(origins[0] >= 0)

    def partners(origin):  # reference row of each neuron, -1 when it has none (or is spurious)
        return np.where(origin >= 0, row[np.maximum(origin, 0)], -1)

    s = TrackSettings()
    before = partners(origins[1])
    warp = fit_warp(volumes[1].xyz, ref.xyz[np.maximum(before, 0)], (before >= 0).astype(float),
                    s.warp_sigma_um, s.warp_smoothness)
    placed = _geometric_step(ref, volumes[2], warp, s)(volumes[2].xyz)
    target = partners(origins[2])
    target = np.where(target >= 0, target, len(ref.xyz))
    return _example(ref.xyz, placed, target, False, volumes[0], volumes[2])


def collate(examples, torch, colour_dropout: float = 0.0, rng=None):
    """Pad a list of examples into tensors; colour features carry a per-neuron "present" flag
    (dropped for a whole pair with probability ``colour_dropout``)."""
    b = len(examples)
    m = max(len(e[0]) for e in examples)
    n = max(len(e[1]) for e in examples)
    a = torch.zeros(b, m, 3)
    t = torch.zeros(b, n, 3)
    am = torch.zeros(b, m, dtype=torch.bool)
    tm = torch.zeros(b, n, dtype=torch.bool)
    ac = torch.zeros(b, m, len(IDENTITY_CHANNELS) + 1)
    tc = torch.zeros(b, n, len(IDENTITY_CHANNELS) + 1)
    target = torch.full((b, n), -1, dtype=torch.long)
    negative = torch.zeros(b, dtype=torch.bool)
    for k, (ea, eb, et, neg, ca, cb) in enumerate(examples):
        a[k, : len(ea)] = torch.from_numpy(ea)
        t[k, : len(eb)] = torch.from_numpy(eb)
        am[k, : len(ea)] = True
        tm[k, : len(eb)] = True
        drop = rng is not None and rng.random() < colour_dropout
        if ca is not None and cb is not None and not drop:
            ac[k, : len(ea), :-1] = torch.from_numpy(ca)
            ac[k, : len(ea), -1] = 1.0
            tc[k, : len(eb), :-1] = torch.from_numpy(cb)
            tc[k, : len(eb), -1] = 1.0
        # "no match" is column M of this pair's own template; in the padded batch it is column m.
        tt = torch.from_numpy(et)
        tt = torch.where(tt == len(ea), torch.tensor(m), tt)
        target[k, : len(eb)] = tt
        negative[k] = neg
    return a, t, am, tm, target, negative, ac, tc


def _batch(worms, cfg, atlas, rng, torch):
    examples = [sample_example(worms, rng, cfg, atlas) for _ in range(cfg.batch_size)]
    return collate(examples, torch, cfg.colour_dropout, rng)


def training_batches(worms: list[Worm], cfg: TrainConfig, atlas, rng, first_step: int = 1):
    """Batches for steps ``first_step``.. from the training process's ``rng``, or with
    ``cfg.workers`` from that many processes (each seeded by seed, first step and its id)."""
    import multiprocessing

    import torch

    if cfg.workers <= 0:
        if first_step > 1:  # a resumed run goes on with new examples, not those of its first steps
            rng = np.random.default_rng([cfg.seed, first_step])
        while True:
            yield _batch(worms, cfg, atlas, rng, torch)
    # The workers inherit the worms and this function's closures by fork (nothing is pickled).
    if "fork" not in multiprocessing.get_all_start_methods():
        raise FdlcError("--workers needs processes started by fork (Linux, macOS): use --workers 0")

    class ExampleStream(torch.utils.data.IterableDataset):  # endless batches of one worker
        def __iter__(self):
            rng = np.random.default_rng([cfg.seed, first_step, torch.utils.data.get_worker_info().id])
            while True:
                yield _batch(worms, cfg, atlas, rng, torch)

    # Workers need no torch threads of their own: they make examples with numpy.
    loader = torch.utils.data.DataLoader(ExampleStream(), batch_size=None, num_workers=cfg.workers,
                                         worker_init_fn=lambda _: torch.set_num_threads(1),
                                         prefetch_factor=4, persistent_workers=True, multiprocessing_context="fork")
    try:
        yield from loader
    except FdlcError as exc:
        # torch re-raises a worker's error with the worker's whole traceback as its message, whose
        # last line is "module.Error: message": said as without workers, in one line.
        text = str(exc)
        if "Original Traceback" not in text:
            raise
        raise type(exc)(text.rstrip().splitlines()[-1].split(": ", 1)[-1]) from None


def split_worms(worms: list[Worm], cfg: TrainConfig, rng) -> tuple[list[Worm], dict[str, list[Worm]]]:
    """Training worms from the training labs; validation worms per lab: held-out labs whole; of
    each training lab, its ``val_worms_per_lab`` held-out worms first, then 4 of its training
    worms (templates for them, never named: :func:`validation_pairs`)."""
    train, val = [], {}
    for lab in sorted({w.lab for w in worms}):
        lab_worms = [w for w in worms if w.lab == lab]
        if lab in cfg.train_labs:
            order = rng.permutation(len(lab_worms))
            held = {int(i) for i in order[: cfg.val_worms_per_lab]} if lab in cfg.val_labs else set()
            train += [w for k, w in enumerate(lab_worms) if k not in held]
            if held:
                val[lab] = [lab_worms[k] for k in sorted(held)] + [w for k, w in enumerate(lab_worms) if k not in held][:4]
        elif lab in cfg.val_labs:
            val[lab] = lab_worms
    return train, val


def _pair_scores(identifier, pairs, use_colour: bool, scores: Scores | None = None, atlas=None) -> Scores:
    """Each test named from its template (and ``atlas``), scored as ``fdlc evaluate`` scores pairs."""
    scores = scores if scores is not None else Scores()
    for template, test in pairs:
        scores.add(identifier.label(test, [template], use_colour=use_colour, atlas=atlas), test, set(template.names))
    return scores


def _panel_scores(identifier, panel, tests, use_colour: bool, scores: Scores | None = None,
                  handedness_given: bool = False) -> Scores:
    """Each test named by the panel, scored as ``fdlc evaluate`` scores the panel; with
    ``handedness_given`` in the handedness its names give (relative to the panel's atlas)."""
    scores = scores if scores is not None else Scores()
    for test in tests:
        named_by = identifier
        if handedness_given:
            named_by = identifier.with_chirality("mirrored" if mirrored_relative_to(panel.atlas, test) else "same")
        scores.add(named_by.label_panel(test, panel, use_colour=use_colour), test, panel.names)
    return scores


def _validate(identifier, val_pairs: dict[str, list], panel_tests: dict) -> dict[str, dict[str, float]]:
    """Top-1 per lab: pairs position only, pairs with colour, and (labs in ``panel_tests``) the
    panel with colour."""
    out = {"val_top1": {}, "val_top1_colour": {}, "val_panel_top1": {}}
    for lab, pairs in val_pairs.items():
        for key, use_colour in (("val_top1", False), ("val_top1_colour", True)):
            out[key][lab] = round(_pair_scores(identifier, pairs, use_colour).summary()["top1"], 4)
    for lab, (panel, tests) in panel_tests.items():
        out["val_panel_top1"][lab] = round(_panel_scores(identifier, panel, tests, True).summary()["top1"], 4)
    return out


def tracking_sequences(val: dict[str, list[Worm]], cfg: TrainConfig, frames: int = 40) -> dict[str, list]:
    """Per lab: recordings of its held-out worms (the first ``val_worms_per_lab`` of each
    validation list), at motion 1 and 3, with known tracks."""
    from .track import SequenceParams, simulate_sequence

    out = {}
    for lab, worms in val.items():
        held = worms[: cfg.val_worms_per_lab] if lab in cfg.train_labs else worms
        out[lab] = [simulate_sequence(w.table, cfg.seed + 1000 * k + int(motion), SequenceParams(frames=frames).scaled(motion))
                    for k, w in enumerate(held) for motion in (1.0, 3.0)]
    return out


def _validate_tracking(follower, sequences: dict[str, list]) -> dict[str, dict[str, float]]:
    """Tracking accuracy per lab (``fdlc track`` defaults, positions only) with ``follower``
    answering for the placed volumes; the first volume is the reference."""
    from .identify import default_identifier
    from .track import TrackSettings, track, tracking_accuracy

    identifier = default_identifier()
    out = {"val_track": {}}
    for lab, recordings in sequences.items():
        hit = total = 0
        for volumes, origins in recordings:
            result = track(volumes, identifier=identifier, follower=follower, settings=TrackSettings(use_colour=False))
            acc = tracking_accuracy(result, origins, origins[0])
            hit += acc["accuracy"] * acc["neurons"]
            total += acc["neurons"]
        out["val_track"][lab] = round(hit / max(total, 1), 4)
    return out


def held_out(worms: list[Worm], cfg: TrainConfig) -> tuple[list[Worm], dict[str, list[Worm]], dict[str, list]]:
    """The training worms, the validation worms per lab and the validation pairs
    (:func:`split_worms`, :func:`validation_pairs`), drawn from ``cfg.split_seed``."""
    train, val = split_worms(worms, cfg, np.random.default_rng(cfg.split_seed))
    trained = {id(w) for w in train}
    unseen = {lab: sum(id(w) not in trained for w in lab_worms) for lab, lab_worms in val.items()}
    return train, val, validation_pairs(val, cfg.val_pairs_per_lab, np.random.default_rng(cfg.split_seed + 1), unseen)


def validation_pairs(val: dict[str, list[Worm]], per_lab: int, rng, unseen: dict[str, int] | None = None) -> dict[str, list]:
    """Up to ``per_lab`` (template, test) pairs per lab. ``unseen``: per lab, how many of its
    validation worms (the first ones, as :func:`split_worms` lists them) training never saw;
    only those are tests, the others serve as templates (default: every worm is unseen)."""
    out = {}
    for lab, worms in val.items():
        tests = {id(w) for w in worms[: (unseen or {}).get(lab, len(worms))]}
        pairs = [(a.table, b.table) for a in worms for b in worms if a is not b and id(b) in tests]
        idx = rng.permutation(len(pairs))[:per_lab]
        out[lab] = [pairs[i] for i in idx]
    return out


def _load_start(model, path: str, resume: bool, log) -> tuple[int, list, float]:
    """Copy the weights at ``path`` into ``model``: those that fit (``init_from``), or every one
    (``resume``: the checkpoint must be this very model). Returns the step to continue from, the
    validation history so far and the best mean top-1 in it (1, [], -1 when not resuming)."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from .model import check_finite, model_config, model_files

    weights, config_path = model_files(path)
    if not weights.exists():
        raise ModelError(f"{weights}: no checkpoint to start from")
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelError(f"{weights}: not a valid safetensors file ({str(exc).splitlines()[0]})") from None
    check_finite(state, weights)
    own = model.state_dict()
    fitting = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    if not fitting:
        raise ModelError(f"{weights}: none of its tensors fits this model (weights of another architecture?)")
    if resume:
        try:
            meta = json.loads(config_path.read_text())
            history = list(meta.get("history", []))
            best_step = int(meta.get("best_step", 0))
            theirs = model_config(meta.get("config"))
            best = max((float(h.get("mean_top1", -1.0)) for h in history if h.get("step") == best_step), default=-1.0)
            # The run goes on from the checkpoint (its best step): later entries belong to steps undone.
            history = [h for h in history if int(h.get("step", 0)) <= best_step]
        except (OSError, ValueError, TypeError, AttributeError, ModelError) as exc:
            raise ModelError(f"{config_path}: not a readable checkpoint record ({exc})") from None
        if len(fitting) != len(own) or len(state) != len(own) or theirs != model.config:
            raise ModelError(f"{weights}: --resume needs the checkpoint's own model, and this one's configuration differs "
                             "(give its --config, or --init-from to start a new run from it)")
    model.load_state_dict(fitting, strict=False)
    log(f"started from {weights}: {len(fitting)}/{len(own)} tensors")
    if not resume:
        return 1, [], -1.0
    return best_step + 1, history, best


def _check_labs(cfg: TrainConfig, corpus_labs: set[str]) -> None:
    """Labs named for training or validation must be in the corpus (the default list, all five
    labs, stands for those of them the corpus has); some training lab must be."""
    for name, labs in (("--train-labs", cfg.train_labs), ("--val-labs", cfg.val_labs)):
        missing = [lab for lab in labs if lab not in corpus_labs]
        if missing and tuple(labs) != LABS:
            raise FdlcError(f"{name}: no worms of lab(s) {', '.join(missing)} in the corpus (labs: {', '.join(sorted(corpus_labs))})")
    if not set(cfg.train_labs) & corpus_labs:
        raise FdlcError(f"no worms of the training labs {', '.join(cfg.train_labs)} in the corpus (labs: {', '.join(sorted(corpus_labs))})")


def _need_own_validation(cfg: TrainConfig, own: dict[str, list]) -> None:
    """Refused before any work: no validation of a training lab to choose the checkpoint on
    and to calibrate with (a held-out lab is watched, never chosen on; scores of nothing
    would keep the first checkpoint and pick settings among NaNs)."""
    if not any(own.values()):
        raise FdlcError(f"no held-out worms of a training lab ({', '.join(cfg.train_labs)}) to choose the checkpoint on "
                        f"and calibrate with (val_worms_per_lab {cfg.val_worms_per_lab}, --val-labs "
                        f"{', '.join(cfg.val_labs)}): hold out worms of a training lab and keep it in --val-labs")


def train(cfg: TrainConfig, log=print) -> dict:
    cfg.check()
    import torch

    from .identify import Identifier, InferenceSettings
    from .model import CorrespondenceModel, matching_loss, model_files, save_model

    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)  # the stream of training examples (the split has split_seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    device = cfg.device or ("cuda" if torch.cuda.is_available() else "cpu")
    worms = load_corpus(cfg.corpus)
    _check_labs(cfg, {w.lab for w in worms})
    train_worms, val_worms, val_pairs = held_out(worms, cfg)
    needed = 1 if cfg.task == "track" else 2  # a real pair is two worms
    if len(train_worms) < needed:
        raise FdlcError(f"{len(train_worms)} training worm(s) left after holding out val_worms_per_lab "
                        f"({cfg.val_worms_per_lab}) of each lab; {cfg.task} training needs {needed}: "
                        "lower val_worms_per_lab or add worms")
    recordings = tracking_sequences(val_worms, cfg) if cfg.task == "track" else None
    atlas = build_atlas(train_worms) if cfg.panel_fraction > 0 else None
    own_pairs = {lab: p for lab, p in val_pairs.items() if lab in cfg.train_labs}
    _need_own_validation(cfg, {lab: r for lab, r in recordings.items() if lab in cfg.train_labs}
                         if recordings is not None else own_pairs)
    panel_tests = _panel_tests(worms, own_pairs, cfg.train_labs) if atlas is not None else {}
    trained_labs = [lab for lab in cfg.train_labs if any(w.lab == lab for w in train_worms)]  # those the corpus has
    log(f"training on {len(train_worms)} worms of {', '.join(trained_labs)}; validating on "
        + ", ".join(f"{lab} ({len(p)} pairs)" for lab, p in val_pairs.items()))

    model = CorrespondenceModel(cfg.model).to(device)
    first_step, history, best = 1, [], -1.0
    start_from = cfg.out if cfg.resume else cfg.init_from
    if start_from:
        first_step, history, best = _load_start(model, start_from, cfg.resume, log)
    if first_step > cfg.steps:
        raise FdlcError(f"--steps {cfg.steps}: the checkpoint at --out is at step {first_step - 1} already; give more steps")
    if cfg.stop_at is not None and not first_step <= cfg.stop_at <= cfg.steps:
        raise FdlcError(f"--stop-at {cfg.stop_at}: must be a step this run takes ({first_step} to {cfg.steps})")
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    warmup = max(1, min(100, cfg.steps // 10))
    done = first_step - 1  # a resumed run's schedule continues where it stopped

    def lr_factor(s):
        s += done
        return min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(s, cfg.steps) / cfg.steps))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor)
    _, config_path = model_files(cfg.out)
    start = time.time()
    running = []
    settings = InferenceSettings()
    from tqdm import tqdm

    batches = training_batches(train_worms, cfg, atlas, rng, first_step)
    progress = tqdm(range(first_step, cfg.steps + 1), desc="training", unit="step", disable=not sys.stderr.isatty())
    for step in progress:
        model.train()
        a, t, am, tm, target, negative, ac, tc = (x.to(device) for x in next(batches))
        colour = model.config["colour_channels"] > 0
        log_p = model(a, t, am, tm, ac if colour else None, tc if colour else None)
        loss = matching_loss(log_p, target, negative)
        value = loss.item()
        if not math.isfinite(value):  # the best checkpoint saved so far stays as it is
            raise FdlcError(f"training diverged at step {step} (the loss is not a finite number): lower lr "
                            f"(now {cfg.lr:g})")
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        running.append(value)
        progress.set_postfix(loss=f"{value:.3f}", refresh=False)
        elapsed = (time.time() - start) / 60
        out_of_time = (cfg.time_limit_min is not None and elapsed > cfg.time_limit_min) or step == cfg.stop_at
        if step % cfg.eval_every == 0 or step == cfg.steps or out_of_time:
            model.eval()
            identifier = Identifier(model, settings, device)
            scores = (_validate_tracking(identifier, recordings) if recordings is not None
                      else _validate(identifier, val_pairs, panel_tests))
            # Keep the checkpoint best on average over the *training* labs' held-out worms
            # (pairs position only and with colour, the panel with colour when it is trained):
            # a held-out lab is watched, never used to choose.
            first = next(iter(scores.values()))
            own = [lab for lab in first if lab in cfg.train_labs]
            # A lab without validation pairs (one worm) scores NaN: left out, not made the mean.
            values = [d[lab] for d in scores.values() for lab in own if lab in d and math.isfinite(d[lab])]
            mean = float(np.mean(values)) if values else 0.0
            entry = {"step": step, "minutes": round(elapsed, 2), "loss": float(np.mean(running)), **scores,
                     "mean_top1": round(mean, 4)}
            history.append(entry)
            running = []
            log(json.dumps(entry))
            if mean > best:
                best = mean
                save_model(model, cfg.out, {"train_config": cfg.to_json(), "history": history,
                                        "inference": asdict(settings), "best_step": step})
        if out_of_time:
            log(f"stopped at step {step} (--stop-at)" if step == cfg.stop_at
                else f"stopped at step {step} (the time limit of {cfg.time_limit_min} min)")
            break
    minutes = (time.time() - start) / 60
    where = {"train_minutes": round(minutes, 1), "device": device, "torch_threads": torch.get_num_threads()}
    if best >= 0:
        # The record: where it trained, and every validation (also those after the best step).
        meta = {**json.loads(config_path.read_text()), **where, "history": history}
        with atomic_write(config_path, "w", encoding="utf-8") as handle:
            handle.write(json.dumps(meta, indent=2))
        if cfg.calibrate and cfg.task == "identify":  # the tracking model keeps the default settings
            calibrate_checkpoint(cfg, val_pairs, log=log)
    return {"best_mean_top1": best, "history": history, "minutes": minutes}


def calibrate_checkpoint(cfg: TrainConfig, val_pairs: dict | None = None, log=print) -> dict:
    """Calibrate the checkpoint at ``cfg.out`` on the validation pairs of its training labs
    (the same pairs training validated on) and write the settings into its JSON."""
    from .identify import Identifier
    from .model import model_files

    start = time.time()
    if cfg.threads:  # --calibrate-only comes here without train(), which sets them
        import torch

        torch.set_num_threads(cfg.threads)
    corpus = load_corpus(cfg.corpus)
    if val_pairs is None:
        val_pairs = held_out(corpus, cfg)[2]
    _, config_path = model_files(cfg.out)
    own_labs = {lab: p for lab, p in val_pairs.items() if lab in cfg.train_labs}
    _need_own_validation(cfg, own_labs)
    doubt = round(mixed_handedness_rate([w for w in corpus if w.lab in cfg.train_labs]), 3)
    log(f"calibrate: template_chirality_doubt {doubt} "
        "(how often two worms of a training lab differ in handedness, by their names)")
    settings = calibrate(Identifier.load(cfg.out, cfg.device), own_labs, log,
                         panel_tests=_panel_tests(corpus, own_labs, cfg.train_labs), template_chirality_doubt=doubt)
    meta = json.loads(config_path.read_text())
    meta.update(inference=settings, calibration_minutes=round((time.time() - start) / 60, 1))
    with atomic_write(config_path, "w", encoding="utf-8") as handle:
        handle.write(json.dumps(meta, indent=2))
    log(f"calibrated inference settings: {settings}")
    return settings


def mixed_handedness_rate(worms: list[Worm]) -> float:
    """How often a template and a test of the same lab differ in handedness, over these worms'
    labs (ordered pairs within each lab; each worm's handedness from its names, relative to an
    atlas of all of them). With a template, ``fdlc label`` keeps the template's handedness
    unless told otherwise (the model's preference is noise on a lab it has not seen), so this
    is how often its names come out left/right swapped: the weight the answer reported gives
    the other handedness (``template_chirality_doubt``). The validation pairs cannot fit it:
    6 per lab, they rarely differ in handedness (KK's fold fitted 0)."""
    atlas = build_atlas(worms)
    differing = total = 0
    for lab in sorted({w.lab for w in worms}):
        flags = [mirrored_relative_to(atlas, w.table) for w in worms if w.lab == lab]
        n, k = len(flags), sum(flags)
        differing, total = differing + 2 * k * (n - k), total + n * (n - 1)
    return differing / total if total else 0.0


def _panel_tests(corpus: list[Worm], val_pairs: dict[str, list], train_labs) -> dict[str, tuple]:
    """Per training lab: the built-in panel rebuilt from the *other* training labs' worms, and
    that lab's validation worms to identify with it (as the panel protocol scores a new lab)."""
    from .reference import make_panel

    out = {}
    for lab, pairs in val_pairs.items():
        others = [w for w in corpus if w.lab in train_labs and w.lab != lab]
        tests = list({id(t): t for _, t in pairs}.values())  # the worms named: held out of training
        if others and tests:
            out[lab] = (make_panel(build_atlas(others)), tests)
    return out


def memoised(method, key, cache: dict):
    """``method`` answering each call once per ``key(*args, **kwargs)`` in ``cache``. The
    arguments are kept with the answer: keys may hold ids, and an id is reused once its object
    is gone (the panel registers each test's head window, a new table on every call, which then
    got another window's registration)."""
    def call(*args, **kwargs):
        k = (id(method), *key(*args, **kwargs))
        if k not in cache:
            cache[k] = (args, kwargs, method(*args, **kwargs))
        return cache[k][-1]
    return call


def calibrate(identifier, val_pairs: dict[str, list], log=print, panel_tests: dict | None = None,
              template_chirality_doubt: float = 0.0) -> dict:
    """Fit the inference settings that are not learned by gradient descent, on validation
    pairs of the *training* labs: the weight of leaving a neuron unnamed (top-1, position
    only), the colour fusion weight (top-1 with colour), then the temperature that minimises
    the expected calibration error of ``auto_conf``. With ``panel_tests`` (see _panel_tests),
    the weights of the atlas's own answer beside a template (top-1, each lab's pairs with an
    atlas built without it), the weight of the atlas's answer in the panel (top-1), the panel's
    temperature (calibration error, each test in its own handedness) and its chirality doubt
    (calibration error on `auto`). ``template_chirality_doubt`` (counted, not fitted: see
    :func:`mixed_handedness_rate`) is in the answers the temperature is fitted on. The prior
    against a mirrored placement is not fitted (identify.MIRROR_PRIOR)."""
    # Every setting fitted here acts after the registrations and the model's forward passes:
    # compute those once (instance attributes shadow the methods until the end).
    cache = {}

    def cached(method, key):
        return memoised(method, key, cache)

    patched = [(identifier, "_forward_grid", lambda templates, tests, tc=None, sc=None: (
                   tuple(t.tobytes() for t in templates), tuple(t.tobytes() for t in tests), tc is not None)),
               (identifier, "place", lambda template, tests, use_colour=True: (
                   id(template), tuple(map(id, tests)), use_colour))]
    patched += [(panel.atlas, "register", lambda test, use_colour=True, chiralities=(False, True), stretch_z=True: (
                    id(test), use_colour, chiralities, stretch_z))
                for panel, _ in (panel_tests or {}).values()]
    for owner, name, key in patched:
        setattr(owner, name, cached(getattr(owner, name), key))
    try:
        return _fit_settings(identifier, val_pairs, log, panel_tests, template_chirality_doubt)
    finally:
        for owner, name, _ in patched:
            delattr(owner, name)


def _fit_settings(identifier, val_pairs: dict[str, list], log, panel_tests: dict | None, template_chirality_doubt: float) -> dict:
    from .identify import MIRROR_PRIOR

    # Each lab's pairs are joined by an atlas built without that lab (the panel tests' atlas),
    # as a lab the atlas has never seen would be: its own worms in the atlas would flatter it.
    atlases = {lab: panel.atlas for lab, (panel, _) in (panel_tests or {}).items()}

    def run(use_colour):  # every training lab's validation pairs, pooled
        scores = Scores()
        for lab, pairs in val_pairs.items():
            _pair_scores(identifier, pairs, use_colour, scores, atlases.get(lab))
        return scores

    settings = identifier.settings
    # Every fitted setting starts from its default, not from what the model's JSON holds, so
    # that calibrating twice gives the same settings (each choice below depends on the others).
    defaults = type(settings)()
    for name in ("no_match_weight", "colour_weight", "atlas_weight", "atlas_weight_position", "atlas_worm_weight",
                 "atlas_worm_weight_position", "temperature", "chirality_doubt", "panel_temperature",
                 "panel_atlas_weight", "panel_atlas_weight_position"):
        setattr(settings, name, getattr(defaults, name))

    def choose(name, values, score):
        """Set ``settings.name`` to the value with the highest score (first one on ties)."""
        results = []
        for value in values:
            setattr(settings, name, value)
            results.append(score())
            log(f"calibrate: {name} {value}: {results[-1]:.3f}")
        setattr(settings, name, values[int(np.argmax(results))])

    settings.mirror_penalty = MIRROR_PRIOR  # not fitted: why at identify.MIRROR_PRIOR
    choose("no_match_weight", (0.05, 0.2, 0.5, 1.0), lambda: run(False).summary()["top1"])
    choose("colour_weight", (0.0, 0.25, 0.5, 1.0), lambda: run(True).summary()["top1"])
    if atlases:  # with a template, the weights of the atlas's answers (top-1)
        # The atlas's own answer, then the atlas worm's beside it, then the first again (they
        # share what they correct: a single template's individual variation).
        for name in ("atlas_weight", "atlas_worm_weight", "atlas_weight"):
            for suffix, use_colour in (("_position", False), ("", True)):
                values = (0.0, 0.25, 0.5, 0.75) if name == "atlas_worm_weight" else (0.0, 0.25, 0.5, 1.0, 2.0)
                choose(name + suffix, values, lambda c=use_colour: run(c).summary()["top1"])
    # lowest expected calibration error, position only and with colour, of the answers as
    # reported: with the other handedness's share already in them
    settings.template_chirality_doubt = template_chirality_doubt
    choose("temperature", (0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.5, 2.0, 3.0),
           lambda: -np.mean([run(c).summary()["ece"] for c in (False, True)]))

    def run_panel(use_colour, handedness_given=False):
        scores = Scores()
        for panel, tests in panel_tests.values():
            _panel_scores(identifier, panel, tests, use_colour, scores, handedness_given)
        return scores

    if panel_tests:
        # The atlas's answer in the panel (top-1; each lab's tests against a panel and atlas
        # built without it). It names the test in the handedness chosen before it, so it is
        # fitted with each test's handedness given (by its names): on `auto` a few wrongly
        # chosen handedness among 2 worms per lab would decide it.
        choose("panel_atlas_weight_position", (0.0, 0.25, 0.5, 1.0), lambda: run_panel(False, True).summary()["top1"])
        choose("panel_atlas_weight", (0.0, 0.25, 0.5, 1.0), lambda: run_panel(True, True).summary()["top1"])
        # The temperature calibrates the answer in the right handedness (fitted with it given);
        # the doubt then gives the other handedness the share that calibrates `auto`. Fitted
        # jointly on `auto`, a wrongly chosen handedness among 2 worms per lab (confidently
        # wrong everywhere) flattened every answer instead (the NP fold: temperature 1.0, ECE
        # 0.39 on NP with its handedness given).
        choose("panel_temperature", (0.25, 0.35, 0.5, 0.7, 1.0, 1.4),
               lambda: -np.mean([run_panel(c, True).summary()["ece"] for c in (False, True)]))
        choose("chirality_doubt", (0.0, 0.15, 0.3), lambda: -np.mean([run_panel(c).summary()["ece"] for c in (False, True)]))
    return asdict(settings)
