"""fdlc track: sequences of volumes of one worm -> track IDs (and names) per time point."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from napari_fdlc.cli import main
from napari_fdlc.errors import FdlcError
from napari_fdlc.table import NeuronTable, write_table
from napari_fdlc.track import (
    SequenceParams,
    TrackResult,
    TrackSettings,
    join_by_time,
    read_sequence,
    simulate_sequence,
    track,
    tracking_accuracy,
)

GENTLE = SequenceParams(frames=8, bend_curvature=0.002, roll=0.05, xy_rotation=0.3, drift_um=4.0,
                        drop_fraction=(0.0, 0.05), max_spurious=3, jitter_um=0.2)


@pytest.fixture(scope="module")
def identifier(untrained_weights):
    from napari_fdlc.identify import Identifier

    return Identifier.load(untrained_weights, device="cpu")


@pytest.fixture(scope="module")
def gentle(worm):
    return simulate_sequence(worm, 3, GENTLE)


def _sequence_csv(volumes, path):
    write_table(join_by_time(volumes).drop(columns=["label"]), path)
    return path


def test_moved_copies_track_near_perfectly_with_untrained_model(identifier, gentle):
    """The geometric prior and the propagated warp do the work: even an untrained model tracks
    slightly moved, jittered copies with drops and spurious points."""
    volumes, origins = gentle
    result = track(volumes, identifier=identifier, settings=TrackSettings(use_colour=False, follow_with="full"))
    score = tracking_accuracy(result, origins, origins[0])
    assert score["accuracy"] >= 0.95, score
    # The reference is the first volume: it is matched to itself.
    ids0 = result.track_id[0]
    real0 = origins[0] >= 0
    assert (ids0[real0] == np.flatnonzero(real0)).mean() >= 0.97
    # Only the first volume needed the orientation search; the rest were propagated.
    searched = [any(i["searched"]) for i in result.info]
    assert searched[0] and not any(searched[1:])
    assert all(len(t) == len(v) for t, v in zip(result.track_id, volumes))
    assert all(((c >= 0) & (c <= 1)).all() for c in result.confidence)


def test_the_tracking_model_follows_and_full_searches_use_the_identifier(identifier, gentle, monkeypatch):
    """By default the shipped tracking model answers for every volume placed from the one
    before, and the identification model makes the full search of the first volume only."""
    from napari_fdlc.identify import Identifier, default_identifier, default_tracker

    follower = default_tracker("cpu")
    shipped = default_identifier().model.config
    assert follower.model.config["dim"] * follower.model.config["layers"] < shipped["dim"] * shipped["layers"]
    volumes, origins = gentle
    passes = {"identifier": 0, "follower": 0}
    for name, ident in (("identifier", identifier), ("follower", follower)):
        original = ident._model_pass
        monkeypatch.setattr(ident, "_model_pass", lambda *a, _o=original, _n=name: passes.__setitem__(_n, passes[_n] + 1) or _o(*a))
    result = track(volumes, identifier=identifier, settings=TrackSettings(use_colour=False, chunk=1))
    assert tracking_accuracy(result, origins, origins[0])["accuracy"] >= 0.97
    # the follower: each later volume, and the first once (the yardstick of a jump: its match rate)
    assert passes["follower"] == len(volumes) and 0 < passes["identifier"] <= 4
    assert isinstance(follower, Identifier)


def test_cpd_tracker_follows_from_the_volume_before(gentle, monkeypatch):
    """The CPD baseline searches orientations on the first volume only, then registers once
    per volume from the one before, and still tracks a gentle sequence."""
    from napari_fdlc import baselines

    volumes, origins = gentle
    calls = []
    follow = baselines.cpd_follow
    monkeypatch.setattr(baselines, "cpd_follow", lambda *a, **k: calls.append(1) or follow(*a, **k))
    result = track(volumes, method="cpd")
    assert len(calls) == len(volumes) - 1
    assert tracking_accuracy(result, origins, origins[0])["accuracy"] >= 0.9


def test_shuffled_exact_copies_are_tracked_exactly(identifier, worm):
    rng = np.random.default_rng(0)
    volumes, perms = [], []
    for _ in range(4):
        perm = rng.permutation(len(worm))
        volumes.append(worm.subset(perm))
        perms.append(perm)
    result = track(volumes, references=[worm], identifier=identifier, settings=TrackSettings(use_colour=False))
    for tid, perm in zip(result.track_id, perms):
        assert (tid == perm).mean() >= 0.98


def test_batching_and_placement_modes_agree_on_gentle_motion(identifier, gentle):
    volumes, origins = gentle
    scores = []
    for settings in (TrackSettings(use_colour=False), TrackSettings(use_colour=False, chunk=1),
                     TrackSettings(use_colour=False, chunk=3, refine_steps=1)):
        result = track(volumes, identifier=identifier, settings=settings)
        scores.append(tracking_accuracy(result, origins, origins[0])["accuracy"])
    assert min(scores) >= 0.95
    assert scores[0] == scores[1]  # the geometric placement does not depend on the chunking
    # the model alone (no geometric pre-placement, no position likelihood) tracks too
    alone = TrackSettings(use_colour=False, placement="model", chunk=1, position_sigma_um=0)
    assert tracking_accuracy(track(volumes, identifier=identifier, settings=alone), origins, origins[0])["accuracy"] >= 0.9


def test_several_references_share_track_ids(identifier, gentle):
    volumes, origins = gentle
    result = track(volumes, references=[volumes[0], volumes[5]], identifier=identifier,
                   settings=TrackSettings(use_colour=False))
    assert tracking_accuracy(result, origins, origins[0])["accuracy"] >= 0.93
    assert {i["reference"] for i in result.info} <= {0, 1}


def test_labelled_reference_gives_names(identifier, worm):
    moved = NeuronTable(worm.xyz + [3.0, -2.0, 0.5], worm.colours)
    result = track([moved, moved], references=[worm], identifier=identifier, settings=TrackSettings(use_colour=False))
    df = result.frame([moved, moved])
    assert "name" in df.columns
    assert (df["name"].to_numpy()[: len(worm)] == worm.labels).mean() >= 0.98


# ------------------------------------------------------------------------------------------------
# Input and the command line

def test_read_sequence_csv_with_t_column(tmp_path, gentle):
    volumes, _ = gentle
    path = _sequence_csv(volumes[:3], tmp_path / "seq.csv")
    seq = read_sequence([str(path)])
    assert seq.times == [0, 1, 2]
    assert [len(v) for v in seq.volumes] == [len(v) for v in volumes[:3]]
    assert np.allclose(seq.volumes[1].xyz, volumes[1].xyz, atol=1e-4)
    assert "t" not in seq.volumes[0].extra.columns


def test_read_sequence_folder_in_natural_order(tmp_path, gentle):
    volumes, _ = gentle
    folder = tmp_path / "vols"
    for k, name in ((2, "t2"), (7, "t10"), (1, "t1")):
        write_table(volumes[k], folder / f"vol_{name}.csv")
    (folder / "notes.txt").write_text("not a table")
    seq = read_sequence([str(folder)])
    assert seq.sources == ["vol_t1.csv", "vol_t2.csv", "vol_t10.csv"]
    assert len(seq.volumes[2]) == len(volumes[7])


def test_cli_track_csv_with_t_column(tmp_path, gentle, untrained_weights):
    volumes, origins = gentle
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--weights", str(untrained_weights), "--no-color", "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out)
    assert list(df.columns[:7]) == ["t", "neuron_index", "x_um", "y_um", "z_um", "track_id", "track_conf"]
    assert len(df) == sum(len(v) for v in volumes)
    assert sorted(df["t"].unique()) == list(range(len(volumes)))
    first = df[df["t"] == 0]
    assert (first["track_id"].to_numpy() == first["neuron_index"].to_numpy()).mean() >= 0.97
    assert df["track_conf"].between(0, 1).all()
    assert df["track_id"].min() >= -1


def test_cli_track_folder_with_labelled_reference(tmp_path, worm, untrained_weights):
    folder = tmp_path / "vols"
    for k in range(3):
        write_table(NeuronTable(worm.xyz + [k, 0.5 * k, 0], worm.colours), folder / f"t{k}.csv")
    ref = tmp_path / "ref.csv"
    write_table(worm, ref)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(folder), "--reference", str(ref), "--weights", str(untrained_weights), "--quiet", "--out", str(out)]) == 0
    df = pd.read_csv(out, keep_default_na=False)
    assert {"name", "file"} <= set(df.columns)
    assert list(df["file"].unique()) == ["t0.csv", "t1.csv", "t2.csv"]
    assert (df["name"].to_numpy() == np.tile(worm.labels, 3)).mean() >= 0.98


def test_cli_track_warns_of_a_recording_not_in_micrometres(tmp_path, worm, untrained_weights, capsys):
    folder = tmp_path / "pixels"
    for k in range(2):
        write_table(NeuronTable((worm.xyz + [k, 0, 0]) * [4, 4, 1], worm.colours), folder / f"t{k}.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(folder), "--weights", str(untrained_weights), "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "t0.csv: its neurons lie" in err[0] and "must be micrometres" in err[0]


@pytest.mark.parametrize(
    "make, expected",
    [
        (lambda d, v: write_table(v, d / "no_t.csv") or d / "no_t.csv", "no 't' column"),
        (lambda d, v: _bad_t(d, v), "column 't'"),
        (lambda d, v: (d / "empty").mkdir() or d / "empty", "holds no .csv file"),
        (lambda d, v: d / "missing.csv", "no such file"),
    ],
)
def test_cli_track_bad_input_is_one_line(tmp_path, capsys, worm, untrained_weights, make, expected):
    src = make(tmp_path, worm)
    out = tmp_path / "tracks.csv"
    code = main(["track", str(src), "--weights", str(untrained_weights), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert expected in err and len(err.splitlines()) == 1
    assert not out.exists()


def _bad_t(folder, worm):
    df = worm.to_dataframe()
    df.insert(0, "t", ["0"] * (len(df) - 1) + ["soon"])
    write_table(df, folder / "bad_t.csv")
    return folder / "bad_t.csv"


def test_cli_track_bad_reference_time(tmp_path, capsys, gentle, untrained_weights):
    volumes, _ = gentle
    src = _sequence_csv(volumes[:2], tmp_path / "seq.csv")
    code = main(["track", str(src), "--reference-t", "7", "--weights", str(untrained_weights), "--out", str(tmp_path / "o.csv")])
    assert code == 2 and "no time point 7" in capsys.readouterr().err


def test_cli_track_follow_with_the_full_model(tmp_path, gentle, untrained_weights):
    volumes, _ = gentle
    src = _sequence_csv(volumes, tmp_path / "seq.csv")
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--weights", str(untrained_weights), "--follow-with", "full",
                 "--no-color", "--quiet", "--out", str(out)]) == 0
    assert (pd.read_csv(out)["track_id"] >= 0).mean() > 0.9


def test_cli_track_an_image_recording(tmp_path, recording):
    """A stack file with a time axis is segmented at every time point, then tracked; the output
    also has what the segmentation measured (colours, voxel coordinates)."""
    from scipy.spatial import cKDTree

    path, truths, origins = recording
    out = tmp_path / "tracks.csv"
    assert main(["track", str(path), "--out", str(out), "--quiet"]) == 0
    df = pd.read_csv(out)
    assert sorted(df["t"].unique()) == [0, 1, 2]
    assert {"neuron_index", "track_id", "track_conf", "R", "G", "B", "W", "x_px", "score"} <= set(df.columns)
    # Each detection's source neuron (through the rendered truth) keeps the track it had at t = 0.
    track_of_source, kept, found = {}, [], []
    for t, truth in enumerate(truths):
        rows = df[df["t"] == t]
        distance, nearest = cKDTree(truth.xyz).query(rows[["x_um", "y_um", "z_um"]].to_numpy())
        source = np.where(distance < 1.5, origins[t][nearest], -1)
        found.append(len(set(source[source >= 0])) / len(truth))
        for s, tid in zip(source, rows["track_id"]):
            if s < 0:
                continue
            if t == 0:
                track_of_source[s] = tid
            elif s in track_of_source:
                kept.append(track_of_source[s] == tid)
    assert min(found) >= 0.9, found
    assert np.mean(kept) >= 0.9, np.mean(kept)


def test_track_settings_are_checked():
    with pytest.raises(FdlcError, match="chunk"):
        TrackSettings(chunk=0).check()
    with pytest.raises(FdlcError, match="search"):
        TrackSettings(search="sideways").check()
    with pytest.raises(FdlcError, match="follow_with"):
        TrackSettings(follow_with="nobody").check()


def test_cli_track_chirality_option(tmp_path, worm):
    """Volumes of a z-mirrored recording, a labelled reference recorded the usual way: told
    `--chirality mirrored`, the shipped model keeps left and right apart."""
    folder = tmp_path / "vols"
    for k in range(2):
        write_table(NeuronTable((worm.xyz + [k, 0.5 * k, 0]) * [1, 1, -1], worm.colours), folder / f"t{k}.csv")
    ref = tmp_path / "ref.csv"
    write_table(worm, ref)
    right = {}
    for chirality in ("same", "mirrored"):
        out = tmp_path / f"{chirality}.csv"
        assert main(["track", str(folder), "--reference", str(ref), "--chirality", chirality, "--quiet", "--out", str(out)]) == 0
        names = pd.read_csv(out, keep_default_na=False)["name"].to_numpy()
        paired = np.tile([n[-1:] in ("L", "R") for n in worm.labels], 2)
        right[chirality] = (names == np.tile(worm.labels, 2))[paired].mean()
    assert right["mirrored"] > 0.9 and right["mirrored"] > right["same"] + 0.3, right


def test_track_positions_in_nanometres_do_not_exhaust_memory(identifier, gentle):
    """A recording in nm is tracked (poorly) or refused in one line; the warp's grid once asked
    numpy for hundreds of GiB (a dense grid over the extent; now only occupied cubes count)."""
    volumes, _ = gentle
    nm = [NeuronTable(v.xyz * 1000, v.colours, source=v.source) for v in volumes[:3]]
    try:
        result = track(nm, identifier=identifier)
    except FdlcError:
        return
    assert [len(t) for t in result.track_id] == [len(v) for v in nm]


def test_track_with_an_empty_first_volume_and_no_reference(identifier, gentle):
    """The reference defaults to the first volume: when that is empty, a one-line refusal or an
    answer with nothing in it, not numpy's error from a maximum over no track IDs."""
    volumes, _ = gentle
    empty = volumes[0].subset(np.arange(0))
    try:
        result = track([empty, *volumes[1:]], identifier=identifier)
    except FdlcError:
        return
    assert len(result.track_id[0]) == 0


