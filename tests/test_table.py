import numpy as np
import pandas as pd
import pytest

from napari_fdlc.errors import TableError
from napari_fdlc.table import (
    NEUROPAL_ID_HEADER,
    NeuronTable,
    parse_name,
    read_table,
    table_from_dataframe,
    write_neuropal_id,
    write_table,
)


def write(path, text):
    path.write_text(text)
    return path


def test_round_trip_keeps_everything(tmp_path, worm):
    worm.extra["my_note"] = [f"n{i}" for i in range(len(worm))]
    write_table(worm, tmp_path / "a.csv")
    back = read_table(tmp_path / "a.csv")
    assert np.allclose(back.xyz, worm.xyz, atol=1e-3)
    assert list(back.labels) == list(worm.labels)
    assert set(back.colours) == set(worm.colours)
    assert list(back.extra["my_note"]) == list(worm.extra["my_note"])
    del worm.extra["my_note"]


def test_columns_without_name_or_value_are_not_written_back(tmp_path):
    """Excel's trailing commas on every line (',,' after the last column) make columns with no
    name and no value: they were kept and written back as 'Unnamed: 4' and 'Unnamed: 5'. A
    nameless column that holds values is kept."""
    back = read_table(write(tmp_path / "a.csv", "x_um,y_um,z_um,label,,,\n1,2,3,AVAL,,,7\n4,5,6,AVAR,,,\n"))
    write_table(back, tmp_path / "b.csv")
    header = (tmp_path / "b.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["x_um", "y_um", "z_um", "label"] and "Unnamed: 4" not in header and "Unnamed: 5" not in header, header
    assert list(back.extra[""]) == ["7", ""]  # its blank name kept, as written


def test_numbers_are_read_to_the_last_digit(tmp_path):
    """Positions and colours written with every digit come back bit for bit. With pandas 2 (which
    the package allows), its parser left a third of such numbers one unit in the last place off."""
    rng = np.random.default_rng(0)
    xyz, red = rng.uniform(0, 100, (300, 3)), rng.uniform(0, 1, 300)
    lines = ["x_um,y_um,z_um,R"] + [f"{x!r},{y!r},{z!r},{r!r}" for (x, y, z), r in zip(xyz.tolist(), red.tolist())]
    back = read_table(write(tmp_path / "a.csv", "\n".join(lines) + "\n"))
    np.testing.assert_array_equal(back.xyz, xyz)
    np.testing.assert_array_equal(back.colours["R"], red)


def test_neuropal_id_round_trip(tmp_path, worm):
    t = NeuronTable(worm.xyz, worm.colours, worm.labels, np.where(np.arange(len(worm)) % 5 == 0, 0.5, 1.0))
    write_neuropal_id(t, tmp_path / "np.csv", voxel_size_zyx=(1.5, 0.3, 0.3))
    lines = (tmp_path / "np.csv").read_text().splitlines()
    assert lines[7].startswith("User ID,User Confidence,Emphasized?,Auto ID")
    back = read_table(tmp_path / "np.csv")
    assert np.allclose(back.xyz, t.xyz, atol=1e-3)
    assert list(back.labels) == list(t.labels)
    assert np.array_equal(back.label_conf, t.label_conf)
    # 1-based internal voxel coordinates
    assert float(back.extra["Internal X (px)"][0]) == pytest.approx(t.xyz[0, 0] / 0.3 + 1, abs=1e-2)


def test_names_unsure_and_duplicates(tmp_path, capsys):
    p = write(tmp_path / "t.csv", "x_um,y_um,z_um,label\n0,0,0, AVAL \n1,0,0,AVAR?\n2,0,0,?\n3,0,0,\n4,0,0,RIAL\n5,0,0,RIAL\n")
    t = read_table(p)
    assert list(t.labels) == ["AVAL", "AVAR", "", "", "", ""]
    assert list(t.label_conf) == [1.0, 0.5, 0.0, 0.0, 0.0, 0.0]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RIAL" in err[0]
    assert parse_name("I1-alt") == ("I1-alt", 1.0)
    assert parse_name("RMDDR??") == parse_name("RMDDR ?") == ("RMDDR", 0.5)  # '??' was the name 'RMDDR?', sure


@pytest.mark.parametrize(
    "content, expected",
    [
        ("", "empty"),
        ("x_um,y_um\n1,2\n", "missing column(s) z_um"),
        ("x_um,y_um,z_um\n", "no rows"),
        ("x_um,y_um,z_um\n1,2,3\n1,abc,3\n", "line 3, column 'y_um'"),
        ("x_um,y_um,z_um\n1,2,nan\n", "line 2, column 'z_um'"),
        ("x_um,y_um,z_um\n1,inf,2\n", "line 2, column 'y_um'"),
        ("x_um,y_um,z_um,R\n1,2,3,red\n", "column 'R'"),
    ],
)
def test_bad_tables_are_refused_with_one_line(tmp_path, content, expected):
    p = write(tmp_path / "bad.csv", content)
    with pytest.raises(TableError) as info:
        read_table(p)
    message = str(info.value)
    assert expected in message and str(p) in message and "\n" not in message


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(TableError, match="no such file"):
        read_table(tmp_path / "nope.csv")
    with pytest.raises(TableError, match="folder"):
        read_table(tmp_path)


def test_atomic_write_leaves_no_partial_file(tmp_path, worm):
    target = tmp_path / "out.csv"
    write_table(worm, target)
    before = target.read_text()

    class Boom:
        def to_dataframe(self):
            raise RuntimeError("boom")

    with pytest.raises(Exception):
        write_table(Boom(), target)
    assert target.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_pixel_coordinates_are_told_from_micrometres(worm):
    """A head in pixels of 0.25-0.33 µm (x, y, and z too or not) lies 3+ times further apart
    than a worm's neurons do; the worm as it is, and a sparse subset of it, do not."""
    from napari_fdlc.table import TOO_SPREAD, implausible_scale, spread_factor

    assert implausible_scale(worm) is None
    for factors in ((4, 4, 4), (4, 4, 1), (3, 3, 3)):
        in_pixels = NeuronTable(worm.xyz * np.array(factors), worm.colours, source="px.csv")
        reason = implausible_scale(in_pixels)
        assert reason and reason.startswith("px.csv: its neurons lie") and "micrometres" in reason and "\n" not in reason
    rng = np.random.default_rng(0)
    sparse = [spread_factor(worm.xyz[rng.choice(len(worm), 15, replace=False)]) for _ in range(50)]
    assert max(sparse) < TOO_SPREAD


def test_no_corpus_table_or_sparse_subset_looks_like_pixels(corpus_path):
    """Every corpus table, and random subsets of 15 to 160 of its neurons (sparser annotation),
    lies closer together than TOO_SPREAD times a young adult's head of as many neurons."""
    from napari_fdlc.corpus import load_corpus
    from napari_fdlc.table import TOO_SPREAD, implausible_scale, spread_factor

    rng = np.random.default_rng(0)
    for worm in load_corpus(corpus_path):
        table = worm.table
        assert implausible_scale(table) is None, worm.name
        for n in (15, 30, 50, 160):
            if len(table) > n:
                assert spread_factor(table.xyz[rng.choice(len(table), n, replace=False)]) < TOO_SPREAD, (worm.name, n)


@pytest.mark.parametrize("header", ["x_um,y_um,z_um,note,note ", "x_um,y_um,z_um, x_um"])
def test_two_columns_that_are_one_name_without_spaces_are_refused(tmp_path, header):
    """Spaces around column names are stripped; two names that became one made df[c] a frame
    and a traceback further on."""
    path = tmp_path / "t.csv"
    path.write_text(header + "\n" + "\n".join(f"{i},{i * 2},{i % 3},{i},{i}" for i in range(12)) + "\n")
    with pytest.raises(TableError, match="two columns are named"):
        read_table(path)


def test_a_neuropal_id_exports_problems_name_its_own_columns(tmp_path):
    """A bad cell of a NeuroPAL_ID export was reported in column 'x_um', which that file does
    not have; its column is 'Real X (um)'."""
    from napari_fdlc.reference import generate_worm

    npid = tmp_path / "npid.csv"
    write_neuropal_id(generate_worm(seed=3), npid)
    lines = npid.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if "Real X (um)" in line)
    row = lines[header + 2].split(",")
    row[lines[header].split(",").index("Real X (um)")] = "abc"
    lines[header + 2] = ",".join(row)
    npid.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match=r"column 'Real X \(um\)': abc"):
        read_table(npid)


