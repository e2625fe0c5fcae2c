"""The ``psdbake`` command's first code: Ctrl-C or SIGTERM while ``psdbake.cli`` loads (click and
psdbake's light modules) exits at once with ``psdbake: interrupted`` and 130 (as later), then
``cli.main``, which handles signals with clean-up. The heavy modules (numpy, USD, SciPy) load
inside the command that needs them, under ``cli.main``'s handling: a signal while they load
unwinds as ``KeyboardInterrupt`` before anything is written, with the same line and code."""

from __future__ import annotations

import os
import signal

_INTERRUPTED = b"psdbake: interrupted\n"
EXIT_INTERRUPTED = 130  # as cli.EXIT_INTERRUPTED, for SIGINT and SIGTERM alike


def _quit(signum, frame) -> None:
    """Nothing is written yet, so nothing to clean: the one line and exit 130, with calls that
    are safe at any point of an import (a raw write to fd 2, then _exit: no buffered I/O)."""
    try:
        os.write(2, _INTERRUPTED)
    finally:
        os._exit(EXIT_INTERRUPTED)


def main() -> None:
    signal.signal(signal.SIGINT, _quit)
    signal.signal(signal.SIGTERM, _quit)
    from .cli import main as cli_main

    signal.signal(signal.SIGINT, signal.default_int_handler)
    cli_main()
