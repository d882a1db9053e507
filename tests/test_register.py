"""Registration of a test worm onto a reference (napari_fdlc.register): the atlas or a template."""

import numpy as np
import pytest

from napari_fdlc.errors import FdlcError
from napari_fdlc.geometry import canonical_frame
from napari_fdlc.reference import atlas_worm, load_atlas
from napari_fdlc.register import register, template_mixture
from napari_fdlc.table import NeuronTable


def _posed(table, roll_deg: float, mirrored: bool, rng):
    """``table`` rolled about its body axis, turned in XY, maybe z-mirrored, shifted, noisy."""
    from napari_fdlc.table import NeuronTable

    r = np.radians(roll_deg)
    roll = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    a = rng.uniform(-np.pi, np.pi)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    xyz = table.xyz @ roll.T @ turn.T + rng.normal(0, 0.5, table.xyz.shape) + [40.0, -12.0, 7.0]
    if mirrored:
        xyz[:, 2] *= -1
    return NeuronTable(xyz, table.colours, table.labels)


def test_registration_finds_any_roll_and_both_chiralities():
    """A worm rolled by an angle that is not a right angle lands on the atlas: the right
    chirality's placement is about as close to each name's mean as the worm itself was."""
    atlas = load_atlas()
    rng = np.random.default_rng(1)
    worm = atlas_worm(atlas, rng)
    index = {n: i for i, n in enumerate(atlas.names)}
    rows = [index[n] for n in worm.labels]
    own = np.median(np.linalg.norm(worm.xyz - atlas.mean[rows], axis=1))  # sampled around the mean
    for roll, mirrored in [(37, False), (-115, True), (160, False)]:
        placements = atlas.register(_posed(worm, roll, mirrored, rng))
        assert [p.mirrored for p in placements] == [False, True]
        error = np.median(np.linalg.norm(placements[int(mirrored)].xyz - atlas.mean[rows], axis=1))
        assert error < own + 1.0, (roll, mirrored, error, own)


def test_registration_onto_a_template_keeps_its_scale():
    """Between two worms (both in µm) the scale is not fitted: the rolled, mirrored copy of a
    worm lands on the worm itself, neuron for neuron, in the template's canonical frame."""
    from napari_fdlc.geometry import canonical_frame

    rng = np.random.default_rng(2)
    worm = atlas_worm(load_atlas(), rng)
    mixture = template_mixture(worm)
    assert mixture.scale_range == (1.0, 1.0)
    assert np.allclose(mixture.mean, canonical_frame(worm.xyz)[0])
    for roll, mirrored in [(65, True), (-20, False)]:
        placements = register(_posed(worm, roll, mirrored, rng), mixture)
        error = np.linalg.norm(placements[int(mirrored)].xyz - mixture.mean, axis=1)
        assert np.median(error) < 1.0, (roll, mirrored, np.median(error))


def test_a_smaller_worm_is_taken_to_a_templates_size():
    """Onto a template (scale kept: both in µm), a test whose neurons lie closer together than
    a complete head's is first taken up (smaller_worm_factor): a copy of a template as dense as
    a young adult's head, shrunk to 0.7 (and noisy), lands on it neuron for neuron."""
    from napari_fdlc.register import YOUNG_ADULT_SPACING_UM, neuron_spacing
    from napari_fdlc.table import NeuronTable

    rng = np.random.default_rng(3)
    worm = atlas_worm(load_atlas(), rng)
    dense = NeuronTable(worm.xyz * YOUNG_ADULT_SPACING_UM / neuron_spacing(worm.xyz), worm.colours, worm.labels)
    mixture = template_mixture(dense)
    small = _posed(NeuronTable(dense.xyz * 0.7, dense.colours, dense.labels), 40, False, rng)
    error = np.linalg.norm(register(small, mixture, chiralities=(False,))[0].xyz - mixture.mean, axis=1)
    assert np.median(error) < 1.5, np.median(error)  # without: 4.1 µm