def _csv(tmp_path, text: str, name: str = "t.csv"):
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return path


def test_rows_ending_in_a_comma_keep_their_columns(tmp_path):
    """Data rows ending in ',' (Excel leaves them) under a header without: pandas took the first
    column as the index and read x from y_um and z from R, silently (fdlc label then wrote the
    shifted positions and exited 0)."""
    table = read_table(_csv(tmp_path, "x_um,y_um,z_um,R\n1,2,3,10,\n4,5,6,11,\n7,8,9,12,\n"))
    assert table.xyz.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert table.colours["R"].tolist() == [10, 11, 12]


@pytest.mark.parametrize("text, message", [
    ("x_um,y_um,z_um\n1,2,3,4\n4,5,6\n", "line 2 has 4 fields, the header 3"),  # blamed line 3's "empty" z
    ("x_um,y_um,z_um,R,R\n1,2,3,10,99\n4,5,6,11,98\n", "two columns are named 'R'"),  # read as R and R.1
    ("x_um,y_um,z_um, x_um\n1,2,3,100\n4,5,6,200\n", "two columns are named 'x_um'"),
    ("x_um;y_um;z_um;label\n1,5;2,5;3,5;AVAL\n", "separated by semicolons"),  # "missing column(s) x_um, ..."
    ("x_um\ty_um\tz_um\n1.5\t2.5\t3.5\n", "separated by tabs"),
    ("sep=;\nx_um;y_um;z_um\n1;2;3\n", "separated by ';'"),
], ids=["extra field", "repeated colour", "repeated position", "semicolons", "tabs", "Excel sep=;"])
def test_a_table_pandas_would_misread_is_one_line(tmp_path, text, message):
    with pytest.raises(TableError, match=message):
        read_table(_csv(tmp_path, text))


