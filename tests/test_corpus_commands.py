"""The commands that read a corpus (`fdlc atlas`, `fdlc evaluate`) on corpora as others lay them
out, from session 33's review: each docstring says what is expected and what used to happen.
Small corpora of generated worms under tmp_path (no NeuroPAL corpus, no GPU)."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np
import pytest

from napari_fdlc.cli import main
from napari_fdlc.corpus import Worm, load_corpus
from napari_fdlc.errors import FdlcError
from napari_fdlc.reference import atlas_worm, build_atlas, generate_worm, load_atlas
from napari_fdlc.table import NeuronTable, write_table
import os
import shlex
import subprocess
import sys
from dataclasses import replace

FAST = ("--pairs-per-lab", "1", "--panel-worms-per-lab", "0", "--synthetic-pairs", "0", "--no-cpd")


def run(*args) -> int:
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def two_lab_corpus(tmp_path_factory, write_corpus) -> Path:
    worms = {lab: [generate_worm(seed=500 + 3 * k + i) for i in range(3)] for k, lab in enumerate(("NP", "EY"))}
    return write_corpus(tmp_path_factory.mktemp("corpus"), worms)


# --------------------------------------------------------------------------------------------
# fdlc evaluate: the reliability plot beside the report


def _plot_link(report: Path) -> Path:
    match = re.search(r"!\[reliability\]\(([^)]+)\)", report.read_text())
    assert match, "the report links no reliability plot"
    return report.parent / match.group(1)


def test_a_file_named_images_beside_the_report_does_not_lose_the_finished_run(tmp_path, two_lab_corpus,
                                                                             untrained_weights, monkeypatch, capsys):
    """Expected: the plot's place (images/ beside --out) is checked before any work as --out is,
    or the report is written without the plot; either way no finished run is thrown away.
    Actual: the whole evaluation runs, then `mkdir images` fails (FileExistsError) and the run
    ends with exit 2 and no report: the work is lost (check_output covers --out only)."""
    import napari_fdlc.evaluate as evaluate

    started = []
    original = evaluate.pair_list
    monkeypatch.setattr(evaluate, "pair_list", lambda *a, **k: started.append(1) or original(*a, **k))
    (tmp_path / "images").write_text("a file, not a folder\n")
    out = tmp_path / "acc.md"
    code = run("evaluate", "--corpus", two_lab_corpus, "--labs", "NP", *FAST, "--weights", untrained_weights, "--out", out)
    assert "Traceback" not in capsys.readouterr().err
    assert out.exists() or (code == 2 and not started), f"exit {code} after the evaluation ran: the report is lost"


def test_evaluate_out_dev_null_writes_no_plot_under_dev(tmp_path, two_lab_corpus, untrained_weights, monkeypatch):
    """Expected: `--out /dev/null` (a stream, written through; the report is printed anyway)
    writes no reliability plot into /dev.
    Actual: the plot goes to out.parent / "images" / "calibration.png" = /dev/images/calibration.png
    (as root: a folder and a PNG created in /dev). Nothing is written here: the plot and the
    report writers are replaced to record where they would write."""
    import napari_fdlc._cli_evaluate as cli_evaluate

    plotted = []
    monkeypatch.setattr(cli_evaluate, "_plot_reliability", lambda calib, path, rel: plotted.append(Path(path)) or False)
    monkeypatch.setattr(cli_evaluate, "atomic_write", lambda *a, **k: contextlib.nullcontext(io.StringIO()))
    assert run("evaluate", "--corpus", two_lab_corpus, "--labs", "NP", *FAST, "--weights", untrained_weights,
               "--out", "/dev/null") == 0
    assert not any(Path("/dev") in p.parents for p in plotted), plotted


def test_evaluate_without_weights_refuses_an_out_onto_the_shipped_model(tmp_path, two_lab_corpus, untrained_weights,
                                                                       monkeypatch, capsys):
    """Expected: the shipped model is an input when --weights is left out, so `--out` onto its
    JSON is refused before any work (exit 2, "replace an input"), as it is with --weights.
    Actual: check_output gets inputs=() without --weights; the report is written over the model
    JSON and the installed package no longer loads. (Here "shipped" is a copy under tmp_path.)"""
    import napari_fdlc.identify as identify

    weights = tmp_path / "shipped" / "fdlc_model"
    weights.parent.mkdir()
    for suffix in (".safetensors", ".json"):
        Path(str(weights) + suffix).write_bytes(Path(str(untrained_weights) + suffix).read_bytes())
    monkeypatch.setattr(identify, "shipped_weights", lambda: weights)
    config = Path(str(weights) + ".json")
    before = config.read_bytes()
    code = run("evaluate", "--corpus", two_lab_corpus, "--labs", "NP", *FAST, "--out", config)
    assert config.read_bytes() == before, "the shipped model's JSON was replaced by the report"
    assert code == 2


# --------------------------------------------------------------------------------------------
# worms.csv


def test_worms_csv_with_spaces_after_the_commas_of_its_header_is_read(tmp_path, write_corpus):
    """Expected: a worms.csv typed as "dataset, dandiset, worm, ..." is read (its values are
    already stripped, and a neuron table's header is read so: "spaces around names do not
    count").
    Actual: FdlcError "no column 'worm'", though the header has one (the column is ' worm')."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": [generate_worm(seed=1), generate_worm(seed=2)]})
    index = corpus / "worms.csv"
    index.write_text(index.read_text().replace("dataset,dandiset,worm,n_neurons,n_labeled",
                                               "dataset, dandiset, worm, n_neurons, n_labeled"))
    assert [(w.lab, w.name) for w in load_corpus(corpus)] == [("NP", "w0"), ("NP", "w1")]


