"""Place a test worm in a reference's frame before the model compares them.

The reference is a Gaussian mixture: the atlas (one component per name: its mean position,
spread and colour; :meth:`napari_fdlc.reference.Atlas.mixture`) or a labelled template worm
(one component per neuron; :func:`template_mixture`). EM fits a similarity transform of the
test's points to it (against the atlas, with a stretch along the test's own z: labs differ in
apparent z scale), with a uniform outlier class for neurons the reference lacks, from
``ROLL_STEPS`` rolls about the body axis × 2 head directions per chirality (and, against the
atlas, offsets along the body axis for a partial field of view). Unlike the 16
right-angle orientations of ``geometry.ORIENTATIONS`` this finds rolls that are not right
angles, and it does not ask the model to judge orientations it was not trained on: between
worms of a lab the model never saw, it took pairs with colour from 37 to 50 % top-1 averaged
over the five leave-one-lab-out folds (docs/leave_one_lab_out.md).

Neither chirality can be ruled out here: the head is nearly left/right symmetric and NeuroPAL
colours are shared by left/right pairs, so a mirrored worm fits almost as well (measured: the
likelihood difference has a random sign). :func:`register` returns the likeliest placement
per chirality (or every start's, ``every_start``) and the caller decides (a prior, the model's
score, or a name the user fixed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .colour import IDENTITY_CHANNELS, has_colour, normal_scores, read_channels
from .errors import FdlcError
from .geometry import canonical_frame
from .table import YOUNG_ADULT_SPACING_UM, NeuronTable, neuron_spacing

ROLL_STEPS = 12  # starting rolls about the body axis (every 30°)
# µm: how far a neuron of one worm lies from the same neuron of another after the best
# similarity transform (measured on corpus pairs within a lab: median 3.6–8 µm).
TEMPLATE_SD = 3.35
_COLOUR_VAR = 0.15  # added to each component's colour variance (normal-score units)
_TEMPLATE_COLOUR_SD = 0.4  # one worm's colour against another's, same neuron
_MIN_SHIFT_UM = 2.0  # below this, the starts' own EM steps cover the offset
# A partial view keeps this many times ``keep`` starts (of 24 poses × 5 offsets per
# chirality, at each of PARTIAL_VIEW_SIZES). EM from fewer missed the pose its names give on 4
# of SF's 36 worms although that pose is the likelier one (a search failure, not the
# likelihood's): 2× kept, 3 of them were named at 0-9 %. 8× (24 starts): the panel on SF, held
# out, the handedness given, 67.4 -> 70.6 % (2× / 4× / 8× / 12× / 16×: 67.4 / 69.2 / 70.6 /
# 71.3 / 71.5) for 7 ms more per registration (16×: 18 ms); benchmarks.md.
PARTIAL_VIEW_KEEP = 8
# A view of less than this fraction of the reference's extent along the body (at the size it is
# expected to have there) runs EM from every start. Such a view fits many places of the head,
# and the coarse scores kept the wrong ones: SF's worms cropped to 60 % of their length
# (0.43-0.56 of the atlas) were placed 14-27 µm from their names on 9 of 12 worms, 7 of them at
# a lower likelihood than where their names are. The shipped model named 21 % of them, 55 %
# with this (11 of the 12 are under half; 16× / 24× the kept starts instead of all: 42 / 44 %);
# benchmarks/robustness.py --shipped. Such views have few neurons: EM from all 240 starts took
# one 40-neuron view's registration from 18 to 63 ms, its panel call from 86 to 125 ms. No
# corpus worm is this short (SF's shortest: 0.52 of an atlas without SF): none changes.
SHORT_VIEW = 0.5
# A partial view also starts at larger sizes than a median corpus worm's (its extent cannot
# tell part of a big head from more of a small one; sparse tables cannot show their size by
# their spacing, see YOUNG_ADULT_SPACING_UM), each with the scale bound around it; the kept
# starts are chosen among all. From 1 alone, SF's recordings shrunk to 0.75 / 0.6 were placed on
# their names 8 / 4 times of 12 (an atlas without SF) and named at 60.9 / 23.9 % (shipped
# model): EM kept to too small a scale, where a wrong part of the head fits, although the pose
# the names give is the likelier one. With 1.4: 71.7 / 72.0 % (1.3: 71.9 / 65.7; 1, 1.3, 1.6:
# 71.8 / 72.6), SF as it is 71.5 either way; every corpus answer of accuracy.md the same. It
# costs a partial view about 1.3x its registration (SF 49 -> 63 ms, its panel call 1.1x).
PARTIAL_VIEW_SIZES = (1.0, 1.4)
# Onto a template (no partial-view search: between two worms of a lab it cost SK1's pairs 4.6
# points, see Mixture.partial_views), a test shorter than this fraction of the template's
# length (5-95 % along the body) is still started at offsets along it, at scale 1, and the
# model chooses among the best starts of each offset and of the centred one. A view cropped to
# 60 % of a worm's neurons, named beside the next worm of its lab: EY 62.1 -> 74.8 % top-1, KK
# 46.0 -> 48.8, SK1 45.7 -> 43.8, NP and SF within 0.1 (benchmarks/robustness.py --protocol
# pairs). No two corpus worms of a lab are that different (SK1's most: 0.52), so no corpus
# answer changes; at 0.75 EY / KK / SF gained 11 / 7 / 7 points more but corpus pairs moved
# (benchmarks.md). Without the centred starts NP's crops fell 81.0 -> 73.7 (wrong offsets).
TEMPLATE_SHORT_VIEW = 0.5
_EM_BUDGET = 2**24  # elements (64 MB in single precision) of one (starts, N, K) array of EM
# A test whose neurons spread further along the body axis than HEAD_WINDOW times the reference's
# length (5-95 % of its body axis, at the reference's scale) is cut to its head first
# (head_window). The corpus's heads spread over 1.3-1.7 times the atlas's length, NP's over
# 1.7-2.1 (they reach into the ventral cord).
HEAD_WINDOW = 1.8
HEAD_WINDOW_STEP_UM = 10.0  # at the reference's scale
_OUTLIER_LOG_DENSITY = -15.0  # per point: a neuron the reference lacks (-7 fitted closer but scored worse)
_EXP_FLOOR = -80.0  # log-densities relative to their bound are exponentiated from here (_log_likelihood)


@dataclass
class Mixture:
    """What a test is registered to, in the reference's frame."""

    mean: np.ndarray  # (K, 3) µm
    var: np.ndarray  # (K, 3) µm²
    log_weight: np.ndarray  # (K,)
    colour: np.ndarray | None  # (K, 3) normal scores of R, G, B, or None
    colour_var: np.ndarray | None  # (K, 3)
    # Bounds on the fitted scale, in total, relative to the size the test is expected to have
    # here (partial_view_scale). Labs' worms differ in size and the atlas needs some freedom;
    # a template is in µm like the test, and a free scale let EM shrink the test into the dense
    # head (pairs top-1 with colour fell by 5–35 points).
    scale_range: tuple[float, float] = (1.0, 1.0)
    # The reference spans the whole head (the atlas) while a test may show part of it: start
    # also at offsets along the body axis (partial_view_shifts). Between two worms of a lab it
    # cost SK1's pairs 4.6 points (their fields of view vary), so templates do not, unless the
    # test is much shorter than the template (TEMPLATE_SHORT_VIEW).
    partial_views: bool = False
    # The test's size relative to the reference (µm): what scale_range bounds, and where the
    # starts of a partial view are. The atlas is smaller than real worms (Procrustes): 1 /
    # Atlas.worm_scale. A whole head starts at scale 1 and EM shrinks it; from a partial view
    # EM did not find the pose its names give (the likelihood there is higher than at every
    # pose found: a search failure).
    partial_view_scale: float = 1.0
    # Bounds on a stretch of the test along its own z (the optical axis) on top of the
    # similarity: labs differ in apparent z scale (refractive-index mismatch between immersion
    # and sample, z-step calibration). (1, 1): none.
    z_scale_range: tuple[float, float] = (1.0, 1.0)
    # A template's smaller_worm_factor (1 for the atlas): a test is taken to its size.
    size_factor: float = 1.0


