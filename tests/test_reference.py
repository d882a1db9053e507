import numpy as np
import pytest

from napari_fdlc.errors import FdlcError, ModelError
from napari_fdlc.reference import (Atlas, atlas_worm, build_atlas, generate_worm, load_atlas, load_panel, make_panel,
                                   shipped_atlas_path)
from napari_fdlc.table import NeuronTable
from napari_fdlc.corpus import Worm


def test_shipped_atlas_and_panel():
    atlas = load_atlas()
    assert len(atlas.names) > 100 and len(set(atlas.names)) == len(atlas.names)
    assert np.all(atlas.sd > 0) and np.all((atlas.frequency > 0) & (atlas.frequency <= 1))
    panel = load_panel()
    assert len(panel.templates) >= 2 and all(t.named.all() for t in panel.templates)


def test_panel_is_the_mean_worm_and_samples_at_the_chosen_spread():
    from napari_fdlc.reference import PANEL_SAMPLES, PANEL_SPREAD, make_panel

    atlas = load_atlas()
    panel = make_panel(atlas)
    assert len(panel.templates) == 1 + PANEL_SAMPLES
    assert np.allclose(panel.templates[0].xyz, atlas.mean)
    # each sample's offsets from the mean, in units of the atlas's spread, have SD ≈ the spread factor
    for spread in (PANEL_SPREAD, 1.0):
        offsets = np.concatenate([(t.xyz - atlas.mean) / atlas.sd for t in make_panel(atlas, spread=spread).templates[1:]])
        assert abs(offsets.std() - spread) < 0.05 * spread


def test_atlas_round_trip(tmp_path):
    atlas = load_atlas()
    atlas.save(tmp_path / "a.csv")
    back = Atlas.load(tmp_path / "a.csv")
    assert list(back.names) == list(atlas.names)
    assert np.allclose(back.mean, atlas.mean, atol=1e-3)
    assert back.labs == atlas.labs and back.worm_scale == atlas.worm_scale > 1.0


def test_generated_worm_is_plausible_and_deterministic():
    a, b = generate_worm(seed=3), generate_worm(seed=3)
    assert np.array_equal(a.xyz, b.xyz)
    assert 60 <= len(a) <= 250 and a.named.all()
    assert np.all(a.xyz > 0)
    assert all(np.all(v > 0) for v in a.colours.values())  # raw-looking intensities
    # at a real worm's size, not the (Procrustes-shrunk) atlas's
    from napari_fdlc.geometry import canonical_frame

    atlas = load_atlas()
    length = np.ptp(np.percentile(canonical_frame(a.xyz)[0][:, 0], [5, 95]))
    assert length / np.ptp(np.percentile(atlas.mean[:, 0], [5, 95])) > 1.1


def test_build_atlas_recovers_a_known_layout():
    """Worms that are rotated, mirrored (acquisition convention) and noisy copies of one layout
    give back that layout up to a similarity transform."""
    from napari_fdlc.corpus import Worm

    truth = atlas_worm(load_atlas())
    rng = np.random.default_rng(0)
    worms = []
    for k in range(6):
        angle = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(angle), np.sin(angle)
        xyz = truth.xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + rng.normal(0, 0.5, truth.xyz.shape)
        if k % 2:
            xyz[:, 2] *= -1
        worms.append(Worm("X", str(k), NeuronTable(xyz, truth.colours, truth.labels)))
    atlas = build_atlas(worms)
    assert set(atlas.names) == set(truth.labels)
    order = [list(truth.labels).index(n) for n in atlas.names]
    ref = truth.xyz[order] - truth.xyz[order].mean(0)
    got = atlas.mean - atlas.mean.mean(0)
    # compare pairwise distances (invariant to the similarity transform)
    from scipy.spatial.distance import pdist

    assert np.corrcoef(pdist(ref), pdist(got))[0, 1] > 0.99
    assert np.median(atlas.sd) < 1.0
    # worms of the same size: the atlas keeps their size (Procrustes shrinks it only with noise)
    assert 1.0 <= atlas.worm_scale < 1.05


def test_an_atlas_takes_the_colours_recordings_give_a_name_often_enough():
    """Atlas.with_colours_of: a name given in at least ``min_worms`` recordings gets the mean and
    spread of their normal scores there; other names and every position stay."""
    from napari_fdlc.colour import IDENTITY_CHANNELS, normal_scores

    atlas = load_atlas()
    tables = [generate_worm(seed=s) for s in range(3)]
    often, rarely = tables[0].labels[0], tables[0].labels[1]
    names = []
    for k, t in enumerate(tables):
        given = np.full(len(t), "", dtype=object)
        rows = {n: i for i, n in enumerate(t.labels)}
        for name in (often,) + ((rarely,) if k < 2 else ()):
            if name in rows:
                given[rows[name]] = name
        names.append(given)
    assert all(often in set(g) for g in names) and sum(rarely in set(g) for g in names) == 2
    adapted = atlas.with_colours_of(tables, names, min_worms=3)
    scores = np.array([normal_scores(t, IDENTITY_CHANNELS)[list(g).index(often)] for t, g in zip(tables, names)])
    k_often, k_rarely = list(atlas.names).index(often), list(atlas.names).index(rarely)
    assert np.allclose(adapted.colour[k_often], scores.mean(0)) and np.allclose(adapted.colour_sd[k_often], scores.std(0))
    unchanged = np.ones(len(atlas.names), bool)
    unchanged[k_often] = False
    assert np.array_equal(adapted.colour[unchanged], atlas.colour[unchanged]) and k_rarely in np.flatnonzero(unchanged)
    assert np.array_equal(adapted.mean, atlas.mean) and np.array_equal(adapted.sd, atlas.sd)


def test_load_panel_sees_an_atlas_rebuilt_at_the_same_path(tmp_path):
    """load_panel's cache is keyed on the atlas file's modification time too: an atlas rebuilt
    at the same path in one session is seen, not the old panel."""
    from napari_fdlc.corpus import Worm

    worms = [Worm("L", f"w{i}", generate_worm(seed=i)) for i in range(6)]
    path = tmp_path / "atlas.csv"
    build_atlas(worms[:3]).save(path)
    load_panel(path)
    build_atlas(worms[3:]).save(path)
    assert list(load_panel(path).atlas.names) == list(load_atlas(path).names)


def test_an_atlas_built_from_worms_without_colour_does_not_name_by_colour(shipped):
    """An atlas built from worms without R, G, B has no colour (not a made-up 0 ± 1): its panel
    names a coloured test by position, not by its templates' random colours."""
    from napari_fdlc.corpus import Worm

    worms = [Worm("X", str(s), NeuronTable(generate_worm(seed=s).xyz, {}, generate_worm(seed=s).labels))
             for s in range(10, 22)]
    panel = make_panel(build_atlas(worms))
    test = generate_worm(seed=3)
    with_colour = np.mean(np.asarray(shipped.label_panel(test, panel).auto_id, dtype=object) == test.labels)
    position_only = np.mean(np.asarray(shipped.label_panel(test, panel, use_colour=False).auto_id, dtype=object) == test.labels)
    # once 0.09 against 0.27
    assert with_colour >= position_only - 0.03


def _edited_atlas(tmp_path, edit=None, header=None):
    lines = shipped_atlas_path().read_text().splitlines()
    import io

    import pandas as pd

    df = pd.read_csv(io.StringIO("\n".join(lines[1:])))
    if edit:
        edit(df)
    path = tmp_path / "atlas.csv"
    with open(path, "w", encoding="utf-8") as handle:
        handle.write((header if header is not None else lines[0]) + "\n")
        df.to_csv(handle, index=False)
    return path


@pytest.mark.parametrize("column", ["R", "G_sd", "frequency", "x_sd", "y_um"])
def test_load_atlas_refuses_a_value_that_is_not_a_finite_number(tmp_path, column):
    """An atlas file edited by hand with an empty cell is refused in one line naming the atlas,
    not loaded to fail later in numpy or to blame the test's positions."""
    def blank(df):
        df.loc[5, column] = np.nan

    path = _edited_atlas(tmp_path, blank)
    with pytest.raises(ModelError, match="atlas"):
        load_atlas(path)


@pytest.mark.parametrize("scale", ["0", "nan", "-1.2"])
def test_load_atlas_refuses_a_worm_scale_that_is_not_positive(tmp_path, scale):
    """A worm scale of 0, NaN or below 0 in the atlas's header is refused in one line."""
    header = shipped_atlas_path().read_text().splitlines()[0].split("; worm scale")[0] + f"; worm scale {scale}"
    path = _edited_atlas(tmp_path, header=header)
    with pytest.raises(ModelError, match="atlas"):
        load_atlas(path)


def test_an_atlas_keeps_lab_names_with_spaces(tmp_path):
    """The header joined labs with spaces and load split on them: 'my lab' came back as two
    labs. Atlases written before (spaces between labs) still load."""
    from dataclasses import replace

    replace(load_atlas(), labs=("my lab", "x")).save(tmp_path / "a.csv")
    assert Atlas.load(tmp_path / "a.csv").labs == ("my lab", "x")
    old = tmp_path / "old.csv"
    text = (tmp_path / "a.csv").read_text().splitlines()
    old.write_text("\n".join(["# napari-fdlc atlas: 97 worms of EY KK NP; worm scale 1.2623", *text[1:]]) + "\n")
    assert Atlas.load(old).labs == ("EY", "KK", "NP")


