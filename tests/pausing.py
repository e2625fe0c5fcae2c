"""Hold a psdbake process at exact moments of its commit, from the test side.

The fault and concurrency tests stop a run at a known moment rather than after a guessed delay.
psdbake itself knows nothing of this: the run is started as ``python tests/pausing.py SPEC --
ARGS...`` (``argv``), which wraps a few functions of ``psdbake.atomic`` before running
``psdbake ARGS...`` exactly as the ``psdbake`` command does. SPEC is ``MOMENT=MARKER[,...]``;
at each MOMENT named (its first occurrence) the run creates MARKER and waits, up to
``HOLD_SECONDS``, until the test removes it (``release``). Moments:

- ``lock``: before the run first waits for a folder lock (``atomic._acquire``);
- ``locked``: just after it got that lock;
- ``commit``: every output written to its temporary file, the outputs' folders locked, nothing
  renamed, signals not yet held;
- ``rename``: the first output renamed, the others not, SIGINT/SIGTERM held back.

``waiting_for_lock(pid)`` tells, from ``/proc/locks``, that a run is blocked on a folder lock,
so a test knows a released run got as far as the lock without sleeping.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator

HERE = os.path.abspath(__file__)
HOLD_SECONDS = 120.0  # a held run gives up after this, so a broken test cannot hang forever
MOMENTS = ("lock", "locked", "commit", "rename")


def argv(moments: dict[str, str], *args: str) -> list[str]:
    """The command line of ``psdbake ARGS`` held at moments ({moment: marker file})."""
    unknown = set(moments) - set(MOMENTS)
    assert not unknown, f"no such moment: {sorted(unknown)}"
    spec = ",".join(f"{m}={marker}" for m, marker in moments.items())
    return [sys.executable, HERE, spec, "--", *map(str, args)]


def wait_for(marker: str, proc: subprocess.Popen, what: str = "", seconds: float = 120.0) -> None:
    """Until marker exists (the run is held there); fails if the run ends first."""
    deadline = time.monotonic() + seconds
    while not os.path.exists(marker):
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"the run ended (exit {proc.returncode}) before {what or marker}: {err}")
        if time.monotonic() > deadline:
            raise AssertionError(f"the run never reached {what or marker}")
        time.sleep(0.01)


def release(marker: str) -> None:
    os.remove(marker)


def waiting_for_lock(pid: int) -> bool:
    """Whether process pid is blocked waiting for a flock (a ``->`` line of /proc/locks)."""
    with open("/proc/locks", encoding="utf-8") as fh:
        for line in fh:
            fields = line.split()
            if len(fields) > 5 and fields[1] == "->" and fields[2] == "FLOCK" and fields[5] == str(pid):
                return True
    return False


def wait_blocked(proc: subprocess.Popen, seconds: float = 120.0) -> None:
    """Until proc waits for a folder lock; fails if it ends first."""
    deadline = time.monotonic() + seconds
    while not waiting_for_lock(proc.pid):
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"the run ended (exit {proc.returncode}) instead of waiting for the lock: {err}")
        if time.monotonic() > deadline:
            raise AssertionError("the run never waited for the lock")
        time.sleep(0.01)


# --- the held run ------------------------------------------------------------------------------

def _install(spec: str) -> None:
    from psdbake import atomic

    wanted = dict(item.split("=", 1) for item in spec.split(",") if item)
    renaming: list[bool] = []

    def hold(moment: str) -> None:
        marker = wanted.pop(moment, None)
        if marker is None:
            return
        with open(marker, "w", encoding="utf-8"):
            pass
        deadline = time.monotonic() + HOLD_SECONDS
        while os.path.exists(marker) and time.monotonic() < deadline:
            time.sleep(0.01)

    acquire, signals_held, replace = atomic._acquire, atomic._signals_held, os.replace

    def held_acquire(folder: str) -> int:
        hold("lock")
        fd = acquire(folder)
        hold("locked")
        return fd

    @contextlib.contextmanager
    def held_signals() -> Iterator[None]:
        hold("commit")
        with signals_held():
            renaming.append(True)
            try:
                yield
            finally:
                renaming.clear()

    def held_replace(src, dst, *args, **kwargs) -> None:
        replace(src, dst, *args, **kwargs)
        if renaming:
            renaming.clear()
            hold("rename")

    atomic._acquire = held_acquire
    atomic._signals_held = held_signals
    os.replace = held_replace


if __name__ == "__main__":
    if sys.path and os.path.abspath(sys.path[0]) == os.path.dirname(HERE):
        del sys.path[0]  # the tests' folder: the run imports what psdbake would, nothing of ours
    spec, dashes, *rest = sys.argv[1:]
    assert dashes == "--", "usage: pausing.py MOMENT=MARKER[,...] -- PSDBAKE_ARGS..."
    _install(spec)
    sys.argv = ["psdbake", *rest]
    from psdbake._entry import main

    main()
