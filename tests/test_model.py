import json

import numpy as np
import pytest
import torch

from napari_fdlc.errors import FdlcError, ModelError
from napari_fdlc.identify import FEW_NEURONS, Identifier
from napari_fdlc.model import CorrespondenceModel, load_model, matching_loss, save_model
from napari_fdlc.table import NeuronTable


@pytest.fixture(scope="module")
def identifier(untrained_weights):
    return Identifier.load(untrained_weights)


def test_model_is_permutation_equivariant():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32}).eval()
    a, b = torch.randn(1, 12, 3) * 20, torch.randn(1, 9, 3) * 20
    perm_a, perm_b = torch.randperm(12), torch.randperm(9)
    with torch.no_grad():
        out = model(a, b)
        out_p = model(a[:, perm_a], b[:, perm_b])
    expected = torch.cat([out[:, :, :12][:, :, perm_a], out[:, :, 12:]], dim=2)[:, perm_b]
    assert torch.allclose(out_p, expected, atol=1e-5)
    assert torch.allclose(out.exp().sum(-1), torch.ones(1, 9), atol=1e-5)


def test_padding_does_not_change_results():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32}).eval()
    a, b = torch.randn(1, 7, 3) * 20, torch.randn(1, 5, 3) * 20
    pa = torch.cat([a, torch.zeros(1, 3, 3)], 1)
    pb = torch.cat([b, torch.zeros(1, 2, 3)], 1)
    ma = torch.tensor([[True] * 7 + [False] * 3])
    mb = torch.tensor([[True] * 5 + [False] * 2])
    with torch.no_grad():
        out = model(a, b)
        padded = model(pa, pb, ma, mb)
    assert torch.allclose(padded[:, :5, :7], out[:, :, :7], atol=1e-5)
    assert torch.allclose(padded[:, :5, 10], out[:, :, 7], atol=1e-5)


def test_templates_in_one_batch_answer_as_one_at_a_time(worm, other_worm):
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 2, "dim": 32, "colour_channels": 3})
    for p in model.parameters():  # no zero-initialised branch: every input must count
        torch.nn.init.normal_(p, std=0.2)
    identifier = Identifier(model)
    rng = np.random.default_rng(0)
    templates = [worm.xyz, worm.xyz[:150] + rng.normal(0, 2, (150, 3))]  # two sizes: padded
    tests = [other_worm.xyz[:120], other_worm.xyz[10:] @ np.diag([1.0, 1.0, -1.0])]
    colours = [rng.normal(size=(len(t), 3)) for t in templates]
    test_colours = [rng.normal(size=(len(t), 3)) for t in tests]
    grid = identifier._forward_grid(templates, tests, colours, test_colours)
    for t, (xyz, colour) in enumerate(zip(templates, colours)):
        for v, one in enumerate(identifier._forward_many(xyz, tests, colour, test_colours)):
            assert grid[t][v].shape == (len(tests[v]), len(xyz) + 1)
            assert np.allclose(grid[t][v], one, atol=1e-4)


def test_loss_falls_on_one_pair():
    torch.manual_seed(0)
    model = CorrespondenceModel({"layers": 1, "dim": 32})
    a = torch.randn(1, 10, 3) * 20
    b = a[:, torch.randperm(10)]
    target = (b[0, :, None] == a[0, None]).all(-1).float().argmax(-1)[None]
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    first = None
    for _ in range(30):
        loss = matching_loss(model(a, b), target)
        first = first if first is not None else loss.item()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < first * 0.5


def _rotate_xy(xyz, angle):
    c, s = np.cos(angle), np.sin(angle)
    return xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


def test_labels_do_not_depend_on_how_the_worm_lies(identifier, worm, other_worm):
    base = identifier.label(worm, [other_worm], use_colour=False)
    rng = np.random.default_rng(0)
    for angle in rng.uniform(-np.pi, np.pi, 3):
        turned = _rotate_xy(worm.xyz, angle) + [100, -50, 7]
        got = identifier.label(NeuronTable(turned, worm.colours), [other_worm], use_colour=False)
        assert np.mean(np.array(got.auto_id) == np.array(base.auto_id)) > 0.97
    # The other side: 180° about the body axis (a proper rotation, not a mirror).
    from napari_fdlc.geometry import canonical_frame

    canon, centre, rot = canonical_frame(worm.xyz)
    other_side = (canon * [1, -1, -1]) @ rot + centre
    got = identifier.label(NeuronTable(other_side, worm.colours), [other_worm], use_colour=False)
    assert np.mean(np.array(got.auto_id) == np.array(base.auto_id)) > 0.97


