"""The widgets' warm-up: the model's first use (torch's import, the shipped weights' load, the
traces) run in a thread as soon as a widget is docked, while the user picks the inputs, so that
the first click is as quick as the next ones (docs/speed.md, ``benchmarks/first_click.py``).
A job joins the thread before it uses the model: one model, used by one thread at a time."""

from __future__ import annotations

import threading

THREAD_NAME = "napari-fdlc warm-up"


def start_warm_up(warm) -> threading.Thread:
    """Run ``warm()`` in a thread and return it. Not a daemon thread, so that the interpreter
    never exits under torch; errors are left to the first real job, which shows them in the
    GUI."""

    def run():
        try:
            warm()
        except Exception:  # a broken install is reported by the first real job
            pass

    thread = threading.Thread(target=run, name=THREAD_NAME)
    thread.start()
    return thread