def test_track_with_an_empty_reference_is_a_one_line_error(identifier, gentle):
    """A reference without neurons: nothing can be tracked onto it, so a one-line refusal."""
    volumes, _ = gentle
    with pytest.raises(FdlcError):
        track(volumes, references=[volumes[0].subset(np.arange(0))], identifier=identifier)


@pytest.mark.parametrize("case", ["no frames", "time point beyond the frames"])
def test_simulate_sequence_bad_request_is_a_one_line_error(case, worm):
    """No frames gives an empty sequence (or a one-line refusal); a time point beyond the
    frames is refused in one line."""
    try:
        if case == "no frames":
            volumes, origins = simulate_sequence(worm, 0, SequenceParams(frames=0))
            assert volumes == [] and origins == []
        else:
            simulate_sequence(worm, 0, SequenceParams(frames=10), only=(12,))
            pytest.fail("a time point beyond the sequence was simulated")
    except FdlcError:
        pass


def test_two_labelled_references_never_give_one_name_to_two_tracks(identifier, worm):
    """Two labelled references that put one name on different neurons: the first reference's
    name wins, and no two tracks share a name."""
    n = len(worm)
    first = np.full(n, "", dtype=object)
    first[0] = "AVAL"
    second = np.full(n, "", dtype=object)
    second[40] = "AVAL"  # the second reference's annotator named another neuron AVAL
    refs = [NeuronTable(worm.xyz, worm.colours, first), NeuronTable(worm.xyz + 0.3, worm.colours, second)]
    result = track([worm, worm], references=refs, identifier=identifier, settings=TrackSettings(use_colour=False))
    named = [i for i, name in enumerate(result.names) if name == "AVAL"]
    assert named == [0], named
    df = result.frame([worm, worm])
    assert df[df["name"] == "AVAL"].groupby("t")["track_id"].nunique().max() == 1


