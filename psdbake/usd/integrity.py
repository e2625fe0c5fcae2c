"""Binary layer files are read whole, in a child process, before psdbake opens them.

USD's crate reader (``.usdc``, ``.usdz``) unpacks values lazily, and a corrupt file
(bits flipped on a disk, a copy cut short) can fail late — while a fit is half done —
or crash the reader outright (SIGSEGV, abort), which no Python code can turn into a
message. So each crate file an input reaches is first read whole by
``_crate_probe.py`` in a process of its own (about 0.2 s per command: the child's Python
and USD start-up): a file it cannot read, or that crashes it, is refused in one line
naming it. Text layers are parsed whole when opened, so they need no probe.

A file the probe read whole is remembered twice over. Within a process, by its real
path, size and mtime (``_checked``), so an unchanged file is neither probed nor hashed
again. Across
processes — every farm chunk and batch job reads the same unchanged inputs again — by
content: an empty file in the cache folder (``cache_folder``) named by the SHA-256 of
the file's bytes, its extension, USD's version and the probe's own source. The verdict
is a function of exactly those: the same bytes, read by the same reader through the same
file format, by the same probe, give the same verdict, wherever the file lies and
whatever its mtime. So a cache hit is as good as probing again, and an edited
file, a new USD or a changed probe is probed afresh. Only files that passed are stored
(a refused file is probed, and refused, every time), and only when the bytes the probe
read are the ones hashed before it (a file replaced meanwhile is not vouched for): the
file's device, inode, size, mtime and ctime are the same after the probe as before the
hash, and its last change was ``SETTLED_SECONDS`` before that (any write or rename moves
the ctime, which no file API sets; a change within the same timestamp tick could not be
told, so a file changed that recently is hashed again after the probe instead: that
second pass cost 7 ms on a 13 MB CORRECTIVES). Beside each verdict goes a shortcut named by
the settled file's identity (device, inode, size, mtime, ctime: ``_identity_entry``), so a later
process finds an unchanged file without hashing it; a copy, a rename or any write gives another
identity, and the content verdict is looked up by hash as before. A layer a file reaches (sublayer,
reference) is checked as a file of its own by the dependency walk, under its own key. The cache is an optimisation only: a
folder that cannot be made, read or written is skipped without a word (read-only homes),
and any entry may be deleted at any time. ``PSDBAKE_CACHE_DIR=`` (empty) turns it off.
Whoever can write the folder can make psdbake skip the probe of a file, which at worst
brings back the crash the probe exists to prevent: it is the user's own (``~/.cache``).
SHA-256 rather than BLAKE2b: OpenSSL's SHA-256 runs at ~1.8 GB/s here against
hashlib's BLAKE2b at ~1.3 GB/s (2.4 ms for the 100k-point rig's two files, 70 ms at 1M).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

from ..errors import InputError
from .diagnostics import first_line

_PROBE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_crate_probe.py")
#: A corrupt size field can make the reader loop over a huge count: the probe gets this long.
PROBE_SECONDS = 120.0
_checked: dict[tuple[str, int, int], None] = {}  # (real path, size, mtime) of files already read whole
#: Environment variable naming the cache folder; set but empty, no cache.
CACHE_ENV = "PSDBAKE_CACHE_DIR"
#: Subfolder of the cache folder holding one empty file per crate file the probe passed.
_VERDICTS = "crate-probe-ok"
#: Subfolder of shortcuts to those verdicts by settled file identity (``_identity_entry``).
_BY_IDENTITY = "crate-probe-ok-by-identity"
#: A file changed this recently may change again within the same timestamp tick and look
#: unchanged to ``os.stat``: its bytes are hashed again after the probe (as ``dependencies``
#: does not remember the walk of such a file).
SETTLED_SECONDS = 2.0


def is_crate(path: str) -> bool:
    """A binary layer: ``.usdc``, ``.usdz``, or a ``.usd`` that starts with the crate magic."""
    ext = os.path.splitext(path)[1].lower()
    if ext in (".usdc", ".usdz"):
        return True
    if ext != ".usd":
        return False
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"PXR-USDC"
    except OSError:
        return False


def _key(path: str) -> tuple[str, int, int]:
    st = os.stat(path)
    return os.path.realpath(path), st.st_size, st.st_mtime_ns


def _settled_identity(path: str) -> tuple[int, ...] | None:
    """(device, inode, size, mtime, ctime) of path when its last change is at least
    SETTLED_SECONDS old, else None: two equal identities mean the same bytes."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if time.time() - st.st_ctime < SETTLED_SECONDS:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def cache_folder() -> str | None:
    """The folder of psdbake's caches, None when turned off: ``$PSDBAKE_CACHE_DIR`` when set
    (empty: off), else ``$XDG_CACHE_HOME/psdbake``, else ``~/.cache/psdbake`` (the XDG
    base-directory rules: a relative ``XDG_CACHE_HOME`` is ignored). It need not exist."""
    chosen = os.environ.get(CACHE_ENV)
    if chosen is not None:
        return chosen or None
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = xdg if os.path.isabs(xdg) else os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "psdbake") if os.path.isabs(base) else None


@functools.cache
def _reader_and_probe() -> bytes:
    """What besides a file's bytes decides the probe's verdict: USD's version (imported here,
    not with this module: pxr is loaded by the time a layer is checked) and the probe's source."""
    from pxr import Usd

    with open(_PROBE, "rb") as fh:
        probe = hashlib.sha256(fh.read()).hexdigest()
    return f"psdbake crate probe\0usd {'.'.join(map(str, Usd.GetVersion()))}\0probe {probe}\0".encode()


def _verdict_entry(path: str) -> str | None:
    """The cache entry that says path's bytes passed the probe (None when the cache is off or
    path cannot be read): named by SHA-256 of the reader, the probe, path's extension (USD
    picks its file format by it, and the probe opens a ``.usdz`` as a package) and its bytes."""
    folder = cache_folder()
    if folder is None:
        return None
    try:
        key = hashlib.sha256(_reader_and_probe())
        key.update(os.path.splitext(path)[1].lower().encode() + b"\0")
        with open(path, "rb") as fh:
            key.update(hashlib.file_digest(fh, "sha256").digest())
    except (OSError, ValueError):
        return None
    return os.path.join(folder, _VERDICTS, key.hexdigest())


def _identity_entry(path: str, identity: tuple[int, ...] | None) -> str | None:
    """The shortcut entry for a settled file's identity (device, inode, size, mtime, ctime)
    read through path's extension by this reader and probe (None when the cache is off or the
    file is not settled). Made beside a content verdict for the same bytes, it spares every
    later process the hash: a 1M-point fit's inputs took 68 ms to hash, a farm chunk's large
    CORRECTIVES more. Two settled files with one identity hold the same bytes (the ctime moves
    with every write or rename and no file API sets it), which is what ``_checked`` already
    relies on within a process."""
    folder = cache_folder()
    if folder is None or identity is None:
        return None
    key = hashlib.sha256(_reader_and_probe())
    key.update(os.path.splitext(path)[1].lower().encode() + b"\0")
    key.update(" ".join(map(str, identity)).encode())
    return os.path.join(folder, _BY_IDENTITY, key.hexdigest())


def _remember(path: str, entry: str | None, before: tuple[int, ...] | None) -> None:
    """Store the entry (an empty file, made under a temporary name and renamed into place, so
    a reader never sees half of one) if path still holds the bytes it was named for: its
    settled identity ``before`` the hash unchanged, else the same bytes hashed again; a file
    replaced while the probe read it is not vouched for. With the identity unchanged, its
    shortcut is stored too. Any failure is silently skipped."""
    if entry is None:
        return
    unchanged = before is not None and _settled_identity(path) == before
    if not unchanged and _verdict_entry(path) != entry:
        return
    _store(entry)
    if unchanged:
        _store(_identity_entry(path, before))


