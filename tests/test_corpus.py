"""corpus.load_corpus: an annotated corpus folder as someone else assembles it (worms.csv and one
table per worm), read in place; what is wrong with it is one line that says what to do.

Everything runs on small worms generated from the shipped atlas under tmp_path."""

from __future__ import annotations

import pytest

from napari_fdlc.cli import main
from napari_fdlc.corpus import load_corpus
from napari_fdlc.errors import FdlcError
from napari_fdlc.reference import generate_worm


def run(*args) -> int:
    return main([str(a) for a in args])


@pytest.fixture(scope="module")
def two_worms():
    return [generate_worm(seed=1), generate_worm(seed=2)]


def test_a_worm_listed_twice_in_worms_csv_is_refused(tmp_path, write_corpus, two_worms):
    """A worms.csv row repeated is refused in one line naming the worm: loaded twice, a worm was
    its own template in `fdlc evaluate` and could be trained and validated on."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": two_worms})
    index = corpus / "worms.csv"
    index.write_text(index.read_text() + index.read_text().splitlines()[1] + "\n")
    with pytest.raises(FdlcError) as err:
        load_corpus(corpus)
    assert "worms.csv" in str(err.value) and "w0" in str(err.value), err.value


def test_worms_csv_with_a_trailing_comma_on_every_row_is_read_or_refused_in_its_own_name(tmp_path, write_corpus, two_worms):
    """Rows ending in a comma (as some exports write) are read, or refused naming worms.csv;
    pandas once took the first column as the index, shifting every column."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": two_worms})
    index = corpus / "worms.csv"
    lines = index.read_text().splitlines()
    index.write_text("\n".join([lines[0]] + [line + "," for line in lines[1:]]) + "\n")
    try:
        worms = load_corpus(corpus)
    except FdlcError as exc:
        assert "worms.csv" in str(exc), exc
    else:
        assert [(w.lab, w.name) for w in worms] == [("NP", "w0"), ("NP", "w1")]


def test_a_worms_csv_row_without_a_worm_id_names_worms_csv(tmp_path, write_corpus, two_worms):
    """A row with an empty dataset or worm (',,,,' left by a spreadsheet) is refused as a bad
    worms.csv row, not looked up as `corpus/NP/.csv`."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": two_worms})
    index = corpus / "worms.csv"
    index.write_text(index.read_text() + "NP,0,,0,0\n")
    with pytest.raises(FdlcError) as err:
        load_corpus(corpus)
    assert "worms.csv" in str(err.value), err.value


def test_a_worm_file_missing_from_the_corpus_says_worms_csv_lists_it(tmp_path, write_corpus, two_worms, capsys):
    """A listed worm whose file is absent: one line saying worms.csv lists it, so what to do (add
    the file or remove the row)."""
    corpus = write_corpus(tmp_path / "corpus", {"NP": two_worms})
    (corpus / "NP" / "w1.csv").unlink()
    assert run("atlas", "--corpus", corpus, "--out", tmp_path / "atlas.csv") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "w1.csv" in err[0] and "worms.csv" in err[0], err


def test_fdlc_corpus_pointing_at_no_corpus_is_not_replaced_by_another(tmp_path, write_corpus, two_worms, monkeypatch):
    """$FDLC_CORPUS naming a folder without worms.csv is refused, not silently passed over for
    ../shared/data/neuropal_corpus (another corpus than asked)."""
    write_corpus(tmp_path / "shared" / "data" / "neuropal_corpus", {"NP": two_worms})
    (tmp_path / "run").mkdir()
    (tmp_path / "mine").mkdir()
    monkeypatch.chdir(tmp_path / "run")
    monkeypatch.setenv("FDLC_CORPUS", str(tmp_path / "mine"))
    with pytest.raises(FdlcError) as err:
        load_corpus()
    assert "mine" in str(err.value) or "FDLC_CORPUS" in str(err.value), err.value



def test_default_corpus_lookup_survives_a_shallow_install(tmp_path, monkeypatch, capsys):
    """`fdlc atlas --out atlas.csv` without --corpus on a package installed at a shallow path
    (``pip install --target /opt`` → /opt/napari_fdlc/corpus.py, or a container's
    PYTHONPATH=/app) should end with the one-line "NeuroPAL corpus not found: pass --corpus
    PATH ..." and exit code 2. Instead corpus.default_corpus_path takes
    ``Path(__file__).resolve().parents[3]`` (the source checkout's layout), which does not exist
    there: an IndexError traceback escapes cli.main."""
    from napari_fdlc import corpus
    from napari_fdlc.cli import main

    monkeypatch.delenv("FDLC_CORPUS", raising=False)
    monkeypatch.setattr(corpus, "__file__", "/opt/napari_fdlc/corpus.py")  # where --target /opt puts it
    work = tmp_path / "a" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)  # ../shared/data/neuropal_corpus is not there either
    try:
        code = main(["atlas", "--out", str(tmp_path / "atlas.csv")])
    except IndexError as exc:
        pytest.fail(f"IndexError escaped `fdlc atlas` ({exc}) instead of 'NeuroPAL corpus not found'")
    assert code == 2
    assert "corpus not found" in capsys.readouterr().err
