"""Several tests named in one call (Identifier.label_panel_many's shared handedness and adapted
colours, Identifier.label_many): a test's answer does not depend on the others but as
documented. From session 33's review; each docstring says what used to happen."""

from __future__ import annotations

import numpy as np
import pytest

from napari_fdlc.reference import generate_worm, load_panel
from napari_fdlc.table import NeuronTable
import pandas as pd
from napari_fdlc.cli import main
from napari_fdlc.table import write_table
from napari_fdlc.errors import FdlcError
from napari_fdlc.reference import load_atlas, make_panel

# Generated worms, z mirrored, whose two pieces of evidence (model and registration) both lean
# mirrored with the shipped model: 7 of them are the fewest the sign test decides on.
MIRRORED_SEEDS = (16, 20, 29, 31, 42, 26, 34)


@pytest.fixture(scope="module")
def ident():
    from napari_fdlc.identify import Identifier

    return Identifier.load(device="cpu")


@pytest.fixture(scope="module")
def panel():
    return load_panel()


def _test(table: NeuronTable, source: str, rows=slice(None), flip_z: bool = False, channels="RGB") -> NeuronTable:
    """A test (no names) from a generated worm: some of its rows, z mirrored or not, some channels."""
    xyz = table.xyz[rows] * (np.array([1.0, 1.0, -1.0]) if flip_z else 1.0)
    return NeuronTable(xyz, {c: table.colours[c][rows] for c in channels}, source=source)


@pytest.fixture(scope="module")
def mirrored_batch(ident, panel):
    """Seven mirrored recordings and their own (first, one at a time) answers."""
    tests = [_test(generate_worm(seed=s), f"m{s}", flip_z=True) for s in MIRRORED_SEEDS]
    return tests, [ident.label_panel(t, panel) for t in tests]


def _same_answers(a, b) -> bool:
    return list(a.auto_id) == list(b.auto_id) and np.allclose(a.probs, b.probs, atol=1e-9)


def test_a_three_neuron_test_does_not_swing_the_shared_handedness(ident, panel, mirrored_batch):
    """Three points always lie in one plane: their mirror image is the same points turned, so a
    3-neuron test has no evidence about handedness at all (docs/cli.md: "a worm and its mirror
    image are then the same points"; a flat table of 10 neurons or more is refused for it).
    Expected: it abstains in the sign test, and the seven mirrored recordings are named
    'mirrored' with or without it in the call. Actual: the registration's and the model's
    search noise (-0.42 and -0.23 here) make it vote 'same'; 7 of 8 is no longer significant,
    nothing is decided, and the seven recordings (935 names) go back to the atlas's handedness,
    left and right swapped."""
    tests, first = mirrored_batch
    tiny = _test(generate_worm(seed=0), "tiny", rows=slice(20, 23))
    alone = ident.label_panel_many(tests, panel, first=first)
    assert alone[0].info["batch_handedness"]["decided"] == "mirrored"  # the setting: 7 of 7 votes
    together = ident.label_panel_many(tests + [tiny], panel, first=first + [ident.label_panel(tiny, panel)])
    assert together[0].info["batch_handedness"]["decided"] == "mirrored", together[0].info["batch_handedness"]
    assert all(_same_answers(a, b) for a, b in zip(alone, together))


def test_a_copy_of_a_recording_is_not_a_second_vote(ident, panel, mirrored_batch):
    """The sign test is over recordings (docs/cli.md: "if significantly many votes go one way
    ... all tests are named that way"). Expected: the same recording given twice (a copy of
    the file under another name, as a glob over a folder with a backup picks up) counts once:
    6 of 6 votes is not significant (p = 0.016), so each keeps its own choice. Actual: the copy
    votes again, 7 of 7 decides 'mirrored', and the six other recordings (800 names) are
    renamed because of the copy."""
    tests, first = mirrored_batch
    tests, first = tests[:6], first[:6]
    copy = NeuronTable(tests[0].xyz.copy(), dict(tests[0].colours), source="m16 copy")
    alone = ident.label_panel_many(tests, panel, first=first)
    assert alone[0].info["batch_handedness"]["decided"] is None  # the setting: 6 of 6 is not enough
    together = ident.label_panel_many(tests + [copy], panel, first=first + [first[0]])
    assert together[0].info["batch_handedness"]["decided"] is None, together[0].info["batch_handedness"]
    assert all(_same_answers(a, b) for a, b in zip(alone, together))


@pytest.fixture(scope="module")
def three_recordings(ident, panel):
    tests = [_test(generate_worm(seed=s), f"w{s}") for s in range(3)]
    return tests, [ident.label_panel(t, panel) for t in tests]