def test_reference_t_picks_the_exact_integer_time_point(tmp_path, gentle, monkeypatch):
    """--reference-t with integer clocks beyond 2**53 (nanoseconds, which the t column keeps
    exact) picks the volume asked for: compared as an integer, not as a float."""
    import napari_fdlc.track as track_module

    volumes = gentle[0][:3]
    times = [1_700_000_000_000_000_000 + k for k in range(3)]
    src = tmp_path / "seq.csv"
    write_table(join_by_time(volumes, times).drop(columns=["label"]), src)
    seen = {}
    real = track_module.track

    def spy(seq, references=None, *args, **kwargs):
        seen["references"] = references
        return real(seq, references, *args, **kwargs)

    monkeypatch.setattr(track_module, "track", spy)
    out = tmp_path / "tracks.csv"
    assert main(["track", str(src), "--method", "geometry", "--reference-t", str(times[2]), "--quiet", "--out", str(out)]) == 0
    (reference,) = seen["references"]
    sizes = (len(reference), [len(v) for v in volumes])
    assert len(reference) == len(volumes[2]), sizes
    assert np.allclose(reference.xyz, volumes[2].xyz, atol=1e-3)


def test_folder_order_does_not_depend_on_the_directory_listing(tmp_path, worm, monkeypatch):
    """Files at the same place in natural order (t1.csv, t01.csv) are ordered by name, not by
    the file system's listing, so a folder gives the same volumes in the same order anywhere."""
    from pathlib import Path

    folder = tmp_path / "vols"
    folder.mkdir()
    for name in ("t1.csv", "t01.csv", "t2.csv"):
        write_table(worm, folder / name)
    listing = Path.iterdir
    orders = []
    for reverse in (False, True):
        monkeypatch.setattr(Path, "iterdir", lambda self, r=reverse: iter(sorted(listing(self), reverse=r)))
        orders.append(read_sequence([str(folder)]).sources)
    assert orders[0] == orders[1], orders


