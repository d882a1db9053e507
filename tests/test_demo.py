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
