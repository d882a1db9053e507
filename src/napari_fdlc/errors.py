"""Errors a user can act on, and the one-line warnings the faces print.

Every problem with user input is raised once, as an :class:`FdlcError` whose message is a
single line that says what is wrong and where; the CLI prints it and exits non-zero, the napari
widgets show it as a notification.
"""

from __future__ import annotations

import os
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path


class FdlcError(Exception):
    """A problem with the user's input or environment, with a one-line message."""


class TableError(FdlcError, ValueError):
    """A neuron table that cannot be used."""


class ModelError(FdlcError):
    """Weights or a model configuration that cannot be used."""


def warn(message: str) -> None:
    """Print one warning line on stderr (the contract asks for one line, no traceback)."""
    print(f"fdlc: warning: {message}", file=sys.stderr, flush=True)


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs):
    """Open a temporary file beside ``path``; rename it over ``path`` only if the block succeeds.

    A crash or an exception never leaves a half-written file, and an existing file is replaced in
    one step.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # said of the file asked for, not of the temporary one
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        with os.fdopen(fd, mode, **kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        # mkstemp creates 0600; give the file the permissions a plain open() would have.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