def _store(entry: str | None) -> None:
    """An empty file at entry, made atomically; any failure silently skipped."""
    if entry is None:
        return
    try:
        os.makedirs(os.path.dirname(entry), exist_ok=True)
        fd, temp = tempfile.mkstemp(prefix=".tmp-", dir=os.path.dirname(entry))
        os.close(fd)
        try:
            os.replace(temp, entry)
        except OSError:
            os.unlink(temp)
            raise
    except (OSError, ValueError):  # ValueError: a NUL in PSDBAKE_CACHE_DIR
        pass


def verdict_of_written(tmp: str) -> str | None:
    """The content verdict entry of a crate file psdbake has just written (its temporary file,
    before the commit renames it): USD wrote these very bytes, so they need no probe."""
    return _verdict_entry(tmp) if is_crate(tmp) else None


def vouch_written(entries: list[str | None]) -> None:
    """Store the verdicts ``verdict_of_written`` named, once the commit has renamed the files into
    place: a later command that reads such an output, or checks what kind of output it is before
    replacing it, finds it vouched for by content and does not probe it again (every farm re-run
    of a ``.usdc`` output would otherwise pay a child process)."""
    for entry in entries:
        _store(entry)


def require_readable_crates(paths: list[str]) -> None:
    """Read every crate file among paths whole in a child process; raise InputError naming
    the first one that cannot be read or crashes USD's reader. A file already read whole in
    this process, or whose bytes passed the same probe under the same USD before (the cache
    folder), is not read again."""
    todo: list[str] = []
    keys: dict[str, tuple[str, int, int]] = {}
    entries: dict[str, str | None] = {}
    identities: dict[str, tuple[int, ...] | None] = {}
    for path in dict.fromkeys(paths):
        if not (os.path.isfile(path) and is_crate(path)):
            continue
        key = _key(path)  # before hashing: a file changed after it is not taken as checked
        if key in _checked:
            continue
        identity = _settled_identity(path)  # before hashing too: what _remember compares
        shortcut = _identity_entry(path, identity)
        if shortcut is not None and os.path.isfile(shortcut):
            _checked[key] = None
            continue
        entry = _verdict_entry(path)
        if entry is not None and os.path.isfile(entry):
            _checked[key] = None
            if identity is not None and _settled_identity(path) == identity:  # the bytes hashed are the identity's
                _store(shortcut)
            continue
        todo.append(path)
        keys[path], entries[path], identities[path] = key, entry, identity
    if not todo:
        return
    try:
        done = subprocess.run([sys.executable, _PROBE, *todo], capture_output=True, text=True, errors="replace",
                              timeout=PROBE_SECONDS, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise InputError(f"{todo[0]}: USD did not finish reading it in {PROBE_SECONDS:g} s (a corrupt file?)") from None
    reading, error = -1, None
    for line in done.stdout.splitlines():
        word, _, rest = line.partition(" ")
        if word == "reading":
            reading = int(rest)
        elif word == "ok":
            path = todo[int(rest)]
            _checked[keys[path]] = None
            _remember(path, entries[path], identities[path])
        elif word == "error":
            index, _, error = rest.partition(" ")
            reading = int(index)
    if done.returncode == 0:
        return
    culprit = todo[max(reading, 0)]
    if error is not None:
        raise InputError(f"{culprit}: not a readable USD file ({first_line(json.loads(error))})")
    if done.returncode < 0:
        name = signal.Signals(-done.returncode).name
        raise InputError(f"{culprit}: not a readable USD file (USD's reader crashed on it with {name}: a corrupt file?)")
    raise InputError(f"{culprit}: not a readable USD file (USD's reader failed, exit {done.returncode})")
