"""The ``psdbake`` command's first code: Ctrl-C or SIGTERM while ``psdbake.cli`` loads (click and
psdbake's light modules) exits at once with ``psdbake: interrupted`` and 130 (as later), then
``cli.main``, which handles signals with clean-up. The heavy modules (numpy, USD, SciPy) load
inside the command that needs them, under ``cli.main``'s handling: a signal while they load
unwinds as ``KeyboardInterrupt`` before anything is written, with the same line and code.

Before all that, a closed standard stream is opened on /dev/null (``_standard_streams``)."""

from __future__ import annotations

import os
import signal
import sys

_INTERRUPTED = b"psdbake: interrupted\n"
EXIT_INTERRUPTED = 130  # as cli.EXIT_INTERRUPTED, for SIGINT and SIGTERM alike


def _quit(signum, frame) -> None:
    """Nothing is written yet, so nothing to clean: the one line and exit 130, with calls that
    are safe at any point of an import (a raw write to fd 2, then _exit: no buffered I/O)."""
    try:
        os.write(2, _INTERRUPTED)
    finally:
        os._exit(EXIT_INTERRUPTED)


def _standard_streams() -> None:
    """Open /dev/null on a closed stdin, stdout or stderr (``2>&-``), so the command runs as
    usual and what it would print there is lost: else the first file psdbake opens takes that
    descriptor and receives what is printed (USD's C++ diagnostics write straight to fd 2), and
    Python's ``sys.stderr`` is None, which no message or progress bar can be written to."""
    closed = []
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            closed.append(fd)
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
    if 1 in closed and 2 not in closed:
        os.write(2, b"psdbake: warning: stdout is closed: the summary is not shown\n")
    if sys.stdout is None:
        sys.stdout = open(1, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
    if sys.stderr is None:
        sys.stderr = open(2, "w", encoding="utf-8", errors="backslashreplace", closefd=False)


def main() -> None:
    _standard_streams()
    # SIGINT inherited ignored stays ignored, as Python itself leaves it: a script's background
    # job (``psdbake fit ... &``) has it ignored so that Ctrl-C at the terminal spares it, the
    # POSIX shells' rule for asynchronous commands. SIGTERM still interrupts such a run.
    catch_sigint = signal.getsignal(signal.SIGINT) != signal.SIG_IGN
    if catch_sigint:
        signal.signal(signal.SIGINT, _quit)
    signal.signal(signal.SIGTERM, _quit)
    from .cli import main as cli_main

    if catch_sigint:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    cli_main()
