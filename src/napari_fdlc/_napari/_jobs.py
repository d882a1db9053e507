"""Waiting for a widget's job from a script or a test (``widget.wait()``)."""

from __future__ import annotations

from typing import Callable

from qtpy.QtCore import QEventLoop, QTimer


def wait_until_idle(is_busy: Callable[[], bool], idle, timeout: float | None = None) -> bool:
    """Process GUI events until ``is_busy()`` is false; True when idle (False on ``timeout``).

    ``idle`` is a signal the widget emits on the GUI thread when its job has ended. A worker's
    own ``finished`` will not do: it is emitted from the worker's thread, so a job that fails at
    once may have emitted it before the loop could connect to it, and the loop would then wait
    forever (it did, for a job refused on its first line). The busy flag changes only on the GUI
    thread, while events are processed, so nothing can end the job between the check and
    ``exec``."""
    if not is_busy():
        return True
    loop = QEventLoop()
    idle.connect(loop.quit)
    if timeout is not None:
        QTimer.singleShot(int(timeout * 1000), loop.quit)
    try:
        if is_busy():
            loop.exec()
    finally:
        idle.disconnect(loop.quit)
    return not is_busy()