def test_a_short_view_onto_a_template_is_searched_along_it():
    """A test showing a quarter of its template's neurons (one end of the same worm, under half
    its length) is started at offsets along the template too and lands neuron on neuron; at the
    centred offset alone (as before TEMPLATE_SHORT_VIEW) EM stayed 27-32 µm off."""
    from napari_fdlc.geometry import canonical_frame
    import napari_fdlc.register as registration

    for seed in (6, 7):
        rng = np.random.default_rng(seed)
        worm = atlas_worm(load_atlas(), rng)
        x = canonical_frame(worm.xyz)[0][:, 0]
        rows = np.flatnonzero(x > np.quantile(x, 0.75))
        mixture = template_mixture(worm)
        posed = _posed(worm.subset(rows), 30, False, rng)

        def error():
            placed = register(posed, mixture, chiralities=(False,))[0].xyz
            return np.median(np.linalg.norm(placed - mixture.mean[rows], axis=1))

        assert error() < 1.5
        original = registration.TEMPLATE_SHORT_VIEW
        try:
            registration.TEMPLATE_SHORT_VIEW = 0.0
            assert error() > 10.0
        finally:
            registration.TEMPLATE_SHORT_VIEW = original


def test_every_start_gives_each_kept_pose_and_the_default_is_the_likeliest():
    rng = np.random.default_rng(4)
    worm = atlas_worm(load_atlas(), rng)
    mixture = template_mixture(worm)
    test = _posed(worm, 100, False, rng)
    every = register(test, mixture, keep=3, every_start=True)
    assert [p.mirrored for p in every] == [False] * 3 + [True] * 3
    best = register(test, mixture, keep=3)
    for chosen in best:
        own = [p for p in every if p.mirrored == chosen.mirrored]
        assert chosen.score == max(p.score for p in own)
        assert any(np.array_equal(chosen.xyz, p.xyz) for p in own)
    assert [p.mirrored for p in register(test, mixture, chiralities=(True,))] == [True]


def test_a_partial_field_of_view_is_searched_along_the_body():
    """A test that shows only one end of the head is started at offsets along the body axis
    (the atlas spans the whole head) and lands where it belongs; a whole worm is not shifted."""
    from dataclasses import replace

    from napari_fdlc.geometry import canonical_frame
    from napari_fdlc.register import partial_view_shifts

    atlas = load_atlas()
    rng = np.random.default_rng(5)
    worm = atlas_worm(atlas, rng)
    x = canonical_frame(worm.xyz)[0][:, 0]
    # real worms are 1.1-1.7x the atlas's size (Procrustes shrinks it)
    assert partial_view_shifts(1.3 * x, atlas.mean[:, 0], 0.8) == (0.0,)
    index = {n: i for i, n in enumerate(atlas.names)}
    end = -(x - np.median(x))
    part = worm.subset(np.flatnonzero(end > np.quantile(end, 0.55)))
    assert len(partial_view_shifts(canonical_frame(part.xyz)[0][:, 0], atlas.mean[:, 0], 0.8)) == 5
    posed = _posed(part, 50, False, rng)
    rows = [index[n] for n in part.labels]

    def error(mixture):
        return np.median(np.linalg.norm(register(posed, mixture)[0].xyz - atlas.mean[rows], axis=1))

    assert error(atlas.mixture()) < 4.0 < 10.0 < error(replace(atlas.mixture(), partial_views=False))


def test_a_short_partial_view_at_real_size_is_placed_on_its_names():
    """The last quarter of a head at a real worm's size (the atlas is smaller) lands on the
    names' means: started at 1 / worm_scale, and even from a wrong starting scale (1), which
    the search's PARTIAL_VIEW_KEEP starts cover (with 2× kept, EM landed 26-28 µm off from there
    on 5 of 6 seeds)."""
    from dataclasses import replace

    from napari_fdlc.geometry import canonical_frame
    from napari_fdlc.table import NeuronTable

    atlas = load_atlas()
    assert 1.1 < atlas.worm_scale < 1.5
    index = {n: i for i, n in enumerate(atlas.names)}
    for seed in (0, 1, 3):
        rng = np.random.default_rng(seed)
        worm = atlas_worm(atlas, rng)
        x = canonical_frame(worm.xyz)[0][:, 0]
        part = worm.subset(np.flatnonzero(np.median(x) - x > np.quantile(np.median(x) - x, 0.75)))
        posed = _posed(NeuronTable(part.xyz * atlas.worm_scale, part.colours, part.labels), 50, False, rng)
        rows = [index[n] for n in part.labels]

        def error(mixture):
            return np.median(np.linalg.norm(register(posed, mixture)[0].xyz - atlas.mean[rows], axis=1))

        assert error(atlas.mixture()) < 4.0
        assert error(replace(atlas.mixture(), partial_view_scale=1.0)) < 4.0


