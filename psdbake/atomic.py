"""All-or-nothing output files: temp files beside the destinations, fsync, rename together.

A failed or interrupted run leaves either every old file or every complete new one,
never a partial one and never a mix: a command with several outputs (``eval
--points-cache``, a chunked eval, ``fit --report``) writes all of them to temporary
files first and renames them only once all are written (``Transaction``). The renames
run with SIGINT/SIGTERM held back, and a rename that fails puts the old files back.

An output that is also an input is refused up front: ``inputs`` are compared by real
path *and* by file identity (device, inode), so a symbolic or hard link to an input is
refused too. Callers pass every file the command reads (``psdbake.usd.dependencies``
walks the layers an input reaches), not only the paths typed on the command line.

An existing file is replaced only when it is the command's own earlier output: a file of the
same kind that psdbake wrote (``outputs.OutputKind``), with a write permission bit set. An
asset, a sculpt, a WEIGHTS layer given to ``fit -o`` or a published file locked read-only
(mode 0444) is refused (exit 6) unless the user asks with ``--force`` (``forcing``).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import signal
import stat
import tempfile
from collections.abc import Iterable, Iterator

from .errors import OutputError
from .outputs import OutputKind

#: Temporary files are ``.psdbake-XXXXXXXX.tmp.EXT`` beside the destination: short, so a
#: destination name of any legal length has a legal temporary name, and ``.tmp`` in every
#: one, so leftovers are easy to spot (there are none unless the process is SIGKILLed).
_TEMP_PREFIX = ".psdbake-"


def _identity(path: str) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


#: ``--force``: replace an existing output that is not the command's own earlier output, or is read-only.
_FORCE: contextvars.ContextVar[bool] = contextvars.ContextVar("psdbake_force", default=False)


@contextlib.contextmanager
def forcing(enabled: bool = True) -> Iterator[None]:
    """Within the block, outputs may replace any regular file (the user's ``--force``)."""
    token = _FORCE.set(enabled)
    try:
        yield
    finally:
        _FORCE.reset(token)


def forced() -> bool:
    """Whether ``--force`` is in effect (``forcing``)."""
    return _FORCE.get()


def _check_replace(path: str, real: str, kind: OutputKind | None) -> None:
    """Refuse to replace a file that is read-only or is not this kind's earlier output, unless forced."""
    if _FORCE.get() or not os.path.isfile(real):
        return
    mode = os.stat(real).st_mode
    if not mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH) or not os.access(real, os.W_OK):
        raise OutputError(f"{path}: exists and is read-only (mode {stat.S_IMODE(mode):04o}: a published file?); "
                          "give --force to replace it")
    if kind is not None and kind.identify(real) != kind.name:
        raise OutputError(f"{path}: exists and is {kind.describe(real)}, not a psdbake {kind.label}; "
                          "give --force to replace it")


def check_output(path: str, inputs: Iterable[str] = (), extensions: Iterable[str] | None = None,
                 kind: OutputKind | None = None) -> str:
    """Refuse an output that would overwrite an input, cannot be written, or would replace a
    file that is not ``kind``'s earlier output (or is read-only) without ``--force``; return
    its real path. ``kind`` gives the extensions when ``extensions`` is None."""
    if extensions is None and kind is not None:
        extensions = kind.extensions
    ext = os.path.splitext(path)[1].lower()
    if extensions is not None and ext not in tuple(extensions):
        raise OutputError(f"{path}: output must end in {', '.join(extensions)} (got {ext or 'no extension'!r})")
    real = os.path.realpath(path)
    same = _identity(real)
    for src in inputs:
        if src and (os.path.realpath(src) == real or (same is not None and _identity(src) == same)):
            also = "" if os.path.abspath(src) == os.path.abspath(path) else f" ({src})"
            raise OutputError(f"{path}: output path is also an input{also}; inputs are never modified")
    folder = os.path.dirname(real) or "."
    shown = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OutputError(f"{path}: output folder {shown} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: output folder {shown} is not writable")
    if os.path.isdir(real):
        raise OutputError(f"{path}: is a folder")
    if os.path.exists(real) and not os.path.isfile(real):
        raise OutputError(f"{path}: exists and is not a regular file (a FIFO or device is never replaced)")
    _check_replace(path, real, kind)
    return real


def check_outputs(outputs: Iterable[tuple[str, OutputKind]], inputs: Iterable[str] = ()) -> list[str]:
    """``check_output`` for every (path, kind) of one command, and no two the same file;
    returns their real paths. Run before any work, so a bad output fails in a second."""
    inputs = list(inputs)
    seen: dict[str, str] = {}
    for path, kind in outputs:
        real = check_output(path, inputs, kind=kind)
        if real in seen:
            also = "" if seen[real] == path else f" (also as {seen[real]})"
            raise OutputError(f"{path}: names two outputs of this run{also}; each output needs its own file")
        seen[real] = path
    return list(seen)


