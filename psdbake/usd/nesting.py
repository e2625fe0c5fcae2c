"""Text layers are checked for runaway nesting before USD parses them.

USD's ``.usda`` parser recurses once per nesting level: a layer of 100,000 nested dictionaries
(2.4 MB, under any size limit) or prims crashes it outright (SIGSEGV, exit 139, no message), and
10,000 nested parentheses take it 10 s. Binary layers are read in a child process first
(``integrity``), where a crash is caught; text layers are parsed in-process, so their nesting
is counted here first: every ``(``, ``[`` and ``{`` outside strings, comments and asset paths,
at C speed (``bytes.translate`` keeps the few characters that matter, numpy sums them). A
100 MB layer takes about a second less than USD's own parse of it.
"""

from __future__ import annotations

import hashlib
import os
import re

import numpy as np

from .. import tolerances as tol
from ..errors import InputError
from .integrity import cache_folder, settled_identity, store_entry

#: Bytes that open or close a level, start or end a string, a comment or an asset path, escape,
#: or end a line; every other byte is deleted before the scan.
_KEEP = b"()[]{}\"'#@\\\n"
_DROP = bytes(b for b in range(256) if b not in _KEEP)
#: Strings and asset paths that may span lines (their newlines are kept, for the line number).
_MULTILINE = re.compile(rb'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|@@@[\s\S]*?@@@')
#: What cannot hold a level: one-line strings (escapes kept), comments, asset paths.
_INERT = re.compile(rb'"(?:[^"\\\n]|\\.)*"|\'(?:[^\'\\\n]|\\.)*\'|#[^\n]*|@[^@\n]*@')
_STEP = np.zeros(256, dtype=np.int8)
_STEP[list(b"([{")] = 1
_STEP[list(b")]}")] = -1
_checked: set[tuple[str, int, int]] = set()  # (real path, size, mtime) of text layers already scanned
#: Subfolder of the cache folder: one empty file per settled text layer that passed the scan.
_PASSED = "text-nesting-ok-by-identity"


def is_text_layer(path: str) -> bool:
    """A ``.usda``, or a ``.usd`` that is not a crate file (USD reads either format from ``.usd``)."""
    ext = os.path.splitext(path)[1].lower()
    if ext == ".usda":
        return True
    if ext != ".usd":
        return False
    try:
        with open(path, "rb") as fh:
            return fh.read(8) != b"PXR-USDC"
    except OSError:
        return False


def deepest(data: bytes, limit: int = tol.MAX_TEXT_NESTING) -> tuple[int, int]:
    """(deepest nesting of USD text, the line where it first goes past limit; 0 if it never does)."""
    kept = data.translate(None, _DROP)
    kept = _MULTILINE.sub(lambda m: b"\n" * m.group().count(b"\n"), kept)
    kept = _INERT.sub(b"", kept)
    levels = np.cumsum(_STEP[np.frombuffer(kept, dtype=np.uint8)], dtype=np.int32)
    depth = int(levels.max(initial=0))
    if depth <= limit:
        return depth, 0
    return depth, kept.count(b"\n", 0, int(np.argmax(levels > limit))) + 1


def _passed_entry(identity: tuple[int, ...] | None) -> str | None:
    """The cache entry saying that the settled file with this identity (device, inode, size, mtime,
    ctime: the same bytes, as ``integrity`` argues) passed this scan at this limit; None when the
    cache is off or the file changed too recently. A farm's chunks then scan a large CORRECTIVES
    once, not once per chunk."""
    folder = cache_folder()
    if folder is None or identity is None:
        return None
    key = hashlib.sha256(f"psdbake text nesting v1\0{tol.MAX_TEXT_NESTING}\0{' '.join(map(str, identity))}".encode())
    return os.path.join(folder, _PASSED, key.hexdigest())


def require_shallow(path: str) -> None:
    """Refuse a text layer nested deeper than ``tolerances.MAX_TEXT_NESTING`` (InputError naming
    the file and line), before USD parses it. A file scanned before, unchanged, is not read again
    (in this process, and across processes through the cache folder)."""
    if not is_text_layer(path):
        return
    try:
        st = os.stat(path)
        key = (os.path.realpath(path), st.st_size, st.st_mtime_ns)
        if key in _checked:
            return
        identity = settled_identity(path)
        entry = _passed_entry(identity)
        if entry is not None and os.path.isfile(entry):
            _checked.add(key)
            return
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError:
        return  # missing or unreadable: the caller's open names it
    depth, line = deepest(data)
    if depth > tol.MAX_TEXT_NESTING:
        raise InputError(f"{path}: line {line}: nested deeper than {tol.MAX_TEXT_NESTING} levels (brackets, braces or "
                         f"parentheses; {depth} in all), more than psdbake reads: USD's text parser would crash or "
                         "stall on it")
    _checked.add(key)
    if identity is not None and settled_identity(path) == identity:  # the bytes scanned are the identity's
        store_entry(entry)
