"""Defect hunt: `fdlc label`, `fdlc handedness` and `fdlc atlas` used as a lab or an external
benchmark uses them (../shared/docs/neuron_table.md, docs/cli.md). Each test fails on the code
as it stands because of a real defect; its docstring says the input, what happens now, and
what should happen."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.table import NeuronTable, write_table


def run(*args):
    return main([str(a) for a in args])


def _run_caught(*args):
    """main(), with an exception that escapes it turned into a failure that names it (the
    contract: exit 0, or non-zero with one line on stderr; never a traceback)."""
    try:
        return run(*args)
    except Exception as exc:  # noqa: BLE001 - the defect is that it escapes
        pytest.fail(f"fdlc {args[0]} raised {type(exc).__name__}: {exc} (a traceback, not a one-line message)")


def _one_line_or_answer(code, err_lines, out, n_rows):
    """Either an answer of one row per test neuron, or a refusal in one `fdlc: error:` line."""
    assert all(line.startswith("fdlc: ") for line in err_lines), err_lines
    if code == 0:
        assert len(pd.read_csv(out, keep_default_na=False)) == n_rows
    else:
        assert code == 2 and sum(line.startswith("fdlc: error:") for line in err_lines) == 1, err_lines


# --------------------------------------------------------------------------------------------
# 1. A huge but finite coordinate: a traceback


@pytest.mark.parametrize("value", [1.7e308, 1e60])
@pytest.mark.parametrize("where", ["test_panel", "test_template", "template"])
def test_a_huge_finite_coordinate_is_answered_or_refused_in_one_line(tmp_path, capsys, worm, other_worm, where, value):
    """Input: one row of a neuron table with x_um = 1.7e308 (DBL_MAX / MATLAB's realmax, a
    common "missing" sentinel) or 1e60 — finite, so not refused by the reader — in the test
    (with the built-in panel or a template) or in the template.
    Now: `fdlc label` dies with a traceback, numpy.linalg.LinAlgError 'Eigenvalues did not
    converge' (geometry._levelling: np.linalg.eigh on np.cov of overflowing positions,
    geometry.py:90) or 'SVD did not converge' (1e60: register.py:191 casts the positions to
    float32, which overflows to inf, then register._weighted_similarity's SVD, register.py:442).
    Should: answer every row (as it does for 1e30, test_label_contract) or refuse in one
    `fdlc: error:` line naming the file (neuron_table.md: "non-zero with a one-line message on
    stderr for any bad input")."""
    bad = worm.xyz.copy() if where != "template" else other_worm.xyz.copy()
    bad[5, 0] = value
    test, template, out = tmp_path / "test.csv", tmp_path / "template.csv", tmp_path / "out.csv"
    if where == "template":
        write_table(worm, test)
        write_table(NeuronTable(bad, other_worm.colours, other_worm.labels), template)
    else:
        write_table(NeuronTable(bad, worm.colours), test)
        write_table(other_worm, template)
    args = ["label", test, "--out", out] + ([] if where == "test_panel" else ["--template", template])
    code = _run_caught(*args)
    err = capsys.readouterr().err.strip().splitlines()
    _one_line_or_answer(code, err, out, len(worm))


def test_handedness_of_a_table_with_a_sentinel_coordinate_is_one_line(tmp_path, capsys, worm):
    """Input: `fdlc handedness` on a labelled worm one of whose rows has x_um = 1.7e308.
    Now: numpy.linalg.LinAlgError 'Eigenvalues did not converge' escapes (geometry.py:90,
    canonical_frame -> _levelling). Should: print the handedness (the named neurons decide it)
    or refuse in one `fdlc: error:` line."""
    xyz = worm.xyz.copy()
    xyz[0, 0] = 1.7e308
    table = tmp_path / "labelled.csv"
    write_table(NeuronTable(xyz, worm.colours, worm.labels), table)
    code = _run_caught("handedness", table)
    err = capsys.readouterr().err.strip().splitlines()
    assert code in (0, 2) and all(line.startswith("fdlc: ") for line in err), (code, err)


# --------------------------------------------------------------------------------------------
# 2. Python's own warnings reach the user's stderr


def test_a_far_outlier_leaves_only_fdlc_lines_on_stderr(tmp_path, worm):
    """Input: `python -m napari_fdlc.cli label test.csv --out out.csv` (as a benchmark runs
    it), one row of the test at x_um = 1e155 (finite, named fine otherwise). Now: exit 0, but
    stderr also carries numpy's multi-line RuntimeWarnings ('.../numpy/lib/_function_base_impl.py:
    2887: RuntimeWarning: overflow encountered in dot' and the source line 'c = dot(X,
    X_T.conj())', from geometry.canonical_frame / _levelling's np.cov). Should: every line on
    stderr is one of fdlc's own ('fdlc: warning: ...'), as the contract asks of warnings."""
    xyz = worm.xyz.copy()
    xyz[5, 0] = 1e155
    test, out = tmp_path / "test.csv", tmp_path / "out.csv"
    write_table(NeuronTable(xyz, worm.colours), test)
    proc = subprocess.run([sys.executable, "-m", "napari_fdlc.cli", "label", str(test), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    foreign = [line for line in proc.stderr.splitlines() if not line.startswith("fdlc: ")]
    assert not foreign, foreign


# --------------------------------------------------------------------------------------------
# 3. A table in millimetres is refused as "flat"


def test_a_table_in_millimetres_is_not_refused_as_lying_in_a_plane(tmp_path, capsys, worm, other_worm):
    """Input: a whole 3D head written in millimetres (the generated worm's µm × 1e-3: 155
    neurons, ~0.1 mm long, 0.02 mm deep), with the panel and with a template.
    Now: exit 2 after a warning line, with 'fdlc: error: ...: the neurons lie in a plane (0.01
    µm thick), so left cannot be told from right; a 3D table is needed (check the z positions
    and the voxel size in z)': the worm is not flat, and the advice sends the user to the wrong
    column. geometry.refuse_flat compares the thickness with an absolute FLAT_UM = 1.0
    (geometry.py:101/116) whatever the table's units. docs/cli.md: "a table in nanometres or
    millimetres would be named meaninglessly" after its one-line units warning.
    Should: named with the units warning (as docs/cli.md says, and as a table in nanometres is),
    or refused in one line that says the coordinates are not µm — not as a plane."""
    test, template = tmp_path / "mm.csv", tmp_path / "template.csv"
    write_table(NeuronTable(worm.xyz * 1e-3, worm.colours), test)
    write_table(other_worm, template)
    for extra in ([], ["--template", template]):
        out = tmp_path / f"out{len(extra)}.csv"
        code = run("label", test, *extra, "--out", out)
        err = capsys.readouterr().err.strip().splitlines()
        assert not any("lie in a plane" in line for line in err), err
        _one_line_or_answer(code, err, out, len(worm))


def test_handedness_of_a_labelled_worm_in_millimetres(tmp_path, capsys, worm):
    """Input: `fdlc handedness` on a labelled worm written in millimetres (µm × 1e-3) and on its
    z-flipped copy. Handedness is a property of the shape, not of the units (the command
    compares canonical frames and names). Now: exit 2, 'fdlc: error: ...: the neurons lie in a
    plane (0.01 µm thick) ...' (geometry.refuse_flat's absolute FLAT_UM, geometry.py:116, called
    from evaluate.handedness, evaluate.py:129). Should: 'same' and 'mirrored', as for the same
    worms in µm."""
    same, flipped = tmp_path / "same_mm.csv", tmp_path / "flipped_mm.csv"
    write_table(NeuronTable(worm.xyz * 1e-3, worm.colours, worm.labels), same)
    write_table(NeuronTable(worm.xyz * [1, 1, -1] * 1e-3, worm.colours, worm.labels), flipped)
    assert run("handedness", same, flipped) == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert f"{same}: same" in out and f"{flipped}: mirrored" in out, out


# --------------------------------------------------------------------------------------------
# 4. neuron_index is not the row number of the test table


def test_neuron_index_stays_the_row_number_of_the_test_table(tmp_path, capsys, worm):
    """Input: a test table with a row of empty cells (',,,,,,') between its 10th and 11th
    neurons — what a spreadsheet leaves when a row is cleared; pandas.read_csv, as a benchmark
    reads the test, keeps it as row 10 (NaN). Now: exit 0 and the row is silently dropped
    (table._read_csv, table.py: 'A row of blank cells ... is no neuron: dropped'), so every
    later neuron_index is one less than its row in the test table: joined on neuron_index, 145
    of 155 answers land on the wrong neuron. neuron_table.md: "neuron_index: 0-based row number
    of the neuron in the test table", and a row whose coordinates are not numbers is refused
    naming the row. Should: refuse it in one line naming the line, or keep neuron_index the row
    number (the answer after the blank row at neuron_index 11, ...)."""
    test, out = tmp_path / "test.csv", tmp_path / "out.csv"
    write_table(NeuronTable(worm.xyz, worm.colours), test)
    lines = test.read_text().splitlines()
    lines.insert(11, "," * lines[0].count(","))  # after the header and 10 neurons
    test.write_text("\n".join(lines) + "\n")
    code = run("label", test, "--out", out)
    err = capsys.readouterr().err.strip().splitlines()
    if code != 0:
        assert code == 2 and len(err) == 1 and "line 12" in err[0], err
        return
    answer = pd.read_csv(out)
    given = pd.read_csv(test)  # as a benchmark reads the test it gave
    joined = answer.merge(given.reset_index(), left_on="neuron_index", right_on="index", suffixes=("", "_given"))
    wrong = int((joined["x_um"] != joined["x_um_given"]).sum())
    assert wrong == 0, f"{wrong} of {len(answer)} answers join to another row of the test on neuron_index"


# --------------------------------------------------------------------------------------------
# 5. A long cell in another column: a traceback


@pytest.mark.parametrize("role", ["test", "template"])
def test_a_long_text_cell_in_another_column_is_kept_not_a_traceback(tmp_path, capsys, worm, other_worm, role):
    """Input: a neuron table with an extra 'note' column, one cell of which holds 200 000
    characters (a pasted comment; valid CSV that pandas reads), as test or as template.
    Now: `_csv.Error: field larger than field limit (131072)` escapes fdlc label as a traceback
    (table._read_csv iterates csv.reader over the file to check field counts and does not catch
    csv.Error; the limit is the csv module's default field_size_limit). Should: the table is
    read (other columns are kept: neuron_table.md), or refused in one line."""
    table = worm if role == "test" else other_worm
    df = table.to_dataframe()
    df["note"] = ["x" * 200_000 if i == 0 else "n" for i in range(len(df))]
    given = tmp_path / f"{role}.csv"
    df.to_csv(given, index=False)
    plain = tmp_path / "plain.csv"
    write_table(worm if role == "template" else other_worm, plain)
    test, template = (given, plain) if role == "test" else (plain, given)
    out = tmp_path / "out.csv"
    code = _run_caught("label", test, "--template", template, "--out", out)
    err = capsys.readouterr().err.strip().splitlines()
    _one_line_or_answer(code, err, out, len(worm))


# --------------------------------------------------------------------------------------------
# 6. --out can replace the model weights


def test_out_may_not_replace_the_weights_it_names_with(tmp_path, capsys, worm, untrained_weights):
    """Input: `fdlc label test.csv --weights W --out W.safetensors` (a slip of the path).
    Now: exit 0 and the model's weights file is silently replaced by the answer CSV (its
    first bytes 'neuron_index,x_um,...'): label._output_paths checks --out only against the
    tables (label.py: `_output_paths(tests, out, [*tests, *(templates or [])])`), not the
    weights read. The same goes for the shipped src/napari_fdlc/data/fdlc_model.safetensors
    without --weights. docs/cli.md: an output "that would replace an input ... before any work"
    is refused (fdlc track refuses its models). Should: exit 2 with one line, the weights intact."""
    weights = tmp_path / "model"
    for suffix in (".safetensors", ".json"):
        shutil.copy(f"{untrained_weights}{suffix}", f"{weights}{suffix}")
    before = (tmp_path / "model.safetensors").read_bytes()
    test = tmp_path / "test.csv"
    write_table(worm, test)
    code = run("label", test, "--weights", weights, "--out", tmp_path / "model.safetensors")
    err = capsys.readouterr().err.strip().splitlines()
    assert (tmp_path / "model.safetensors").read_bytes() == before, "the weights were replaced by the answer"
    assert code == 2 and len(err) == 1 and err[0].startswith("fdlc: error:"), (code, err)


# --------------------------------------------------------------------------------------------
# 7. fdlc atlas


def _corpus(root, lab: str, worms: list[NeuronTable]):
    (root / lab).mkdir(parents=True)
    rows = ["dataset,dandiset,worm,n_neurons,n_labeled"]
    for i, table in enumerate(worms):
        write_table(table, root / lab / f"w{i}.csv")
        rows.append(f"{lab},0,w{i},{len(table)},{int(table.named.sum())}")
    (root / "worms.csv").write_text("\n".join(rows) + "\n")
    return root


def test_an_atlas_of_one_lab_whose_name_holds_a_space_reads_back_that_lab(tmp_path, capsys):
    """Input: `fdlc atlas --corpus C --out atlas.csv` where C's one lab is called 'Lab A'
    (Atlas.save says "a lab's name may hold spaces"). The file's header reads '# napari-fdlc
    atlas: 4 worms of Lab A; ...'. Now: Atlas.load reads its labs as ('Lab', 'A') — two labs —
    because a header without a comma is split on whitespace (reference.py:151, the fallback
    for atlases written before session 31). Should: ('Lab A',), the lab it was built from."""
    from napari_fdlc.reference import generate_worm, load_atlas

    corpus = _corpus(tmp_path / "corpus", "Lab A", [generate_worm(seed=s) for s in range(10, 14)])
    out = tmp_path / "atlas.csv"
    assert run("atlas", "--corpus", corpus, "--out", out) == 0, capsys.readouterr().err
    assert load_atlas(out).labs == ("Lab A",)


def test_the_atlas_takes_the_handedness_of_its_worms_not_of_the_best_named_one(tmp_path, capsys):
    """Input: `fdlc atlas` on a corpus of 5 labelled worms: 4 recorded one way and 1, the one
    with the most names (183 against 150-156), z-flipped (a mirrored acquisition, as most of
    SF's). Now: the atlas is built in the frame of the best-named worm
    (reference.build_atlas: `reference = int(np.argmax([t.named.sum() for t in tables]))`,
    reference.py:222, every other worm aligned to it with mirroring allowed), so it comes out
    mirrored: all 4 majority worms are then 'mirrored' relative to it (geometry.mirrored_by_names),
    while an atlas of the same 4 worms alone has them 'same'. One well-annotated worm of the
    other handedness flips what --chirality same/mirrored and `fdlc handedness` mean, and the
    panel's `auto` (which keeps the atlas's handedness) names the majority left/right swapped.
    Should: the atlas in the handedness of most of its worms (here: that of the 4)."""
    from napari_fdlc.geometry import mirrored_by_names
    from napari_fdlc.reference import atlas_worm, generate_worm, load_atlas

    worms = [generate_worm(seed=s) for s in range(10, 14)]
    full = atlas_worm(load_atlas(), np.random.default_rng(5))  # every name of the shipped atlas
    flipped = NeuronTable(full.xyz * [1.0, 1.0, -1.0] * 1.3, full.colours, full.labels)
    assert flipped.named.sum() > max(w.named.sum() for w in worms)
    corpus = _corpus(tmp_path / "corpus", "L", worms + [flipped])
    out = tmp_path / "atlas.csv"
    assert run("atlas", "--corpus", corpus, "--out", out) == 0, capsys.readouterr().err
    atlas = load_atlas(out)
    mirrored = [mirrored_by_names(atlas.names, atlas.mean, w, 6) for w in worms]
    assert mirrored == [False] * 4, f"the 4 worms of the majority are mirrored relative to the atlas: {mirrored}"