@dataclass
class Placement:
    """A test worm placed in a reference's frame by :func:`register`."""

    xyz: np.ndarray  # (N, 3) µm in the reference frame
    mirrored: bool  # the recording's z had to be mirrored
    score: float  # mean log-likelihood per neuron under the mixture
    partial_view: bool = False  # shorter than the reference: started at offsets along its body axis


def template_mixture(template: NeuronTable) -> Mixture:
    """A labelled (or unlabelled) worm as a mixture in its canonical frame."""
    mean = canonical_frame(template.xyz)[0]
    colour = colour_var = None
    if has_colour(template):
        colour = normal_scores(template, IDENTITY_CHANNELS)
        colour_var = np.full_like(colour, _TEMPLATE_COLOUR_SD**2)
    return Mixture(mean, np.full_like(mean, TEMPLATE_SD**2), np.zeros(len(mean)), colour, colour_var,
                   size_factor=smaller_worm_factor(template.xyz))


def register(test: NeuronTable, mixture: Mixture, use_colour: bool = True, iterations: int = 6, keep: int = 3,
             chiralities: tuple[bool, ...] = (False, True), every_start: bool = False) -> list[Placement]:
    """Place ``test`` in the mixture's frame, once per chirality (``chiralities``: mirrored or
    not; default proper first, then mirrored): the ``keep`` best of the starting poses by
    likelihood, ``iterations`` EM steps each, the most likely result per chirality — or, with
    ``every_start``, every start's result (``keep`` per chirality) for the caller to choose.
    With ``mixture.partial_views`` (the atlas), a table denser than a young adult's head is
    first taken up to its size (:func:`smaller_worm_factor`), and a test that covers less of the
    body than the reference starts at ``mixture.partial_view_scale`` times each of
    PARTIAL_VIEW_SIZES and at several offsets along the body axis (:func:`partial_view_shifts`),
    and PARTIAL_VIEW_KEEP times as many starts are kept. Onto a template (in µm like the test),
    a test denser than a young adult's head is taken to the template's size the same way, and a
    test shorter than TEMPLATE_SHORT_VIEW of it starts at offsets along it too."""
    if len(test) == 0 or not chiralities or keep < 1:
        raise FdlcError(f"register: nothing to place ({len(test)} neurons, chiralities {chiralities}, keep {keep}); "
                        "a test with neurons, one chirality or more and keep ≥ 1 are needed")
    canon, _, frame = canonical_frame(test.xyz)
    # A smaller worm than a young adult is taken up to one's size (the atlas's size_factor is 1);
    # onto a template, to the template's own size.
    canon = canon * (smaller_worm_factor(test.xyz) / mixture.size_factor)
    # The optical axis in the canonical frame: z itself, unless a tilted worm was levelled.
    # The stretch acts along it (what differs between labs is the z step's calibration).
    optical = frame[:, 2].astype(np.float32)

    def shifts_of(points):
        if mixture.partial_views:
            return partial_view_shifts(points[:, 0], mixture.mean[:, 0], mixture.scale_range[0])
        if _extent(points[:, 0]) < TEMPLATE_SHORT_VIEW * _extent(mixture.mean[:, 0]):
            return partial_view_shifts(points[:, 0], mixture.mean[:, 0], 1.0)
        return (0.0,)

    partial = len(shifts_of(canon)) > 1
    atlas_view = partial and mixture.partial_views  # part of the head, against the atlas
    template_view = partial and not mixture.partial_views  # much shorter than its template
    if partial:  # start at the scale it has against the reference
        canon = canon * mixture.partial_view_scale
    sizes = PARTIAL_VIEW_SIZES if atlas_view else (1.0,)
    # Each start block: one size and one offset along the body axis
    blocks = [(size, dx) for size in sizes for dx in shifts_of(canon * size)]
    keep = PARTIAL_VIEW_KEEP * keep if atlas_view else keep
    if atlas_view and _extent(canon[:, 0]) < SHORT_VIEW * _extent(mixture.mean[:, 0]):
        # every start (see SHORT_VIEW), as far as EM's (starts, N, K) arrays stay within budget
        fits = _EM_BUDGET // (len(chiralities) * len(canon) * len(mixture.mean))
        keep = max(keep, min(len(_START_ROTATIONS) // 2 * len(blocks), fits))
    # The scores of every start are (starts, N, K) exponentials: single precision halves their
    # cost and changes a log-likelihood per neuron by ~1e-6.
    f32 = np.float32
    coefficients, constant, shift = _component_terms(test, mixture, use_colour)
    coefficients, constant = coefficients.astype(f32), np.asarray(constant, f32)
    mean, canon = mixture.mean.astype(f32), canon.astype(f32)

    def log_components(points):
        return _log_components(points, coefficients, constant)

    def log_likelihood(comp, responsibilities=False):
        return _log_likelihood(comp, shift, responsibilities)

    tried = np.isin(_START_MIRRORED, chiralities)
    mirrored = np.tile(_START_MIRRORED[tried], len(blocks))
    rotations = np.tile(_START_ROTATIONS[tried].astype(f32), (len(blocks), 1, 1))
    start_size = np.repeat(np.array([size for size, _ in blocks], f32), tried.sum())
    turned = np.einsum("kij,nj->kni", _START_ROTATIONS[tried].astype(f32), canon)
    offsets = [size * turned + np.array([dx, 0.0, 0.0], f32) for size, dx in blocks]
    starts = np.concatenate(offsets)
    # one offset at a time: the (starts, N, K) scores of every offset at once would take 100+ MB
    coarse = np.concatenate([log_likelihood(log_components(o)).sum(axis=-1) for o in offsets])

    def best(among):
        return np.flatnonzero(among)[np.argsort(-coarse[among])[:keep]]

    chosen = np.concatenate([best(mirrored == m) for m in chiralities])
    if template_view:
        # A short view onto a template keeps the best starts of its centred block too (what a
        # whole worm gets): the model chooses among them (TEMPLATE_SHORT_VIEW).
        centred = np.repeat([dx == 0.0 for _, dx in blocks], tried.sum())
        chosen = np.concatenate([np.unique(np.concatenate([best((mirrored == m) & centred), best(mirrored == m)]))
                                 for m in chiralities])
    points = starts[chosen]  # EM from every kept start at once: (S, N, 3)
    stretchable = mixture.z_scale_range != (1.0, 1.0)
    if stretchable:  # points = (canon stretched along the optical axis by stretch) @ linear + shift
        linear = start_size[chosen, None, None] * np.transpose(rotations[chosen], (0, 2, 1))
        stretch = np.ones(len(chosen), f32)
        canon_z = canon @ optical
    # The scale is bounded in total, relative to the size the test is expected to have in the
    # reference's frame (the starts of a partial view are at that size times their own, a whole
    # head's are in µm). Each EM step's similarity is biased toward shrinking (its targets are
    # posterior means, pulled toward the middle by diffuse responsibilities), and a bound per
    # step let the steps compound: NP's heads ended at 0.64 of the scale their names give.
    expected = start_size[chosen] if partial else mixture.partial_view_scale
    low, high = (expected * bound for bound in mixture.scale_range)
    total_scale = start_size[chosen] if partial else np.ones(len(chosen), f32)
    for _ in range(iterations):
        resp = log_likelihood(log_components(points), responsibilities=True)[1]
        weight = resp.sum(axis=-1)
        targets = (resp @ mean) / np.maximum(weight[..., None], 1e-12)
        points, scale, rotation = _weighted_similarity(points, targets, weight, (low / total_scale, high / total_scale))
        total_scale = total_scale * scale
        if stretchable:
            linear = scale[:, None, None] * linear @ rotation
            points, stretch = _stretch_z(points, targets, weight, canon_z, optical @ linear, stretch, mixture.z_scale_range)
    scores = log_likelihood(log_components(points)).mean(axis=-1, dtype=np.float64)
    points = points.astype(np.float64)
    if every_start:
        return [Placement(p, bool(m), float(s), partial) for p, m, s in zip(points, mirrored[chosen], scores)]
    placements = []
    for m in chiralities:
        own = np.flatnonzero(mirrored[chosen] == m)
        k = own[np.argmax(scores[own])]
        placements.append(Placement(points[k], bool(m), float(scores[k]), partial))
    return placements


def posterior(test: NeuronTable, mixture: Mixture, placed: np.ndarray, use_colour: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """For ``test`` placed at ``placed`` (N, 3) in the mixture's frame (a :class:`Placement`):
    the probability (N, K) that each neuron is each component, and (N,) that it is none (the
    outlier class) — an answer from positions and colours alone, without the model."""
    coefficients, constant, shift = _component_terms(test, mixture, use_colour)
    total, resp = _log_likelihood(_log_components(placed, coefficients, constant), shift, responsibilities=True)
    return resp, np.exp(_OUTLIER_LOG_DENSITY - total)


def _component_terms(test: NeuronTable, mixture: Mixture, use_colour: bool):
    """What the log-density of each component at a point needs (:func:`_log_components`): the
    coefficients (6, K) of [points², points], i.e. -1 / (2 variance) and mean / variance, the
    rest (N, K or K: log weight, normalisation, the colour term) less ``shift``, and ``shift``:
    a bound no component's log-density exceeds at any point (its Mahalanobis term is ≤ 0), or
    the outlier class's if that is higher. The log-densities come out relative to it, ≤ 0, so
    :func:`_log_likelihood` can exponentiate them without first finding each point's largest."""
    var = mixture.var
    log_weight = mixture.log_weight - 0.5 * np.log(var).sum(axis=1)
    colour_term = 0.0
    present = [IDENTITY_CHANNELS.index(c) for c in read_channels(test)]
    if use_colour and mixture.colour is not None and present:
        # A channel the test lacks is left out (each channel is its own factor): without B,
        # held out, the panel kept 25.5 % of SF's names instead of 10.1 (benchmarks/robustness.py).
        scores = normal_scores(test, tuple(IDENTITY_CHANNELS[i] for i in present))
        cvar = (mixture.colour_var + _COLOUR_VAR)[:, present]
        colour_term = -0.5 * (((scores[:, None] - mixture.colour[None][..., present]) ** 2) / cvar[None]).sum(-1)
        colour_term = colour_term - 0.5 * np.log(cvar).sum(axis=1)[None]
    inv_var = 1.0 / var
    coefficients = np.concatenate([-0.5 * inv_var, mixture.mean * inv_var], axis=1).T
    highest = log_weight + (colour_term.max(axis=0) if np.ndim(colour_term) else colour_term)
    shift = max(float(highest.max()), _OUTLIER_LOG_DENSITY)
    return coefficients, log_weight - 0.5 * (mixture.mean**2 * inv_var).sum(axis=1) + colour_term - shift, shift


def _log_components(points, coefficients, constant):
    """(..., N, K): log weight × density of each component at each point. The Mahalanobis
    distance is expanded into one matrix product of [points², points] (..·N, 6) with the
    components' ``coefficients`` (6, K, :func:`_component_terms`): 10× faster than
    broadcasting, and 12× faster again than two stacked products with an inner size of 3 (48
    starts of a 130-neuron test: 4.5 → 0.4 ms)."""
    flat = points.reshape(-1, points.shape[-1])
    out = (np.concatenate([flat * flat, flat], axis=1) @ coefficients).reshape(*points.shape[:-1], -1)
    out += constant
    return out


def _log_likelihood(comp: np.ndarray, shift: float, responsibilities: bool = False):
    """(..., N) per point from its log components (..., N, K) less ``shift``, their bound
    (:func:`_component_terms`), with a uniform outlier class (a neuron the reference lacks, a
    spurious detection); with ``responsibilities``, also the probability (..., N, K) of each
    component at each point (the outlier class has the rest), from the same exponentials.
    ``comp`` is overwritten: these arrays are megabytes (48 starts), and a new one per step
    cost more than the arithmetic (page faults). Exponentiated relative to the bound, not to
    each point's largest component (a clamp instead of a maximum and a subtraction: one pass
    over the array fewer), and from no lower than ``_EXP_FLOOR``: a quarter of the 48 starts'
    log-densities lie further below, where single precision's exp is denormal and several
    times slower (their exponentials 5.0 -> 2.8 ms; docs/speed.md). e^-80 per component is
    nothing beside the outlier class's e^(-15 - shift), and keeps every total above 0."""
    np.maximum(comp, _EXP_FLOOR, out=comp)
    share = np.exp(comp, out=comp)  # each component's density relative to the bound
    total = share.sum(axis=-1) + np.exp(_OUTLIER_LOG_DENSITY - shift)
    log_likelihood = shift + np.log(total)
    if not responsibilities:
        return log_likelihood
    share /= total[..., None]
    return log_likelihood, share


def head_window(test: NeuronTable, mixture: Mixture, use_colour: bool = True,
                reach: float = HEAD_WINDOW) -> np.ndarray | None:
    """The rows of ``test`` that lie in its head, when its neurons spread further along the body
    axis than a head's (more than ``reach`` times the reference's length, :func:`body_reach`;
    None otherwise, and for a reference without ``partial_views``, i.e. a template). A window
    that long slides along the test's body axis; each window is registered and the one the
    reference explains best wins (the summed log-likelihood of its neurons above the outlier
    class's). Registered whole, a head with 40 neurons more over 60 µm of body was placed
    12-14 µm from its names' atlas positions (5-7 µm for the head alone) and the panel's top-1
    fell from 75 to 40 % (NP; 120 over 250 µm: 13 %); benchmarks/robustness.py. NP's own heads lose 2-5 ventral-cord neurons
    (VB3, VA2, DA1, ...) that an atlas without NP does not name, and place the rest better."""
    if not mixture.partial_views:
        return None
    x = _body_axis(test, mixture)
    length = reach * _extent(mixture.mean[:, 0])
    if np.ptp(x) <= length:  # body_reach(test) <= reach
        return None
    best, best_gain = None, -np.inf
    for low in _window_starts(x, length, HEAD_WINDOW_STEP_UM):
        rows = np.flatnonzero((x >= low) & (x <= low + length))
        if len(rows) < 4:
            continue
        score = max(p.score for p in register(test.subset(rows), mixture, use_colour))
        gain = len(rows) * (score - _OUTLIER_LOG_DENSITY)
        if gain > best_gain:
            best, best_gain = rows, gain
    return best


def _window_starts(x: np.ndarray, length: float, step: float) -> np.ndarray:
    """The starts ``x.min() + k * step`` of the windows [start, start + length] that slide over
    ``x``, one per distinct set of points inside (the first start of each): the windows are
    scored in this order, so the answer is that of every start, but a neuron far out (a unit
    slip in one row, 1e8 µm) no longer makes span / step windows to go through."""
    x0 = float(x.min())
    count = np.ceil((x.max() - length + step - x0) / step)  # starts of the whole slide (np.arange's count)
    # A point enters a window at k = (x - length - x0) / step and leaves after k = (x - x0) / step;
    # between such changes the window holds the same points. Neighbours of each change are
    # kept as well, so that rounding cannot hide one.
    changes = np.concatenate([np.ceil((x - length - x0) / step), np.floor((x - x0) / step) + 1, [0.0]])
    k = np.unique(np.clip(np.concatenate([changes - 1, changes, changes + 1]), 0, count - 1))
    starts = x0 + k * step
    xs = np.sort(x)
    first, last = np.searchsorted(xs, starts, side="left"), np.searchsorted(xs, starts + length, side="right")
    distinct = np.ones(len(k), dtype=bool)
    distinct[1:] = (first[1:] != first[:-1]) | (last[1:] != last[:-1])
    return starts[distinct]


def body_reach(table: NeuronTable, mixture: Mixture) -> float:
    """How far ``table``'s neurons spread along its body axis, in lengths of the reference (the
    atlas: 5-95 % of its names' means along the body), at the size it is expected to have there."""
    return float(np.ptp(_body_axis(table, mixture))) / _extent(mixture.mean[:, 0])


def _body_axis(table: NeuronTable, mixture: Mixture) -> np.ndarray:
    """Each neuron's place along ``table``'s body axis (µm at the reference's scale)."""
    return canonical_frame(table.xyz)[0][:, 0] * mixture.partial_view_scale * smaller_worm_factor(table.xyz)


# A table whose neurons lie closer together than a complete young adult's head
# (table.YOUNG_ADULT_SPACING_UM: NP's heads, every head neuron named; 4.0-7.0 µm in the other
# labs' sparser tables, and sparser annotation, dropped neurons or part of a head only make it
# longer) is a smaller worm. Against the atlas such a table is taken up to that spacing first:
# the registration's starts and scale bounds are at a young adult's size, and from NP's heads
# shrunk to 0.75 EM placed them 8-20 µm from their names (5.4-6.5 at full size). The panel on
# NP's heads shrunk to 0.75 / 0.6: 64.4 / 26.6 -> 79.8 / 79.8 % (as they are: 80.3), EY's at 0.6
# 76.3 -> 80.8 (shipped model, panel without the lab; benchmarks/robustness.py). No corpus table
# is that dense (20 % spurious points 3-8 µm from NP's neurons: 3.33 at least).
def smaller_worm_factor(xyz: np.ndarray) -> float:
    """How much ``xyz`` must grow for its neurons to lie no closer together than in a complete
    young adult's head (YOUNG_ADULT_SPACING_UM); 1 for a table no denser than that."""
    spacing = neuron_spacing(xyz)
    return max(1.0, YOUNG_ADULT_SPACING_UM / spacing) if spacing else 1.0


def _extent(x: np.ndarray) -> float:
    low, high = np.percentile(x, [5, 95])
    return float(high - low)


def partial_view_shifts(test_x: np.ndarray, reference_x: np.ndarray, min_scale: float, steps: int = 5) -> tuple[float, ...]:
    """Offsets along the body axis (µm) to start the registration from. Both are centred on
    their own median, so a test that shows only part of the reference's body (a partial field
    of view, e.g. SF's ~60-neuron recordings against the whole-head atlas) may sit anywhere
    along it: starts spread over the length the test's extent leaves free, at the smallest
    scale the fit allows. With the handedness given, this took the panel on SF from 25.8 to
    42.5 % top-1 (leave-one-lab-out fold model); the other labs moved by 0.3 points at most
    with the same settings. A whole worm gets (0,)."""
    free = (_extent(reference_x) - min_scale * _extent(test_x)) / 2
    return tuple(np.linspace(-free, free, steps)) if free > _MIN_SHIFT_UM else (0.0,)


def _start_rotations() -> tuple[np.ndarray, np.ndarray]:
    """Starting poses: ROLL_STEPS rolls about the body axis × head left/right × chirality (the
    conventions of :data:`napari_fdlc.geometry.ORIENTATIONS`, on a finer grid of rolls)."""
    head_tail = np.diag([-1.0, -1.0, 1.0])
    mirror = np.diag([1.0, 1.0, -1.0])
    rotations, mirrored = [], []
    for m in (False, True):
        for head in (np.eye(3), head_tail):
            for k in range(ROLL_STEPS):
                angle = 2 * np.pi * k / ROLL_STEPS
                c, s = np.cos(angle), np.sin(angle)
                roll = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
                rotations.append(head @ roll @ (mirror if m else np.eye(3)))
                mirrored.append(m)
    return np.array(rotations), np.array(mirrored)


_START_ROTATIONS, _START_MIRRORED = _start_rotations()


def _weighted_similarity(points: np.ndarray, targets: np.ndarray, weight: np.ndarray, scale_range) -> np.ndarray:
    """``points`` (S, N, 3) each moved by the weighted least-squares proper similarity onto
    ``targets`` (S, N, 3), weights (S, N); the scale clipped to ``scale_range`` (low, high:
    numbers, or one per start)."""
    w = weight / np.maximum(weight.sum(axis=-1, keepdims=True), 1e-12)
    mu_p, mu_t = np.einsum("sn,snd->sd", w, points), np.einsum("sn,snd->sd", w, targets)
    p0, t0 = points - mu_p[:, None], targets - mu_t[:, None]
    u, sig, vt = np.linalg.svd(np.einsum("sni,snj->sij", p0 * w[..., None], t0))
    d = np.ones_like(sig)
    d[:, 2] = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    rotation = (u * d[:, None, :]) @ vt  # targets ≈ p0 @ rotation, a proper rotation
    spread = np.maximum((w[..., None] * p0**2).sum(axis=(-1, -2)), 1e-12)
    scale = np.clip((sig * d).sum(axis=-1) / spread, *scale_range)
    return scale[:, None, None] * p0 @ rotation + mu_t[:, None], scale, rotation


def _stretch_z(points, targets, weight, canon_z, z_image, stretch, z_scale_range):
    """``points`` (S, N, 3), placed from the test's canonical frame stretched along its optical
    axis by ``stretch`` (S,) (``canon_z``: each point's coordinate along that axis, which now
    points along ``z_image`` (S, 3)), moved by the weighted
    least-squares change of that stretch toward ``targets`` (the rest of the placement kept),
    the stretch kept within ``z_scale_range``. Returns the points and the new stretches."""
    base_z = canon_z[None] * stretch[:, None]  # (S, N)
    along = np.einsum("snd,sd->sn", targets - points, z_image)
    change = (weight * base_z * along).sum(axis=1) / np.maximum((z_image**2).sum(axis=1) * (weight * base_z**2).sum(axis=1), 1e-12)
    new = np.clip(stretch * (1 + change), *z_scale_range)
    change = new / stretch - 1
    return points + (change[:, None] * base_z)[..., None] * z_image[:, None], new.astype(stretch.dtype)