def test_worms_csv_row_error_names_its_line_after_blank_lines(tmp_path, write_corpus):
    """Expected: a row without its worm, below two blank lines, is reported at its own line of
    worms.csv (line 6 here).
    Actual: "line 4" — the line is counted over pandas's rows, which skip blank lines."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": [generate_worm(seed=1), generate_worm(seed=2)]})
    index = corpus / "worms.csv"
    index.write_text(index.read_text() + "\n\nNP,0,,0,0\n")  # lines 4 and 5 blank, the bad row on 6
    assert index.read_text().splitlines()[5] == "NP,0,,0,0"
    with pytest.raises(FdlcError) as err:
        load_corpus(corpus)
    assert "line 6" in str(err.value), err.value


def test_a_corpus_worm_of_several_time_points_is_refused(tmp_path, write_corpus, capsys):
    """Expected: a corpus table of several time points (a 't' column, as `fdlc track` / `fdlc
    segment` write) is refused in one line saying so, as `fdlc label`, `simulate` and
    `handedness` refuse one where one worm is meant (table.read_volume).
    Actual: load_corpus uses read_table: every name repeats once per time point, so all are
    dropped with a warning about repeated names, and `fdlc atlas` exits 0 with an atlas of the
    other worms (the recording's positions of both time points merged into one "worm")."""
    from napari_fdlc.track import join_by_time

    worms = [generate_worm(seed=s) for s in range(1, 7)]
    corpus = write_corpus(tmp_path / "corpus", {"A": worms[:3], "B": worms[3:]})
    write_table(join_by_time([worms[0], worms[0]]), corpus / "A" / "w0.csv")
    out = tmp_path / "atlas.csv"
    code = run("atlas", "--corpus", corpus, "--out", out)
    err = capsys.readouterr().err
    assert code == 2 and "time points" in err, (code, err)
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# fdlc atlas / reference.build_atlas


def _worm(lab: str, name: str, table: NeuronTable) -> Worm:
    return Worm(lab, name, table)


def test_the_atlas_does_not_depend_on_the_order_of_worms_csv():
    """Expected: the same worms give the same atlas whatever the order of worms.csv's rows
    (`fdlc atlas` is documented to reproduce the shipped atlas from the corpus).
    Actual: build_atlas anchors its Procrustes on the best-named worm, ties broken by row
    order, and its scale never comes back to one independent of that worm: two equally named
    worms of different sizes in the other order give an atlas of another size. The real corpus
    has such a tie (NP 11_YAaLR and 70_YAaLR, 193 names each): worms.csv reversed gives an atlas
    with every mean and spread 0.81x the shipped one (worm scale 1.5411 instead of 1.2623)."""
    base = generate_worm(seed=11)
    big = NeuronTable(base.xyz * 1.3, base.colours, base.labels)  # the same names, a bigger worm
    others = [generate_worm(seed=s) for s in (12, 13, 14)]
    others = [t.subset(np.arange(len(t) - 40)) for t in others]  # fewer names: the tie is for the best-named
    worms = [_worm("A", "small", base), _worm("A", "big", big)] + [_worm("B", f"w{i}", t) for i, t in enumerate(others)]
    one = build_atlas(worms)
    other = build_atlas([worms[1], worms[0]] + worms[2:])
    assert list(one.names) == list(other.names)
    np.testing.assert_allclose(other.sd, one.sd, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(other.mean, one.mean, rtol=1e-3, atol=1e-2)


def test_the_atlas_header_names_only_the_labs_it_was_built_from(tmp_path, write_corpus, capsys):
    """Expected: the atlas's labs (its header, and `fdlc atlas`'s "N names from M worms of ...")
    are those of the worms it used.
    Actual: Atlas.labs lists every lab given, also one none of whose worms entered the atlas
    (here lab B's worms carry no names: "3 worms of A, B", B contributing nothing)."""
    named = [generate_worm(seed=s) for s in (1, 2, 3)]
    unnamed = [NeuronTable(generate_worm(seed=s).xyz) for s in (4, 5)]
    corpus = write_corpus(tmp_path / "corpus", {"A": named, "B": unnamed})
    out = tmp_path / "atlas.csv"
    assert run("atlas", "--corpus", corpus, "--out", out) == 0
    header = out.read_text().splitlines()[0]
    assert "3 worms of A," in header and "B" not in header.split(" of ", 1)[1].split(";")[0], header


# --------------------------------------------------------------------------------------------
# fdlc evaluate: what the report and the errors say


def test_evaluate_report_names_the_corpus_it_read_from_fdlc_corpus(tmp_path, two_lab_corpus, untrained_weights,
                                                                   monkeypatch):
    """Expected: the report's "Made by" line reproduces the run, so a corpus taken from
    $FDLC_CORPUS (no --corpus) is named in it (as --corpus, or FDLC_CORPUS=...).
    Actual: only the options given are written; the line reads as a run on the default
    ../shared/data/neuropal_corpus, which is another corpus than the one scored."""
    monkeypatch.setenv("FDLC_CORPUS", str(two_lab_corpus))
    out = tmp_path / "acc.md"
    assert run("evaluate", "--labs", "NP", *FAST, "--weights", untrained_weights, "--out", out) == 0
    made_by = next(line for line in out.read_text().splitlines() if line.startswith("Made by"))
    assert str(two_lab_corpus) in made_by, made_by


def test_evaluate_on_a_corpus_of_one_lab_says_why_it_cannot(tmp_path, write_corpus, untrained_weights, capsys):
    """Expected: a corpus of one lab (a lab's own annotated worms, a natural first use) is either
    scored (the pairs do not need an atlas) or refused in a line that says why: the atlas beside
    each lab is rebuilt from the *other* labs, and there are none.
    Actual: "fdlc: error: no worms to build an atlas from", though the corpus has 3 worms."""
    corpus = write_corpus(tmp_path / "corpus", {"MINE": [generate_worm(seed=s) for s in (1, 2, 3)]})
    out = tmp_path / "acc.md"
    code = run("evaluate", "--corpus", corpus, *FAST, "--weights", untrained_weights, "--out", out)
    err = capsys.readouterr().err
    assert code == 0 or ("MINE" in err or "other lab" in err), err


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, write_corpus) -> Path:
    worms = {lab: [generate_worm(seed=700 + 3 * k + i) for i in range(3)] for k, lab in enumerate(("NP", "EY"))}
    return write_corpus(tmp_path_factory.mktemp("corpus"), worms)


def test_min_frequency_keeps_a_name_seen_in_exactly_that_fraction_of_worms():
    """Expected (cli.md, `fdlc atlas`): "names seen in at least F of the worms" are kept, so with
    `--min-frequency 0.28` a name seen in 7 of 25 worms (exactly 0.28) is in the atlas.
    Actual: build_atlas compares the count with `min_frequency * used` in floating point;
    0.28 * 25 = 7.000000000000001 > 7, so the name is dropped (likewise 0.56 of 25, 0.07 of 100,
    0.55 of 100 ...)."""
    atlas = load_atlas()
    rng = np.random.default_rng(0)
    anchor = list(atlas.names).index("AVAL")
    worms = []
    for k in range(25):
        worm = atlas_worm(atlas, rng, spread=0.3)
        if k < 7:  # one more neuron, named XTRA, in 7 of the 25 worms
            xyz = np.vstack([worm.xyz, worm.xyz[anchor] + [0.0, 0.0, 4.0]])
            colours = {c: np.append(v, 0.0) for c, v in worm.colours.items()}
            worm = NeuronTable(xyz, colours, np.append(worm.labels, "XTRA").astype(object))
        worms.append(Worm("A" if k % 2 else "B", f"w{k}", worm))
    built = build_atlas(worms, min_frequency=0.28)
    assert built.worms == 25
    assert "XTRA" in set(built.names), "a name in 7 of 25 worms (0.28) was dropped at --min-frequency 0.28"


def test_an_atlas_saved_as_utf8_loads_whatever_the_locale(tmp_path):
    """Expected: Atlas.save writes UTF-8 (encoding="utf-8"), so Atlas.load reads its header the
    same way on any machine; a lab named "Zürich" comes back as written.
    Actual: Atlas.load reads the header with `path.read_text()`, in the locale's encoding: under a
    non-UTF-8 locale (LC_ALL=C here; cp1252 on Windows gives 'ZÃ¼rich' silently) the atlas is
    refused as "not a valid atlas file ('ascii' codec can't decode byte 0xc3 ...)"."""
    path = tmp_path / "atlas.csv"
    replace(load_atlas(), labs=("Zürich",)).save(path)
    env = {**os.environ, "LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONCOERCECLOCALE": "0"}
    code = f"from napari_fdlc.reference import Atlas; print(ascii(Atlas.load({str(path)!r}).labs))"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr.strip().splitlines()[-1]
    assert done.stdout.strip() == ascii(("Zürich",))


def test_a_corpus_folder_not_found_is_named_in_the_error(tmp_path, capsys):
    """Expected: `fdlc atlas --corpus PATH` with no worms.csv at PATH says which folder it looked
    in (a typo in PATH is then plain).
    Actual: "NeuroPAL corpus not found: pass --corpus PATH (the folder with worms.csv) or set
    FDLC_CORPUS" — the folder given is not named, and the advice is to pass the option that
    was passed (corpus.load_corpus ignores which path it was given)."""
    missing = tmp_path / "my_corpus_typo"
    missing.mkdir()
    assert run("atlas", "--corpus", missing, "--out", tmp_path / "atlas.csv") == 2
    err = capsys.readouterr().err
    assert "my_corpus_typo" in err, err


def test_evaluate_labs_are_matched_as_the_corpus_is_read(tmp_path, corpus, untrained_weights, capsys):
    """Expected: `--labs " NP"` names lab NP in `fdlc evaluate` as it does in `fdlc atlas`
    (load_corpus strips the labs asked for, as it strips worms.csv's; tested for atlas).
    Actual: evaluate_corpus compares the labs unstripped with the corpus's: exit 2,
    "no worms of lab(s)  NP in the corpus"."""
    out = tmp_path / "acc.md"
    code = run("evaluate", "--corpus", corpus, "--labs", " NP", *FAST, "--weights", untrained_weights, "--out", out)
    assert code == 0, capsys.readouterr().err


def test_evaluate_made_by_line_reproduces_a_corpus_path_with_a_space(tmp_path, write_corpus, untrained_weights,
                                                                      monkeypatch):
    """Expected: the report's "Made by `...`" line is the command that reproduces the run, so a
    corpus folder with a space ("my corpus") is quoted and reads back as one argument.
    Actual: the options are joined unquoted: `--corpus /…/my corpus --labs NP …` reruns on the
    folder "/…/my" with a stray argument "corpus"."""
    import napari_fdlc._cli_evaluate as cli_evaluate

    monkeypatch.setattr(cli_evaluate, "_plot_reliability", lambda *a, **k: False)
    folder = write_corpus(tmp_path / "my corpus", {lab: [generate_worm(seed=800 + 3 * k + i) for i in range(2)]
                                                   for k, lab in enumerate(("NP", "EY"))})
    out = tmp_path / "acc.md"
    assert run("evaluate", "--corpus", folder, "--labs", "NP", *FAST, "--weights", untrained_weights, "--out", out) == 0
    made_by = next(line for line in out.read_text().splitlines() if line.startswith("Made by"))
    argv = shlex.split(made_by.split("`")[1])
    assert argv[argv.index("--corpus") + 1] == str(folder), argv


def test_evaluate_where_the_other_labs_are_too_few_for_an_atlas_says_so(tmp_path, write_corpus, untrained_weights,
                                                                        capsys):
    """Expected: scoring NP beside a lab of one worm (the atlas beside a template and the panel
    are rebuilt without NP, from that one worm) is refused in a line that says so: the lab
    scored, or that the atlas is built from the other labs (as a corpus of one lab is told).
    Actual: "no atlas from these 1 worm(s): ... an atlas needs 2 such worms" for a corpus of 4
    worms, naming neither the lab nor that the other labs are meant."""
    folder = write_corpus(tmp_path / "corpus", {"NP": [generate_worm(seed=s) for s in (1, 2, 3)],
                                                "EY": [generate_worm(seed=4)]})
    code = run("evaluate", "--corpus", folder, "--labs", "NP", *FAST, "--weights", untrained_weights,
               "--out", tmp_path / "acc.md")
    err = capsys.readouterr().err
    assert code == 0 or "NP" in err or "other lab" in err, err


def test_evaluate_through_a_link_puts_the_plot_beside_the_report(tmp_path, corpus, untrained_weights, monkeypatch):
    """Expected: `--out` a link writes the report into the file it names (check_output: "a link
    stands for the file it names"), and the reliability plot goes "into images/ beside the
    report" (cli.md), where the report's `![reliability](images/calibration.png)` finds it.
    Actual: the plot goes beside the link (Path(args.out).parent), the report to the link's
    target in another folder: the report's image link is broken there."""
    import napari_fdlc._cli_evaluate as cli_evaluate

    plotted = []
    monkeypatch.setattr(cli_evaluate, "_plot_reliability", lambda calib, path, rel: plotted.append(Path(path)) or True)
    real = tmp_path / "reports" / "acc.md"
    real.parent.mkdir()
    real.write_text("old\n")
    link = tmp_path / "links" / "acc.md"
    link.parent.mkdir()
    link.symlink_to(real)
    assert run("evaluate", "--corpus", corpus, "--labs", "NP", *FAST, "--weights", untrained_weights, "--out", link) == 0
    assert "images/acc_calibration.png" in real.read_text()
    assert plotted == [real.parent / "images" / "acc_calibration.png"], plotted


def test_a_second_report_in_one_folder_does_not_replace_the_first_reports_plot(tmp_path, corpus, untrained_weights):
    """Expected: `fdlc evaluate --out docs/b.md` writes b.md and its own plot; docs/a.md (an
    earlier report, e.g. docs/accuracy.md) keeps the plot it links to. Only an output named on
    the command line is replaced.
    Actual: every report's plot is images/calibration.png beside it, so the second run silently
    replaces the first report's plot with its own: a.md now shows another run's reliability."""
    first, second = tmp_path / "a.md", tmp_path / "b.md"
    assert run("evaluate", "--corpus", corpus, "--labs", "NP", *FAST, "--weights", untrained_weights, "--out", first) == 0
    plot = tmp_path / "images" / "a_calibration.png"
    assert plot.exists() and "images/a_calibration.png" in first.read_text()
    before = plot.read_bytes()
    assert run("evaluate", "--corpus", corpus, "--labs", "EY", *FAST, "--weights", untrained_weights, "--out", second) == 0
    assert plot.read_bytes() == before, "the first report's plot was replaced by the second run's"


def test_a_checkpoint_inside_the_corpus_is_refused_before_any_folder_is_made(tmp_path, capsys):
    """fdlc atlas and fdlc evaluate refuse an output inside the corpus (read, never written);
    fdlc train wrote its checkpoint there, and fdlc atlas made the output's folder inside the
    corpus before refusing."""
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    (corpus / "worms.csv").write_text("dataset,dandiset,worm,n_neurons,n_labeled\n")
    for args in (["train", "--corpus", str(corpus), "--steps", "1", "--out", str(corpus / "runs" / "model")],
                 ["atlas", "--corpus", str(corpus), "--out", str(corpus / "made" / "atlas.csv")],
                 ["evaluate", "--corpus", str(corpus), "--out", str(corpus / "made" / "report.md")]):
        assert main(args) == 2
        assert "inside the corpus folder" in capsys.readouterr().err
    assert sorted(p.name for p in corpus.iterdir()) == ["worms.csv"]