def test_the_atlas_posterior_names_a_posed_worm_without_the_model():
    """The atlas's own answer (registration, then each neuron's posterior over the names):
    a worm drawn from the atlas, rolled, turned and mirrored, is mostly named right in its
    handedness, and far less in the other; each row with its "none" share sums to 1."""
    atlas = load_atlas()
    rng = np.random.default_rng(3)
    worm = atlas_worm(atlas, rng, spread=0.5)
    posed = _posed(worm, 70.0, True, rng)
    right = {}
    for mirrored in (True, False):
        resp, none = atlas.posterior(posed, use_colour=True, mirrored=mirrored)
        assert resp.shape == (len(posed), len(atlas.names)) and np.allclose(resp.sum(1) + none, 1.0)
        right[mirrored] = np.mean(atlas.names[resp.argmax(1)] == posed.labels)
    assert right[True] > 0.8 and right[False] < right[True] - 0.2


def test_registration_onto_the_atlas_undoes_a_stretch_along_the_optical_axis():
    """Labs differ in apparent z scale (refractive-index mismatch, z-step calibration): the
    atlas's own mean worm recorded with its z squeezed to 0.8 lands back on the atlas, because
    the registration stretches the test along its own z (Mixture.z_scale_range); without that
    it stays further off."""
    from dataclasses import replace

    from napari_fdlc.table import NeuronTable

    atlas = load_atlas()
    mean_worm = NeuronTable(atlas.mean, {c: atlas.colour[:, i] for i, c in enumerate("RGB")}, atlas.names)
    posed = _posed(mean_worm, 20, False, np.random.default_rng(3))
    squeezed = NeuronTable(posed.xyz * [1.0, 1.0, 0.8], posed.colours, posed.labels)
    errors = {}
    for stretch in (atlas.mixture().z_scale_range, (1.0, 1.0)):
        placed = register(squeezed, replace(atlas.mixture(), z_scale_range=stretch), chiralities=(False,))[0]
        errors[stretch] = np.median(np.linalg.norm(placed.xyz - atlas.mean, axis=1))
    assert errors[atlas.mixture().z_scale_range] < 1.0 < errors[(1.0, 1.0)], errors


def test_a_colour_channel_the_test_lacks_is_left_out_not_all_colour():
    """Colour columns need not all be present (the table contract): without B, the atlas's
    answer still uses R and G, and names a posed worm better than from positions alone."""
    from napari_fdlc.table import NeuronTable

    atlas = load_atlas()
    rng = np.random.default_rng(4)
    worm = atlas_worm(atlas, rng, spread=1.0)
    posed = _posed(worm, 30.0, False, rng)
    without_b = NeuronTable(posed.xyz, {c: v for c, v in posed.colours.items() if c != "B"}, posed.labels)
    right = {}
    for use_colour in (True, False):
        resp, _ = atlas.posterior(without_b, use_colour=use_colour)
        right[use_colour] = np.mean(atlas.names[resp.argmax(1)] == posed.labels)
    assert right[True] > right[False] + 0.1, right


def test_mixture_densities_match_their_definition():
    """The fast forms (one matrix product for the Mahalanobis terms; the log-likelihood and the
    responsibilities from the same exponentials, in place, relative to the components' bound)
    give the Gaussian mixture with its outlier class as written out directly, for a batch of
    starts as for one placement, in single precision too, and for points so far from every
    component that only the outlier class is left."""
    from scipy.special import logsumexp

    from napari_fdlc.register import _OUTLIER_LOG_DENSITY, _log_components, _log_likelihood

    rng = np.random.default_rng(0)
    mean, var = rng.normal(0, 10, (7, 3)), rng.uniform(1, 9, (7, 3))
    constant = rng.normal(0, 1, (5, 7))  # per point and component, as the colour term is
    points = rng.normal(0, 10, (4, 5, 3))
    points[0, 0] = 500.0  # ~1e4 below every component: an outlier
    direct = constant - 0.5 * (((points[..., None, :] - mean) ** 2) / var).sum(-1)
    coefficients = np.concatenate([-0.5 / var, mean / var], axis=1).T
    shift = max(constant.max(), _OUTLIER_LOG_DENSITY)  # direct <= constant: the bound
    comp = _log_components(points, coefficients, constant - 0.5 * (mean**2 / var).sum(1) - shift)
    assert np.allclose(comp + shift, direct)
    with_outlier = np.concatenate([direct, np.full(direct.shape[:-1] + (1,), _OUTLIER_LOG_DENSITY)], axis=-1)
    expected = logsumexp(with_outlier, axis=-1)
    assert np.isclose(expected[0, 0], _OUTLIER_LOG_DENSITY)
    for dtype, tol in ((np.float64, 1e-9), (np.float32, 1e-4)):
        assert np.allclose(_log_likelihood(comp.astype(dtype), shift), expected, atol=tol)
        total, resp = _log_likelihood(comp.astype(dtype), shift, responsibilities=True)
        assert np.allclose(total, expected, atol=tol)
        assert np.allclose(resp, np.exp(direct - expected[..., None]), atol=tol)