def test_a_jump_the_chain_still_pairs_up_is_searched_again(worm):
    """The whole worm turned 180° in XY between two volumes: the geometric chain still paired
    most neurons with some neighbour, so the jump was not seen and every later volume was tracked
    0 % right (a helper review, session 32). The tracking model's match rate falling below half
    the first volume's now sends that volume to the full search, and the chain on from it."""
    params = SequenceParams(frames=6, bend_curvature=0.002, roll=0.05, xy_rotation=0.3, drift_um=4.0,
                            drop_fraction=(0.0, 0.05), max_spurious=4, jitter_um=0.2)
    volumes, origins = simulate_sequence(worm, 3, params)
    turned = [v if k < 3 else NeuronTable(2 * v.xyz.mean(0) * [1, 1, 0] + v.xyz * [-1, -1, 1], dict(v.colours))
              for k, v in enumerate(volumes)]
    result = track(turned)
    assert result.info[3]["searched"]
    for k in range(3, len(volumes)):
        one = TrackResult([result.track_id[k]], [result.confidence[k]], result.names, [])
        assert tracking_accuracy(one, [origins[k]], origins[0], reference_t=None)["accuracy"] >= 0.9


def _track_result(track_ids):
    from napari_fdlc.track import TrackResult

    return TrackResult([np.asarray(t) for t in track_ids], [np.ones(len(t)) for t in track_ids], [], [])


