"""Binary layer files are read whole, in a child process, before psdbake opens them.

USD's crate reader (``.usdc``, ``.usdz``) unpacks values lazily, and a corrupt file
(bits flipped on a disk, a copy cut short) can fail late — while a fit is half done —
or crash the reader outright (SIGSEGV, abort), which no Python code can turn into a
message. So each crate file an input reaches is first read whole by
``_crate_probe.py`` in a process of its own (about 0.2 s per command, once per file
per process): a file it cannot read, or that crashes it, is refused in one line naming
it. Text layers are parsed whole when opened, so they need no probe.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

from ..errors import InputError
from .diagnostics import first_line

_PROBE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_crate_probe.py")
#: A corrupt size field can make the reader loop over a huge count: the probe gets this long.
PROBE_SECONDS = 120.0
_checked: dict[tuple[str, int, int], None] = {}  # (real path, size, mtime) of files already read whole


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


def require_readable_crates(paths: list[str]) -> None:
    """Read every crate file among paths whole in a child process; raise InputError naming
    the first one that cannot be read or crashes USD's reader."""
    todo = [p for p in dict.fromkeys(paths) if os.path.isfile(p) and is_crate(p) and _key(p) not in _checked]
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
            _checked[_key(todo[int(rest)])] = None
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