def test_a_two_neuron_test_does_not_change_the_colours_measured_on_the_others(ident, panel, three_recordings):
    """--adapt-colours measures each name's colour on the tests' confident names. A test of 2
    neurons is named by guesses, "and so are their confidences" (docs/cli.md: fewer than 10
    neurons), and its per-volume normal scores are ±0.67 whatever was measured. Expected: such
    a test leaves the colours measured on three full recordings, and so their names, as they
    are without it. Actual: its two guesses (RIVR at 0.94, SMDVL at 0.86) enter the measured
    means and spreads; the three recordings' probabilities move by up to 0.18 and 5 of their
    names change. (It also counts toward the 3 recordings that turn adaptation on.)"""
    tests, first = three_recordings
    tiny = _test(generate_worm(seed=9), "tiny", rows=slice(0, 2))
    alone = ident.label_panel_many(tests, panel, first=first, share_handedness=False, adapt_colours=True)
    together = ident.label_panel_many(tests + [tiny], panel, first=first + [ident.label_panel(tiny, panel)],
                                      share_handedness=False, adapt_colours=True)
    changed = sum(a != b for x, y in zip(alone, together) for a, b in zip(x.auto_id, y.auto_id))
    moved = max(float(np.abs(x.probs - y.probs).max()) for x, y in zip(alone, together))
    assert changed == 0 and moved < 1e-9, f"{changed} names changed, probabilities moved by {moved:.3f}"


def test_three_copies_of_one_recording_do_not_adapt_the_colours_to_itself(ident, panel, three_recordings):
    """Adapting needs 3 recordings, and a name's colour is measured when given in 3 of them
    (docs/cli.md). Expected: one recording given three times (copies under other names) is one
    recording: nothing to measure on, the answer as for the recording alone. Actual: every
    confident name is 'given in 3 recordings', its colour is measured on the one worm with a
    spread of exactly 0, and the recording is named again against its own colours: 17 names
    change and the probabilities move by up to 0.46."""
    worm = generate_worm(seed=3)
    test = _test(worm, "w3")
    alone = ident.label_panel(test, panel)
    copies = [test, NeuronTable(test.xyz, test.colours, source="w3 copy"),
              NeuronTable(test.xyz, test.colours, source="w3 copy 2")]
    named = ident.label_panel_many(copies, panel, first=[alone] * 3, share_handedness=False, adapt_colours=True)
    changed = sum(a != b for a, b in zip(alone.auto_id, named[0].auto_id))
    assert "adapted_colours" not in named[0].info and _same_answers(alone, named[0]), \
        f"{named[0].info.get('adapted_colours')} names' colours measured on the one recording; {changed} names changed"


def test_label_many_gives_a_test_the_same_answer_beside_a_test_without_blue(ident, panel):
    """Identifier.label_many promises ":meth:`label` for several tests ... the same answers".
    Expected: a test with R, G and B gets the same names beside a test that has only R and G
    (a channel not acquired) as alone. Actual: the model's colour input is decided for the
    whole batch (``_model_colours``/``_takes_colour`` over every test of ``search``), so the
    full-colour test is matched without colour input and with the position-only model's colour
    weight: 84 of its 152 names change and its top-1 drops from 46.7 to 41.4 %. (_label_many
    splits the batch by channels in common, not by whether the model can take the colour;
    _atlas_views already groups by it.)"""
    template = generate_worm(seed=5)
    full = _test(generate_worm(seed=6), "full")
    no_blue = _test(generate_worm(seed=7), "no blue", channels="RG")
    alone = ident.label_many([full], [template], atlas=panel.atlas)[0]
    beside = ident.label_many([full, no_blue], [template], atlas=panel.atlas)[0]
    changed = sum(a != b for a, b in zip(alone.auto_id, beside.auto_id))
    assert changed == 0 and np.allclose(alone.probs, beside.probs, atol=1e-9), f"{changed} of {len(full)} names changed"


def test_adapting_the_colours_does_not_undo_the_shared_handedness(tmp_path, capsys):
    """docs/cli.md: several tests on `auto` "are named in one handedness when they clearly
    agree", and adapting the colours (the default from 3 coloured tests) names them again "with
    a panel drawn from that atlas (positions unchanged)". Ten z-mirrored recordings: named
    once, they vote 7 of 7 mirrored and all are named 'mirrored' (with --no-adapt-colours:
    64-80 % top-1 and the warning line). With the default (colours adapted) the second naming
    runs on `auto` again from scratch (identify.Identifier.label_panel_many calls itself with
    the adapted panel and re-runs the sign test), votes only 6 of 6, decides nothing, and every
    recording is named in the atlas's handedness: 5-12 % top-1, left and right swapped, and no
    line on stderr at all. The colours were even measured on the mirrored names."""
    paths = []
    for seed in range(10):
        w = generate_worm(seed)
        path = tmp_path / f"m{seed}.csv"
        write_table(NeuronTable(w.xyz * [1, 1, -1], w.colours, w.labels), path)
        paths.append(path)
    assert main(["label", *map(str, paths), "--out", str(tmp_path / "out") + "/"]) == 0
    err = capsys.readouterr().err
    top1 = []
    for path in paths:
        got = pd.read_csv(tmp_path / "out" / path.name, keep_default_na=False)["auto_id"].to_numpy()
        truth = pd.read_csv(path, keep_default_na=False)["label"].to_numpy()
        top1.append(float(np.mean(got == truth)))
    assert "all are named as 'mirrored'" in err and np.mean(top1) > 0.5, (
        f"mirrored recordings named in the atlas's handedness after adapting the colours: top-1 "
        f"{np.round(top1, 2).tolist()}, stderr {err!r}")


