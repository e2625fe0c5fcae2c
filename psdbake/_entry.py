"""The ``psdbake`` command's first code: quiet exits on Ctrl-C or SIGTERM while the heavy
modules (USD, SciPy) load, then ``cli.main``, which handles signals with clean-up."""

from __future__ import annotations

import os
import signal


def _quit(signum, frame) -> None:
    os._exit(130 if signum == signal.SIGINT else 143)  # nothing written yet: nothing to clean


def main() -> None:
    signal.signal(signal.SIGINT, _quit)
    signal.signal(signal.SIGTERM, _quit)
    from .cli import main as cli_main

    signal.signal(signal.SIGINT, signal.default_int_handler)
    cli_main()