def test_excels_separator_line_is_skipped(tmp_path):
    """Excel's 'sep=,' first line: the table was refused for missing columns that are there."""
    table = read_table(_csv(tmp_path, "sep=,\r\nx_um,y_um,z_um,label\r\n1.5,2.5,3.5,AVAL\r\n4.5,5.5,6.5,AVAR\r\n"))
    assert table.xyz[:, 0].tolist() == [1.5, 4.5] and list(table.labels) == ["AVAL", "AVAR"]


def test_a_colour_written_nan_is_no_reading(tmp_path):
    """MATLAB (NeuroPAL_ID) and R write a missing value as NaN / NA: read as an empty colour cell
    (the volume's median), not refused ("NaN is not a finite number"). Positions stay refused."""
    def row(uid, x, y, z):
        return f"{uid},1,0,,,,{x},{y},{z},,1,1,1,,NaN,0.5,NA,nan,,NaN,NaN,NaN"
    pre = "Version,1.0\nGFP,0\nZ-Score Means,0,0,0,0\nZ-Score SDs,1,1,1,1\nNeuron Count,2\nComment,x\n\n"
    text = pre + ",".join(NEUROPAL_ID_HEADER) + "\n" + row("AVAL", 1, 2, 3) + "\n" + row("AVAR", 4, 5, 6) + "\n"
    table = read_table(_csv(tmp_path, text, "npid.csv"))
    assert list(table.labels) == ["AVAL", "AVAR"] and table.colours["G"].tolist() == [0.5, 0.5]
    with pytest.raises(TableError, match="NaN is not a finite number"):
        read_table(_csv(tmp_path, "x_um,y_um,z_um\n1,2,NaN\n", "pos.csv"))


def test_a_position_column_written_otherwise_is_named_in_the_error(tmp_path):
    """'X (um)' or 'Y_UM' for x_um, y_um: refused as missing columns without a word on the
    columns that are there under another spelling."""
    with pytest.raises(TableError, match=r"rename 'X \(um\)' to x_um; rename 'Y_UM' to y_um"):
        read_table(_csv(tmp_path, "X (um),Y_UM,z_um\n1,2,3\n"))


def test_rows_of_blank_cells_below_the_table_are_no_neurons(tmp_path):
    """Rows of commas alone below a table (Excel leaves them) were refused as empty cells; they are
    dropped. One between neurons was dropped too (session 31), which shifted every later
    neuron_index against the file's row numbers as pandas reads them: it is refused, with its line,
    and a bad cell after blank lines is still named on its own line."""
    table = read_table(_csv(tmp_path, "x_um,y_um,z_um,label\n1,2,3,AVAL\n4,5,6,AVAR\n,,,\n, ,,\n"))
    assert table.xyz.tolist() == [[1, 2, 3], [4, 5, 6]] and list(table.labels) == ["AVAL", "AVAR"]
    with pytest.raises(TableError, match="line 3, column 'x_um': an empty cell"):
        read_table(_csv(tmp_path, "x_um,y_um,z_um\n1,2,3\n,,\n4,5,6\n", "middle.csv"))
    with pytest.raises(TableError, match="line 5, column 'z_um': abc"):
        read_table(_csv(tmp_path, "x_um,y_um,z_um\n1,2,3\n\n\n7,8,abc\n,,\n", "bad.csv"))



# Session 32 (a helper review of the Python API); each says what used to happen.