def test_log_components_are_at_most_their_bound():
    """The shift the registration exponentiates against bounds every component's log-density
    at any point, with the atlas's colours and a template's (none is above 0 relative to it,
    so none can overflow), and is not loose by orders of magnitude at the components' means."""
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.register import _component_terms, _log_components

    test = generate_worm(seed=5)
    rng = np.random.default_rng(0)
    for mixture in (load_atlas().mixture(), template_mixture(generate_worm(seed=6))):
        coefficients, constant, shift = _component_terms(test, mixture, use_colour=True)
        spread = rng.normal(0, 30, (1, len(test), 3))
        at_means = mixture.mean[np.arange(len(test)) % len(mixture.mean)][None]
        for points in (spread, at_means):
            assert _log_components(points, coefficients, constant).max() <= 1e-9
        assert _log_components(at_means, coefficients, constant).max() > -10


def _with_body(head, extra: int, length_um: float, rng):
    """``head`` and ``extra`` unnamed neurons over ``length_um`` behind it, along its body axis."""
    from napari_fdlc.geometry import canonical_frame
    from napari_fdlc.table import NeuronTable

    canon, centre, rotation = canonical_frame(head.xyz)
    nose = np.array([str(n).startswith(("IL1", "IL2", "OLQ", "CEP")) for n in head.labels])
    back = -np.sign(canon[nose, 0].mean())
    end = canon[:, 0].max() if back > 0 else canon[:, 0].min()
    body = np.column_stack([end + back * rng.uniform(5, length_um, extra), rng.normal(0, 3, extra), rng.normal(0, 3, extra)])
    donor = rng.integers(len(head), size=extra)
    return NeuronTable(np.vstack([head.xyz, body @ rotation + centre]),
                       {c: np.concatenate([v, v[donor]]) for c, v in head.colours.items()},
                       np.concatenate([head.labels, np.full(extra, "", dtype=object)]))


def test_a_view_into_the_body_is_cut_to_its_head():
    """A head with much of the body behind it is cut to the window the atlas explains best;
    a head alone is left whole."""
    from napari_fdlc.reference import generate_worm
    from napari_fdlc.register import head_window

    atlas = load_atlas()
    head = generate_worm(seed=3)
    assert head_window(head, atlas.mixture()) is None
    assert head_window(head, template_mixture(head)) is None  # a template is never cut
    for extra, length in ((40, 60), (120, 250)):
        wider = _with_body(head, extra, length, np.random.default_rng(extra))
        rows = head_window(wider, atlas.mixture())
        assert rows is not None and np.isin(np.arange(len(head)), rows).mean() > 0.9
    # the window is longer than a head: 60 µm of body fit in it, 250 do not
    assert np.isin(np.arange(len(head), len(wider)), rows).mean() < 0.5


def test_corpus_heads_lose_at_most_a_few_neurons_to_the_window(corpus_path):
    """The corpus's heads fit in the window, except NP's, which reach into the ventral cord:
    they lose a few of those neurons (2-5 of ~190) and nothing else changes."""
    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.register import head_window

    mixture = load_atlas().mixture()
    for worm in load_corpus(corpus_path):
        rows = head_window(worm.table, mixture)
        assert rows is None or (worm.lab == "NP" and len(rows) >= 0.95 * len(worm.table)), worm.source


def _placement_error(table, atlas, mirrored: bool) -> float:
    """Median distance (µm) from each named neuron of ``table`` placed on ``atlas`` in the
    handedness ``mirrored`` to its name's mean there."""
    index = {n: i for i, n in enumerate(atlas.names)}
    placed = register(table, atlas.mixture(), chiralities=(mirrored,))[0].xyz
    named = np.flatnonzero(np.isin(table.labels, atlas.names))
    return float(np.median(np.linalg.norm(placed[named] - atlas.mean[[index[n] for n in table.labels[named]]], axis=1)))