def _pause_for_tests(moment: str) -> None:
    """Fault tests (tests/test_faults.py) kill a run at an exact moment of the commit rather
    than after a guessed delay: with ``PSDBAKE_PAUSE_AT=MOMENT:MARKER`` (MOMENT ``commit``:
    every output written, none renamed; ``rename``: the first output renamed, signals held)
    the run creates MARKER and waits up to 30 s. Unset (always, outside tests) it costs a lookup."""
    wanted = os.environ.get("PSDBAKE_PAUSE_AT", "")
    if not wanted.startswith(moment + ":"):
        return
    import time

    marker = wanted.split(":", 1)[1]
    with open(marker, "w", encoding="utf-8"):
        pass
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline and os.path.exists(marker):
        time.sleep(0.01)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT/SIGTERM back while files are renamed, so an interruption lands before
    the first rename or after the last one. Python runs signal handlers in the main thread
    whichever thread the signal reaches (USD's threads do not block it), so the handlers
    are swapped for one that only records, and a recorded signal is raised again after."""
    received: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    try:
        previous = {s: signal.signal(s, lambda signum, frame: received.append(signum)) for s in held}
    except ValueError:  # not the main thread: its signals are someone else's business
        yield
        return
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if received:
            signal.raise_signal(received[0])


class Transaction:
    """Several outputs committed together.

    ``path(dest)`` checks ``dest`` and returns a temporary path beside it to write;
    ``commit()`` fsyncs every temporary file and renames them over their destinations
    (the old files are put back if a rename fails); ``abort()`` removes the temporaries.
    Used as a context manager, it commits when the block succeeds and aborts otherwise.
    """

    def __init__(self, inputs: Iterable[str] = ()) -> None:
        self.inputs = [str(p) for p in inputs if p]
        self._planned: list[tuple[str, str, str]] = []  # (shown path, real path, temp path)

    def path(self, dest: str, extensions: Iterable[str] | None = None, kind: OutputKind | None = None) -> str:
        real = check_output(dest, self.inputs, extensions, kind)
        for shown, other, _ in self._planned:
            if other == real:
                raise OutputError(f"{dest}: written twice by this run (also as {shown})")
        folder, name = os.path.split(real)
        ext = os.path.splitext(name)[1]
        try:
            fd, tmp = tempfile.mkstemp(prefix=_TEMP_PREFIX, suffix=f".tmp{ext}", dir=folder)
        except OSError as exc:
            raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from None
        os.close(fd)
        self._planned.append((dest, real, tmp))
        return tmp

    def commit(self) -> list[str]:
        try:
            for shown, _, tmp in self._planned:
                try:
                    with open(tmp, "rb+") as fh:
                        os.fsync(fh.fileno())
                    os.chmod(tmp, 0o666 & ~_umask())
                except OSError as exc:
                    raise OutputError(f"{shown}: cannot write ({exc.strerror or exc})") from None
            _pause_for_tests("commit")
            with _signals_held():
                self._rename_all()
        finally:
            self.abort()
        return [shown for shown, _, _ in self._planned]

    def _rename_all(self) -> None:
        backups: list[tuple[str, str | None]] = []  # (real, backup of the old file or None)
        current = ""
        try:
            for shown, real, tmp in self._planned:
                current, backup = shown, None
                if os.path.exists(real) and len(self._planned) > 1:
                    backup = tmp + ".old"
                    try:
                        os.link(real, backup)
                    except OSError:  # no hard links here: that old file cannot be put back
                        backup = None
                os.replace(tmp, real)
                backups.append((real, backup))
                if len(backups) == 1:
                    _pause_for_tests("rename")
        except OSError as exc:
            for real, backup in reversed(backups):  # put every old file back
                with contextlib.suppress(OSError):
                    if backup:
                        os.replace(backup, real)
                    else:
                        os.remove(real)
            raise OutputError(f"{current}: cannot write ({exc.strerror or exc}); no output was changed") from None
        finally:
            for _, backup in backups:
                if backup:
                    with contextlib.suppress(FileNotFoundError):
                        os.remove(backup)

    def abort(self) -> None:
        for _, _, tmp in self._planned:
            for leftover in (tmp, tmp + ".old"):
                with contextlib.suppress(FileNotFoundError):
                    os.remove(leftover)

    def __enter__(self) -> Transaction:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.commit()
        else:
            self.abort()


@contextlib.contextmanager
def replacing(path: str, inputs: Iterable[str] = (), extensions: Iterable[str] | None = None,
              kind: OutputKind | None = None) -> Iterator[str]:
    """Yield a temp path to write; on success it is fsynced and renamed over path."""
    with Transaction(inputs) as tx:
        tmp = tx.path(path, extensions, kind)
        try:
            yield tmp
        except OSError as exc:
            raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None


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