def test_generate_worm_refuses_a_negative_count_of_unnamed_neurons():
    with pytest.raises(FdlcError):
        generate_worm(seed=0, n_unnamed=-1)


# Session 32 (a helper review of fdlc atlas); each says what used to happen.


def _corpus(root, lab: str, worms: list) -> str:
    from napari_fdlc.table import write_table

    (root / lab).mkdir(parents=True)
    rows = ["dataset,dandiset,worm,n_neurons,n_labeled"]
    for i, table in enumerate(worms):
        write_table(table, root / lab / f"w{i}.csv")
        rows.append(f"{lab},0,w{i},{len(table)},{int(table.named.sum())}")
    (root / "worms.csv").write_text("\n".join(rows) + "\n")
    return str(root)


def test_an_atlas_of_one_lab_whose_name_holds_a_space_reads_back_that_lab(tmp_path):
    """One lab called 'Lab A': the header had no comma and was read the old way, ('Lab', 'A')."""
    from napari_fdlc.cli import main

    corpus = _corpus(tmp_path / "corpus", "Lab A", [generate_worm(seed=s) for s in range(10, 14)])
    assert main(["atlas", "--corpus", corpus, "--out", str(tmp_path / "atlas.csv")]) == 0
    assert load_atlas(tmp_path / "atlas.csv").labs == ("Lab A",)


def test_the_atlas_takes_the_handedness_of_most_of_its_worms(tmp_path):
    """Four worms one way and a z-flipped one with the most names: the atlas took the best-named
    worm's handedness, so the four were 'mirrored' relative to it (and --chirality meant the
    opposite for them)."""
    from napari_fdlc.geometry import mirrored_by_names

    worms = [generate_worm(seed=s) for s in range(10, 14)]
    full = atlas_worm(load_atlas(), np.random.default_rng(5))
    flipped = NeuronTable(full.xyz * [1.0, 1.0, -1.0] * 1.3, full.colours, full.labels)
    assert flipped.named.sum() > max(w.named.sum() for w in worms)
    from napari_fdlc.corpus import load_corpus

    atlas = build_atlas(load_corpus(_corpus(tmp_path / "corpus", "L", worms + [flipped])))
    assert [mirrored_by_names(atlas.names, atlas.mean, w, 6) for w in worms] == [False] * 4


def test_the_atlas_takes_the_handedness_of_most_labs_not_of_most_worms():
    """Two labs' worms one way, a bigger lab's all mirrored (SF's convention): the atlas keeps
    the two labs' handedness. Counted by worm, the bigger lab flipped it (the corpus atlas
    without EY: 40 of 76 worms mirrored, 33 of them SF's; EY's panel on auto 77.6 -> 10.9 %)."""
    from napari_fdlc.corpus import Worm
    from napari_fdlc.geometry import mirrored_by_names

    def worm(lab, seed, mirrored=False):
        table = generate_worm(seed=seed)
        if mirrored:
            table = NeuronTable(table.xyz * [1.0, 1.0, -1.0], table.colours, table.labels)
        return Worm(lab, f"w{seed}", table)

    worms = [worm("A", s) for s in (1, 2, 3)] + [worm("B", s) for s in (4, 5, 6)]
    worms += [worm("C", s, mirrored=True) for s in range(7, 15)]
    atlas = build_atlas(worms)
    assert [mirrored_by_names(atlas.names, atlas.mean, w.table, 6) for w in worms] == [False] * 6 + [True] * 8


@pytest.mark.filterwarnings("ignore")
def test_the_corpus_atlas_without_ey_keeps_the_corpus_handedness():
    """The atlas rebuilt without EY (EY's panel in accuracy.md, leave_one_lab_out.md) has the
    corpus atlas's handedness, and EY's worms are named on auto, not left/right swapped."""
    from napari_fdlc.corpus import default_corpus_path, load_corpus
    from napari_fdlc.evaluate import Scores, mirrored_relative_to
    from napari_fdlc.identify import default_identifier

    path = default_corpus_path()
    if path is None:
        pytest.skip("the NeuroPAL corpus is not here")
    worms = load_corpus(path)
    ey = [w.table for w in worms if w.lab == "EY"][:5]
    atlas = build_atlas([w for w in worms if w.lab != "EY"])
    assert [mirrored_relative_to(atlas, t) for t in ey] == [mirrored_relative_to(load_atlas(), t) for t in ey]
    scores = Scores()
    for test in ey[:2]:
        scores.add(default_identifier().label_panel(test, make_panel(atlas), use_colour=True), test, set(atlas.names))
    assert scores.summary()["top1"] > 0.6


