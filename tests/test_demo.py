"""`make demo` (napari_fdlc.demo): what it does when it cannot run."""

import os
import subprocess
import sys


def test_demo_with_demo_output_a_file_is_one_line(tmp_path):
    """`make demo` where ./demo_output is a file: one line and exit 2, the file left alone (not a
    FileExistsError traceback)."""
    (tmp_path / "demo_output").write_text("not a folder")
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", FDLC_SESSION_DIR=str(tmp_path / "sessions"))
    env.pop("FDLC_NO_GUI", None)
    proc = subprocess.run([sys.executable, "-m", "napari_fdlc.demo", "--headless"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2 and "demo_output" in proc.stderr, (proc.returncode, proc.stderr)
    assert (tmp_path / "demo_output").read_text() == "not a folder"
