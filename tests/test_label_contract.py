"""Promises of docs/cli.md and the external contract ../shared/docs/neuron_table.md that an
audit of the docs against the code (session 27) found broken, each kept since."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.label import labelling_frame
from napari_fdlc.match import Labelling
from napari_fdlc.reference import generate_worm
from napari_fdlc.sample import sample_paths
from napari_fdlc.table import NeuronTable, read_table, write_neuropal_id, write_table
import csv


def run(*args):
    return main([str(a) for a in args])


def _prob_sums(path) -> np.ndarray:
    df = pd.read_csv(path, keep_default_na=False)
    probs = [c for c in df.columns if c.startswith("prob_")]
    # 1e-9: float noise in adding the written decimals, far below the 6th decimal written
    return df[probs].astype(float).to_numpy().sum(axis=1) - 1e-9


def test_written_candidate_probabilities_sum_to_at_most_one(tmp_path):
    """neuron_table.md: "names only; 'no match' is not a candidate, so the probabilities sum to
    at most 1". Each prob_k is rounded to 6 decimals on its own, so three probabilities that
    sum to 0.9999999 are written as 0.999991 + 0.000005 + 0.000005 = 1.000001."""
    n = 3
    table = NeuronTable(np.arange(3 * n, dtype=float).reshape(n, 3))
    probs = np.array([[0.9999906, 0.0000047, 0.0000046]] * n)
    assert (probs.sum(axis=1) <= 1).all()
    result = Labelling(["A", "B", "C"], probs, ["A"] * n, probs[:, 0].copy())
    out = tmp_path / "out.csv"
    write_table(labelling_frame(table, result), out)
    assert (_prob_sums(out) <= 1).all(), _prob_sums(out)


def test_fdlc_label_on_the_sample_writes_probabilities_summing_to_at_most_one(tmp_path):
    """The same through `fdlc label` as an external benchmark calls it: the bundled sample
    against itself as a position-only template (the shipped model)."""
    _, sample = sample_paths()
    df = pd.read_csv(sample)
    template = tmp_path / "template.csv"
    df[["x_um", "y_um", "z_um", "label"]].to_csv(template, index=False)
    out = tmp_path / "ids.csv"
    assert run("label", sample, "--template", template, "--out", out) == 0
    sums = _prob_sums(out)
    assert (sums <= 1).all(), f"rows {np.flatnonzero(sums > 1).tolist()} sum to {sums[sums > 1].tolist()}"


def test_a_bad_cell_is_reported_at_its_line_in_the_file(tmp_path, capsys):
    """cli.md: refused "with one line naming file, line and column". A blank line in the CSV
    (pandas skips it) shifts every line number the message gives."""
    bad = tmp_path / "bad.csv"
    bad.write_text("x_um,y_um,z_um\n\n1,2,3\n4,5,6\n7,abc,9\n")  # 'abc' is on line 5
    assert run("label", bad, "--out", tmp_path / "out.csv") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "column 'y_um'" in err[0]
    assert "line 5" in err[0], err[0]


def test_one_test_into_a_folder_that_does_not_exist_yet(tmp_path):
    """`fdlc label a.csv --out results/run1/a_ids.csv` was refused ("the folder does not exist")
    while segment and track create theirs: a benchmark writing to a fresh results path failed."""
    _, sample = sample_paths()
    out = tmp_path / "results" / "run1" / "ids.csv"
    assert run("label", sample, "--out", out) == 0
    assert len(pd.read_csv(out)) == len(pd.read_csv(sample))


# --------------------------------------------------------------------------------------------
# Session 30's review of `fdlc label` against the contract


def _sample_frame() -> pd.DataFrame:
    return pd.read_csv(sample_paths()[1], keep_default_na=False)


def test_a_neuron_far_out_is_answered_not_a_traceback(tmp_path):
    """One finite but absurd coordinate (1e8 µm, within what is read: a unit slip in one row):
    the head window slid 10 µm at a time over the whole span, so fdlc label took ~50 s (at 1e30
    it died in np.arange). It now answers every row."""
    df = _sample_frame().iloc[:60][["x_um", "y_um", "z_um", "R", "G", "B"]].copy()
    df.loc[5, "x_um"] = 1e8
    test = tmp_path / "outlier.csv"
    df.to_csv(test, index=False)
    out = tmp_path / "out.csv"
    assert run("label", test, "--out", out) == 0
    assert len(pd.read_csv(out)) == len(df)


def test_written_positions_are_the_inputs_to_the_last_digit(tmp_path):
    """Output x_um, y_um, z_um were written to 6 significant digits: 100012.43 came back as
    100012 (a stage offset), and a benchmark joining the answer to its truth on the positions
    found no partner. They read back exactly as given."""
    df = _sample_frame().iloc[:40][["x_um", "y_um", "z_um", "R", "G", "B"]].copy()
    rng = np.random.default_rng(0)
    df[["x_um", "y_um", "z_um"]] += rng.uniform(0, 1e-3, (len(df), 3))
    df["y_um"] += 1e5
    test = tmp_path / "test.csv"
    df.to_csv(test, index=False, float_format="%.10f")
    out = tmp_path / "out.csv"
    assert run("label", test, "--out", out) == 0
    written = pd.read_csv(out)[["x_um", "y_um", "z_um"]].to_numpy()
    assert np.array_equal(written, pd.read_csv(test)[["x_um", "y_um", "z_um"]].to_numpy())


def test_cpd_answers_a_test_of_one_neuron(tmp_path, capsys):
    """neuron_table.md: "Edge cases that must work: a test with 1 neuron". --method cpd refused
    it (CPD cannot register fewer than 3 points); it now answers with every template name
    equally likely."""
    sample = _sample_frame()
    test, template = tmp_path / "one.csv", tmp_path / "template.csv"
    sample.iloc[:1][["x_um", "y_um", "z_um"]].to_csv(test, index=False)
    sample.iloc[:60][["x_um", "y_um", "z_um", "label"]].to_csv(template, index=False)
    out = tmp_path / "out.csv"
    assert run("label", test, "--template", template, "--method", "cpd", "--out", out) == 0, capsys.readouterr().err
    answer = pd.read_csv(out, keep_default_na=False)
    assert len(answer) == 1 and answer["prob_1"].iloc[0] == answer["prob_2"].iloc[0] > 0


def test_two_columns_named_alike_are_refused_and_nothing_is_written(tmp_path, capsys):
    """`note,note ` (or `x_um, x_um`) are one name once spaces are stripped: fdlc label died with
    a traceback, after the outputs of the tests before had been written."""
    sample = _sample_frame()
    good, bad = tmp_path / "good.csv", tmp_path / "bad.csv"
    sample.iloc[:40].to_csv(good, index=False)
    rows = [f"{x:.4f},{y:.4f},{z:.4f},a{i},b{i}" for i, (x, y, z) in enumerate(sample[["x_um", "y_um", "z_um"]].to_numpy()[:12])]
    bad.write_text("x_um,y_um,z_um,note,note \n" + "\n".join(rows) + "\n")
    out = tmp_path / "outdir"
    assert run("label", good, bad, "--out", out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "note" in err[0], err
    assert not out.exists() or not any(out.iterdir())


def test_cpd_refuses_a_flat_test_as_the_model_does(tmp_path, capsys):
    """docs/cli.md: a test of 10 neurons or more in one plane is refused (left cannot be told
    from right); --method cpd named it."""
    sample = _sample_frame()
    flat = sample.iloc[:20][["x_um", "y_um", "z_um"]].copy()
    flat["z_um"] = 5.0
    test, template = tmp_path / "flat.csv", tmp_path / "template.csv"
    flat.to_csv(test, index=False)
    sample.iloc[:60][["x_um", "y_um", "z_um", "label"]].to_csv(template, index=False)
    assert run("label", test, "--template", template, "--method", "cpd", "--out", tmp_path / "out.csv") == 2
    assert "plane" in capsys.readouterr().err


# Session 32 (a helper review of fdlc label / handedness against the contract); each says what used to happen.


def _stderr_lines(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("value", [1.7e308, 1e60, 1e155])
def test_a_sentinel_coordinate_is_refused_in_one_line(tmp_path, capsys, worm, other_worm, value):
    """x_um = 1.7e308 (MATLAB's realmax, a missing-value marker) or 1e60 in a test or template:
    a LinAlgError traceback (the geometry overflowed); at 1e155 numpy's own RuntimeWarnings on
    stderr. Beyond 1e9 µm the row is now refused in one line naming it."""
    bad = worm.xyz.copy()
    bad[5, 0] = value
    test, template = tmp_path / "test.csv", tmp_path / "template.csv"
    write_table(NeuronTable(bad, worm.colours, worm.labels), test)
    write_table(other_worm, template)
    for args in (["label", test], ["label", worm_csv := tmp_path / "w.csv", "--template", test], ["handedness", test]):
        if args[1] == worm_csv:
            write_table(worm, worm_csv)
        assert run(*args, *(["--out", tmp_path / "o.csv"] if args[0] == "label" else [])) == 2
        err = _stderr_lines(capsys)
        assert len(err) == 1 and "line 7, column 'x_um'" in err[0] and "no position in µm" in err[0], err


def test_a_table_in_millimetres_is_named_with_its_units_warning_not_refused_as_flat(tmp_path, capsys, worm):
    """A whole head in millimetres was refused as "the neurons lie in a plane (0.01 µm thick)",
    after the units warning (two lines, the advice about z wrong); fdlc handedness refused it too.
    The flatness limit now shrinks with the span below a head's."""
    test, flipped = tmp_path / "mm.csv", tmp_path / "flipped_mm.csv"
    write_table(NeuronTable(worm.xyz * 1e-3, worm.colours, worm.labels), test)
    write_table(NeuronTable(worm.xyz * [1, 1, -1] * 1e-3, worm.colours, worm.labels), flipped)
    assert run("label", test, "--out", tmp_path / "o.csv") == 0
    err = _stderr_lines(capsys)
    assert "cannot be µm" in err[0] and all(line.startswith("fdlc: warning:") for line in err), err
    assert run("handedness", test, flipped) == 0
    out = capsys.readouterr().out
    assert f"{test}: same" in out and f"{flipped}: mirrored" in out, out


def test_a_row_of_blank_cells_between_neurons_is_refused_not_dropped(tmp_path, capsys, worm):
    """A cleared row (',,,,') between neurons 10 and 11 was dropped, so every later neuron_index
    was one less than the row pandas (a benchmark) reads there: 145 of 155 answers joined to the
    wrong neuron. Refused now, naming its line."""
    test = tmp_path / "test.csv"
    write_table(NeuronTable(worm.xyz, worm.colours), test)
    lines = test.read_text().splitlines()
    lines.insert(11, "," * lines[0].count(","))
    test.write_text("\n".join(lines) + "\n")
    assert run("label", test, "--out", tmp_path / "o.csv") == 2
    err = _stderr_lines(capsys)
    assert len(err) == 1 and "line 12" in err[0], err


def test_a_long_text_cell_in_another_column_is_kept(tmp_path, worm, other_worm):
    """A 200 000-character note in a column of its own: csv's field limit raised a traceback."""
    df = worm.to_dataframe().drop(columns=["label"])
    df["note"] = ["x" * 200_000] + ["n"] * (len(df) - 1)
    test, template, out = tmp_path / "test.csv", tmp_path / "template.csv", tmp_path / "o.csv"
    df.to_csv(test, index=False)
    write_table(other_worm, template)
    assert run("label", test, "--template", template, "--out", out) == 0
    assert pd.read_csv(out)["note"].iloc[0] == "x" * 200_000


def test_out_may_not_replace_the_weights(tmp_path, capsys, worm, untrained_weights):
    """--out onto the --weights' .safetensors (or, without --weights, the shipped model's):
    the weights were replaced by the answer."""
    import shutil

    weights = tmp_path / "model"
    for suffix in (".safetensors", ".json"):
        shutil.copy(f"{untrained_weights}{suffix}", f"{weights}{suffix}")
    before = (tmp_path / "model.safetensors").read_bytes()
    test = tmp_path / "test.csv"
    write_table(worm, test)
    assert run("label", test, "--weights", weights, "--out", tmp_path / "model.safetensors") == 2
    assert "would replace an input" in _stderr_lines(capsys)[0]
    assert (tmp_path / "model.safetensors").read_bytes() == before
    from napari_fdlc.identify import shipped_weights

    assert run("label", test, "--out", f"{shipped_weights()}.json") == 2
    assert "would replace an input" in _stderr_lines(capsys)[0]


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


@pytest.fixture
def small(tmp_path, worm, other_worm):
    """A 30-neuron test (no label) and a 40-neuron labelled template, as CSV text."""
    test = worm.subset(range(30)).to_dataframe().drop(columns=["label"])
    template = tmp_path / "template.csv"
    write_table(other_worm.subset(range(40)), template)
    return test, template


def test_a_table_with_a_blank_first_line_is_read(tmp_path, capsys, small):
    """A CSV whose header follows one empty line (pandas, like most CSV readers, skips it)
    should be read as the table it is. Instead fdlc label refuses it with a false message:
    "line 2 has 6 fields, the header 0" (table._read_csv takes the blank line as the header,
    while pandas takes line 2)."""
    frame, template = small
    test = tmp_path / "test.csv"
    test.write_text("\n" + frame.to_csv(index=False))
    out = tmp_path / "out.csv"
    code = run("label", test, "--template", template, "--method", "cpd", "--out", out)
    assert code == 0, _err(capsys)
    assert len(pd.read_csv(out)) == len(frame)


def test_a_neuropal_id_export_with_a_quoted_header_is_accepted(tmp_path, capsys, small, other_worm):
    """neuron_table.md: "A NeuroPAL_ID CSV export (recognised by its header) is accepted
    wherever a neuron table is." The same export with its header fields quoted (as a tool that
    quotes every field saves it; the CSV is the same) is not recognised (table._is_neuropal_id
    looks for the raw text 'User ID,'), and is refused as a template with a misleading
    "line 3 has 5 fields, the header 2"."""
    frame, _ = small
    test = tmp_path / "test.csv"
    frame.to_csv(test, index=False)
    export = tmp_path / "export.csv"
    write_neuropal_id(other_worm.subset(range(40)), export)
    lines = export.read_text().split("\n")
    header = next(i for i, line in enumerate(lines) if line.startswith("User ID,"))
    lines[header] = ",".join(f'"{h}"' for h in lines[header].split(","))
    export.write_text("\n".join(lines))
    out = tmp_path / "out.csv"
    code = run("label", test, "--template", export, "--method", "cpd", "--out", out)
    assert code == 0, _err(capsys)
    assert (pd.read_csv(out, keep_default_na=False)["auto_id"] != "").any()


def test_blank_header_cells_do_not_come_back_under_pandas_names(tmp_path, capsys, small):
    """Excel leaves ', ,' header cells (a space, no value below) after a table: columns with
    neither a name nor a value, which the reader means to drop ("kept, it would be written back
    under pandas' name for it"). Two of them are instead read as '' and '.1' (pandas mangles the
    second ' ' to ' .1', then the name is stripped), and fdlc label writes a column named '.1'
    (and one named '') that the input never had."""
    frame, template = small
    test = tmp_path / "test.csv"
    body = frame.to_csv(index=False).splitlines()
    test.write_text("\n".join([body[0] + ", , "] + [line + ",," for line in body[1:]]) + "\n")
    out = tmp_path / "out.csv"
    assert run("label", test, "--template", template, "--method", "cpd", "--out", out) == 0, _err(capsys)
    header = out.read_text().splitlines()[0].split(",")
    assert ".1" not in header and "" not in header, header


def test_one_time_point_written_as_1_and_1_0_is_one_volume(tmp_path, capsys, small):
    """A test with a 't' column of one time point, written '1' on some rows and '1.0' on others
    (as a spreadsheet or a script mixing ints and floats saves it), is one volume. It is refused
    as "a recording of 2 time points": table.read_volume counts distinct t *texts*, not values."""
    frame, template = small
    frame = frame.copy()
    frame["t"] = ["1" if i % 2 else "1.0" for i in range(len(frame))]
    test = tmp_path / "test.csv"
    frame.to_csv(test, index=False)
    out = tmp_path / "out.csv"
    code = run("label", test, "--template", template, "--method", "cpd", "--out", out)
    assert code == 0, _err(capsys)


@pytest.fixture(scope="module")
def small_worm():
    """30 neurons of a generated worm, every one named."""
    return generate_worm(seed=1).subset(range(30))


def test_an_out_that_is_a_symlink_loop_is_one_line_not_a_traceback(tmp_path, small_worm, capsys):
    """Expected (contract: "non-zero with a one-line message on stderr for any bad input"): an
    --out that is a symbolic link loop (a stale link pointing at itself through another) is
    refused with exit 2 and one line. Instead errors.check_output -> _replaces_input calls
    Path.resolve(), which raises RuntimeError("Symlink loop from ...") on Python 3.11: neither
    FdlcError nor OSError, so cli.main lets it out as a traceback."""
    test, template = tmp_path / "test.csv", tmp_path / "template.csv"
    write_table(small_worm, test)
    write_table(small_worm, template)
    (tmp_path / "a.csv").symlink_to(tmp_path / "b.csv")
    (tmp_path / "b.csv").symlink_to(tmp_path / "a.csv")
    try:
        code = run("label", test, "--template", template, "--method", "cpd", "--out", tmp_path / "a.csv")
    except RuntimeError as exc:
        pytest.fail(f"traceback instead of one line: {exc!r}")
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len([line for line in err if "error" in line]) == 1, err


def test_an_r_na_label_is_unnamed_not_a_neuron_called_na(tmp_path, small_worm, capsys):
    """R's write.csv (and readr's write_csv) writes a missing name as a bare NA (quoted names,
    unquoted NA, a row-name column). The reader already takes NA as a missing value in a colour
    column (docs/cli.md: "one written NaN / NA as MATLAB and R write a missing value"), but in
    the label column it is read as a neuron named 'NA' (table.parse_name compares it as a
    name). Expected: an unnamed neuron (contract: "an empty cell means unnamed"). Instead the
    template names a neuron 'NA', and `fdlc label` gives a test neuron auto_id 'NA'."""
    df = small_worm.to_dataframe()
    lines = ['"","x_um","y_um","z_um","R","G","B","label"']
    for i, r in df.iterrows():
        name = "NA" if i == 5 else f'"{r.label}"'
        lines.append(f'"{i + 1}",{r.x_um!r},{r.y_um!r},{r.z_um!r},{r.R!r},{r.G!r},{r.B!r},{name}')
    template = tmp_path / "from_r.csv"
    template.write_text("\n".join(lines) + "\n")
    table = read_table(template)
    test = tmp_path / "test.csv"
    write_table(small_worm, test)
    out = tmp_path / "ids.csv"
    assert run("label", test, "--template", template, "--method", "cpd", "--out", out) == 0, capsys.readouterr().err
    given = pd.read_csv(out, keep_default_na=False)
    assert table.labels[5] == "" and "NA" not in set(given["auto_id"]), (table.labels[5], given.loc[5, "auto_id"])


def test_a_neuropal_id_export_with_spaces_around_its_header_names_is_read(tmp_path, small_worm):
    """A NeuroPAL_ID export whose header cells carry spaces around the names ('User ID, Real X
    (um), ...', as a hand-edited or re-exported file has them) is recognised as a NeuroPAL_ID
    export (table.neuropal_id_header strips the cells), but _from_neuropal_id renames the
    columns by the unstripped names, so the read refuses it as "missing column(s) Real X (um),
    Real Y (um), Real Z (um)" — columns that are there. Expected: read as the same export
    without spaces is (the reader says "spaces around names do not count" elsewhere)."""
    plain = tmp_path / "plain.csv"
    write_neuropal_id(small_worm, plain)
    lines = plain.read_text().splitlines()
    lines[7] = ", ".join(lines[7].split(","))  # the header, after the 7 preamble lines
    spaced = tmp_path / "spaced.csv"
    spaced.write_text("\n".join(lines) + "\n")
    try:
        table = read_table(spaced)
    except FdlcError as exc:
        pytest.fail(f"refused: {exc}")
    assert list(table.labels) == list(read_table(plain).labels)


def test_a_first_line_of_spaces_above_the_header_is_skipped_as_a_blank_one(tmp_path):
    """A line holding only spaces above the header is a blank line to pandas (and to the reader,
    which skips empty lines above the header "as pandas skips them too"). Instead
    table._read_csv takes it as a one-column header and refuses the table with a wrong
    message: "line 2 has 4 fields, the header 1" (line 2 *is* the header)."""
    path = tmp_path / "spaces_first.csv"
    path.write_text("   \nx_um,y_um,z_um,label\n1.5,2.5,3.5,AVAL\n4.5,5.5,6.5,AVAR\n")
    try:
        table = read_table(path)
    except FdlcError as exc:
        pytest.fail(f"refused: {exc}")
    assert table.xyz[:, 0].tolist() == [1.5, 4.5] and list(table.labels) == ["AVAL", "AVAR"]


def _worm(seed: int, n: int | None = None, names: bool = True) -> NeuronTable:
    worm = generate_worm(seed=seed)
    if n is not None:
        worm = worm.subset(np.arange(min(n, len(worm))))
    if not names:
        worm = NeuronTable(worm.xyz, worm.colours, source=worm.source)
    return worm


def test_label_cpd_with_weights_that_do_not_exist_is_not_silently_accepted(tmp_path, capsys):
    """docs/cli.md: `fdlc label --weights PATH` names with other weights, and bad input exits 2
    with one line; docs/tracking.md: `--method cpd` says in one line that it ignores
    `--weights` (fdlc track does). Expected from `fdlc label --method cpd --weights
    /nonexistent/model`: exit 2 naming the missing weights, or one warning line saying --weights
    is ignored with cpd. Instead: exit 0 and nothing said (label.label_files warns only of
    --chirality and --no-atlas for cpd, and never checks the weights on that path)."""
    test, template = tmp_path / "test.csv", tmp_path / "template.csv"
    write_table(_worm(3, 25, names=False), test)
    write_table(_worm(4, 25), template)
    rc = run("label", test, "--template", template, "--method", "cpd", "--no-color",
             "--weights", tmp_path / "nonexistent" / "model", "--out", tmp_path / "out.csv")
    err = capsys.readouterr().err
    assert rc == 2 or "--weights" in err, (rc, err)


def test_label_no_atlas_without_a_template_is_not_silently_ignored(tmp_path, capsys):
    """docs/cli.md: `--no-atlas`: the templates alone (the help: "with --template"); the
    built-in panel also multiplies in the atlas's own answer. Expected from `fdlc label
    TEST --no-atlas` (no template): one warning line that --no-atlas does not apply there, as
    the code does for --adapt-colours, --shared-handedness, and --no-atlas with --method cpd.
    Instead: the flag is dropped silently (identify.label_neurons ignores use_atlas on the
    panel path) and stderr is empty."""
    test = tmp_path / "test.csv"
    write_table(_worm(5, names=False), test)
    assert run("label", test, "--no-atlas", "--chirality", "same", "--out", tmp_path / "out.csv") == 0
    err = capsys.readouterr().err
    assert "--no-atlas" in err, err


def test_label_shared_handedness_with_one_test_says_it_does_not_apply(tmp_path, capsys):
    """docs/cli.md: the shared handedness is for several tests with --chirality auto and no
    template; asked for where it cannot apply, the code says so in one line
    ("--shared-handedness is for the built-in panel with --chirality auto: ignored here"), as
    --adapt-colours does with fewer than 3 tests. Expected with a single test: that line.
    Instead: label.label_files checks only the template and --chirality, and one test's
    --shared-handedness is ignored silently."""
    test = tmp_path / "test.csv"
    write_table(_worm(6, names=False), test)
    assert run("label", test, "--shared-handedness", "--out", tmp_path / "out.csv") == 0
    err = capsys.readouterr().err
    assert "--shared-handedness" in err, err


def _cpd_files(tmp_path, worm, other_worm, n_test: int = 20, n_template: int = 40):
    """A small test (no label) and a labelled template, for the model-free --method cpd."""
    test, template = tmp_path / "test.csv", tmp_path / "template.csv"
    write_table(worm.subset(np.arange(n_test)), test)
    write_table(other_worm.subset(np.arange(n_template)), template)
    return test, template


def test_a_column_without_a_name_comes_back_without_one(tmp_path, worm, other_worm):
    """neuron_table.md: "Other columns are kept when the table is read and written back";
    docs/cli.md: the output carries "the test's other columns exactly as written". A test saved
    by pandas' own `DataFrame.to_csv` (index kept, the most common way a script writes a CSV)
    starts with a column whose header cell is empty. Expected: it comes back under the empty
    header it had. Instead the output names it 'Unnamed: 0', pandas' invented name, a column
    the input never had (table._read_csv keeps a filled blank-header column under pandas' name,
    and label.labelling_frame / write_table write that name)."""
    test, template = _cpd_files(tmp_path, worm, other_worm)
    indexed = tmp_path / "indexed.csv"
    pd.read_csv(test, keep_default_na=False).drop(columns="label").to_csv(indexed)  # header ",x_um,..."
    assert indexed.read_text().startswith(",x_um,")
    out = tmp_path / "out.csv"
    assert run("label", indexed, "--template", template, "--method", "cpd", "--out", out) == 0
    with open(out, newline="") as handle:
        header = next(csv.reader(handle))
    assert "Unnamed: 0" not in header, header
    assert "" in header, header


def test_a_name_written_with_probability_0_is_no_candidate(tmp_path, worm, other_worm):
    """neuron_table.md: cand_k / prob_k are "the k-th most likely names with their
    probabilities ... (empty / 0 when there are fewer candidates)", and match.top_k leaves a name
    of probability 0 out ('' / 0). A template with two names: the rows far from both are
    written `AVAR,0,AVAL,0,,0`, a name beside a written probability of 0 (below 1e-6, rounded
    down to 0 by label._six_decimals after top_k chose the names). A benchmark counting
    non-empty cand_k as candidates counts names the answer gives no probability. Expected: a
    written prob_k of 0 goes with an empty cand_k."""
    test, _ = _cpd_files(tmp_path, worm, other_worm)
    df = pd.read_csv(tmp_path / "template.csv", keep_default_na=False)
    df["label"] = ""
    df.loc[5, "label"], df.loc[9, "label"] = "AVAL", "AVAR"
    template = tmp_path / "two_names.csv"
    df.to_csv(template, index=False)
    out = tmp_path / "out.csv"
    assert run("label", test, "--template", template, "--method", "cpd", "--out", out) == 0
    o = pd.read_csv(out, dtype=str, keep_default_na=False)
    zero_named = [(j, o.loc[j, f"cand_{k}"]) for j in range(len(o)) for k in (1, 2, 3)
                  if o.loc[j, f"cand_{k}"] != "" and float(o.loc[j, f"prob_{k}"]) == 0.0]
    assert not zero_named, f"{len(zero_named)} candidates written with probability 0, e.g. {zero_named[:3]}"


def test_an_absurd_top_k_is_one_line_not_a_traceback(tmp_path, worm, other_worm, capsys):
    """neuron_table.md: "non-zero with a one-line message on stderr for any bad input. All
    inputs are validated before anything is written". `--top-k 100000000000000000000` passes
    label_files' only check (top_k >= 1); after the whole registration, match.top_k builds
    `[""] * (k - kk)` and an OverflowError ("cannot fit 'int' into an index-sized integer")
    escapes cli.main as a traceback. Expected: exit 2 and one line (e.g. refuse K beyond what
    can be written, before any work)."""
    test, template = _cpd_files(tmp_path, worm, other_worm, n_test=3)
    out = tmp_path / "out.csv"
    try:
        code = run("label", test, "--template", template, "--method", "cpd", "--top-k", 10**20, "--out", out)
    except OverflowError as exc:
        raise AssertionError(f"traceback instead of one line: OverflowError: {exc}") from None
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err and err[-1].startswith("fdlc: error:"), (code, err)
    assert not out.exists()


def test_out_may_not_replace_the_built_in_atlas(tmp_path, worm, untrained_weights, monkeypatch, capsys):
    """Without --template, `fdlc label` reads the built-in reference panel, made from the
    shipped atlas (src/napari_fdlc/data/atlas.csv; the atlas's answer joins every template's
    too). It is an input as much as the shipped weights, which --out may not replace
    (test_label_contract.test_out_may_not_replace_the_weights). Expected: `--out` onto the atlas
    is refused in one line (exit 2) and the atlas is left as it was. Instead the answer replaces
    it (label._output_paths lists the tests, templates and model files as inputs, not the atlas),
    and every later call without a template fails or names from a neuron table of answers.
    The atlas is a copy here (reference.shipped_atlas_path patched), so no real file is harmed."""
    import shutil

    from napari_fdlc import reference

    atlas = tmp_path / "data" / "atlas.csv"
    atlas.parent.mkdir()
    shutil.copy(reference.shipped_atlas_path(), atlas)
    before = atlas.read_bytes()
    monkeypatch.setattr(reference, "shipped_atlas_path", lambda: atlas)
    test = tmp_path / "test.csv"
    write_table(worm.subset(np.arange(30)), test)
    code = run("label", test, "--weights", untrained_weights, "--out", atlas)
    err = capsys.readouterr().err.strip().splitlines()
    assert atlas.read_bytes() == before, "the atlas was replaced by the answer"
    assert code == 2 and err and err[-1].startswith("fdlc: error:"), (code, err)
