"""``psdbake batch JOBS.toml``: many pose/fit/eval/stack runs described in one file, on a farm.

The farm in pipeline order:

- ``jobs``: JOBS.toml -> a ``Batch`` of tasks, every job checked against the command schemas
  the caller passes in (the CLI's click commands; nothing here imports the CLI), ordered from
  the files they read and write (``order``);
- ``plan``: how ``eval --frames A:B --chunk-size N`` cuts a shot into chunks, one task each;
  ``chunked``: evaluating chunks and writing them with their value-clip manifests;
- ``runner``: one task as one psdbake process (``python -m psdbake.farm.job``);
- ``backends``: where tasks run (``local`` process pool, ``dask`` cluster), one module each.

Names load on first use (PEP 562), as in ``psdbake``: a Dask worker unpickling
``runner.run_job`` imports neither USD nor SciPy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS = {
    "tasks": ("Batch", "BatchResult", "JobResult", "OnDone", "Task"),
    "psdbake.errors": ("BatchError", "BatchUsageError", "ChunkUsageError"),
    "jobs": ("COMMANDS", "MAX_JOBS_FILE_BYTES", "load_jobs"),
    "order": ("check_reads",),
    "plan": ("MAX_CHUNKS", "Chunk", "ChunkPlan", "eval_chunks", "plan_chunks", "plan_frames"),
    "chunked": ("ChunkedWeights", "WrittenChunks", "evaluate_chunks", "write_chunks"),
    "backends": ("Backend", "run_batch"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'psdbake.farm' has no attribute {name!r}")
    value = getattr(importlib.import_module(module if module.startswith("psdbake.") else f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # for type checkers and IDEs: the same names, eagerly
    from ..errors import BatchError, BatchUsageError, ChunkUsageError  # noqa: F401
    from .backends import Backend, run_batch  # noqa: F401
    from .chunked import ChunkedWeights, WrittenChunks, evaluate_chunks, write_chunks  # noqa: F401
    from .jobs import COMMANDS, MAX_JOBS_FILE_BYTES, load_jobs  # noqa: F401
    from .order import check_reads  # noqa: F401
    from .plan import MAX_CHUNKS, Chunk, ChunkPlan, eval_chunks, plan_chunks, plan_frames  # noqa: F401
    from .tasks import Batch, BatchResult, JobResult, OnDone, Task  # noqa: F401
