"""The demo: napari with the bundled sample and the Auto-label widget.

``run_demo(out_dir, headless=False)`` opens napari for a person to use. With ``headless=True``
(under Xvfb, for ``make demo`` and the docs) it runs Auto-label on the sample, exports the CSV
to ``out_dir/labels.csv``, saves a screenshot of the window to ``out_dir/screenshot.png`` and
returns both paths. Sessions of a headless run go to ``out_dir/sessions`` so that a demo never
restores (or touches) a user's own review of the sample.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FdlcError, atomic_write, one_line
from ._widget import camera

WINDOW_SIZE = (1500, 950)


def run_demo(
    out_dir: str | os.PathLike,
    headless: bool,
    *,
    identifier=None,
    templates=None,
    threshold: float | None = None,
) -> tuple[Path, Path] | None:
    """Open napari with the sample and the widget; headless: label, export, screenshot.

    ``identifier`` / ``templates`` replace the shipped model / built-in reference panel (tests);
    ``threshold`` sets the confidence slider before the export (default: the widget's).
    """
    import napari

    out_dir = Path(out_dir)
    if headless:  # (napari for a person writes nothing there: a read-only checkout opens it too)
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FdlcError(f"{out_dir}: cannot make the demo's output folder there ({exc.strerror or exc}); "
                            "move what is in the way or run from another folder") from None
    old_env = os.environ.get("FDLC_SESSION_DIR")
    if headless:
        os.environ["FDLC_SESSION_DIR"] = str((out_dir / "sessions").resolve())  # (cached by its text)
    try:
        viewer = napari.Viewer(show=not headless, title="napari-fdlc demo")
        try:
            viewer.window._qt_window.resize(*WINDOW_SIZE)
        except AttributeError:
            pass
        widget = open_sample_with_widget(viewer, identifier, templates)
        if not headless:
            napari.run()
            return None
        try:
            layer = widget.auto_label()
            if layer is None:
                raise FdlcError(widget.last_error or "auto-label failed")
            if threshold is not None:
                widget.set_threshold(threshold)
            show_labelled_plane(viewer, layer)
            shot = out_dir / "screenshot.png"
            try:  # first: one that cannot be written leaves no new labels beside an old picture
                save_screenshot(viewer, shot)
            except OSError as exc:
                raise FdlcError(f"{shot}: cannot be written ({exc.strerror or exc})") from None
            labels = widget.export(out_dir / "labels.csv", overwrite=True)
            return labels, shot
        finally:
            viewer.close()
    finally:
        if headless:
            if old_env is None:
                os.environ.pop("FDLC_SESSION_DIR", None)
            else:
                os.environ["FDLC_SESSION_DIR"] = old_env


def open_sample_with_widget(viewer, identifier=None, templates=None):
    """Open the bundled sample and the Auto-label dock; ``identifier`` / ``templates`` replace the
    shipped model / built-in panel (tests, docs)."""
    viewer.open_sample("napari-fdlc", "neuropal")
    _, widget = viewer.window.add_plugin_dock_widget("napari-fdlc", "Auto-label")
    if identifier is not None:
        widget.identifier = identifier
    if templates is not None:
        widget.set_templates(templates)
    return widget


def show_labelled_plane(viewer, layer) -> int:
    """Fit the view and go to the z plane showing the most named neurons; returns the plane."""
    viewer.reset_view()
    camera(viewer).zoom *= 1.2
    data = np.asarray(layer.data)
    labels = np.asarray(layer.features["label"], dtype=object)
    planes = np.rint(data[:, 0]).astype(int)
    named = planes[labels != ""] if (labels != "").any() else planes
    best = int(np.bincount(named - named.min()).argmax() + named.min()) if len(named) else 0
    z_world = best * float(layer.scale[0]) + float(layer.translate[0])
    viewer.dims.set_point(viewer.dims.ndim - 3, z_world)
    viewer.layers.selection.active = layer
    return best


def save_screenshot(viewer, path: Path) -> None:
    """The window as a PNG at ``path``, written whole or not at all (temporary file, renamed)."""
    import imageio.v3 as iio

    image = viewer.screenshot(canvas_only=False, flash=False)
    with atomic_write(path, "wb") as handle:
        handle.write(iio.imwrite("<bytes>", image, extension=".png"))


def docs_screenshot(path: str | os.PathLike, *, identifier=None, templates=None, threshold: float | None = None) -> Path:
    """The screenshot of docs/gui.md: the sample labelled, a few decisions of each kind made
    (so every ring colour shows), one neuron selected with its candidates. Run under Xvfb."""
    import tempfile

    import napari

    path = Path(path)
    with tempfile.TemporaryDirectory() as tmp:
        old_env = os.environ.get("FDLC_SESSION_DIR")
        os.environ["FDLC_SESSION_DIR"] = tmp
        viewer = napari.Viewer(show=False, title="napari-fdlc")
        try:
            viewer.window._qt_window.resize(*WINDOW_SIZE)
            w = open_sample_with_widget(viewer, identifier, templates)
            layer = w.auto_label()
            if layer is None:
                raise FdlcError(w.last_error or "auto-label failed")
            if threshold is not None:
                w.set_threshold(threshold)
            plane = show_labelled_plane(viewer, layer)
            on_plane = [int(i) for i in np.flatnonzero(np.rint(layer.data[:, 0]) == plane)]
            named = [i for i in on_plane if layer.features["label"][i]]
            f = layer.features
            taken = set(f["auto_id"])
            if len(named) >= 4:
                w.accept(named[0])
                w.accept(named[1])
                spare = next((c for c in f["cand_2"] if c and c not in taken), None)
                if spare:
                    w.assign(named[2], spare)
                w.mark_unsure(named[3])
            if named:
                w.select_neuron(named[-1])
            viewer.dims.set_point(viewer.dims.ndim - 3, plane * float(layer.scale[0]))
            viewer.reset_view()
            camera(viewer).zoom *= 1.2
            save_screenshot(viewer, path)
        finally:
            viewer.close()
            if old_env is None:
                os.environ.pop("FDLC_SESSION_DIR", None)
            else:
                os.environ["FDLC_SESSION_DIR"] = old_env
    return path


def main(argv: list[str] | None = None) -> int:  # python -m napari_fdlc._napari.demo_flow OUT [--headless | --docs-screenshot PNG]
    import argparse
    import sys

    from ..demo import OUT_DIR

    parser = argparse.ArgumentParser(description="napari-fdlc demo on the bundled sample")
    parser.add_argument("out_dir", nargs="?", default=str(OUT_DIR))
    parser.add_argument("--headless", action="store_true")
    parser.add_argument("--docs-screenshot", metavar="PNG", help="write the screenshot of docs/gui.md and exit")
    args = parser.parse_args(argv)
    try:
        if args.docs_screenshot:
            print(docs_screenshot(args.docs_screenshot))
            return 0
        result = run_demo(args.out_dir, args.headless)
    except (FdlcError, OSError) as exc:
        print(f"fdlc: error: {one_line(exc)}", file=sys.stderr)
        return 2
    if result:
        print("\n".join(str(p) for p in result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
