import math

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.geometry import canonical_frame
from napari_fdlc.reference import generate_worm
from napari_fdlc.simulate import SimulationParams, simulate_worm
from napari_fdlc.table import NeuronTable, write_table


def test_correspondence_is_known(worm):
    synth = simulate_worm(worm, rng=0)
    real = synth.origin >= 0
    assert (synth.table.labels[real] == worm.labels[synth.origin[real]]).all()
    assert (synth.table.labels[~real] == "").all()
    kept = real.sum() / len(worm)
    assert 0.7 <= kept <= 0.96  # 5–25 % dropped
    assert (~real).sum() <= 20


def test_spurious_points_keep_their_distance(worm):
    from scipy.spatial import cKDTree

    synth = simulate_worm(worm, rng=3, params=SimulationParams(noise_um=0.0, max_spurious=20))
    real = synth.origin >= 0
    if (~real).any():
        d, _ = cKDTree(synth.table.xyz[real]).query(synth.table.xyz[~real])
        assert d.min() > 1.0  # ≥ 2 µm before the global scale/shear


def test_no_mirror_images(worm):
    """The simulator only applies proper transforms: a worm and its copy keep their chirality."""
    params = SimulationParams(drop_fraction=(0.0, 0.0), max_spurious=0, noise_um=0.0, bend_curvature=0.0, shear=0.0,
                              transverse_shear=0.0, scale=0.0)
    for seed in range(5):
        synth = simulate_worm(worm, rng=seed, params=params)
        a = worm.xyz[synth.origin] - worm.xyz[synth.origin].mean(0)
        b = synth.table.xyz - synth.table.xyz.mean(0)
        u, _, vt = np.linalg.svd(b.T @ a)
        assert np.linalg.det(u @ vt) > 0


def test_deterministic_with_seed(worm):
    a = simulate_worm(worm, rng=5)
    b = simulate_worm(worm, rng=5)
    assert np.array_equal(a.table.xyz, b.table.xyz)
    assert canonical_frame(a.table.xyz)[0].shape == a.table.xyz.shape


@pytest.mark.parametrize("what", ["empty", "nan"])
def test_simulate_refuses_empty_or_non_finite_tables(what):
    """An empty table, or one with a NaN position, is refused in one line."""
    if what == "empty":
        table = NeuronTable(np.zeros((0, 3)))
    else:
        xyz = np.random.default_rng(0).normal(size=(10, 3)) * [20, 5, 4]
        xyz[2, 1] = np.nan
        table = NeuronTable(xyz)
    with pytest.raises(FdlcError) as exc:
        simulate_worm(table, 0)
    assert "\n" not in str(exc.value)


def _proper(source, synth) -> bool:
    """Whether the real neurons of ``synth`` are a proper (not mirrored) copy of ``source``'s."""
    real = synth.origin >= 0
    a = source.xyz[synth.origin[real]]
    b = synth.table.xyz[real]
    u, _, vt = np.linalg.svd((b - b.mean(0)).T @ (a - a.mean(0)))
    return np.linalg.det(u @ vt) > 0


def test_a_scale_parameter_of_one_or_more_never_gives_a_mirror_image():
    """A scale of 1 or more is refused: an axis factor 1 ± 1.5 can be negative, and a third of
    the copies came out mirror images (L/R-swapped training pairs)."""
    worm = generate_worm(seed=1)
    params = SimulationParams(scale=1.5, max_spurious=0)
    try:
        copies = [simulate_worm(worm, seed, params) for seed in range(20)]
    except FdlcError:
        return
    mirrored = [seed for seed, synth in enumerate(copies) if not _proper(worm, synth)]
    assert mirrored == [], f"mirror-image copies at seeds {mirrored}"


@pytest.mark.parametrize("bad", [
    {"noise_um": -0.1},  # numpy: ValueError 'scale < 0'
    {"max_spurious": -1},  # numpy: ValueError 'high <= 0'
    {"drop_fraction": (0.3, 0.1)},  # numpy: ValueError 'high - low < 0'
    {"noise_um": math.nan},  # accepted: every position NaN
    {"flip_side_probability": 2.0},  # accepted: not a probability
])
def test_simulation_parameters_out_of_range_are_refused_in_one_line(bad):
    """Each parameter is checked (one FdlcError line); these reached numpy's ValueError or
    passed silently (noise NaN: every position NaN)."""
    worm = generate_worm(seed=1)
    with pytest.raises(FdlcError) as exc:
        simulate_worm(worm, 0, SimulationParams(**bad))
    assert "\n" not in str(exc.value)


