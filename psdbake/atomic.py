"""All-or-nothing output files: temp files beside the destinations, fsync, rename together.

A failed or interrupted run leaves either every old file or every complete new one,
never a partial one and never a mix: a command with several outputs (``eval
--points-cache``, a chunked eval, ``fit --report``) writes all of them to temporary
files first and renames them only once all are written (``Transaction``). The renames
run with SIGINT/SIGTERM held back and under the lock of every output's folder (``updating``:
two commits never interleave their renames), and a rename that fails puts the old files back.

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
import threading
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
    if path.endswith(("/", os.sep)) or os.path.isdir(path):
        raise OutputError(f"{path}: names a folder; give the file to write (e.g. {os.path.join(path, 'out')}"
                          f"{next(iter(extensions or ()), '')})")
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
    existing = _existing_ancestor(folder)
    if existing != folder:  # created when the output is written (make_folders), as --obj-dir and compare do
        blocker = existing if os.path.isabs(path) else os.path.relpath(existing)
        if not os.path.isdir(existing):
            raise OutputError(f"{path}: cannot create output folder {shown}: {blocker} is not a folder")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise OutputError(f"{path}: cannot create output folder {shown}: {blocker} is not writable")
    elif not os.path.isdir(folder):
        raise OutputError(f"{path}: cannot write into {shown}: it is a file, not a folder")
    elif not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: output folder {shown} is not writable")
    if os.path.isdir(real):
        raise OutputError(f"{path}: is a folder")
    if os.path.exists(real) and not os.path.isfile(real):
        raise OutputError(f"{path}: exists and is not a regular file (a FIFO or device is never replaced)")
    _check_replace(path, real, kind)
    return real


def _existing_ancestor(folder: str) -> str:
    """folder, or its nearest ancestor that exists (a file there makes the folder impossible)."""
    while not os.path.exists(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    return folder


def make_folders(folder: str, shown: str) -> list[str]:
    """Create folder and its missing ancestors, as ``mkdir -p``; return the ones this call made,
    outermost first, so a failed run can remove them again (``remove_folders``). Every output
    flag creates its folder: a farm writes into new shot folders."""
    made: list[str] = []
    missing = folder
    while not os.path.isdir(missing) and os.path.dirname(missing) != missing:
        made.insert(0, missing)
        missing = os.path.dirname(missing)
    try:
        for each in list(made):
            try:
                os.mkdir(each)
            except FileExistsError:  # another run made it first: not ours to remove
                made.remove(each)
    except OSError as exc:
        remove_folders(made)
        raise OutputError(f"{shown}: cannot create the output folder ({exc.strerror or exc})") from None
    return made


def remove_folders(made: list[str]) -> None:
    """Remove the folders ``make_folders`` made, innermost first, where they are still empty: a
    failed run leaves no folder it made, and never one another run has written into since."""
    for folder in reversed(made):
        with contextlib.suppress(OSError):
            os.rmdir(folder)


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


def _mode_for(real: str) -> int:
    """The permissions an output gets: those of the file it replaces (a group-writable or a
    read-only published file stays so, as editors keep them), else what the umask allows."""
    try:
        return stat.S_IMODE(os.stat(real).st_mode) & 0o777  # never set-id or sticky bits on a layer
    except OSError:
        return 0o666 & ~_umask()


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
    # an ignored signal stays ignored (a background job's SIGINT): nothing to hold back
    held = tuple(s for s in (signal.SIGINT, signal.SIGTERM) if signal.getsignal(s) != signal.SIG_IGN)
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
        self._made: list[str] = []  # output folders this transaction created, removed if it fails

    def path(self, dest: str, extensions: Iterable[str] | None = None, kind: OutputKind | None = None) -> str:
        real = check_output(dest, self.inputs, extensions, kind)
        for shown, other, _ in self._planned:
            if other == real:
                raise OutputError(f"{dest}: written twice by this run (also as {shown})")
        folder, name = os.path.split(real)
        ext = os.path.splitext(name)[1]
        self._made += make_folders(folder, os.path.dirname(dest) or ".")
        try:
            fd, tmp = tempfile.mkstemp(prefix=_TEMP_PREFIX, suffix=f".tmp{ext}", dir=folder)
        except OSError as exc:
            raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from None
        os.close(fd)
        self._planned.append((dest, real, tmp))
        return tmp

    def commit(self) -> list[str]:
        try:
            for shown, real, tmp in self._planned:
                try:
                    with open(tmp, "rb+") as fh:
                        os.fsync(fh.fileno())
                    os.chmod(tmp, _mode_for(real))
                except OSError as exc:
                    raise OutputError(f"{shown}: cannot write ({exc.strerror or exc})") from None
            with updating(*(real for _, real, _ in self._planned)), _signals_held():
                self._rename_all()
            self._made.clear()  # they hold the outputs now
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
        remove_folders(self._made)
        self._made = []

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


class _Held(threading.local):
    """Folder locks this thread holds: real folder -> (descriptor, holds). A thread takes each
    folder's flock once; nested holds (a commit inside ``fit --group``'s update) count up. Per
    thread: another thread's flock is on its own descriptor, so it waits like another process."""

    def __init__(self) -> None:
        self.folders: dict[str, tuple[int, int]] = {}


