"""Neuron-table round trips found by a seeded fuzzer (session 37, "tablefuzz"): our CSV read and
written back, through napari's reader and writer, and names as a table in memory holds them.
Each docstring says what is expected and what happens instead."""

from __future__ import annotations

import numpy as np
import pandas as pd

from napari_fdlc.table import NeuronTable, parse_name, read_table, table_from_dataframe, write_table


def test_a_segment_table_opened_and_saved_in_napari_keeps_its_positions(tmp_path):
    """Expected: a neuron table as ``fdlc segment`` writes it (positions to the last digit,
    repr, beside x_px, y_px, z_px) opened in napari and saved unchanged with the napari-fdlc
    writer has exactly the positions read (write_table writes them "to the last digit"; the
    sample's 3-decimal table already round-trips). Actual: every 16-17-digit position comes back
    cut to 15 significant digits (12.345678901234567 -> 12.3456789012346), even with a voxel
    size of 0.25 where µm / voxel * voxel is exact. Cause: _napari/_io.py:write_neuron_csv
    rounds every scaled world coordinate to ``.15g`` to undo the division's last bits, which
    also drops the digits that were read."""
    from napari_fdlc._napari._io import get_table_reader, write_neuron_csv

    xyz = np.array([[12.345678901234567, 3.141592653589793, 7.123456789012345],
                    [40.98765432109876, 1.6389409646301716, 10.791468550226549]])
    vox = np.array([0.25, 0.25, 1.5])  # x, y, z
    extra = pd.DataFrame({"x_px": xyz[:, 0] / vox[0], "y_px": xyz[:, 1] / vox[1], "z_px": xyz[:, 2] / vox[2]})
    path = tmp_path / "neurons.csv"
    write_table(NeuronTable(xyz, extra=extra), path)
    data, kwargs, _ = get_table_reader(str(path))(str(path))[0]
    assert kwargs["scale"] == (1.5, 0.25, 0.25)
    [saved] = write_neuron_csv(str(tmp_path / "saved.csv"), data, {"scale": kwargs["scale"], "features": kwargs["features"]})
    back = read_table(saved).xyz
    assert back.tolist() == xyz.tolist(), f"{xyz.tolist()} -> {back.tolist()}"


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


def test_napari_opens_a_table_whose_first_column_name_holds_a_line_break(tmp_path):
    """Expected: a neuron table that read_table reads opens in napari too (its reader claims
    our CSV). A column name with a line break (Excel's Alt+Enter in a header cell, quoted in
    the CSV) in front of x_um: read_table reads it, napari's reader declines the file
    (get_table_reader returns None: "no reader"). Cause: _napari/_io.py:get_table_reader parses
    each physical line on its own (csv.reader([line])), so the quoted header is cut at its line
    break and x_um, y_um, z_um are never seen."""
    from napari_fdlc._napari._io import get_table_reader

    path = tmp_path / "t.csv"
    path.write_text('"cell\nnote",x_um,y_um,z_um\na,1,2,3\nb,4,5,6\n', encoding="utf-8")
    assert read_table(path).xyz.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert get_table_reader(str(path)) is not None, "the napari reader declines a neuron table the core reads"