def test_fdlc_simulate_warns_about_a_table_that_is_not_in_micrometres(tmp_path, capsys):
    """A table in nm gets the units warning, as in fdlc label / track (the recipe's magnitudes
    are µm); it was simulated silently, the bend winding it round a circle many times."""
    worm = generate_worm(seed=1)
    df = worm.to_dataframe()
    for c in ("x_um", "y_um", "z_um"):
        df[c] = df[c] * 1000.0
    src = tmp_path / "nm.csv"
    write_table(df, src)
    assert main(["simulate", str(src), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "µm" in err, f"no unit warning on stderr: {err!r}"


def _source_with_extras(tmp_path):
    worm = generate_worm(seed=1)
    df = worm.to_dataframe()
    df["GFP"] = np.arange(len(df)) * 1.5 + 100.0
    df["cell_id"] = [f"c{i}" for i in range(len(df))]
    df["B"] = df["B"].astype(object)
    df.loc[3, "B"] = ""  # no reading of this neuron's B
    path = tmp_path / "src.csv"
    df.to_csv(path, index=False)
    return path, df


def test_fdlc_simulate_keeps_the_other_columns_of_each_real_neuron(tmp_path):
    """Each real neuron's other columns go with it into its copies (neuron_table.md: other
    columns are kept); they were dropped."""
    path, df = _source_with_extras(tmp_path)
    assert main(["simulate", str(path), "--out", str(tmp_path / "out")]) == 0
    out = pd.read_csv(tmp_path / "out" / "src_syn0.csv", keep_default_na=False, dtype=str)
    assert {"GFP", "cell_id"} <= set(out.columns), f"columns written: {list(out.columns)}"
    real = out["origin"].astype(int) >= 0
    origin = out.loc[real, "origin"].astype(int).to_numpy()
    assert (out.loc[real, "cell_id"].to_numpy() == df["cell_id"].to_numpy()[origin]).all()


def test_fdlc_simulate_does_not_invent_a_colour_reading_for_an_empty_cell(tmp_path):
    """A colour cell empty in the source (no reading) stays empty in the copies; the reader's
    stand-in median was written as if measured."""
    path, _ = _source_with_extras(tmp_path)
    assert main(["simulate", str(path), "--out", str(tmp_path / "out")]) == 0
    out = pd.read_csv(tmp_path / "out" / "src_syn0.csv", keep_default_na=False, dtype=str)
    row = out[out["origin"] == "3"]
    assert len(row) == 1, "pick a seed that keeps neuron 3"
    assert row["B"].iloc[0].strip() == "", f"B of the neuron without a reading written as {row['B'].iloc[0]!r}"


def test_fdlc_simulate_writes_nothing_when_one_output_cannot_be_written(tmp_path, capsys):
    """Every output is checked before the first is written: with src_syn1.csv a folder,
    src_syn0.csv was written first, and the error named the hidden temporary file."""
    path, _ = _source_with_extras(tmp_path)
    out = tmp_path / "out"
    (out / "src_syn1.csv").mkdir(parents=True)
    assert main(["simulate", str(path), "--out", str(out), "--count", "3"]) == 2
    err = capsys.readouterr().err
    assert not (out / "src_syn0.csv").exists(), "a half-done run left src_syn0.csv behind"
    assert ".tmp" not in err and "src_syn1.csv" in err, err


def test_fdlc_simulate_gives_spurious_neurons_no_invented_colour_reading(tmp_path):
    """Expected: a spurious neuron of ``fdlc simulate`` takes its colour from the source's
    neurons (simulate.py: "names and colours travel"), so every G value written in a copy is a
    G reading of the source, or empty where the cell it was drawn from had none (as real
    neurons' empty cells stay empty).
    Before: simulate_worm draws the spurious colours from ``table.colours``, where the reader put
    the volume's median in every empty cell, and the CLI blanks unread cells of *real* neurons
    only: with G read on 4 of 155 neurons, nearly every spurious neuron is written with
    G = the median of those 4 (a value no neuron has), as if measured."""
    worm = generate_worm(seed=1)
    df = worm.to_dataframe().astype(object)
    readings = [101.0, 202.0, 303.0, 404.0]  # the median, 252.5, is not one of them
    df["G"] = [str(v) for v in readings] + [""] * (len(df) - len(readings))
    source = tmp_path / "src.csv"
    df.to_csv(source, index=False)
    out = tmp_path / "out"
    assert main(["simulate", str(source), "--out", str(out), "--count", "3", "--seed", "1"]) == 0
    written = []
    for k in range(3):
        copy = pd.read_csv(out / f"src_syn{k}.csv", keep_default_na=False, dtype=str)
        spurious = copy[copy["origin"] == "-1"]
        written += [float(v) for v in spurious["G"] if v.strip()]
    assert written, "pick a seed that adds spurious neurons"
    invented = sorted({v for v in written if v not in readings})
    assert not invented, f"{len(written)} spurious G values written, {invented} of them no neuron's reading"


def test_simulate_worm_keeps_a_missing_colour_reading_missing():
    """Expected: a neuron without a G reading (NaN, kept as a gap by NeuronTable and written
    back empty) is, in its synthetic copy, still without a G reading: names and colours travel
    with their neurons (simulate.py docstring), and a gap is part of the colour.
    Before: simulate_worm copies ``table.colours``, where the gap holds the volume's median, into
    a new table: the copy's neuron has G = the median and to_dataframe writes it as measured."""
    worm = generate_worm(seed=1)
    g = worm.colours["G"].copy()
    g[3] = np.nan
    table = NeuronTable(worm.xyz, {**worm.colours, "G": g}, worm.labels)
    assert np.isnan(table.to_dataframe()["G"].iloc[3])  # the source writes it back empty
    synth = simulate_worm(table, 0, SimulationParams(drop_fraction=(0.0, 0.0), max_spurious=0))
    row = int(np.flatnonzero(synth.origin == 3)[0])
    written = synth.table.to_dataframe()["G"].iloc[row]
    assert np.isnan(written), f"the copy of the neuron without a G reading has G = {written}"


def test_a_synthetic_copy_carries_no_voxel_coordinates_of_the_old_positions(worm):
    """A source with x_px, y_px, z_px (our exports) or NeuroPAL_ID's Internal X (px) gave its
    copies those columns unchanged beside the moved positions: stale voxel coordinates (napari's
    reader refused the mismatched ratio). Other columns still travel with their neurons."""
    extra = pd.DataFrame({"x_px": np.arange(len(worm)), "Internal Z (slice)": 1.0, "score": np.arange(len(worm)) / 10})
    source = NeuronTable(worm.xyz, worm.colours, worm.labels, extra=extra)
    synth = simulate_worm(source, 0)
    assert list(synth.table.extra.columns) == ["score"]
    real = synth.origin >= 0
    assert np.allclose(synth.table.extra["score"][real].astype(float), synth.origin[real] / 10)
