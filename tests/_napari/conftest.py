"""GUI tests: napari's ``make_napari_viewer`` on a real X server (Xvfb in ``make test``).

Skipped with a one-line reason when there is no display (``FDLC_NO_DISPLAY=1`` or no
``DISPLAY``). The model is real but untrained (tiny, fast) and the template is passed
explicitly, so these tests need neither the shipped weights nor the reference panel.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

_HERE = Path(__file__).resolve().parent


def _no_display_reason() -> str | None:
    if os.environ.get("FDLC_NO_DISPLAY") == "1":
        return "GUI tests skipped: FDLC_NO_DISPLAY=1"
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "GUI tests skipped: no display (run under xvfb-run, as 'make test' does)"
    try:
        import napari  # noqa: F401
        import qtpy  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the environment
        return f"GUI tests skipped: napari/Qt not importable ({type(exc).__name__})"
    return None


NO_DISPLAY = _no_display_reason()


def pytest_collection_modifyitems(config, items):
    if not NO_DISPLAY:
        return
    for item in items:
        if _HERE in Path(str(item.path)).resolve().parents:
            item.add_marker(pytest.mark.skip(reason=NO_DISPLAY))


def pytest_report_header(config):
    return NO_DISPLAY


@pytest.fixture(autouse=True)
def _warm_up_ends_with_its_test():
    """A widget's warm-up thread (_napari/_warm_up.py) never runs on into the next test."""
    yield
    from napari_fdlc._napari._warm_up import THREAD_NAME

    for thread in threading.enumerate():
        if thread.name == THREAD_NAME:
            thread.join()


@pytest.fixture(autouse=True)
def _session_dir(tmp_path, monkeypatch):
    """Sessions of the bundled sample go to the user's data folder: keep them in tmp."""
    monkeypatch.setenv("FDLC_SESSION_DIR", str(tmp_path / "user-data" / "sessions"))


@pytest.fixture(scope="session")
def sample_files(tmp_path_factory):
    """The bundled sample; generated into tmp while the package does not ship it yet."""
    from napari_fdlc import sample

    stack, table = sample.sample_paths()
    if stack.exists() and table.exists():
        yield stack, table
        return
    from napari_fdlc.reference import generate_worm

    paths = sample.make_sample(generate_worm(seed=sample.SAMPLE_SEED), tmp_path_factory.mktemp("sample"), seed=sample.SAMPLE_SEED)
    patch = pytest.MonkeyPatch()
    patch.setattr(sample, "sample_paths", lambda: paths)
    yield paths
    patch.undo()


@pytest.fixture(scope="session")
def identifier():
    """A real, untrained model (small and quick): what the widget runs is the real pipeline."""
    torch = pytest.importorskip("torch")
    from napari_fdlc.identify import Identifier
    from napari_fdlc.model import CorrespondenceModel

    torch.manual_seed(0)
    return Identifier(CorrespondenceModel({"layers": 1, "dim": 32}), device="cpu")


@pytest.fixture(scope="session")
def templates():
    try:
        from napari_fdlc.reference import generate_worm

        return [generate_worm(seed=3)]
    except Exception:  # no atlas: a labelled random worm does as a template
        from napari_fdlc.table import NeuronTable

        rng = np.random.default_rng(3)
        n = 150
        xyz = rng.normal(0, 1, (n, 3)) * [30, 8, 6]
        return [NeuronTable(xyz, {c: rng.normal(size=n) for c in "RGB"}, np.array([f"N{i}" for i in range(n)], dtype=object))]


@pytest.fixture
def labelled_viewer(make_napari_viewer, sample_files, identifier, templates):
    """napari with the sample open and the Auto-label widget docked, model injected."""
    viewer = make_napari_viewer()
    viewer.open_sample("napari-fdlc", "neuropal")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    widget.identifier = identifier
    widget.set_templates(templates)
    return viewer, widget