def test_neuron_table_in_memory_reads_names_and_shapes_as_a_file_is_read(worm):
    """NeuronTable(xyz.T) (a (3, N) array) was reshaped into scrambled rows; labels or colours of
    another length gave numpy's reshape error; a label 'AVAL?' stayed the name 'AVAL?', sure."""
    with pytest.raises(TableError, match="transpose"):
        NeuronTable(worm.xyz.T.copy())
    with pytest.raises(TableError, match="3 labels for 155 neurons"):
        NeuronTable(worm.xyz, labels=["AVAL", "AVAR", "ADAL"])
    with pytest.raises(TableError, match="3 colour R"):
        NeuronTable(worm.xyz, {"R": [1.0, 2.0, 3.0]})
    table = NeuronTable([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], labels=["AVAL?", "AVAR"])
    assert list(table.labels) == ["AVAL", "AVAR"] and list(table.label_conf) == [0.5, 1.0]


def test_write_neuropal_id_with_auto_ids_and_no_confidences(tmp_path, worm):
    """auto_id without auto_conf: a TypeError (iteration over a 0-d array)."""
    write_neuropal_id(worm, tmp_path / "npid.csv", auto_id=list(worm.labels))
    assert len(read_table(tmp_path / "npid.csv")) == len(worm)


def test_an_empty_colour_cell_is_written_back_empty(tmp_path):
    """A neuron without a colour reading is the volume's median for the model, but a table read
    and written back (napari's export, a review session's) wrote that median into the empty cell:
    a reading made up. It stays empty, through a subset too (filled with the subset's median)."""
    table = read_table(_csv(tmp_path, "x_um,y_um,z_um,R,G\n1,2,3,5,1\n4,5,6,,2\n7,8,9,9,3\n1,9,4,7,\n"))
    assert table.colours["R"].tolist() == [5, 7, 9, 7] and table.colours["G"].tolist() == [1, 2, 3, 2]
    out = tmp_path / "back.csv"
    write_table(table, out)
    assert out.read_text().splitlines()[2:] == ["4.0,5.0,6.0,,2.0,", "7.0,8.0,9.0,9.0,3.0,", "1.0,9.0,4.0,7.0,,"]
    part = table.subset([1, 2])
    assert part.colours["R"].tolist() == [9, 9] and np.isnan(part.colours_as_read()["R"][0])
    write_neuropal_id(table, tmp_path / "npid.csv")
    assert read_table(tmp_path / "npid.csv").colour_gaps["R"].tolist() == [False, True, False, False]
    # given in memory with NaN: the same; a channel read nowhere stays NaN (no reading at all)
    memory = NeuronTable(np.zeros((3, 3)) + np.arange(3)[:, None], {"R": [1.0, np.nan, 3.0], "B": [np.nan] * 3})
    assert memory.colours["R"].tolist() == [1, 2, 3] and np.isnan(memory.colours["B"]).all()


def test_a_data_frame_with_nan_colours_is_a_table():
    """table_from_dataframe of a DataFrame in memory holding NaN for no colour reading (what a
    table's own to_dataframe gives, e.g. a sequence joined by time to open in napari) was refused:
    'nan is not a finite number' (pandas keeps NaN through astype(str))."""
    df = pd.DataFrame({"x_um": [1.0, 2, 3], "y_um": [1.0, 2, 3], "z_um": [1.0, 2, 3], "R": [1.0, np.nan, 3.0]})
    table = table_from_dataframe(df)
    assert table.colours["R"].tolist() == [1, 2, 3] and table.colour_gaps["R"].tolist() == [False, True, False]
    with pytest.raises(TableError, match="line 4, column 'z_um': an empty cell"):
        table_from_dataframe(df.assign(z_um=[1.0, 2, np.nan]))


def test_excels_na_is_no_reading_and_no_name(tmp_path):
    """Excel writes a missing value as #N/A (R as NA): a colour so written was refused as 'not a
    finite number', and a name so written named a neuron '#N/A'."""
    table = read_table(_csv(tmp_path, "x_um,y_um,z_um,R,label\n1,2,3,5,#N/A\n4,5,6,#N/A,NA\n7,8,9,9,AVAL\n"))
    assert table.colour_gaps["R"].tolist() == [False, True, False] and list(table.labels) == ["", "", "AVAL"]


def test_a_first_line_of_spaces_keeps_error_line_numbers_right(tmp_path):
    """Since session 35 a first line of spaces is read as a blank line. An error in a row
    below must name that row's own line (here line 4, as an editor shows it); it names line 3:
    table._record_lines counts the line of spaces as the header and gives up on the count."""
    path = tmp_path / "t.csv"
    path.write_text("   \nx_um,y_um,z_um,label\n1,2,3,AVAL\n4,5,x,AVAR\n", encoding="utf-8")
    with pytest.raises(TableError, match=r"line 4\b"):
        read_table(path)


