"""One ``psdbake batch`` task: ``main`` with argv ``PARENT_PID COMMAND ARGS...`` (started by
``runner.job_argv`` with an isolated ``sys.path``).

Exactly ``python -m psdbake COMMAND ARGS...``, except that the process dies with the one that
started it (Linux ``PR_SET_PDEATHSIG``, delivered as SIGTERM, which psdbake unwinds, removing
its temporary file). A batch worker killed mid-job must not leave the job running: the
scheduler reruns it elsewhere, and an orphan would race its rerun on the same outputs.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

from .._entry import main as entry

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _die_with_parent(parent: int) -> None:
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(143)


def main() -> None:
    """Tie this process to its parent, then run the command as ``psdbake`` would."""
    _die_with_parent(int(sys.argv[1]))
    sys.argv = ["psdbake", *sys.argv[2:]]
    entry()


if __name__ == "__main__":
    main()
