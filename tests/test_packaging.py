"""Packaging: the Makefile's setup and the source distribution.

Nothing here installs anything or creates a real virtual environment: the Makefile test runs a
copy of the Makefile in tmp_path with stub interpreters, and the sdist is built from a copy of
the source in tmp_path (the checkout is never written).
"""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import tarfile
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


# ----- the Makefile's setup on a .venv left without pip --------------------------------------


def _stub(path: Path, body: str) -> Path:
    path.write_text("#!/bin/sh\n" + textwrap.dedent(body))
    path.chmod(path.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    return path


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_setup_recovers_a_venv_left_without_pip(tmp_path):
    """`make setup` (run first by `make demo` / `make test`, README's two commands) should
    recover a .venv whose interpreter has no pip -- what `python3 -m venv .venv` leaves behind
    on Debian/Ubuntu when python3-venv (ensurepip) is missing: it prints "install the
    python3-venv package" and exits 1 after creating .venv/bin/python. After the user installs
    python3-venv and runs `make demo` again, setup should recreate the venv and go on. Instead
    the Makefile only checks `test -x .venv/bin/python`, keeps the broken venv and fails with
    "No module named pip" on every later run until .venv is deleted by hand.

    (Run on a copy of the Makefile in tmp_path with stub interpreters: nothing is installed.)"""
    work = tmp_path / "checkout"
    work.mkdir()
    for name in ("Makefile", "pyproject.toml", "constraints.txt"):
        shutil.copy2(ROOT / name, work / name)
    log = tmp_path / "log.txt"
    # a venv interpreter that works: pip "installs" by logging
    good = _stub(tmp_path / "good-venv-python", f"""\
        echo "venv-python $*" >> {log}
        exit 0
    """)
    # the system python: the version check runs for real; -m venv makes a working (stub) venv
    real = sys.executable
    python3 = _stub(tmp_path / "python3", f"""\
        if [ "$1" = "-c" ]; then exec {real} "$@"; fi
        if [ "$1" = "-m" ] && [ "$2" = "venv" ]; then
            for last; do :; done
            rm -rf "$last"; mkdir -p "$last/bin"; cp {good} "$last/bin/python"
            echo "venv $*" >> {log}; exit 0
        fi
        echo "unexpected: python3 $*" >> {log}; exit 1
    """)
    # the .venv a failed `python3 -m venv` left: an interpreter without pip (nor ensurepip)
    (work / ".venv" / "bin").mkdir(parents=True)
    _stub(work / ".venv" / "bin" / "python", """\
        if [ "$1" = "-m" ] && { [ "$2" = "pip" ] || [ "$2" = "ensurepip" ]; }; then
            echo "/checkout/.venv/bin/python: No module named $2" >&2; exit 1
        fi
        exit 0
    """)
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(tmp_path)}
    proc = subprocess.run(["make", "-C", str(work), "setup", f"PYTHON={python3}"], capture_output=True,
                          text=True, timeout=60, env=env)
    assert proc.returncode == 0, (
        "make setup kept the .venv without pip and failed:\n" + (proc.stdout + proc.stderr)[-800:])
    assert (work / ".venv" / ".installed").exists()


# ----- the sdist ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sdist_names(tmp_path_factory):
    """Names in the sdist built (setuptools, no isolation) from a copy of the checkout."""
    try:
        from setuptools import build_meta
    except ImportError:  # pragma: no cover
        pytest.skip("setuptools is not importable")
    src = tmp_path_factory.mktemp("copy")
    ignore = shutil.ignore_patterns(".venv", ".git", "__pycache__", "*.egg-info", "build", "runs", "demo_output")
    for name in ("pyproject.toml", "README.md", "MANIFEST.in", "LICENSE", "constraints.txt", "Makefile"):
        shutil.copy2(ROOT / name, src / name)
    for folder in ("src", "tests"):
        shutil.copytree(ROOT / folder, src / folder, ignore=ignore)
    out = tmp_path_factory.mktemp("sdist")
    cwd = os.getcwd()
    try:
        os.chdir(src)
        name = build_meta.build_sdist(str(out))
    finally:
        os.chdir(cwd)
    with tarfile.open(out / name) as tar:
        top = name.removesuffix(".tar.gz")
        return {m.name.removeprefix(top + "/") for m in tar.getmembers()}


def test_sdist_ships_its_tests_with_their_fixtures(sdist_names):
    """The sdist ships tests/test_*.py (setuptools' default); they should come with the
    conftest.py that defines their fixtures (``worm``, ``untrained_weights``, ``shipped``, ...),
    so that `pytest` in the unpacked sdist runs them. Instead tests/conftest.py (and
    tests/io/, tests/_napari/) are left out: every test using a shared fixture errors with
    "fixture 'worm' not found"."""
    shipped_tests = sorted(n for n in sdist_names if n.startswith("tests/test_") and n.endswith(".py"))
    if not shipped_tests:  # an sdist without tests is fine too
        return
    fixtures = ("worm", "untrained_weights", "shipped", "table_files")
    uses_fixture = [n for n in shipped_tests if (ROOT / n).exists()
                    and any(f"({fx}" in (ROOT / n).read_text() or f", {fx}" in (ROOT / n).read_text() for fx in fixtures)]
    assert "tests/conftest.py" in sdist_names, (
        f"{len(shipped_tests)} test files shipped, {len(uses_fixture)} of them using conftest fixtures, "
        "but tests/conftest.py is not in the sdist")