def test_permuting_the_test_permutes_the_output(identifier, worm, other_worm):
    base = identifier.label(worm, [other_worm])
    perm = np.random.default_rng(3).permutation(len(worm))
    got = identifier.label(worm.subset(perm), [other_worm])
    assert np.mean(np.array(got.auto_id) == np.array(base.auto_id)[perm]) > 0.97
    assert np.allclose(got.probs, base.probs[perm], atol=1e-4)


@pytest.mark.parametrize("n", [1, 2, 2000])
def test_any_neuron_count(identifier, other_worm, n):
    from napari_fdlc.reference import load_atlas

    rng = np.random.default_rng(n)
    test = NeuronTable(rng.normal(size=(n, 3)) * [40, 10, 8], {c: rng.random(n) for c in "RGB"})
    joined = identifier.with_settings(atlas_weight=1.0, template_chirality_doubt=0.2).label(
        test, [other_worm], atlas=load_atlas())
    assert len(joined.auto_id) == n and joined.info["atlas"] == (n >= FEW_NEURONS)  # a handful: no atlas answer
    assert np.all(joined.probs.sum(1) <= 1 + 1e-6)
    result = identifier.label(test, [other_worm])
    assert len(result.auto_id) == n
    assert np.all(result.probs.sum(1) <= 1 + 1e-6)
    named = [x for x in result.auto_id if x]
    assert len(named) == len(set(named))


@pytest.mark.parametrize("n", [1, 2, 2000])
def test_any_neuron_count_against_the_panel(identifier, n):
    from napari_fdlc.reference import load_panel

    rng = np.random.default_rng(n)
    test = NeuronTable(rng.normal(size=(n, 3)) * [40, 10, 8], {c: rng.random(n) for c in "RGB"})
    result = identifier.label_panel(test, load_panel())
    assert len(result.auto_id) == n
    assert np.all(result.probs.sum(1) <= 1 + 1e-6)
    named = [x for x in result.auto_id if x]
    assert len(named) == len(set(named))


def test_panel_chooses_the_handedness_on_its_first_templates(identifier, worm, monkeypatch):
    """The first PANEL_HANDEDNESS_TEMPLATES templates see both placements and decide; the others
    run once, in the chosen one; with the handedness set, every template runs once. The answer
    equals averaging every template's answer for the chosen placement."""
    from napari_fdlc import identify
    from napari_fdlc.reference import load_panel

    panel = load_panel()
    k = identify.PANEL_HANDEDNESS_TEMPLATES
    calls = []
    grid = identify.Identifier._forward_grid

    def counting(self, templates, tests, *rest):
        calls.append((len(templates), len(tests)))
        return grid(self, templates, tests, *rest)

    monkeypatch.setattr(identify.Identifier, "_forward_grid", counting)
    auto = identifier.label_panel(worm, panel, use_colour=False)
    assert calls == [(k, 2), (len(panel.templates) - k, 1)]
    calls.clear()
    told = identifier.with_chirality("mirrored" if auto.info["mirrored"] else "same")
    same = told.label_panel(worm, panel, use_colour=False)
    assert calls == [(len(panel.templates), 1)]
    assert list(same.auto_id) == list(auto.auto_id)
    np.testing.assert_allclose(same.probs, auto.probs, atol=1e-6)