def test_corpus_views_shorter_than_half_the_head_are_found_from_every_start(corpus_path):
    """SF's recordings cut to 60 % of their length (under half the atlas along the body) are
    placed on their names' means by an atlas without SF, in each worm's own handedness: 10 of
    its first 12 worms (EM from the coarse scores' 24 best starts per handedness placed 4:
    SHORT_VIEW); and no corpus worm is that short, so none of their answers changes."""
    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.evaluate import mirrored_relative_to
    from napari_fdlc.geometry import canonical_frame
    from napari_fdlc.reference import build_atlas
    from napari_fdlc.register import SHORT_VIEW, _extent

    worms = load_corpus(corpus_path)
    atlas = build_atlas([w for w in worms if w.lab != "SF"])
    mixture = atlas.mixture()
    length = _extent(mixture.mean[:, 0])
    for worm in worms:
        x = canonical_frame(worm.table.xyz)[0][:, 0] * mixture.partial_view_scale
        assert _extent(x) >= SHORT_VIEW * length, worm.source
    placed_right = 0
    for worm in [w.table for w in worms if w.lab == "SF"][:12]:
        centred = worm.xyz - worm.xyz.mean(axis=0)
        along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
        view = worm.subset(np.flatnonzero(along <= np.quantile(along, 0.6)))
        placed_right += _placement_error(view, atlas, mirrored_relative_to(atlas, worm)) < 4.0
    assert placed_right >= 8, placed_right


def test_a_worm_tilted_out_of_the_image_plane_lands_on_the_atlas():
    """A head raised 30° out of the image plane (and its z step miscalibrated) is levelled
    before the starts (geometry.canonical_frame): the right placement is about as close to each
    name's mean as the worm itself was (0.7 µm further), with the stretch still along the
    optical axis. Without the levelling EM, started from rolls about a tilted axis, stopped 2.0
    and 2.2 µm further off."""
    from napari_fdlc.table import NeuronTable

    atlas = load_atlas()
    rng = np.random.default_rng(7)
    worm = atlas_worm(atlas, rng)
    index = {n: i for i, n in enumerate(atlas.names)}
    rows = [index[n] for n in worm.labels]
    own = np.median(np.linalg.norm(worm.xyz - atlas.mean[rows], axis=1))
    t = np.radians(30)
    pitch = np.array([[np.cos(t), 0, -np.sin(t)], [0, 1, 0], [np.sin(t), 0, np.cos(t)]])
    posed = _posed(NeuronTable(worm.xyz @ pitch.T, worm.colours, worm.labels), 0, False, rng)
    squeezed = NeuronTable(posed.xyz * [1.0, 1.0, 0.85], posed.colours, posed.labels)
    for test in (posed, squeezed):
        placed = atlas.register(test, chiralities=(False,))[0]
        error = np.median(np.linalg.norm(placed.xyz - atlas.mean[rows], axis=1))
        assert error < own + 0.8, (error, own)


def test_the_scale_bound_holds_for_the_whole_fit():
    """The atlas's scale bound (0.8-1.25 of the size a test is expected to have there) holds
    for the whole EM fit: a worm twice the expected size stops at the bound. Bounded per EM
    step, the steps compounded (NP's heads shrank to 0.64 of the scale their names give)."""
    from dataclasses import replace

    from napari_fdlc.geometry import canonical_frame
    from napari_fdlc.register import PARTIAL_VIEW_SIZES, smaller_worm_factor
    from napari_fdlc.table import NeuronTable

    atlas = load_atlas()
    mixture = replace(atlas.mixture(), z_scale_range=(1.0, 1.0))
    rng = np.random.default_rng(8)
    worm = atlas_worm(atlas, rng)
    for size in (0.5, 2.0):
        test = NeuronTable(worm.xyz * size, worm.colours, worm.labels)
        placement = register(test, mixture, chiralities=(False,))[0]
        # expected: the size of a median corpus worm (more for a table denser than a head), and
        # for a partial view each of PARTIAL_VIEW_SIZES times it
        sizes = PARTIAL_VIEW_SIZES if placement.partial_view else (1.0,)
        expected = mixture.partial_view_scale * smaller_worm_factor(test.xyz)
        low, high = expected * min(sizes) * mixture.scale_range[0], expected * max(sizes) * mixture.scale_range[1]
        placed = placement.xyz
        canon = canonical_frame(test.xyz)[0]
        scale = np.sqrt(((placed - placed.mean(0)) ** 2).sum() / ((canon - canon.mean(0)) ** 2).sum())
        assert low - 1e-4 <= scale <= high + 1e-4, (size, scale, low, high)