def test_tracking_accuracy_untracked_right_with_nothing_to_leave_untracked():
    """'Untracked right' of a recording with nothing to leave untracked is NaN (left out of the
    benchmarks' means), not 0 % (which read as all wrong and pulled the means down)."""
    from napari_fdlc.track import tracking_accuracy

    origins = [np.array([0, 1, 2]), np.array([2, 0, 1])]
    score = tracking_accuracy(_track_result([[0, 1, 2], [2, 0, 1]]), origins, origins[0])
    assert score["accuracy"] == 1.0
    assert score["untracked_right"] == 1.0 or np.isnan(score["untracked_right"]), score


def test_simulate_sequence_copies_no_reading_as_none(gap_table):
    """simulate_sequence's copy of a neuron without a colour reading should have none (as
    simulate_worm's copies since session 35); it copies the filled median times noise, a
    measurement nobody made (track.simulate_sequence reads ``table.colours``)."""
    from napari_fdlc.track import SequenceParams, simulate_sequence

    table = gap_table
    volumes, origins = simulate_sequence(table, 0, SequenceParams(frames=1, drop_fraction=(0.0, 0.0), max_spurious=0))
    row = int(np.flatnonzero(origins[0] == 3)[0])
    assert np.isnan(volumes[0].colours_as_read()["R"][row]), volumes[0].colours["R"][row]
