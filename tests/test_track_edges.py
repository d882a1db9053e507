"""fdlc track at its edges: the baselines' confidences, colour in some volumes only, time
values of every kind, empty volumes, options refused before any work. These came from a review
of the tracking feature (session 26); each says what used to happen."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.table import NeuronTable, write_table
import napari_fdlc.track as track_module
from napari_fdlc.track import (SequenceParams, TrackResult, TrackSettings, join_by_time, simulate_sequence, track,
                                 tracking_accuracy)
import re
from pathlib import Path
from napari_fdlc.reference import generate_worm

GENTLE = SequenceParams(frames=4, bend_curvature=0.002, roll=0.05, xy_rotation=0.3, drift_um=4.0,
                        drop_fraction=(0.0, 0.05), max_spurious=4, jitter_um=0.2)


@pytest.fixture(scope="module")
def gentle(worm):
    return simulate_sequence(worm, 3, GENTLE)


@pytest.fixture(scope="module")
def identifier(untrained_weights):
    from napari_fdlc.identify import Identifier

    return Identifier.load(untrained_weights, device="cpu")


def _sequence_csv(volumes, path, times=None):
    write_table(join_by_time(volumes, times).drop(columns=["label"]), path)
    return path


def test_geometry_method_untracked_conf_is_the_probability_of_untracked(tmp_path, gentle):
    """docs/tracking.md: track_conf is the probability of the track given, "of 'untracked'
    when -1". The geometric chain is certain either way: 1 (untracked neurons used to get 0,
    'certainly not untracked')."""
    volumes, origins = gentle
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out)
    untracked = df[df["track_id"] == -1]
    assert len(untracked) > 0  # spurious detections are left untracked
    assert (untracked["track_conf"] > 0.5).all(), untracked["track_conf"].unique()


def test_chunk_does_not_change_the_answers_when_the_first_volume_lacks_colour(tmp_path, worm, gentle, untrained_weights):
    """docs/tracking.md: `--chunk N` does not change the answers with the default placement,
    also when the first file of a folder has no colour columns and the others have R, G, B
    (whether colour was used used to be decided per chunk, from its first volume)."""
    volumes, _ = gentle
    folder = tmp_path / "vols"
    write_table(NeuronTable(volumes[0].xyz), folder / "t0.csv")  # positions only
    for k in range(1, len(volumes)):
        write_table(volumes[k], folder / f"t{k}.csv")
    ref = tmp_path / "ref.csv"
    write_table(worm, ref)
    outs = {}
    for chunk in ("1", "16"):
        out = tmp_path / f"chunk{chunk}.csv"
        assert main(["track", str(folder), "--reference", str(ref), "--weights", str(untrained_weights),
                     "--chunk", chunk, "--quiet", "--out", str(out)]) == 0
        outs[chunk] = pd.read_csv(out, keep_default_na=False)
    assert (outs["1"]["track_id"] == outs["16"]["track_id"]).all()
    assert np.allclose(outs["1"]["track_conf"], outs["16"]["track_conf"], atol=1e-3), \
        np.abs(outs["1"]["track_conf"] - outs["16"]["track_conf"]).max()


def test_unknown_reference_t_is_refused_before_segmenting_a_recording(tmp_path, recording, capsys):
    """docs/tracking.md: bad input is refused before any work: a --reference-t that the image
    recording does not have is refused before it is segmented (it used to be after)."""
    path, _, _ = recording
    out = tmp_path / "tracks.csv"
    code = main(["track", str(path), "--reference-t", "7", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "time points 0 to 2" in err
    assert "segmented" not in err, err


def test_distinct_integer_time_points_stay_distinct_volumes(tmp_path, gentle):
    """docs/tracking.md: t is any numbers, and the output's t is the input's. Integer time
    stamps above 2**53 (nanosecond clocks) stay distinct volumes with their exact t (they used
    to be parsed as float64 and collapse into one volume)."""
    volumes, _ = gentle
    times = [1_700_000_000_000_000_000 + k for k in range(3)]
    src = _sequence_csv(volumes[:3], tmp_path / "seq.csv", times)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out, dtype={"t": str})
    assert list(df["t"].unique()) == [str(t) for t in times]
    assert df.groupby("t", sort=False).size().tolist() == [len(v) for v in volumes[:3]]


def test_an_empty_first_volume_is_not_an_unexpected_crash(gentle, worm, identifier):
    """A volume with no neuron gets no rows, also when it is the first (or with
    search="full"): the first volume with neurons is searched instead (the registration used to
    fail with an IndexError)."""
    volumes, _ = gentle
    empty = volumes[0].subset(np.arange(0))
    try:
        result = track([empty, *volumes[1:]], references=[worm], identifier=identifier,
                       settings=TrackSettings(use_colour=False))
    except FdlcError:
        return  # refused in one line: fine
    assert len(result.track_id[0]) == 0
    assert all((t >= 0).mean() > 0.8 for t in result.track_id[1:])


def test_model_options_ignored_by_a_baseline_say_so(tmp_path, gentle, capsys):
    """--chirality (or --weights) with --method geometry: tracked, and one warning line says
    the option is ignored (it used to be ignored silently)."""
    volumes, _ = gentle
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--chirality", "same", "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fdlc: warning: --chirality: for the fdlc method; ignored with --method geometry"]


@pytest.mark.parametrize("method", ["fdlc", "geometry"])
def test_an_unsure_reference_name_keeps_its_question_mark(tmp_path, gentle, worm, method, untrained_weights):
    """A labelled reference with an unsure name (AVAL?): the tracks carry it as written, "?"
    included (it used to lose the "?")."""
    volumes, origins = gentle
    names = np.array([worm.labels[o] if o >= 0 else "" for o in origins[0]], dtype=object)
    named = int(np.flatnonzero(names != "")[0])
    conf = np.where(names != "", 1.0, 0.0)
    conf[named] = 0.5
    ref = tmp_path / "ref.csv"
    write_table(NeuronTable(volumes[0].xyz, volumes[0].colours, names, label_conf=conf), ref)
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    weights = ["--weights", str(untrained_weights)] if method == "fdlc" else []
    assert main(["track", str(src), "--reference", str(ref), "--method", method, *weights, "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out, keep_default_na=False)
    assert f"{names[named]}?" in set(df["name"]) and names[named] not in set(df["name"])


def test_a_sequence_labelled_at_every_time_point_keeps_its_names(tmp_path, gentle, worm, capsys):
    """One CSV with a t column, each time point labelled (a name once per time point): the
    reference taken from it keeps its names (every name used to be dropped as a duplicate of
    the whole file's)."""
    volumes, origins = gentle
    labelled = [NeuronTable(v.xyz, v.colours, np.array([worm.labels[o] if o >= 0 else "" for o in orig], dtype=object))
                for v, orig in zip(volumes, origins)]
    src = tmp_path / "seq.csv"
    write_table(join_by_time(labelled), src)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    assert "more than once" not in capsys.readouterr().err
    df = pd.read_csv(out, keep_default_na=False)
    first = df[df["t"] == 0]
    assert (first["name"].to_numpy() == labelled[0].labels).all() and (first["name"] != "").sum() > 50


# ----- session 30's review of fdlc track's inputs and output ---------------------------------------

def _write_exact(volumes, times, path):
    """A sequence CSV whose t cells are exactly the text given (pandas, not write_table: the
    input must hold the times as the user's own tool wrote them)."""
    join_by_time(volumes, times).drop(columns=["label"]).to_csv(path, index=False)
    return path


def test_fractional_time_stamps_are_written_back_as_given(tmp_path, gentle):
    """Time stamps in seconds come back as given (tracking.md: the input's t); written with 6
    significant digits, 1700000000.0, .2 and .4 all came out as 1.7e+09, one time point."""
    volumes, _ = gentle
    times = ["1700000000.0", "1700000000.2", "1700000000.4", "1700000000.6"]
    src = _write_exact(volumes, times, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out, dtype={"t": str})
    written = [float(t) for t in df["t"].unique()]
    assert written == [float(t) for t in times], df["t"].unique()
    assert df.groupby("t", sort=False).size().tolist() == [len(v) for v in volumes]


def test_a_bad_t_cell_is_reported_on_its_own_line_of_the_file(tmp_path, capsys):
    """A bad t cell is reported at its own line of the file, as a bad coordinate is; after a
    blank line it was reported one line early."""
    src = tmp_path / "seq.csv"
    src.write_text("t,x_um,y_um,z_um\n0,1,2,3\n0,4,5,6\n\n1,1,2,3\n,4,5,6\n")
    out = tmp_path / "tracks.csv"
    code = main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "line 6, column 't'" in err, err
    assert not out.exists()


def test_bad_weights_are_refused_before_a_recording_is_segmented(tmp_path, recording, capsys):
    """Weights that cannot be read are refused before a recording is segmented, not after every
    time point of it."""
    path, _, _ = recording
    out = tmp_path / "tracks.csv"
    code = main(["track", str(path), "--weights", str(tmp_path / "no_such_model"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "no_such_model" in err, err
    assert "segmented" not in err, err


def test_a_repeated_name_in_a_long_labelled_sequence_is_one_warning(tmp_path, worm, capsys):
    """A name repeated within the time points of a labelled sequence is one warning line (cli.md),
    not one per time point."""
    volumes, origins = simulate_sequence(worm, 3, SequenceParams(**{**GENTLE.__dict__, "frames": 6}))
    labelled = []
    for v, origin in zip(volumes, origins):
        names = np.array([worm.labels[o] if o >= 0 else "X" for o in origin], dtype=object)
        names[:2] = "X"  # at least two placeholders in every volume
        labelled.append(NeuronTable(v.xyz, v.colours, names))
    src = tmp_path / "seq.csv"
    join_by_time(labelled).to_csv(src, index=False)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    repeated = [line for line in capsys.readouterr().err.splitlines() if "more than once" in line]
    assert len(repeated) <= 1, repeated


# Session 32 (a helper review of fdlc track)


@pytest.mark.parametrize("flag", ["--weights", "--tracking-weights"])
def test_track_out_onto_its_own_model_is_refused(tmp_path, gentle, untrained_weights, capsys, flag):
    """--out typed onto the model's own JSON: the tracks replaced it (the model no longer
    loaded), as fdlc evaluate already refused. Now refused before any work."""
    import shutil
    from pathlib import Path

    model = tmp_path / "m"
    for suffix in (".safetensors", ".json"):
        shutil.copy(Path(untrained_weights).with_suffix(suffix), model.with_suffix(suffix))
    before = model.with_suffix(".json").read_bytes()
    models = ["--weights", model] if flag == "--weights" else ["--weights", untrained_weights, "--tracking-weights", model]
    seq = _sequence_csv(gentle[0], tmp_path / "seq.csv")
    assert main([str(a) for a in ("track", seq, *models, "--quiet", "--out", model.with_suffix(".json"))]) == 2
    assert "would replace an input" in capsys.readouterr().err
    assert model.with_suffix(".json").read_bytes() == before


def test_track_weights_of_four_colour_channels_are_one_line(tmp_path, gentle, untrained_weights, capsys):
    """A model JSON with "colour_channels": 4 loaded, then died in its first pass with a
    RuntimeError traceback (only R, G, B are fed). Now refused when loaded."""
    import json
    import shutil
    from pathlib import Path

    model = tmp_path / "c4"
    shutil.copy(Path(untrained_weights).with_suffix(".safetensors"), model.with_suffix(".safetensors"))
    meta = json.loads(Path(untrained_weights).with_suffix(".json").read_text())
    meta["config"]["colour_channels"] = 4
    model.with_suffix(".json").write_text(json.dumps(meta))
    seq = _sequence_csv(gentle[0], tmp_path / "seq.csv")
    assert main([str(a) for a in ("track", seq, "--weights", model, "--quiet", "--out", tmp_path / "t.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "colour_channels" in err[0], err
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.parametrize("method", ["geometry", "cpd"])
def test_baselines_refuse_a_second_reference(gentle, worm, method):
    """track(references=[a, b], method=geometry|cpd) used a alone: b's names were lost, silently
    (the CLI refused it already)."""
    with pytest.raises(FdlcError, match="one reference"):
        track(gentle[0], references=[NeuronTable(worm.xyz, worm.colours), worm], method=method)


def test_join_by_time_and_track_settings_refuse_what_they_would_misread(worm, gentle):
    """join_by_time with fewer times than volumes dropped the volumes beyond them; a chunk of 2.5
    or 1.5 refinement steps passed the check and died in range() after the reference search."""
    volumes = [worm.subset(np.arange(10)), worm.subset(np.arange(10, 20)), worm.subset(np.arange(20, 30))]
    with pytest.raises(FdlcError, match="2 times for 3 volumes"):
        join_by_time(volumes, times=[0, 1])
    for bad in ({"chunk": 2.5}, {"refine_steps": 1.5}):
        with pytest.raises(FdlcError, match="whole number"):
            track(gentle[0], settings=TrackSettings(**bad))
    # NaN was ignored and a negative warp width changed the tracks, silently
    for bad in ({"lost_fraction": float("nan")}, {"warp_sigma_um": -5.0}, {"gate_um": -1.0}, {"position_sigma_um": float("nan")}):
        with pytest.raises(FdlcError, match=next(iter(bad))):
            track(gentle[0], settings=TrackSettings(**bad))


# ----- session 33's review of tracking -----------------------------------------------------------


def _per_volume(result, origins, reference_origin):
    return [tracking_accuracy(TrackResult([result.track_id[k]], [], [], []), [origins[k]], reference_origin,
                              reference_t=None)["accuracy"] for k in range(len(origins))]


def _count_full_searches(monkeypatch):
    calls = []
    original = track_module._full_search

    def counting(identifier, ref, volumes, s):
        calls.append(len(volumes))
        return original(identifier, ref, volumes, s)

    monkeypatch.setattr(track_module, "_full_search", counting)
    return calls


def test_a_reference_with_fewer_neurons_is_no_jump_on_every_volume(worm, identifier, monkeypatch):
    """A reference of 40 % of the neurons (the named ones only) on a gently moving worm: one
    full search. Every volume was 'lost' (paired neurons counted against all of the volume's,
    which cannot reach lost_fraction then) and searched in full."""
    volumes, origins = simulate_sequence(worm, 3, GENTLE)
    keep = np.sort(np.random.default_rng(0).choice(len(volumes[0]), int(0.4 * len(volumes[0])), replace=False))
    reference = volumes[0].subset(keep)
    calls = _count_full_searches(monkeypatch)
    track(volumes, [reference], identifier=identifier, settings=TrackSettings(use_colour=False))
    assert sum(calls) <= 1, f"{sum(calls)} volumes searched in full for {len(volumes)} volumes without a jump"


def test_a_second_reference_does_not_untrack_what_it_lacks(worm, shipped):
    """With two references (--reference-t 0 --reference-t 8), a volume answered by the second
    keeps the IDs the first gives the neurons the second lacks: each volume took one
    reference's answer whole, and every neuron that reference lacked lost its track there
    (tracks flickered between their ID and -1). The reference a volume takes is still chosen
    by match rate: 97.1 % here against 99.4 % with the first alone (left as it is)."""
    volumes, origins = simulate_sequence(worm, 7, SequenceParams(frames=12))
    settings = TrackSettings(use_colour=False)
    two = track(volumes, [volumes[0], volumes[8]], identifier=shipped, settings=settings)
    in_first = [np.isin(o, origins[0][origins[0] >= 0]) & (o >= 0) for o in origins]
    untracked = np.mean(np.concatenate([t[m] == -1 for t, m in zip(two.track_id, in_first)]))
    assert untracked < 0.02, (untracked, [i["reference"] for i in two.info])  # 4.6 % before


def test_neurons_that_appear_later_do_not_send_volumes_to_the_full_search(worm, shipped, monkeypatch):
    """A first volume (the reference) lacking 40 % of the neurons later volumes show: tracked
    about as well as the geometric chain alone. The extra neurons pulled the match rate below
    half the first volume's (every volume 'a jump', searched in full), and the full search won
    by a rate of the identification model compared with the tracking model's (89 %)."""
    volumes, origins = simulate_sequence(worm, 5, SequenceParams(frames=10))
    keep = np.sort(np.random.default_rng(0).choice(len(volumes[0]), int(0.6 * len(volumes[0])), replace=False))
    volumes = [volumes[0].subset(keep)] + volumes[1:]
    origins = [origins[0][keep]] + origins[1:]
    geometry = tracking_accuracy(track(volumes, method="geometry"), origins, origins[0])["accuracy"]
    calls = _count_full_searches(monkeypatch)
    result = track(volumes, identifier=shipped, settings=TrackSettings(use_colour=False))
    score = tracking_accuracy(result, origins, origins[0])["accuracy"]
    assert score >= min(0.95, geometry - 0.01), (score, geometry, f"{sum(calls)} full searches")


def _two_jumps(worm):
    params = SequenceParams(frames=10, bend_curvature=0.002, roll=0.05, xy_rotation=0.3, drift_um=4.0,
                            drop_fraction=(0.0, 0.05), max_spurious=4, jitter_um=0.2)
    volumes, origins = simulate_sequence(worm, 3, params)
    turned = [v if k < 3 else NeuronTable(2 * v.xyz.mean(0) * [1, 1, 0] + v.xyz * [-1, -1, 1], dict(v.colours))
              for k, v in enumerate(volumes)]  # a 180° turn in XY at t = 3 (the chain still pairs it)
    shifted = [v if k < 6 else NeuronTable(v.xyz + [30, 0, 0], dict(v.colours)) for k, v in enumerate(turned)]
    return shifted, origins  # and a 30 µm shift at t = 6 (the chain loses it)


def test_chunk_does_not_change_the_answers_after_two_jumps_in_one_chunk(worm, shipped):
    """Two jumps in one chunk (a 180° turn at t=3 caught by the match rate, a 30 µm shift at t=6
    caught by the chain): the same tracks with chunk 1 and 16. The turn's re-search re-chained
    the rest of the chunk without the lost test: volume 6 tracked 0 % with chunk 16."""
    volumes, origins = _two_jumps(worm)
    results = {chunk: track(volumes, identifier=shipped, settings=TrackSettings(chunk=chunk)) for chunk in (1, 16)}
    per = {chunk: np.round(_per_volume(r, origins, origins[0]), 2).tolist() for chunk, r in results.items()}
    assert min(per[16]) >= 0.9, per
    assert all(np.array_equal(a, b) for a, b in zip(results[1].track_id, results[16].track_id)), per


def _turned_about_z(volume, degrees):
    a, centre = np.radians(degrees), volume.xyz.mean(0)
    about_z = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return NeuronTable((volume.xyz - centre) @ about_z.T + centre, dict(volume.colours))


@pytest.mark.parametrize("jump", ["turn 45°", "shift 10 µm"])
def test_a_jump_the_chain_pairs_a_neighbour_off_is_searched_again(worm, shipped, jump):
    """A 45° turn about z or a 10 µm shift between two volumes: the chain paired most neurons
    with a neighbour about 3 µm off (its residual was 0.4 µm before) and the match rate stayed
    above half the first volume's, so neither test saw the jump: after the turn every volume
    was tracked about 10 % right to the end (the shift, 40-60 % for a few volumes). The
    chain's residual, far above its recent median, now sends the volume to the full search."""
    volumes, origins = simulate_sequence(worm, 3, replace(GENTLE, frames=8))
    moved = {"turn 45°": lambda v: _turned_about_z(v, 45), "shift 10 µm": lambda v: NeuronTable(v.xyz + [10, 0, 0], dict(v.colours))}
    volumes = [v if k < 4 else moved[jump](v) for k, v in enumerate(volumes)]
    for chunk in (1, 16):
        result = track(volumes, identifier=shipped, settings=TrackSettings(use_colour=False, chunk=chunk))
        assert result.info[4]["searched"] == [True], chunk
        assert min(_per_volume(result, origins, origins[0])[4:]) >= 0.9, chunk


def test_residual_ratio_is_checked():
    """TrackSettings.residual_ratio below 1 would call every volume a jump: refused."""
    with pytest.raises(FdlcError, match="residual_ratio"):
        TrackSettings(residual_ratio=0.5).check()


def test_cpd_tracks_a_recording_with_one_nearly_empty_time_point(tmp_path, worm, capsys):
    """A time point with 2 nuclei (out of focus) is left untracked by --method cpd and
    geometry, the rest tracked: the whole cpd run was refused at it."""
    volumes, _ = simulate_sequence(worm, 3, GENTLE)
    folder = tmp_path / "vols"
    for k, v in enumerate(volumes):
        write_table(v.subset(np.arange(2)) if k == 3 else v, folder / f"t{k}.csv")
    for method in ("geometry", "cpd"):
        out = tmp_path / f"{method}.csv"
        code = main(["track", str(folder), "--method", method, "--quiet", "--out", str(out)])
        assert code == 0, (method, capsys.readouterr().err.strip())
        df = pd.read_csv(out)
        assert (df["t"] == 3).sum() == 2


def test_the_first_reference_given_is_the_first_reference(tmp_path, gentle, untrained_weights):
    """docs/tracking.md: "Track IDs are the row indices of the first reference" (and "the first
    one's names win"). `--reference-t 0 --reference R.csv` names t=0 first, so at t=0 every
    neuron's track ID is its own row. Instead _cli_track.run always puts every --reference
    file before every --reference-t (two separate argparse lists, the order typed is lost):
    the IDs are R.csv's rows (here R.csv is t=0 in reverse order: every ID at t=0 is reversed)."""
    volumes, _ = gentle
    volumes = volumes[:2]
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    reversed_t0 = tmp_path / "reversed_t0.csv"
    write_table(NeuronTable(volumes[0].xyz[::-1].copy()), reversed_t0)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--reference-t", "0", "--reference", str(reversed_t0),
                 "--weights", str(untrained_weights), "--no-color", "--threads", "1", "--quiet", "--out", str(out)]) == 0
    first = pd.read_csv(out).query("t == 0")
    same_row = (first["track_id"] == first["neuron_index"]).mean()
    assert same_row >= 0.95, f"{same_row:.0%} of t=0's neurons got their own row as track ID"


def test_a_reference_that_is_the_first_volume_is_warned_of_once(tmp_path, gentle, capsys):
    """docs/tracking.md: "A first volume or reference whose neurons cannot be in µm gets a
    one-line warning." With `--reference-t 0` the reference is the first volume itself, yet
    _cli_track.run passes it to warn_implausible_scales twice ([seq.volumes[0], *references]):
    the same warning line is printed twice."""
    volumes, _ = gentle
    pixels = [NeuronTable(v.xyz * [4, 4, 1]) for v in volumes]  # pixel coordinates, not µm
    src = _sequence_csv(pixels, tmp_path / "px.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--reference-t", "0", "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "must be micrometres" in line]
    assert len(lines) == 1, lines


DOCS = Path(__file__).resolve().parents[1] / "docs" / "tracking.md"




GENTLE_8 = replace(GENTLE, frames=8)


SEQUENCES = {"gentle": (3, GENTLE_8), "default": (0, SequenceParams(frames=8))}


JUMPS = {"turn 45°": lambda v: _turned_about_z(v, 45), "shift 20 µm": lambda v: NeuronTable(v.xyz + [20, 0, 0], dict(v.colours))}


@pytest.mark.parametrize("jump, at, motion", [("turn 45°", 1, "gentle"), ("turn 45°", 2, "gentle"), ("turn 45°", 1, "default"),
                                             ("turn 45°", 3, "default"), ("shift 20 µm", 3, "default")])
def test_a_jump_in_the_first_chained_volumes_is_searched_again(worm, shipped, jump, at, motion):
    """docs/tracking.md step 2: a volume whose pairs lie more than twice as far apart as usual
    has jumped and gets the full search (a 45° turn about z, a 10-20 µm shift). The residual
    test needs 3 earlier chained volumes (RESIDUAL_HISTORY; the docs do not say so), so a jump
    at t = 1, 2 or 3 is never seen. A 45° turn at t = 1 or 2 of a gently moving worm: every later
    volume tracked about 5 % right to the end (the chain goes on at the wrong placement, whose
    ~3 µm residuals then become the yardstick); of the default motion: 7-80 % for 4 volumes. At
    t = 3 the jumped volume itself is tracked 0-16 % right (a 45° turn, a 20 µm shift; after the
    turn the next volumes 53-77 %)."""
    seed, params = SEQUENCES[motion]
    volumes, origins = simulate_sequence(worm, seed, params)
    volumes = [v if k < at else JUMPS[jump](v) for k, v in enumerate(volumes)]
    result = track(volumes, identifier=shipped, settings=TrackSettings(use_colour=False))
    per = np.round(_per_volume(result, origins, origins[0]), 2)
    assert min(per[at:]) >= 0.9, (per.tolist(), [i["searched"] for i in result.info])


def test_the_sudden_moves_section_the_docs_point_to_exists():
    """docs/tracking.md step 2 ends "Measured below ("Sudden moves")": the measurement of the
    session-34 jump handling. No such section (or any other mention of "Sudden moves") is in
    the file: the claimed measurement is nowhere."""
    text = DOCS.read_text(encoding="utf-8")
    assert "Sudden moves" in text  # the pointer is there
    headings = [line for line in text.splitlines() if re.match(r"#+\s.*sudden moves", line, re.I)]
    assert headings, "docs/tracking.md points to a section 'Sudden moves' that it does not have"


def test_residual_ratio_range_in_the_message_is_what_is_accepted():
    """TrackSettings.check refuses residual_ratio=inf (the natural 'never a jump by residual')
    with "residual_ratio must be a number from 1 to inf (got inf)": the message names inf as
    allowed. Either inf is accepted or the message must not say the range reaches it."""
    try:
        TrackSettings(residual_ratio=float("inf")).check()
    except FdlcError as error:
        assert "to inf" not in str(error), str(error)


QUIET = SequenceParams(frames=3, bend_curvature=0.002, roll=0.05, xy_rotation=0.2, drift_um=2.0,
                        drop_fraction=(0.0, 0.0), max_spurious=0, jitter_um=0.1)


@pytest.fixture(scope="module")
def small_worm():
    """30 neighbouring neurons of a generated worm (a small, quick recording)."""
    worm = generate_worm(seed=1)
    return worm.subset(np.sort(np.argsort(worm.xyz[:, 0])[:30]))


@pytest.mark.parametrize("option", [["--voxel-size", "2", "0.5", "0.5"], ["--diameter-um", "5"],
                                    ["--channels", "R", "G", "B", "W"], ["--axes", "TZCYX"]],
                         ids=["voxel-size", "diameter-um", "channels", "axes"])
def test_image_options_on_a_table_sequence_are_not_ignored_silently(tmp_path, small_worm, capsys, option):
    """`fdlc track` takes the `fdlc segment` options for an image recording. Given with a table
    sequence (a CSV with a t column), where they cannot apply, they should be refused or said to
    be ignored in one line, as the model options ignored by --method cpd/geometry are
    (tests/test_track_edges.py::test_model_options_ignored_by_a_baseline_say_so): a user whose
    CSV is in pixels and who adds `--voxel-size` expects µm. Instead _cli_track.run drops them
    without a word (the output is byte-identical to a run without them, exit 0, stderr empty)."""
    volumes, _ = simulate_sequence(small_worm, 1, QUIET)
    src = tmp_path / "seq.csv"
    write_table(join_by_time(volumes).drop(columns=["label"]), src)
    out = tmp_path / "tracks.csv"
    code = main(["track", str(src), "--method", "geometry", "--quiet", *option, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 or option[0] in err, (code, err)


def test_a_reference_t_left_out_of_a_recording_is_said_so(tmp_path, small_worm, capsys):
    """`fdlc track rec.ome.tif --reference-t 1` where time point 1 holds no nucleus (left out):
    one line saying so, exit 2. It said "no time point 1 in the sequence", of a recording that
    has one."""
    from napari_fdlc.io.images import StackSeries, write_tiff
    from napari_fdlc.render import render_recording

    volumes, origins = simulate_sequence(small_worm, 1, QUIET)
    series, _ = render_recording(volumes, origins, seed=0)
    data = np.array(series.data)
    data[1] = 0  # out of focus: nothing to find
    path = tmp_path / "rec.ome.tif"
    write_tiff(path, StackSeries(data, series.voxel_size_zyx, series.channel_roles, str(path), series.channel_names))
    code = main(["track", str(path), "--reference-t", "1", "--method", "geometry", "--quiet",
                 "--out", str(tmp_path / "tracks.csv")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "no nucleus was found at that time point" in err[-1], err


def test_geometry_leaves_a_time_point_of_under_three_nuclei_untracked(tmp_path, gentle):
    """docs/tracking.md: with `--method cpd` and `geometry`, "a time point of fewer than 3
    distinct nuclei (out of focus) is left untracked by them, and the next one goes on from the
    one before". CPD does so; the geometric chain only checks that before it has started
    (`_track_geometry`: `warp is None and _too_few_to_register(vol)`): a later out-of-focus
    time point of 6 rows at 2 positions gets 6 different tracks, each with track_conf 1
    ("certain"), though at most 2 of them can be right."""
    volumes, _ = gentle
    blurred = list(volumes)
    blurred[2] = NeuronTable(np.repeat(volumes[2].xyz[:2], 3, axis=0))
    src = _sequence_csv(blurred, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out)
    at_2 = df[df["t"] == 2]
    assert len(at_2) == 6
    assert (at_2["track_id"] == -1).all(), at_2[["neuron_index", "x_um", "track_id", "track_conf"]].to_string()


def test_a_bad_sequence_table_is_refused_before_the_models_load(tmp_path, monkeypatch, capsys):
    """docs/tracking.md: bad input (a non-numeric t, ...) "is refused with one line ... before
    any work" (and _cli_track.run: "Validate every input before any model work"). The table
    sequence is read only after the identification model is loaded (`read_sequence` comes
    after `default_identifier()`): a t cell of 'abc' was refused after ~6 s of torch import and
    model load (3.5 s with --method geometry)."""
    import napari_fdlc.identify as identify

    loaded = []

    def spy(*args, **kwargs):
        loaded.append(True)
        raise FdlcError("the model was loaded before the input was read")

    monkeypatch.setattr(identify, "default_identifier", spy)
    src = tmp_path / "seq.csv"
    src.write_text("t,x_um,y_um,z_um\n0,1,2,3\n0,4,5,6\nabc,1,2,3\n")
    out = tmp_path / "tracks.csv"
    code = main(["track", str(src), "--threads", "1", "--quiet", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "column 't'" in err, err
    assert not loaded, "the model was loaded before the sequence table was validated"


def test_a_table_sequences_measured_columns_reach_the_output(tmp_path, gentle):
    """tracking.md offers `fdlc segment recording.ome.tif --out neurons.csv` ("or first the
    neuron tables only: one CSV with a t column") beside `fdlc track recording.ome.tif`, whose
    output keeps what the segmentation measured (GFP: "the activity trace of each track");
    neuron_table.md: "Other columns are kept". Tracking that CSV drops every column but t and the
    positions (`_cli_track.run` joins the measured columns back for a recording only): the GFP
    trace, the colours and any column of the user's are lost."""
    volumes, _ = gentle
    src = tmp_path / "neurons.csv"
    df = join_by_time(volumes).drop(columns=["label"])
    df["GFP"] = np.arange(len(df), dtype=float) + 0.5
    df.to_csv(src, index=False)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    tracks = pd.read_csv(out)
    assert "GFP" in tracks.columns, tracks.columns.tolist()
    assert np.allclose(tracks["GFP"].to_numpy(), df["GFP"].to_numpy())


def test_track_output_name_is_not_an_earlier_runs_name(tmp_path):
    """An fdlc track output read again as the sequence (another method, another reference)
    has a ``name`` column; the first volume, the reference, has no ``label``, so the new run
    names nothing. Since session 35 the input's other columns are passed on, and the earlier
    run's ``name`` column goes out beside the new ``track_id`` (docs/tracking.md: ``name`` is
    the reference neuron's name, only when a reference is labelled). Expected: no ``name``
    column (or one that agrees with the new tracks); got the stale names of the input."""
    from napari_fdlc.cli import main
    from napari_fdlc.table import write_table

    rng = np.random.default_rng(1)
    base = rng.uniform(0, 40, (15, 3))
    rows = []
    for t in range(3):
        xyz = base + rng.normal(0, 0.2, base.shape)
        for k, p in enumerate(xyz):
            rows.append({"t": t, "x_um": p[0], "y_um": p[1], "z_um": p[2], "track_id": k,
                         "name": f"STALE{(k + 5) % 15}"})
    src = tmp_path / "earlier_output.csv"
    write_table(pd.DataFrame(rows), src)
    out = tmp_path / "again.csv"
    assert main(["track", str(src), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out, keep_default_na=False)
    assert "name" not in df.columns or not df["name"].astype(str).str.startswith("STALE").any(), \
        df[["t", "track_id", "name"]].head()


@pytest.fixture(scope="module")
def worm2():
    return generate_worm(seed=2)


def test_chunk_does_not_change_the_answers_with_refine_steps_and_a_reference_file(worm2, shipped):
    """docs/tracking.md: `--chunk N` "does not change the answers with the default placement".
    With a reference that is not the first volume (a labelled file) and `--refine-steps 1`, chunk
    1 and chunk 16 give different track IDs to 24 neurons of 2 volumes: with chunk 1 the first
    volume's chunk ends with it, and `_match_chunk` then hands the next chunk the first volume's
    *refined* warp (`ref.warp = found[last]["warp"]`, as `rest` is empty), where within one
    chunk the geometric chain starts from the full search's warp (`chain = ref.warp`)."""
    volumes, _ = simulate_sequence(worm2, 2, SequenceParams(frames=3).scaled(3))
    answers = [track(volumes, [worm2], shipped, TrackSettings(chunk=chunk, refine_steps=1)) for chunk in (1, 16)]
    differ = [int((a != b).sum()) for a, b in zip(answers[0].track_id, answers[1].track_id)]
    assert differ == [0, 0, 0], differ


@pytest.fixture(scope="module")
def small_sequence(worm2):
    return simulate_sequence(worm2, 3, SequenceParams(frames=3, drift_um=2.0))


def test_a_folder_with_a_superscript_digit_in_a_file_name_is_no_traceback(tmp_path, small_sequence, capsys):
    """A folder of CSVs is read in natural name order (`track._natural_key`). A file name with
    a superscript digit between numbers ("1²2.csv", e.g. an area in µm²) crashes with a
    ValueError traceback: `str.isdigit()` is true for "²" but `int("²")` fails (the regex `\\d`
    splits on decimal digits only). Expected: the folder is tracked (or refused in one line)."""
    volumes, _ = small_sequence
    folder = tmp_path / "volumes"
    folder.mkdir()
    for name, volume in zip(["1²2.csv", "t3.csv", "t4.csv"], volumes):
        write_table(volume, folder / name)
    out = tmp_path / "tracks.csv"
    code = main(["track", str(folder), "--method", "geometry", "--quiet", "--out", str(out)])
    assert code == 0 and out.exists()
    capsys.readouterr()


def test_a_repeated_name_in_a_labelled_folder_is_one_warning(tmp_path, worm2, small_sequence, capsys):
    """docs/tracking.md: a name given twice within a time point is left unnamed there, "said in
    one warning line for the whole sequence" (what a sequence CSV gets). The same recording as
    a folder of labelled CSVs (one per time point) prints one warning per file: 200 lines for
    a 200-volume folder (`read_sequence` reads each file with `read_volume`, which warns)."""
    volumes, origins = small_sequence
    folder = tmp_path / "volumes"
    folder.mkdir()
    for k, (volume, origin) in enumerate(zip(volumes, origins)):
        labels = np.array([worm2.labels[o] if o >= 0 else "" for o in origin], dtype=object)
        labels[:2] = "AVAL"  # one name given twice in every volume
        named = volume.subset(np.arange(len(volume)))
        named.labels, named.label_conf = labels, np.where(labels != "", 1.0, 0.0)
        write_table(named, folder / f"t{k}.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(folder), "--method", "geometry", "--quiet", "--out", str(out)]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "more than once" in line]
    assert len(lines) == 1, lines


def test_placement_model_tracks_a_gentle_recording(shipped):
    """docs/tracking.md lists `--placement model` and measures "fdlc track, model alone
    (placement=model)" at 96.7 % at 1x motion. Run as `fdlc track --placement model` runs it
    (`TrackSettings(placement="model")`: chunk 16, the 1 um position likelihood on), an
    8-volume recording at 1x motion is tracked 36 % right (97.5 % with position_sigma_um=0):
    every volume of a chunk is placed by the warp of the chunk before, up to 15 volumes stale,
    and `_finish` still fuses the same-worm position likelihood (sigma 1 um) around that stale
    placement, pulling neurons onto the wrong partners. (The benchmark row runs chunk=1 and
    position_sigma_um=0, which the command line cannot ask for.)"""
    from napari_fdlc.track import tracking_accuracy

    worm = generate_worm(seed=4)
    volumes, origins = simulate_sequence(worm, 4, SequenceParams(frames=8))
    result = track(volumes, None, shipped, TrackSettings(placement="model"))
    accuracy = tracking_accuracy(result, origins, origins[0])["accuracy"]
    assert accuracy > 0.9, accuracy
