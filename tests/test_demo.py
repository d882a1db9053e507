"""`make demo` (napari_fdlc.demo): what it does when it cannot run."""

import os
import subprocess
import sys

import pytest


def test_demo_with_demo_output_a_file_is_one_line(tmp_path):
    """`make demo` where ./demo_output is a file: one line and exit 2, the file left alone (not a
    FileExistsError traceback)."""
    pytest.importorskip("napari")
    (tmp_path / "demo_output").write_text("not a folder")
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", FDLC_SESSION_DIR=str(tmp_path / "sessions"))
    env.pop("FDLC_NO_GUI", None)
    proc = subprocess.run([sys.executable, "-m", "napari_fdlc.demo", "--headless"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2 and "demo_output" in proc.stderr, (proc.returncode, proc.stderr)
    assert (tmp_path / "demo_output").read_text() == "not a folder"


def test_demo_without_napari_is_one_line(tmp_path):
    """The demo where only the core is installed (no napari, no Qt): one line that says what to
    install, exit 2. It was a ModuleNotFoundError traceback (seen on the GPU machine, no qtpy)."""
    env = dict(os.environ, FDLC_SESSION_DIR=str(tmp_path / "sessions"))
    env.pop("FDLC_NO_GUI", None)
    missing = "import sys; sys.modules['qtpy'] = sys.modules['napari'] = None; "  # imports of them fail as if absent
    proc = subprocess.run([sys.executable, "-c", missing + "from napari_fdlc.demo import main; sys.exit(main(['--headless']))"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, (proc.returncode, proc.stderr)
    assert "is missing" in proc.stderr and "napari-fdlc[napari]" in proc.stderr, proc.stderr


def test_demo_flow_command_bad_out_dir_is_one_line(tmp_path):
    """docs/gui.md: `python -m napari_fdlc._napari.demo_flow OUT_DIR [--headless]`. With an
    OUT_DIR that cannot be made (a file is in the way) it should say so in one line and exit
    non-zero, as `make demo` does. Instead demo_flow.main lets run_demo's FdlcError out: a
    Python traceback."""
    pytest.importorskip("napari")
    (tmp_path / "afile").write_text("x")
    env = dict(os.environ, FDLC_SESSION_DIR=str(tmp_path / "sessions"))
    proc = subprocess.run([sys.executable, "-m", "napari_fdlc._napari.demo_flow", str(tmp_path / "afile" / "out"),
                           "--headless"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "afile" in proc.stderr, proc.stderr


def test_interactive_demo_needs_no_output_folder(tmp_path, monkeypatch):
    """`make demo` with a display opens napari for a person; it writes nothing to demo_output
    (README: only the run without a display writes demo_output/labels.csv and screenshot.png).
    It should open napari whether or not ./demo_output can be made (a read-only checkout, a
    file named demo_output). Instead run_demo makes the folder first even when not headless,
    and refuses to open napari at all when it cannot ('cannot make the demo's output folder')."""
    napari = pytest.importorskip("napari")
    from napari_fdlc._napari import demo_flow

    class FakeViewer:
        def __init__(self, *args, **kwargs):
            pass

        def close(self):
            pass

    monkeypatch.setattr(napari, "Viewer", FakeViewer)
    monkeypatch.setattr(napari, "run", lambda *a, **k: None)
    monkeypatch.setattr(demo_flow, "open_sample_with_widget", lambda *a, **k: object())
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "demo_output"  # cannot be made, as in a folder the user may not write
    assert demo_flow.run_demo(out, headless=False) is None
    assert (tmp_path / "afile").read_text() == "x"


def test_demo_opens_napari_on_a_desktop_without_DISPLAY(monkeypatch, capsys):
    """On macOS and Windows a desktop has no DISPLAY variable, yet napari opens there (the GUI
    tests' conftest only asks for DISPLAY on Linux). `make demo` there should open napari
    (run_demo with headless=False). Instead demo.main treats every platform as X11: it prints
    'No display and no Xvfb: skipped the napari part' and never opens napari."""
    pytest.importorskip("napari")
    from napari_fdlc import demo
    from napari_fdlc._napari import demo_flow

    calls = []
    monkeypatch.setattr(demo_flow, "run_demo", lambda out, headless, **k: calls.append(headless))
    monkeypatch.setattr(demo, "identify_sample", lambda *a, **k: 0.0)
    monkeypatch.setattr(demo.shutil, "which", lambda name: None)
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "FDLC_NO_GUI"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(sys, "platform", "darwin")
    assert demo.main([]) == 0
    assert calls == [False], capsys.readouterr().out


def test_demo_help_does_not_run_the_demo(capsys):
    """`python -m napari_fdlc.demo --help` printed nothing of use and ran the whole demo (every
    argument but --headless was ignored); an unknown argument is refused."""
    from napari_fdlc import demo

    assert demo.main(["--help"]) == 0 and "usage" in capsys.readouterr().out
    assert demo.main(["--headles"]) == 2 and "--headles" in capsys.readouterr().err