def test_a_smaller_complete_head_is_placed_as_at_full_size(corpus_path):
    """NP's heads (every head neuron) shrunk to 0.75 and 0.6 of their size are placed on an
    atlas without NP within 1.5 µm of where they are at full size (5.7-6.4 µm from their names'
    means; shrunk: 6.0-7.3): their neurons lie closer together than a young adult's
    (smaller_worm_factor). Registered at a young adult's size instead, they landed 8-20 µm off."""
    from dataclasses import replace

    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.evaluate import mirrored_relative_to
    from napari_fdlc.reference import build_atlas
    from napari_fdlc.register import smaller_worm_factor

    worms = load_corpus(corpus_path)
    assert all(smaller_worm_factor(w.table.xyz) == 1.0 for w in worms)  # no corpus worm is that dense
    atlas = build_atlas([w for w in worms if w.lab != "NP"])
    for worm in [w.table for w in worms if w.lab == "NP"][:4]:
        mirrored = mirrored_relative_to(atlas, worm)
        full = _placement_error(worm, atlas, mirrored)
        for size in (0.75, 0.6):
            assert _placement_error(replace(worm, xyz=worm.xyz * size), atlas, mirrored) < full + 1.5, (worm.source, size)


def test_a_partial_view_of_a_smaller_worm_is_placed_on_its_names(corpus_path):
    """SF's recordings (part of a head, sparsely named) shrunk to 0.75 and 0.6 of their size
    are placed on their names' means by an atlas without SF about as often as at full size: a
    partial view also starts at PARTIAL_VIEW_SIZES. From the size of a median corpus worm
    alone, EM kept to a smaller scale and a wrong part of the head: 12 / 8 / 4 of the first 12
    placed within 4 µm at 1 / 0.75 / 0.6 (now 12 / 10 / 12)."""
    from dataclasses import replace

    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.evaluate import mirrored_relative_to
    from napari_fdlc.reference import build_atlas

    worms = load_corpus(corpus_path)
    atlas = build_atlas([w for w in worms if w.lab != "SF"])
    tests = [w.table for w in worms if w.lab == "SF"][:12]
    for size in (1.0, 0.75, 0.6):
        placed_right = sum(_placement_error(replace(t, xyz=t.xyz * size), atlas, mirrored_relative_to(atlas, t)) < 4.0
                           for t in tests)
        assert placed_right >= 10, (size, placed_right)


def test_head_window_starts_are_one_per_distinct_window_of_the_whole_slide():
    """The head window slides 10 µm at a time; only the first start of each distinct set of
    neurons is scored (the same answer as every start), so a neuron at 1e30 µm no longer makes
    1e29 windows."""
    from napari_fdlc.register import _window_starts

    rng = np.random.default_rng(0)
    for _ in range(300):
        x = rng.uniform(-50, rng.uniform(100, 800), rng.integers(5, 200)) + rng.choice([0.0, 1e5])
        length, step = rng.uniform(20, 150), 10.0
        slide = np.arange(x.min(), x.max() - length + step, step)
        inside = [tuple(np.flatnonzero((x >= s) & (x <= s + length))) for s in slide]
        firsts = [s for k, s in enumerate(slide) if k == 0 or inside[k] != inside[k - 1]]
        np.testing.assert_allclose(_window_starts(x, length, step), firsts, rtol=0, atol=1e-6)
    assert len(_window_starts(np.r_[rng.uniform(0, 100, 60), 1e30], 100.0, 10.0)) < 20


def test_nothing_to_place_is_refused():
    """A test without neurons gave mean-of-empty warnings, then an IndexError."""
    with pytest.raises(FdlcError, match="nothing to place"):
        register(atlas_worm(load_atlas(), np.random.default_rng(0)).subset(np.arange(0)), load_atlas().mixture())


# ----- known defects (session 33's review): strict, so a fix must remove the mark ---------------