def test_weights_round_trip_and_refusals(tmp_path):
    model = CorrespondenceModel({"layers": 1, "dim": 32})
    save_model(model, tmp_path / "m", {"note": "x"})
    back = load_model(tmp_path / "m")
    for k, v in model.state_dict().items():
        assert torch.equal(v, back.state_dict()[k])
    # Corrupt weights
    (tmp_path / "m.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ModelError, match="not a valid safetensors"):
        load_model(tmp_path / "m")
    # Weights that do not fit the configuration
    save_model(model, tmp_path / "m")
    meta = json.loads((tmp_path / "m.json").read_text())
    meta["config"]["dim"] = 64
    (tmp_path / "m.json").write_text(json.dumps(meta))
    with pytest.raises(ModelError, match="do not fit"):
        load_model(tmp_path / "m")
    with pytest.raises(ModelError, match="missing"):
        load_model(tmp_path / "absent")


def test_partial_colour_channels_still_count(worm, other_worm):
    """Only R shared: the model gets no colour input, but the shared channel is fused."""
    from napari_fdlc.table import NeuronTable

    torch.manual_seed(0)
    ident = Identifier(CorrespondenceModel({"layers": 1, "dim": 32, "colour_channels": 3}), device="cpu")
    only_r = NeuronTable(worm.xyz, {"R": worm.colours["R"]})
    with_r = ident.label(only_r, [other_worm], use_colour=True)
    without = ident.label(only_r, [other_worm], use_colour=False)
    assert with_r.info["colour"] and not np.allclose(with_r.probs, without.probs)


def test_a_fixed_name_settles_the_chirality():
    """Left/right symmetry leaves the panel unsure of a mirrored recording; one neuron the user
    fixed (a left/right name) makes the orientation that agrees with it win."""
    from napari_fdlc.identify import Identifier
    from napari_fdlc.reference import atlas_worm, load_atlas, make_panel

    atlas = load_atlas()
    panel = make_panel(atlas)
    rng = np.random.default_rng(5)
    worm = atlas_worm(atlas, rng)
    mirrored = NeuronTable(worm.xyz * [1, 1, -1], worm.colours, worm.labels)
    ident = Identifier.load()
    row = next(j for j, n in enumerate(worm.labels) if n.endswith("L") and n[:-1] + "R" in set(worm.labels))
    fixed = {row: worm.labels[row]}
    paired = [j for j, n in enumerate(worm.labels) if n[-1:] in "LR" and n[:-1] + ("R" if n[-1] == "L" else "L") in set(worm.labels)]

    def right(result):
        return np.mean([result.auto_id[j] == worm.labels[j] for j in paired])

    for table, truth in [(worm, False), (mirrored, True)]:
        assert ident.label_panel(table, panel, use_colour=False, fixed=fixed).info["mirrored"] == truth
    settled = right(ident.label_panel(mirrored, panel, use_colour=False, fixed=fixed))
    ident.settings.chirality = "same"  # the atlas's handedness forced: left and right swapped
    swapped = right(ident.label_panel(mirrored, panel, use_colour=False, fixed=fixed))
    assert settled > swapped + 0.15, (settled, swapped)


def test_temperatures_change_the_confidence_not_the_names(worm, other_worm):
    """Calibration (fitted after the settings chosen for top-1) must not change the answers."""
    from napari_fdlc.reference import load_panel
    from napari_fdlc.simulate import simulate_worm

    test = simulate_worm(worm, 3).table
    plain = Identifier.load()
    plain = plain.with_settings(temperature=1.0, panel_temperature=1.0, chirality_doubt=0.0, template_chirality_doubt=0.0)
    sharp = plain.with_settings(temperature=0.4, panel_temperature=0.4)
    for run in (lambda i: i.label(test, [other_worm]), lambda i: i.label_panel(test, load_panel())):
        a, b = run(plain), run(sharp)
        assert a.auto_id == b.auto_id
        named = np.array([bool(n) for n in a.auto_id])
        assert b.auto_conf[named].mean() > a.auto_conf[named].mean() + 0.02


def test_the_doubt_about_the_handedness_mixes_in_the_other_answer(worm, other_worm, monkeypatch):
    """With a template, the probabilities reported are the chosen handedness's answer mixed
    with the other one's (each alone is what --chirality same / mirrored gives, the atlas's
    answer joined in that handedness); the names stay the chosen handedness's, and a
    handedness the user set leaves nothing to doubt."""
    import napari_fdlc.identify as identify
    from napari_fdlc.reference import load_atlas
    from napari_fdlc.simulate import simulate_worm

    answers = []  # what each call hands make_labelling (before its one-to-one normalisation)
    make_labelling = identify.make_labelling
    monkeypatch.setattr(identify, "make_labelling", lambda names, probs, *a, **k: (
        answers.append(probs), make_labelling(names, probs, *a, **k))[1])
    test = simulate_worm(worm, 3).table
    atlas = load_atlas()
    plain = Identifier.load().with_settings(template_chirality_doubt=0.0, atlas_weight=0.5)
    doubtful = plain.with_settings(template_chirality_doubt=0.3)
    a, b = plain.label(test, [other_worm], atlas=atlas), doubtful.label(test, [other_worm], atlas=atlas)
    assert a.auto_id == b.auto_id and a.names == b.names
    assert "other_handedness" not in b.info["templates"][0]  # a few kB per answer, used up
    chosen = "mirrored" if a.info["templates"][0]["mirrored"] else "same"
    plain.with_settings(chirality={"same": "mirrored", "mirrored": "same"}[chosen]).label(test, [other_worm], atlas=atlas)
    doubtful.with_settings(chirality=chosen).label(test, [other_worm], atlas=atlas)
    a_probs, b_probs, other_probs, told_probs = answers
    np.testing.assert_allclose(b_probs, 0.7 * a_probs + 0.3 * other_probs, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(told_probs, a_probs, rtol=1e-4, atol=1e-7)
    assert np.abs(b_probs - a_probs).max() > 0.05


def test_several_recordings_share_a_handedness_when_they_clearly_agree(monkeypatch):
    """Identifier.label_panel_many: a sign test over the tests' votes decides one handedness for
    all. Each test's evidence is stubbed: its source holds the mirrored-minus-same willingness
    and registration score; a test whose two disagree does not vote."""
    from napari_fdlc.match import make_labelling

    def fake_label_panel(self, test, panel, use_colour=True, fixed=None):
        will, reg = map(float, test.source.split())
        mirrored = {"same": False, "mirrored": True}.get(self.settings.chirality, will > self.settings.mirror_penalty)
        info = {"willingness": [0.0, will - self.settings.mirror_penalty], "registration": [0.0, reg], "mirrored": mirrored}
        return make_labelling(["A"], np.array([[0.5]]), info=info)

    monkeypatch.setattr(Identifier, "label_panel", fake_label_panel)
    ident = Identifier(CorrespondenceModel({"layers": 1, "dim": 32}), device="cpu")

    def tests(values):
        return [NeuronTable(np.zeros((1, 3)), source=f"{w} {r}") for w, r in values]

    # 11 of 12 lean mirrored on both, but weakly (below the prior): each alone stays "same"
    leaning = ident.label_panel_many(tests([(0.5, 0.1)] * 11 + [(-0.3, -0.1)]), panel=None)
    assert all(r.info["mirrored"] for r in leaning)
    assert leaning[0].info["batch_handedness"] == {"decided": "mirrored", "lean_mirrored": 11, "votes": 12, "tests": 12}
    # the model leans mirrored on all 12, the registration on 2: 2 votes, nothing decided
    split = ident.label_panel_many(tests([(0.5, 0.1)] * 2 + [(0.5, -0.1)] * 10), panel=None)
    assert not any(r.info["mirrored"] for r in split)
    assert split[0].info["batch_handedness"] == {"decided": None, "lean_mirrored": 2, "votes": 2, "tests": 12}
    mixed = ident.label_panel_many(tests([(0.5, 0.1), (-0.5, -0.1)] * 6), panel=None)
    assert not any(r.info["mirrored"] for r in mixed) and mixed[0].info["batch_handedness"]["decided"] is None
    told = ident.with_chirality("same").label_panel_many(tests([(0.5, 0.1)] * 12), panel=None)
    assert not any(r.info["mirrored"] for r in told) and "batch_handedness" not in told[0].info


def test_the_atlas_joins_a_template_only_when_weighted_and_when_it_knows_the_names(identifier, worm, other_worm):
    from napari_fdlc.reference import load_atlas

    atlas = load_atlas()
    alone = identifier.label(other_worm, [worm])
    assert identifier.label(other_worm, [worm], atlas=atlas).auto_id == alone.auto_id  # weight 0: unchanged
    weighted = identifier.with_settings(atlas_weight=1.0, atlas_weight_position=1.0)
    joined = weighted.label(other_worm, [worm], atlas=atlas)
    assert joined.info["atlas"] and not alone.info["atlas"]
    assert not np.allclose(joined.probs, alone.probs)
    named = [x for x in joined.auto_id if x]
    assert len(named) == len(set(named)) and set(named) <= set(worm.names)
    # The atlas is the better namer here (the untrained model is not): joining it must help.
    truth = other_worm.labels
    hits = {k: np.mean([a == t for a, t in zip(r.auto_id, truth) if t in set(worm.names)]) for k, r in (("alone", alone), ("joined", joined))}
    assert hits["joined"] > hits["alone"] + 0.2
    # A template whose names the atlas does not know cannot say its handedness: no atlas.
    renamed = NeuronTable(worm.xyz, worm.colours, np.array([f"X{i}" for i in range(len(worm))], dtype=object))
    assert not weighted.label(other_worm, [renamed], atlas=atlas).info["atlas"]


def test_a_small_test_keeps_twice_the_registration_starts(identifier, worm, other_worm):
    """Fewer neurons rank the registration's starts less reliably and cost the model little:
    a test under SMALL_TEST neurons keeps 2 × KEPT_STARTS placements per chirality."""
    from napari_fdlc.identify import KEPT_STARTS, SMALL_TEST

    small = other_worm.subset(np.arange(SMALL_TEST - 40))
    big = other_worm.subset(np.arange(min(len(other_worm), SMALL_TEST + 20)))
    assert len(big) >= SMALL_TEST
    _, starts, mirrored, _ = identifier.place(worm, [small, big])
    assert [len(s) for s in starts] == [4 * KEPT_STARTS, 2 * KEPT_STARTS]  # both chiralities on auto
    assert mirrored[0].sum() == 2 * KEPT_STARTS and mirrored[1].sum() == KEPT_STARTS
    one = identifier.with_chirality("same").place(worm, [small])[1][0]
    assert len(one) == 2 * KEPT_STARTS


@pytest.fixture
def assigned(monkeypatch):
    """(names, assign_probs) of every answer handed to make_labelling, in order: what the
    names are assigned on, before the one-to-one normalisation."""
    import napari_fdlc.identify as identify

    seen = []
    real = identify.make_labelling
    monkeypatch.setattr(identify, "make_labelling", lambda names, probs, *a, assign_probs=None, **k: (
        seen.append((names, assign_probs)), real(names, probs, *a, assign_probs=assign_probs, **k))[1])
    return seen


def test_the_atlas_answer_joins_the_panel_at_its_weight(identifier, other_worm, assigned):
    """At ``panel_atlas_weight`` w the panel's answer (what names are assigned on) is its
    templates' average times the atlas's posterior at the test's placement, raised to w; at 0
    it is the average alone. With an untrained model the atlas is the better namer."""
    import napari_fdlc.identify as identify
    from napari_fdlc.reference import load_panel
    from napari_fdlc.register import posterior

    panel = load_panel()
    same = identifier.with_settings(chirality="same", chirality_doubt=0.0)
    alone = same.label_panel(other_worm, panel)
    joined = same.with_settings(panel_atlas_weight=1.0).label_panel(other_worm, panel)
    (names, average), (_, product) = assigned
    placement = panel.atlas.register(other_worm, True, (False,))[0]
    resp, none = posterior(other_worm, panel.atlas.mixture(), placement.xyz, True)
    expected = identify._times(average, identify._in_names(resp, none, panel.atlas.names, names), 1.0)
    assert np.allclose(product, expected)
    truth = other_worm.labels
    hits = [np.mean([a == t for a, t in zip(r.auto_id, truth) if t]) for r in (alone, joined)]
    assert hits[1] > hits[0] + 0.05


def test_the_templates_own_worm_gets_a_second_look_after_a_warp(worm, other_worm):
    """A simulated copy of the template (its own worm, bent and jittered) is warped onto it
    and looked at again with a position likelihood; another worm is left as it was."""
    from napari_fdlc.identify import WARP_SAME_WORM_UM
    from napari_fdlc.reference import load_atlas
    from napari_fdlc.simulate import simulate_worm

    shipped = Identifier.load()
    plain = shipped.with_settings(warp_um=0.0)
    copy = simulate_worm(worm, np.random.default_rng(4)).table

    def top1(result, test):
        return np.mean([a == t for a, t in zip(result.auto_id, test.labels) if t])

    atlas = load_atlas()
    refined = shipped.label(copy, [worm], use_colour=False, atlas=atlas)
    seen = refined.info["templates"][0]
    assert seen["same_worm"] and seen["warp_rms_um"] <= WARP_SAME_WORM_UM
    first = plain.label(copy, [worm], use_colour=False, atlas=atlas)
    assert top1(refined, copy) >= max(0.98, top1(first, copy) + 0.02)
    # Its own worm settles the handedness and needs no atlas: no doubt caps the confidences.
    assert not refined.info["atlas"] and first.info["atlas"]
    assert np.median(refined.auto_conf) > 0.9 > np.median(first.auto_conf)
    other = shipped.label(other_worm, [worm], atlas=atlas)
    assert not other.info["templates"][0]["same_worm"] and other.info["templates"][0]["warp_rms_um"] > WARP_SAME_WORM_UM
    assert np.array_equal(other.probs, plain.label(other_worm, [worm], atlas=atlas).probs)


def test_a_template_without_names_is_refused(identifier, worm, other_worm):
    unnamed = NeuronTable(worm.xyz, worm.colours, np.full(len(worm), "", dtype=object))
    with pytest.raises(FdlcError, match="named neuron"):
        identifier.label(other_worm, [unnamed])


def test_recordings_of_one_microscope_are_named_again_with_their_own_colours(monkeypatch):
    """label_panel_many(adapt_colours=True): named once with the panel, then again with a panel
    drawn from the atlas whose colours were measured on the tests' confident names; too few
    tests, or no colour, leave the first answers."""
    from napari_fdlc.identify import ADAPT_MIN_CONF, ADAPT_MIN_TESTS, ADAPT_MIN_WORMS
    from napari_fdlc.reference import generate_worm, load_panel

    shipped = Identifier.load().with_chirality("same")
    panel = load_panel()
    tests = [generate_worm(seed=s) for s in range(10, 10 + ADAPT_MIN_TESTS)]
    seen = []
    real = Identifier.label_panel
    monkeypatch.setattr(Identifier, "label_panel", lambda self, test, p, *a, **k: (seen.append(p), real(self, test, p, *a, **k))[1])
    first = shipped.label_panel_many(tests, panel, share_handedness=False)
    adapted = shipped.label_panel_many(tests, panel, share_handedness=False, adapt_colours=True)
    second = {id(p): p for p in seen[len(tests):]}  # the first pass again, then the second pass's panel
    assert len(seen) == 3 * len(tests) and len(second) == 2
    again = seen[-1].atlas
    names = [np.where(np.asarray(r.auto_conf) >= ADAPT_MIN_CONF, np.asarray(r.auto_id, dtype=object), "") for r in first]
    expected = panel.atlas.with_colours_of(tests, names, ADAPT_MIN_WORMS)
    assert np.array_equal(again.colour, expected.colour) and np.array_equal(again.mean, panel.atlas.mean)
    assert adapted[0].info["adapted_colours"] == int((expected.colour != panel.atlas.colour).any(axis=1).sum()) > 10
    for few_or_grey in (shipped.label_panel_many(tests[:-1], panel, share_handedness=False, adapt_colours=True),
                        shipped.label_panel_many(tests, panel, use_colour=False, share_handedness=False, adapt_colours=True)):
        assert "adapted_colours" not in few_or_grey[0].info


def test_the_atlas_worm_answer_is_averaged_with_the_template_at_its_weight(identifier, worm, other_worm, assigned,
                                                                           monkeypatch):
    """At ``atlas_worm_weight`` w the answer names are assigned on is (1 - w) × the template's
    + w × the model's answer against the atlas's mean worm — which is what a panel of that one
    worm answers, in the template's names (the panel's registration without its z stretch,
    which the template path does not use)."""
    import napari_fdlc.reference as reference
    from napari_fdlc.reference import Panel, atlas_worm, load_atlas

    atlas = load_atlas()
    same = identifier.with_settings(chirality="same", template_chirality_doubt=0.0)
    for weight in (0.0, 1.0, 0.5):
        same.with_settings(atlas_worm_weight=weight).label(other_worm, [worm], atlas=atlas)
    monkeypatch.setattr(reference, "ATLAS_Z_SCALE_RANGE", (1.0, 1.0))
    same.label_panel(other_worm, Panel(atlas, [atlas_worm(atlas)]))
    (names, alone), (_, worm_only), (_, half), (panel_names, panel) = assigned
    column = {n: i for i, n in enumerate(panel_names)}
    assert set(names) <= set(column)  # the template is drawn from the atlas: every name known
    np.testing.assert_allclose(worm_only, panel[:, [column[n] for n in names]], rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(half, 0.5 * alone + 0.5 * worm_only, rtol=1e-6, atol=1e-9)
    assert np.abs(worm_only - alone).max() > 0.05


def test_beside_a_template_a_view_into_the_body_is_named_in_its_head_only(worm, other_worm):
    """With a template and the atlas beside it, a head and 250 µm of body behind it is named in
    its head window, as the panel does (registered whole beside the next worm of its lab:
    0-48 % top-1 on corpus heads, robustness.py --protocol pairs); a fixed name stays. A
    template that itself reaches as far into the body keeps the test whole."""
    from napari_fdlc.identify import default_identifier
    from napari_fdlc.reference import load_atlas

    from test_register import _with_body

    identifier, atlas = default_identifier().with_chirality("same"), load_atlas()
    wider = _with_body(worm, 120, 250, np.random.default_rng(0))
    alone = identifier.label(worm, [other_worm], atlas=atlas)
    assert "head_window" not in alone.info
    fixed = {len(wider) - 1: "VB1"}
    result = identifier.label(wider, [other_worm], fixed=fixed, atlas=atlas)
    rows = result.info["head_window"]
    assert len(worm) * 0.9 < rows < len(wider)
    right = np.mean(np.array(result.auto_id[: len(worm)]) == worm.labels)
    assert right > np.mean(np.array(alone.auto_id) == worm.labels) - 0.15 and right > 0.4
    assert result.auto_id[len(wider) - 1] == "VB1"
    assert "head_window" not in identifier.label(wider, [other_worm]).info  # no atlas: no window
    long_template = _with_body(other_worm, 120, 250, np.random.default_rng(1))
    assert "head_window" not in identifier.label(wider, [long_template], atlas=atlas).info


def test_a_view_into_the_body_is_named_in_its_head_only(worm):
    """With the panel, a head and 250 µm of body behind it is named nearly as well as the head
    alone (registered whole: 0-13 % top-1 on corpus heads, robustness.py); the neurons outside
    the head window get no name, certainly, and a name fixed there stays."""
    from napari_fdlc.identify import default_identifier
    from napari_fdlc.reference import load_panel

    from test_register import _with_body

    identifier, panel = default_identifier().with_chirality("same"), load_panel()
    wider = _with_body(worm, 120, 250, np.random.default_rng(0))
    alone = identifier.label_panel(worm, panel)
    fixed = {len(wider) - 1: "VB1"}
    result = identifier.label_panel(wider, panel, fixed=fixed)
    rows = result.info["head_window"]
    assert len(worm) * 0.9 < rows < len(wider)
    right = np.mean(np.array(result.auto_id[: len(worm)]) == worm.labels)
    assert right > np.mean(np.array(alone.auto_id) == worm.labels) - 0.15 and right > 0.4
    outside = [k for k in range(len(wider)) if not result.probs[k].any()]
    assert len(outside) == len(wider) - rows
    assert all(result.auto_id[k] == "" and result.auto_conf[k] == 1.0 for k in outside if k not in fixed)
    assert result.auto_id[len(wider) - 1] == "VB1"