def test_adapted_colours_are_not_measured_on_cells_without_a_reading():
    """docs/cli.md: the panel's colour per name is "measured on them" (the tests' normal
    scores); colour.py: "a cell without a reading says nothing". A cell left empty (NaN,
    NeuroPAL_ID's no reading) is filled with the volume's median by NeuronTable, and
    reference.Atlas.with_colours_of takes that filler's normal score (0) as a measurement: a
    name whose R was not read in any of the three tests gets R = 0 with spread 0, replacing the
    atlas's 0.98 +- 0.50 for AVAL, a colour invented with full confidence (the table's
    colour_gaps are ignored). Expected: only cells with a reading are measured (the atlas's R
    kept for a name with no reading of it)."""
    atlas = load_atlas()
    k = list(atlas.names).index("AVAL")
    tests, names = [], []
    for seed in range(3):
        w = generate_worm(seed)
        assert "AVAL" in list(w.labels)
        red = w.colours["R"].copy()
        red[list(w.labels).index("AVAL")] = np.nan  # AVAL's R not read in this recording
        red[::4] = np.nan
        tests.append(NeuronTable(w.xyz, {"R": red, "G": w.colours["G"], "B": w.colours["B"]}, w.labels))
        names.append(np.asarray(w.labels, dtype=object))
    adapted = atlas.with_colours_of(tests, names, 3)
    assert adapted.colour[k, 0] == pytest.approx(atlas.colour[k, 0]) and adapted.colour_sd[k, 0] > 0, (
        f"AVAL's R, read in none of the tests, measured as {adapted.colour[k, 0]:.3f} +- "
        f"{adapted.colour_sd[k, 0]:.3f} (atlas: {atlas.colour[k, 0]:.3f} +- {atlas.colour_sd[k, 0]:.3f})")


def test_a_name_given_twice_in_one_worm_does_not_count_as_two_worms():
    """Expected: build_atlas keeps "names seen in at least min_frequency of the worms, and in two
    worms at least" (reference.py, docs/cli.md `fdlc atlas`), and ``frequency`` is the fraction
    of worms that name it; a name that only one worm gives (twice, an annotation slip) is not
    kept.
    Actual: the positions of a name are counted, not the worms: the name given twice in one
    worm of three is kept, with frequency 2/3 and a spread measured between two neurons of
    that one worm."""
    worms = [generate_worm(seed=s) for s in range(3)]
    first = worms[0]
    xyz = np.vstack([first.xyz, first.xyz[:2] + 3.0])
    colours = {c: np.concatenate([v, v[:2]]) for c, v in first.colours.items()}
    labels = np.concatenate([first.labels, ["XYZ", "XYZ"]])
    twice = NeuronTable(xyz, colours, labels)
    atlas = build_atlas([Worm("A", "w0", twice), Worm("A", "w1", worms[1]), Worm("B", "w2", worms[2])])
    names = list(atlas.names)
    assert "XYZ" not in names, (f"XYZ, named by 1 worm of {atlas.worms}, kept with frequency "
                                f"{atlas.frequency[names.index('XYZ')]:.2f}")


def test_a_panel_of_templates_given_by_hand_follows_its_atlas_colours_with_positions_kept():
    """A panel made by hand (not make_panel) drawn again on an atlas whose colours were
    measured anew (label_panel_many's adapted colours): its own templates, positions unchanged,
    each name's colour moved as the atlas's moved; make_panel's panel is drawn again alike."""
    from dataclasses import replace

    from napari_fdlc.reference import Panel, load_atlas, make_panel, panel_on

    atlas = load_atlas()
    shifted = replace(atlas, colour=atlas.colour + np.array([0.5, 0.0, -0.25]))
    worm = generate_worm(seed=3)
    again = panel_on(Panel(atlas, [worm]), shifted)
    [t] = again.templates
    np.testing.assert_array_equal(t.xyz, worm.xyz)
    named = np.isin(worm.labels, atlas.names)
    np.testing.assert_allclose(t.colours["R"][named], worm.colours["R"][named] + 0.5)
    np.testing.assert_allclose(t.colours["B"][named], worm.colours["B"][named] - 0.25)
    assert len(panel_on(make_panel(atlas, samples=2), shifted).templates) == 3