def _placed_scale(placed: np.ndarray, reference: np.ndarray) -> float:
    """The size of ``placed`` relative to ``reference`` (RMS about their means)."""
    return float(np.sqrt(((placed - placed.mean(0)) ** 2).sum() / ((reference - reference.mean(0)) ** 2).sum()))


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="known (session 33): a sparse template's spacing cannot show its size; the dense test of a smaller worm is taken 1.25x too large")
def test_a_sparse_template_of_a_smaller_worm_keeps_the_test_at_its_size():
    """Expected: a test registered onto a template of its own worm (both in µm, the same size:
    the template is 60 of the test's own neurons) is placed at scale 1 on it, neuron for
    neuron; register's contract is that a test is taken *to the template's size*.
    Actual: the test (a complete head of a worm 0.7 of a young adult's size, so denser than
    YOUNG_ADULT_SPACING_UM) is grown by smaller_worm_factor (1.25) while the sparse template's
    size_factor is 1 (its spacing cannot show its size), and the template's scale is fixed:
    the test is placed 1.25x too large, its neurons ~3.6 µm from their own template positions
    (0.8 µm at full size)."""
    atlas = load_atlas()
    worm = atlas_worm(atlas)  # the mean worm: as dense as a complete head
    small = NeuronTable(worm.xyz * atlas.worm_scale * 0.7, worm.colours, worm.labels)
    rows = np.sort(np.random.default_rng(3).choice(len(small), 60, replace=False))
    mixture = template_mixture(small.subset(rows))  # a labelled subset: the usual template
    placed = register(small, mixture, chiralities=(False,))[0].xyz[rows]
    assert abs(_placed_scale(placed, mixture.mean) - 1.0) < 0.05, _placed_scale(placed, mixture.mean)
    assert np.median(np.linalg.norm(placed - mixture.mean, axis=1)) < 1.5


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="known (session 33): a round field of view's canonical x lies across the body and no start turns about z")
def test_a_round_field_of_view_is_placed_on_its_own_template(corpus_path):
    """Expected: a 40 µm field of view across a real head (113 neurons of NP's worm 55, the
    template's own neurons, unchanged) lands on the template at its own positions.
    Actual: the view is about as wide as it is long, so canonical_frame's principal XY axis is
    across the body; register's starts are rolls about that axis and head flips only (no turn
    about z), so no start is near the true pose and every kept start ends 10-15 µm off
    (the true pose's likelihood is far higher: a search failure). The panel's atlas posterior
    names 2 % of the same view (60 % for the 60 µm view)."""
    from napari_fdlc.table import read_table

    worm = read_table(corpus_path / "NP" / "55_YAaDV.csv")
    x = canonical_frame(worm.xyz)[0][:, 0]
    rows = np.flatnonzero(np.abs(x - np.median(x)) <= 20.0)
    view = worm.subset(rows)
    mixture = template_mixture(worm)
    best = max(register(view, mixture), key=lambda p: p.score)
    error = np.median(np.linalg.norm(best.xyz - mixture.mean[rows], axis=1))
    assert error < 1.0, error


@pytest.mark.xfail(strict=True, raises=AssertionError, reason="known (session 33): registration keeps colour only for a template with R, G and B")
def test_a_template_without_one_channel_still_gives_the_registration_the_other_two():
    """Expected: with R and G in common (one table has no B reading), registering the test
    onto the template uses R and G whichever table lacks B, as it does when the *test* lacks
    B (register._component_terms leaves out only the missing channel; benchmarks.md: without
    it SF fell to 10.1 %): the two placements are the same.
    Actual: template_mixture keeps a template's colour only when it has all of R, G and B
    (has_colour), so a template without B registers every test by position alone; on KK's
    corpus pairs the nearest-name agreement of the placement fell from 0.199 (test lacks B)
    to 0.115 (template lacks B), the position-only figure."""
    from napari_fdlc.reference import generate_worm

    template, test = generate_worm(4), generate_worm(5)

    def without_b(table):
        return NeuronTable(table.xyz, {"R": table.colours["R"], "G": table.colours["G"]}, table.labels)

    test_lacks = register(without_b(test), template_mixture(template), chiralities=(False,))[0]
    template_lacks = register(test, template_mixture(without_b(template)), chiralities=(False,))[0]
    assert np.allclose(test_lacks.xyz, template_lacks.xyz, atol=1e-3)
