"""Claims of the documentation (docs/cli.md, docs/gui.md, README) that the code does not honour."""

from __future__ import annotations

from napari_fdlc.table import read_table


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
