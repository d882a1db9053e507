"""Errors a user can act on, and the one-line warnings the faces print.

Every problem with user input is raised once, as an :class:`FdlcError` whose message is a
single line that says what is wrong and where; the CLI prints it and exits non-zero, the napari
widgets show it as a notification.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Callable


class FdlcError(Exception):
    """A problem with the user's input or environment, with a one-line message."""


class TableError(FdlcError, ValueError):
    """A neuron table that cannot be used."""


class ModelError(FdlcError):
    """Weights or a model configuration that cannot be used."""


def one_line(message: object) -> str:
    """``message`` as one printable line: a control character that came from the input (a line
    break inside a quoted cell, a terminal escape) is shown escaped, as Python writes it, instead
    of breaking the line or acting on the terminal."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(message))


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type's name when it has none): a library's
    error said in one line."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


_warning_handler: ContextVar[Callable[[str], None] | None] = ContextVar("fdlc_warning_handler", default=None)


def warn(message: str) -> None:
    """Print one warning line on stderr (the contract asks for one line, no traceback), and
    hand it to the handler of an enclosing :func:`warnings_to` (a napari notification)."""
    print(f"fdlc: warning: {one_line(message)}", file=sys.stderr, flush=True)
    handler = _warning_handler.get()
    if handler is not None:
        handler(message)


@contextmanager
def warnings_to(handler: Callable[[str], None]):
    """Within this block (and thread), also hand every :func:`warn` line to ``handler``: what
    a reader warns about reaches a napari user, who does not see stderr."""
    token = _warning_handler.set(handler)
    try:
        yield
    finally:
        _warning_handler.reset(token)


def check_output(out: str | os.PathLike, inputs=(), create_folder: bool = False) -> Path:
    """The output file ``out``, refused before any work when it cannot be a file written there:
    an existing folder (or a path ending in a separator), a parent that is a file or (unless
    ``create_folder``) missing, a folder without write permission, a device other than a
    stream, or one of the ``inputs`` (files read; a folder given as input stands for the files
    in it). A stream (/dev/null, /dev/stdout, a named pipe) is written through; a link stands
    for the file it names."""
    text = str(out)
    path = Path(out)
    if not text or path.is_dir() or text.endswith(("/", os.sep)):
        raise FdlcError(f"{text or '--out'}: is a folder; --out must be a file")
    if _is_stream(path):  # /dev/null, /dev/stdout, a named pipe: written through (atomic_write)
        return path
    if path.exists() and not path.is_file():
        raise FdlcError(f"{out}: is a device, not a file; --out must be a file")
    path = _followed(path)
    existing = next(p for p in path.parents if p.exists() or p == Path(p.anchor or "."))
    if not existing.is_dir():
        raise FdlcError(f"{out}: {existing} is a file, not a folder")
    if existing != path.parent and not create_folder:
        raise FdlcError(f"{out}: the folder {path.parent} does not exist")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise FdlcError(f"{out}: cannot write in {existing} (permission denied)")
    if _replaces_input(path, inputs):
        raise FdlcError(f"{out}: --out would replace an input; choose another output")
    return path


def _replaces_input(path: str | os.PathLike, inputs) -> bool:
    """Whether writing ``path`` would replace one of the ``inputs`` (a folder: the files in it)."""
    try:
        target = Path(path).resolve()
    except (RuntimeError, OSError):  # Python 3.11 says a loop of links with RuntimeError, 3.13 with OSError
        raise FdlcError(f"{path}: a loop of symbolic links (it or a folder above it); give another file") from None
    for given in inputs:
        given = Path(given)
        if given.resolve() == target or (given.is_dir() and target.parent == given.resolve()):
            return True
    return False


def _is_stream(path: Path) -> bool:
    """An existing device or named pipe (not a file, not a folder)."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


def _followed(path: Path) -> Path:
    """A link's target (the file it names, which is what gets written, not the link replaced)."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs):
    """Open a temporary file beside ``path``; rename it over ``path`` only if the block succeeds.

    A crash or an exception never leaves a half-written file, and an existing file is replaced in
    one step.
    """
    path = Path(path)
    if _is_stream(path):
        # Renaming a file over a device or a pipe would replace it (as root, /dev/null for the
        # whole machine): written through instead; a stream cannot be half-written in place anyway.
        with open(path, mode, **kwargs) as handle:
            yield handle
        return
    path = _followed(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # a short name: a file name of 245 characters (Linux allows 255) left no room for ".<name>.<random>.tmp"
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:40]}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:  # said of the file asked for, not of the temporary one
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        with os.fdopen(fd, mode, **kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        plain_permissions(tmp)
        try:
            os.replace(tmp, path)
        except OSError as exc:  # e.g. a folder of that name: said of the file asked for
            raise OSError(exc.errno, exc.strerror, str(path)) from None
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def plain_permissions(path: str | Path) -> None:
    """Give a file the permissions a plain open() would have: mkstemp, and safetensors, create
    0600 (trained weights that other users of a shared machine could not read)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def model_files(path: str | Path) -> tuple[Path, Path]:
    """The weights and configuration files of the model at ``path`` (``path.safetensors``,
    ``path.json``; given with either suffix, the same pair). The suffix is added, not put in
    place of one: ``runs/model.v2`` is ``runs/model.v2.safetensors``. Here, not in model.py:
    checking outputs against the weights needs no torch (fdlc track --method geometry,
    fdlc label --method cpd)."""
    text = str(path)
    for suffix in (".safetensors", ".json"):
        if text.endswith(suffix):
            text = text[: -len(suffix)]
    return Path(text + ".safetensors"), Path(text + ".json")
