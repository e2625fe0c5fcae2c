"""The seam between a batch and where its tasks run.

A back end runs every task of a batch once what it waits for is done (``Task.needs`` and
``Task.after``, already in topological order), calls ``on_done`` as each finishes, and returns
one ``JobResult`` per task in task order. How a task runs is the same everywhere
(``runner.run_job``: one psdbake process, rerun when killed by a signal); where and when is
the back end's business. Subclasses register themselves by name (``BACKENDS``), so a new back
end is one module in this package.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from ..tasks import Batch, BatchResult, OnDone

BACKENDS: dict[str, type[Backend]] = {}


class Backend(ABC):
    """Runs a batch somewhere. ``name`` registers it; ``schemes`` are the ``--scheduler``
    address schemes (``slurm`` for ``slurm://...``) that pick it over the default for addresses."""

    name: ClassVar[str]
    schemes: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        BACKENDS[cls.name] = cls

    @abstractmethod
    def run(self, batch: Batch, address: str | None, *, workers: int | None, signal_retries: int,
            on_done: OnDone | None) -> BatchResult:
        """Run every task of batch; address is ``--scheduler`` (None: no address given)."""
