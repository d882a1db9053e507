"""Nuclei detection, colour readout, the bundled sample and ``fdlc segment``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.io.images import Stack, StackSeries, write_tiff
from napari_fdlc.render import random_worm, render_stack
from napari_fdlc.segment import detect_nuclei, measure_colours, score_detections, segment_series, segment_stack
from napari_fdlc.table import NeuronTable, read_table
from napari_fdlc.track import split_by_time


@pytest.fixture(scope="module")
def rendered():
    worm = random_worm(70, size_um=(44, 16, 12), min_spacing_um=2.4, seed=11)
    return render_stack(worm, seed=4, peak_photons=200)


@pytest.fixture(scope="module")
def found(rendered):
    return segment_stack(rendered[0])


def test_detection_f1_and_centre_error(rendered, found):
    _, truth = rendered
    s = score_detections(truth.xyz, found.xyz, max_distance_um=1.5)
    assert s["f1"] >= 0.9, s
    assert s["median_error_um"] <= 0.5, s


def test_table_columns(rendered, found):
    stack, _ = rendered
    df = found.to_dataframe()
    assert list(df.columns[:7]) == ["x_um", "y_um", "z_um", "R", "G", "B", "W"]
    assert {"x_px", "y_px", "z_px", "score"} <= set(df.columns)
    np.testing.assert_allclose(df["x_px"] * stack.voxel_size_zyx[2], df["x_um"])
    for c in "RGBW":  # z-scored per volume
        assert abs(found.colours[c].mean()) < 1e-9 and found.colours[c].std() == pytest.approx(1.0)
    assert (found.extra["score"] >= 6.0).all()


def test_colour_readout_recovers_the_rendered_order(rendered, found):
    _, truth = rendered
    pairs = score_detections(truth.xyz, found.xyz)["pairs"]
    for c in "RGB":
        rho = spearmanr(truth.extra[f"{c}_int"].to_numpy()[pairs[:, 0]], found.colours[c][pairs[:, 1]])[0]
        assert rho >= 0.8, (c, rho)
    rho_w = spearmanr(truth.colours["W"][pairs[:, 0]], found.colours["W"][pairs[:, 1]])[0]
    assert rho_w >= 0.7


def test_coarse_z_and_gfp(rendered):
    worm = random_worm(50, size_um=(40, 15, 12), min_spacing_um=2.6, seed=2)
    stack, truth = render_stack(worm, seed=1, voxel_size_zyx=(1.5, 0.35, 0.35), gfp=True)
    found = segment_stack(stack)
    s = score_detections(truth.xyz, found.xyz)
    assert s["f1"] >= 0.9 and s["median_error_um"] <= 0.5, s
    assert "GFP" in found.extra.columns and "GFP" not in found.colours


def _two_nuclei(distance_um, ratio, radius=1.3):
    """Two nuclei ``distance_um`` apart along x, the second ``ratio`` times dimmer in W."""
    table = NeuronTable([[10.0, 10.0, 6.0], [10.0 + distance_um, 10.0, 6.0]])
    return _render_pair(table, ratio, radius)


def _render_pair(table, ratio, radius):
    stack, truth = render_stack(
        table, seed=0, align=False, shape_zyx=(12, 80, 100), gut=False, brightness_sd=0.0,
        nucleus_radius_sd_um=0.0, nucleus_radius_um=radius, texture=0.0,
    )
    if len(truth) == 2:  # dim the second nucleus: re-render it scaled
        w = stack.role_index("W")
        x_split = int(np.mean(truth.xyz[:, 0]) / stack.voxel_size_zyx[2])
        data = stack.data.astype(float)
        bg = np.median(data[w])
        data[w, :, :, x_split:] = bg + (data[w, :, :, x_split:] - bg) / ratio
        stack = Stack(data.astype(np.uint16), stack.voxel_size_zyx, stack.channel_roles)
    return stack, truth


@pytest.mark.parametrize("distance, ratio", [(2.7, 1.0), (2.7, 3.0), (3.2, 4.0)])
def test_touching_nuclei_are_split(distance, ratio):
    stack, truth = _two_nuclei(distance, ratio)
    found = segment_stack(stack)
    assert len(found) == 2
    assert score_detections(truth.xyz, found.xyz)["tp"] == 2


def test_a_dim_nucleus_pressed_on_a_bright_one_needs_the_fine_scale():
    # 2.4 µm nuclei 2.2 µm apart, the second 2.5x dimmer: one blob at the nominal 3 µm scale
    stack, truth = _two_nuclei(2.2, 2.5, radius=1.2)
    vol = stack.data[stack.role_index("W")]
    one_scale = detect_nuclei(vol, stack.voxel_size_zyx, 3.0, fine_scale=None)[0]
    both = detect_nuclei(vol, stack.voxel_size_zyx, 3.0)[0]
    assert len(one_scale) == 1
    assert len(both) == 2 and score_detections(truth.xyz, both[:, ::-1])["tp"] == 2


@pytest.mark.parametrize("colours, expected", [((1.0, 0.0), 2), ((1.0, 1.0), 1)])
@pytest.mark.parametrize("offset, radius", [((0.0, 0.0, 2.2), 1.0), ((1.6, 0.0, 0.0), 0.8)])
def test_touching_nuclei_of_different_colours_are_split_by_colour(colours, expected, offset, radius):
    # 2 µm nuclei 2.2 µm apart in z (PSF 0.7 µm, 1 µm planes), the upper 1.65x brighter in W,
    # or 1.6 µm nuclei 1.6 µm apart in x (NP's tightest; segment.COLOUR_NEAR): one blob in W;
    # R-only beside G-only is two blobs in the colour channels, R beside R is not.
    r, g = np.array(colours), 1.0 - np.array(colours)
    table = NeuronTable([[10.0, 10.0, 6.0], np.add([10.0, 10.0, 6.0], offset)],
                        colours={"R": r, "G": g, "B": np.zeros(2), "W": np.array([-1.0, 1.0])})
    stack, truth = render_stack(table, seed=0, align=False, shape_zyx=(16, 80, 100), gut=False, brightness_sd=0.0,
                                nucleus_radius_sd_um=0.0, nucleus_radius_um=radius, texture=0.0, min_spacing_um=1.0)
    assert len(segment_stack(stack, colour_split=False)) == 1
    found = segment_stack(stack)
    assert len(found) == expected
    assert score_detections(truth.xyz, found.xyz)["tp"] == expected


@pytest.mark.parametrize("radius, diameter", [(1.8, 3.0), (2.2, 4.5)])
def test_a_large_elongated_nucleus_is_one(radius, diameter):
    table = NeuronTable([[12.0, 10.0, 6.0]])
    for seed in range(3):
        stack, truth = render_stack(
            table, seed=seed, align=False, shape_zyx=(12, 80, 100), gut=False, nucleus_radius_um=radius,
            nucleus_radius_sd_um=0.0, elongation_sd=0.25,
        )
        found = segment_stack(stack, diameter_um=diameter)
        assert len(found) == 1
        assert np.linalg.norm(found.xyz[0] - truth.xyz[0]) < 0.5


def test_pure_noise_gives_almost_nothing():
    rng = np.random.default_rng(0)
    data = (100 + rng.poisson(30, (1, 16, 96, 96))).astype(np.uint16)
    found = segment_stack(Stack(data, (1.0, 0.25, 0.25), ["W"]))
    assert len(found) <= 1


def test_without_w_the_sum_is_used(rendered, capsys):
    stack, truth = rendered
    no_w = Stack(stack.data[:3], stack.voxel_size_zyx, ["R", "G", "B"])
    found = segment_stack(no_w)
    assert "no W" in capsys.readouterr().err
    assert set(found.colours) == {"R", "G", "B"}
    assert score_detections(truth.xyz, found.xyz)["f1"] >= 0.8
    unknown = Stack(stack.data, stack.voxel_size_zyx, [None] * 4)
    found = segment_stack(unknown)
    assert "writing no colours" in capsys.readouterr().err
    assert found.colours == {} and len(found) > 0.8 * len(truth)


def test_a_recording_is_segmented_one_time_point_at_a_time(rendered, capsys):
    stack, truth = rendered
    roles = ["R", "G", "B", None]  # no W: the warning comes once for the whole recording
    series = StackSeries(np.stack([stack.data, stack.data[:, :, :, ::-1]]), stack.voxel_size_zyx, roles)
    seen = []
    tables = segment_series(series, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(1, 2), (2, 2)]
    assert capsys.readouterr().err.count("no W") == 1
    alone = segment_stack(Stack(stack.data, stack.voxel_size_zyx, roles))
    np.testing.assert_allclose(tables[0].xyz, alone.xyz)
    np.testing.assert_allclose(tables[0].colours["R"], alone.colours["R"])
    # the second time point is the first mirrored in x: the same nuclei, mirrored
    width = (stack.shape_zyx[2] - 1) * stack.voxel_size_zyx[2]
    mirrored = tables[1].xyz * [-1, 1, 1] + [width, 0, 0]
    assert score_detections(tables[0].xyz, mirrored, 0.5)["f1"] >= 0.97


def test_cli_segment_a_recording_writes_a_t_column(tmp_path, recording, capsys):
    path, truths, _ = recording
    out = tmp_path / "neurons.csv"
    assert main(["segment", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "segmented 3/3 time points" in err and "in 3 time points" in err
    sequence = split_by_time(read_table(out))
    assert sequence.times == [0, 1, 2]
    for volume, truth in zip(sequence.volumes, truths):
        assert score_detections(truth.xyz, volume.xyz)["f1"] >= 0.9
        assert set(volume.colours) == {"R", "G", "B", "W"}


def test_progress_is_reported(rendered):
    seen = []
    segment_stack(rendered[0], progress=lambda f, m: seen.append((f, m)))
    fractions = [f for f, _ in seen]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0 and fractions == sorted(fractions)
    assert "nuclei" in seen[-1][1]


def test_measure_colours_background_and_gfp():
    data = np.full((2, 9, 40, 40), 100, np.uint16)
    data[:, 3:6, 15:25, 15:25] += np.array([50, 400], np.uint16)[:, None, None, None]
    stack = Stack(data, (1.0, 0.25, 0.25), ["W", "GFP"])
    values = measure_colours(stack, [[5.0, 5.0, 4.0]], radius_um=0.8)
    assert values["GFP"][0] == pytest.approx(400)  # background-subtracted counts
    assert values["W"][0] == 0.0  # one neuron: z-score 0


def test_w_bleed_slopes_find_the_pan_neuronal_share():
    """Most neurons lack a colour: the lower envelope of R against W is the bleed (0.1 here),
    whatever the on-neurons do; B is never unmixed; too few neurons estimate nothing."""
    from napari_fdlc.segment import w_bleed_slopes

    rng = np.random.default_rng(0)
    w = 300 * rng.lognormal(0.0, 0.35, 200)
    on = rng.random(200) < 0.4
    r = np.where(on, rng.uniform(100, 300, 200), rng.uniform(5, 20, 200)) + 0.1 * w
    g = np.where(rng.random(200) < 0.5, rng.uniform(100, 300, 200), rng.uniform(5, 20, 200))
    slopes = w_bleed_slopes({"W": w, "R": r, "G": g, "B": r})
    assert slopes["R"] == pytest.approx(0.1, abs=0.02)
    assert slopes["G"] < 0.02
    assert "B" not in slopes
    assert w_bleed_slopes({"W": w[:10], "R": r[:10]}) == {"R": 0.0}


def test_unmixed_colours_follow_the_rendered_colours_better(rendered):
    stack, truth = rendered
    rho = {}
    for unmix in (False, True):
        values = measure_colours(stack, truth.xyz, radius_um=0.9, unmix=unmix)
        rho[unmix] = spearmanr(values["R"], truth.extra["R_int"])[0]
    assert rho[True] > rho[False] + 0.01, rho


def test_bad_diameter():
    with pytest.raises(FdlcError):
        detect_nuclei(np.zeros((4, 8, 8)), (1, 1, 1), diameter_um=0)


def test_score_detections():
    truth = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0]])
    found = np.array([[0.3, 0, 0], [10, 1.4, 0], [30, 0, 0], [0.1, 0.1, 0]])
    s = score_detections(truth, found, max_distance_um=1.5)
    assert s["tp"] == 2 and s["precision"] == 0.5 and s["recall"] == pytest.approx(2 / 3)
    assert s["median_error_um"] == pytest.approx(np.median([np.hypot(0.1, 0.1), 1.4]))
    assert score_detections(truth, np.zeros((0, 3)))["f1"] == 0.0


# ----- the bundled sample ---------------------------------------------------------------------


def test_bundled_sample():
    from napari_fdlc.sample import load_sample, sample_paths

    stack_path, _ = sample_paths()
    if not stack_path.exists():
        pytest.skip("sample not generated yet (python -m napari_fdlc.sample)")
    assert stack_path.stat().st_size < 6e6
    stack, truth = load_sample()
    assert stack.channel_roles == ["R", "G", "B", "W"] and len(truth) > 100
    s = score_detections(truth.xyz, segment_stack(stack).xyz)
    assert s["f1"] >= 0.9, s


# ----- fdlc segment ---------------------------------------------------------------------------


def test_cli_segment_reports_progress_on_a_long_stack_unless_quiet(tmp_path, rendered, capsys, monkeypatch):
    """A stack above _LONG_VOXELS prints its steps with percentages; --quiet prints none."""
    import napari_fdlc._cli_segment as cli_segment

    monkeypatch.setattr(cli_segment, "_LONG_VOXELS", 1)
    path = tmp_path / "worm.ome.tif"
    write_tiff(path, rendered[0])
    assert main(["segment", str(path), "--out", str(tmp_path / "a.csv")]) == 0
    assert "100% " in capsys.readouterr().err
    assert main(["segment", str(path), "--quiet", "--out", str(tmp_path / "b.csv")]) == 0
    assert "%" not in capsys.readouterr().err


def test_cli_segment_writes_a_table(tmp_path, rendered, capsys):
    stack, truth = rendered
    path = tmp_path / "worm.ome.tif"
    write_tiff(path, stack)
    out = tmp_path / "out" / "neurons.csv"
    assert main(["segment", str(path), "--out", str(out)]) == 0
    table = read_table(out)
    assert score_detections(truth.xyz, table.xyz)["f1"] >= 0.9
    assert set(table.colours) == {"R", "G", "B", "W"}
    assert "nuclei" in capsys.readouterr().err
    # --no-unmix keeps W's bleed-through: same nuclei, same B and W, other R and G.
    raw = tmp_path / "raw.csv"
    assert main(["segment", str(path), "--no-unmix", "--quiet", "--out", str(raw)]) == 0
    kept = read_table(raw)
    np.testing.assert_allclose(kept.xyz, table.xyz)
    np.testing.assert_allclose(kept.colours["B"], table.colours["B"])
    assert not np.allclose(kept.colours["R"], table.colours["R"])
    # --no-colour-split: W's own detections only, which come first in the default table.
    assert main(["segment", str(path), "--no-colour-split", "--quiet", "--out", str(raw)]) == 0
    w_only = read_table(raw)
    assert 0 < len(w_only) <= len(table)
    np.testing.assert_allclose(w_only.xyz, table.xyz[: len(w_only)])
    # Roles and voxel size from the command line win over the file.
    assert main(["segment", str(path), "--voxel-size", "2", "0.5", "0.5", "--channels", "-", "-", "B", "W",
                 "--diameter-um", "3", "--quiet", "--out", str(out)]) == 0
    table = read_table(out)
    assert set(table.colours) == {"B", "W"}
    assert table.xyz[:, 2].max() > truth.xyz[:, 2].max() * 1.5  # z scaled by the new voxel size
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "args, words",
    [
        (["BAD"], "TIFF"),
        (["GOOD", "--channels", "R", "G"], "channel role"),
        (["GOOD", "--diameter-um", "-1"], "diameter"),
        (["MISSING"], "no such file"),
    ],
)
def test_cli_segment_bad_input(tmp_path, rendered, capsys, args, words):
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00" + b"\xff" * 40)
    good = tmp_path / "good.ome.tif"
    write_tiff(good, Stack(rendered[0].data[:, :6, :40, :40], (1, 0.25, 0.25), ["R", "G", "B", "W"]))
    files = {"BAD": str(bad), "GOOD": str(good), "MISSING": str(tmp_path / "missing.tif")}
    out = tmp_path / "neurons.csv"
    argv = ["segment"] + [files.get(a, a) for a in args] + ["--out", str(out)]
    assert main(argv) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fdlc: error:") and words in err[0], err
    assert not out.exists()


def test_positions_and_roles_given_in_memory_are_checked_as_a_file_s_are(tmp_path):
    """measure_colours(stack, xyz.T) read 30 colours at scrambled places; Stack(..., ['R', 'G',
    'W', 'W']) was accepted (detection on one W, colours of the other; read_stack refuses it);
    and a stack's roles written with write_tiff came back as None unless its channel names said
    them (now written as the OME channels' fluorophores)."""
    stack, truth = render_stack(random_worm(30, seed=3), seed=1, gut=False)
    with pytest.raises(FdlcError, match="transpose"):
        measure_colours(stack, truth.xyz.T.copy())
    with pytest.raises(FdlcError, match="W given more than once"):
        Stack(stack.data, stack.voxel_size_zyx, ["R", "G", "W", "W"])
    from napari_fdlc.io.images import read_stack

    write_tiff(tmp_path / "s.ome.tif", Stack(stack.data, stack.voxel_size_zyx, ["R", "G", "B", "W"], channel_names=["ch0", "ch1", "ch2", "ch3"]))
    back = read_stack(tmp_path / "s.ome.tif")
    assert back.channel_roles == ["R", "G", "B", "W"] and back.channel_names == ["ch0", "ch1", "ch2", "ch3"]