def test_a_copy_with_its_rows_in_another_order_is_not_a_recording_of_its_own():
    """docs/cli.md: "a copy of another test never votes, nor are the adapted colours measured
    on it", and three recordings are needed to adapt the colours. A copy of a test whose rows
    are in another order (the same recording re-saved sorted, e.g. in a spreadsheet) is counted
    as a recording of its own: identify._counted_recordings tells copies by the bytes of the
    positions and colours in row order, so [A, B, A with its rows reversed] adapts the colours
    (can_adapt_colours is True, A measured twice) and A would vote twice on the handedness.
    Expected: only 2 distinct recordings, so no adaptation."""
    from napari_fdlc.identify import can_adapt_colours

    a, b = generate_worm(seed=1), generate_worm(seed=2)
    shuffled = NeuronTable(a.xyz[::-1], {c: v[::-1] for c, v in a.colours.items()}, a.labels[::-1])
    assert not can_adapt_colours([a, b, shuffled]), "a reordered copy of A counted as a third recording"


def test_match_many_gives_a_full_colour_test_the_same_answer_beside_a_test_without_blue(ident):
    """Identifier.match_many is documented as ":meth:`match_pair` for many tests against one
    template, batched". Expected: a test with R, G and B gets the same probabilities beside a
    test without B (a channel not acquired) as alone. Actual: ``search``/``_model_colours``
    decide the model's colour input for the whole batch (every test must have R, G, B), so the
    full-colour test is matched without colour input and with the position-only model's colour
    weight: its probabilities move by up to ~1.0 and the top candidate of ~98 of its 152 neurons
    changes. (label_many was fixed by splitting the batch by kind in _label_many; match_many and
    search, which fdlc track's first volumes go through, still batch them together.)"""
    template = generate_worm(seed=5)
    full, no_blue = _test(generate_worm(seed=6), "w6"), _test(generate_worm(seed=7), "w7", channels="RG")
    alone, _ = ident.match_pair(template, full)
    beside, _ = ident.match_many(template, [full, no_blue])[0]
    changed = int((alone.argmax(axis=1) != beside.argmax(axis=1)).sum())
    moved = float(np.abs(alone - beside).max())
    assert moved < 1e-4, f"beside a test without B: probabilities moved by {moved:.3f}, {changed} top candidates changed"


def test_match_pair_refuses_a_fixed_name_on_a_row_the_test_lacks(ident):
    """Names the user fixed are checked in every naming path (label, label_panel:
    match.check_fixed, "a name fixed on a row the test does not have is refused in one line").
    Expected: Identifier.match_pair (documented to take the user's ``fixed`` row -> name)
    refuses a row past the test's end with an FdlcError. Actual: the rows are not checked;
    _agreement_with_fixed indexes the model's answer with it and numpy's IndexError ("index 157
    is out of bounds for axis 0 with size 152") comes out of the model's scoring."""
    template = generate_worm(seed=5)
    test = _test(generate_worm(seed=6), "w6", flip_z=True)
    with pytest.raises(FdlcError):
        ident.match_pair(template, test, fixed={len(test) + 5: "ADAL"})


def test_adapting_the_colours_keeps_the_callers_panel(ident, monkeypatch):
    """label_panel_many(adapt_colours=True) measures the colours on the tests and names them
    again "with a panel drawn from that atlas (positions unchanged)" (docs/cli.md). Expected:
    the second naming uses the caller's panel (here make_panel(atlas, samples=2): the mean worm
    and 2 samples) with the colours adapted. Actual: identify.Identifier.label_panel_many calls
    make_panel(atlas) with the default samples, seed and spread, so the tests are named again
    against the default 10 templates (the mean worm and 9 samples) the caller never chose (other positions), silently."""
    from napari_fdlc.identify import Identifier

    panel = make_panel(load_atlas(), samples=2)
    tests = [_test(generate_worm(seed=s), f"w{s}") for s in (1, 2, 3)]
    first = [ident.label_panel(t, panel) for t in tests]
    used = []
    original = Identifier._label_panel

    def spy(self, test, panel, *args, **kwargs):
        used.append(len(panel.templates))
        return original(self, test, panel, *args, **kwargs)

    monkeypatch.setattr(Identifier, "_label_panel", spy)
    named = ident.label_panel_many(tests, panel, first=first, share_handedness=False, adapt_colours=True)
    assert named[0].info.get("adapted_colours"), "the setting: colours adapted"
    assert set(used) == {len(panel.templates)}, f"named again against {sorted(set(used))} templates, not the caller's {len(panel.templates)}"
