"""All-or-nothing output files: temp file beside the destination, fsync, rename.

A failed or interrupted run leaves either the old file or the complete new one,
never a partial one; an output path that is also an input is refused up front.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator

from .errors import OutputError


def check_output(path: str, inputs: Iterable[str] = (), extensions: Iterable[str] | None = None) -> str:
    """Refuse an output that would overwrite an input or cannot be written; return its real path."""
    ext = os.path.splitext(path)[1].lower()
    if extensions is not None and ext not in tuple(extensions):
        raise OutputError(f"{path}: output must end in {', '.join(extensions)} (got {ext or 'no extension'!r})")
    real = os.path.realpath(path)
    for src in inputs:
        if src and os.path.realpath(src) == real:
            raise OutputError(f"{path}: output path is also an input; inputs are never modified")
    folder = os.path.dirname(real) or "."
    shown = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OutputError(f"{path}: output folder {shown} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: output folder {shown} is not writable")
    if os.path.isdir(real):
        raise OutputError(f"{path}: is a folder")
    return real


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def replacing(path: str, inputs: Iterable[str] = (), extensions: Iterable[str] | None = None) -> Iterator[str]:
    """Yield a temp path to write; on success it is fsynced and renamed over path."""
    real = check_output(path, inputs, extensions)
    folder, name = os.path.split(real)
    stem, ext = os.path.splitext(name)
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".tmp{ext}", dir=folder)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, real)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)


def write_text(path: str, text: str, inputs: Iterable[str] = ()) -> str:
    """Write a small text file (JSON reports) atomically."""
    with replacing(path, inputs) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path


@contextlib.contextmanager
def updating(path: str) -> Iterator[None]:
    """Serialise read-modify-write updates of path (``fit --group`` into one CORRECTIVES
    layer from several processes): an exclusive ``flock`` on path's folder, held while
    the old file is read and the new one renamed over it. Without it, two concurrent
    updates would each keep only their own group."""
    import fcntl

    folder = os.path.dirname(os.path.realpath(path)) or "."
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock
