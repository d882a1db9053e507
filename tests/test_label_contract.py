"""Promises of docs/cli.md and the external contract ../shared/docs/neuron_table.md that an
audit of the docs against the code (session 27) found broken, each kept since."""

from __future__ import annotations

import numpy as np
import pandas as pd

from napari_fdlc.cli import main
from napari_fdlc.label import labelling_frame
from napari_fdlc.match import Labelling
from napari_fdlc.sample import sample_paths
from napari_fdlc.table import NeuronTable, write_table


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
