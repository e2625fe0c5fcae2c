"""What a batch is and what running it returns: tasks in, one result per task out.

Plain data shared by the jobs-file reader (``jobs``), the process runner (``runner``) and
every back end (``backends``), so none of them imports another to know these shapes.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Task:
    """One process to run: a job, or one chunk of a chunked eval job."""

    key: str  # unique and deterministic: the Dask key too
    label: str  # "[[eval]] #1 chunk 2/4"
    job: str  # "[[eval]] #1"
    command: str
    args: tuple[str, ...]  # after "psdbake"
    cwd: str  # the jobs file's folder: relative paths resolve here
    reads: tuple[str, ...]  # real paths, for ordering
    writes: tuple[str, ...]
    outputs: tuple[str, ...]  # as written in the jobs file
    needs: tuple[str, ...] = ()  # keys writing a file this task reads: skipped unless they all succeed
    after: tuple[str, ...] = ()  # keys writing the same file earlier in file order: waited for, not needed

    @property
    def command_line(self) -> str:
        return shlex.join(["psdbake", self.command, *self.args])


@dataclass(frozen=True)
class Batch:
    """A parsed jobs file: tasks in an order that respects their dependencies (file order otherwise)."""

    path: str
    folder: str
    tasks: tuple[Task, ...]


@dataclass(frozen=True)
class JobResult:
    """How one task ended: a status, not an exception, so one failure never hides the others."""

    key: str
    label: str
    status: str  # "ok", "failed", "skipped" (something it needs did not succeed), "lost" (its workers kept dying)
    exit_code: int | None
    seconds: float
    attempts: int
    error: str = ""  # the job's last stderr line when it failed; why it was skipped or lost
    warnings: tuple[str, ...] = ()
    worker: str = ""  # host:pid of the process that ran it


@dataclass(frozen=True)
class BatchResult:
    """Every task's result in task order, whatever back end ran them."""

    batch: Batch
    scheduler: str  # "local" or the scheduler's address
    workers: int
    results: tuple[JobResult, ...]  # in task order
    seconds: float

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def exit_code(self) -> int:
        """0, or the first failed job's psdbake exit code (1 when it died otherwise)."""
        for r in self.results:
            if r.status in ("failed", "lost"):
                return r.exit_code if r.exit_code is not None and 2 <= r.exit_code <= 7 else 1
        return 0

    def summary(self) -> dict[str, Any]:
        """The ``--json`` payload."""
        by_key = {t.key: t for t in self.batch.tasks}
        return {
            "jobs_file": self.batch.path, "folder": self.batch.folder, "scheduler": self.scheduler,
            "workers": self.workers, "seconds": round(self.seconds, 6),
            **{s: self.count(s) for s in ("ok", "failed", "skipped", "lost")},
            "jobs": [
                {"job": r.label, "command": by_key[r.key].command_line, "status": r.status, "exit_code": r.exit_code,
                 "seconds": round(r.seconds, 6), "attempts": r.attempts, "outputs": list(by_key[r.key].outputs),
                 "error": r.error or None, "warnings": list(r.warnings), "worker": r.worker or None}
                for r in self.results
            ],
        }


OnDone = Callable[[JobResult, int, int], None]  # (result, finished so far, total)