def test_an_empty_value_beyond_the_header_on_a_later_row_is_dropped_as_docs_say(tmp_path):
    """docs/cli.md (neuron table): "a row with more values than the header (empty ones beyond
    it, as Excel leaves them, are dropped ...)". Excel leaves such an empty cell on the rows
    where a cell beyond the table once held something, not always on the first data row.
    Expected: the table reads as its three neurons. Instead, when the first data row has no
    trailing comma and a later row has one, pandas' C tokenizer stops and the table is refused
    with "not a valid CSV file (Error tokenizing data. C error: Expected 4 fields in line 3,
    saw 5)" (table._read_csv: pandas fixes its field count from the first row, and only a
    first row's extra empty fields are dropped)."""
    path = tmp_path / "worm.csv"
    path.write_text("x_um,y_um,z_um,label\n1,2,3,A\n4,5,6,B,\n7,8,9,C\n", encoding="utf-8")
    table = read_table(path)
    assert table.xyz.tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert list(table.labels) == ["A", "B", "C"]


def test_a_note_holding_a_carriage_return_is_written_so_that_it_reads_back(tmp_path):
    """Expected: a table written by write_table reads back with read_table, its other columns'
    text as written (docs/cli.md: "other columns are kept when a table is read and written
    back"). A note holding a lone carriage return ('a\rb', text pasted from an old Mac tool or
    a terminal) is written unquoted, and the file written is then refused: "line 4, column
    'x_um': b is not a finite number" (napari's writer, through write_table, writes the same
    broken file). Cause: table.write_table passes the text to DataFrame.to_csv, whose csv
    writer quotes only fields holding the line terminator '\n', and read_table (universal
    newlines, and pandas' parser alike) takes the bare '\r' for the end of a row."""
    table = NeuronTable([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], extra=pd.DataFrame({"note": ["ok", "a\rb"]}))
    write_table(table, tmp_path / "a.csv")
    assert read_table(tmp_path / "a.csv").extra["note"].tolist() == ["ok", "a\rb"]


def test_a_windows_line_break_inside_a_cell_is_kept_as_written(tmp_path):
    """Expected: a note holding a Windows line break ('line 1\r\nline 2'), written by
    write_table (quoted), reads back as written. Actual: it reads back as 'line 1\nline 2'.
    Cause: table.read_table reads the file with Path.read_text (universal newlines), which
    turns every '\r\n' into '\n', inside quoted cells too, before the CSV is parsed (open it
    with newline='' and let the CSV parsers take the line ends)."""
    table = NeuronTable([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], extra=pd.DataFrame({"note": ["ok", "line 1\r\nline 2"]}))
    write_table(table, tmp_path / "a.csv")
    assert read_table(tmp_path / "a.csv").extra["note"].tolist() == ["ok", "line 1\r\nline 2"]


def test_a_missing_name_in_a_nullable_string_column_is_no_name():
    """Expected: a name missing as pandas' nullable types hold it (pd.NA: a label column of
    dtype "string", e.g. after DataFrame.convert_dtypes()) is no name, as None, NaN, '' and 'NA'
    are (table_from_dataframe validates "a data frame in our column layout"). Actual: the
    neuron is named '<NA>' with confidence 1, and such a table used as a template gives that
    name. Cause: table._clean handles None and float NaN only; pd.NA falls through to str()."""
    assert parse_name(pd.NA) == ("", 0.0)
    df = pd.DataFrame({"x_um": [1.0, 2.0, 3.0], "y_um": [1.0, 2.0, 3.0], "z_um": [1.0, 2.0, 3.0],
                       "label": pd.array(["AVAL", None, "AVAR"], dtype="string")})
    assert list(table_from_dataframe(df).labels) == ["AVAL", "", "AVAR"]


def test_a_table_with_old_mac_line_ends_reads(tmp_path):
    """Excel for Mac's "CSV (Macintosh)" ends rows with a bare carriage return: read as rows,
    a quoted cell keeping its own carriage return (the file is read as written, no newline
    translation, and the csv module is given the text as it asks)."""
    path = tmp_path / "mac.csv"
    path.write_bytes(b'x_um,y_um,z_um,label,note\r1,2,3,AVAL,a\r4,5,6,,"p\rq"\r')
    table = read_table(path)
    assert table.xyz.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    assert list(table.labels) == ["AVAL", ""] and table.extra["note"].tolist() == ["a", "p\rq"]