_HELD = _Held()


def _acquire(folder: str) -> tuple[int, list[str]]:
    """An exclusive ``flock`` on folder, waited for, creating the folder if it is missing; returns
    the descriptor holding it and the folders made. A folder removed while this run waited (a
    failed run removing the folder it made) is made again and locked afresh."""
    import fcntl

    made: list[str] = []
    while True:
        made += make_folders(folder, folder)
        try:
            fd = os.open(folder, os.O_RDONLY)
        except OSError as exc:
            raise OutputError(f"{folder}: cannot lock the output folder ({exc.strerror or exc})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError as exc:
            os.close(fd)
            raise OutputError(f"{folder}: cannot lock the output folder ({exc.strerror or exc}): psdbake "
                              "serialises writers of one folder with flock") from None
        except BaseException:  # interrupted while waiting (SIGTERM unwinds as KeyboardInterrupt)
            os.close(fd)
            raise
        try:
            now = os.stat(folder)
        except FileNotFoundError:
            now = None
        mine = os.fstat(fd)
        if now is not None and (now.st_dev, now.st_ino) == (mine.st_dev, mine.st_ino):
            return fd, made
        os.close(fd)


@contextlib.contextmanager
def updating(*paths: str) -> Iterator[None]:
    """Serialise writers: an exclusive ``flock`` on the folder of each path, taken in sorted order
    and held for the block. Every commit holds its outputs' folders while it renames
    (``Transaction.commit``), so two commits never interleave their renames; a read-modify-write
    (``fit --group``, ``mirror`` in place, a chunked eval's manifest) holds them from before the
    read to after the rename, so concurrent updates all land, each on the other's result. The
    lock is on the folder because every output is replaced by a rename, which a lock on the file
    would not survive. Re-entrant: a folder this thread already holds is not locked again.

    The folders are locked in one order (sorted real paths) by every psdbake process, so no two
    runs can each hold a folder the other waits for; a block that already holds a folder may not
    take one that sorts before it (a programming error: RuntimeError)."""
    held = _HELD.folders
    folders = sorted({os.path.dirname(os.path.realpath(p)) or "." for p in paths})
    new = [f for f in folders if f not in held]
    if new and held and new[0] < max(held):
        raise RuntimeError(f"lock order: {new[0]} taken while holding {max(held)}")
    taken: list[str] = []
    made: list[str] = []
    try:
        for folder in folders:
            if folder in held:
                fd, holds = held[folder]
                held[folder] = (fd, holds + 1)
            else:
                fd, made_here = _acquire(folder)
                made += made_here
                held[folder] = (fd, 1)
            taken.append(folder)
        yield
    except BaseException:
        remove_folders(made)  # under the lock still: a run waiting for it finds the folder gone
        raise
    finally:
        for folder in reversed(taken):
            fd, holds = held[folder]
            if holds > 1:
                held[folder] = (fd, holds - 1)
            else:
                del held[folder]
                os.close(fd)  # closing releases the lock
