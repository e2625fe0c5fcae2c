"""Farm back ends, by name: every module of this package that subclasses ``Backend`` is one.

``pick`` chooses for ``--scheduler``: none given is ``local``; an address whose scheme a back
end claims (``Backend.schemes``) is that back end; any other address is ``dask``, which checks
it. A new back end is one module here: a ``Backend`` subclass with a ``name``, the schemes it
claims and ``run``; it is found (and registered) when this package is imported.
"""

from __future__ import annotations

import importlib
import pkgutil

from ..tasks import Batch, BatchResult, OnDone
from .base import BACKENDS, Backend

for _module in sorted(m.name for m in pkgutil.iter_modules(__path__)):
    importlib.import_module(f"{__name__}.{_module}")  # registers its Backend subclasses

DEFAULT, ADDRESSED = "local", "dask"  # no --scheduler; an address no other back end claims


def pick(scheduler: str | None) -> Backend:
    """The back end that ``--scheduler`` (None: not given) selects."""
    if scheduler is None:
        return BACKENDS[DEFAULT]()
    scheme = scheduler.partition("://")[0] if "://" in scheduler else ""
    claimed = [b for b in BACKENDS.values() if scheme and scheme in b.schemes]
    return (claimed[0] if claimed else BACKENDS[ADDRESSED])()


def run_batch(batch: Batch, *, scheduler: str | None = None, workers: int | None = None, signal_retries: int = 2,
              on_done: OnDone | None = None) -> BatchResult:
    """Run on the local pool, or on the back end ``scheduler`` picks (a Dask cluster at tcp://HOST:PORT)."""
    return pick(scheduler).run(batch, scheduler, workers=workers, signal_retries=signal_retries, on_done=on_done)


__all__ = ["BACKENDS", "Backend", "pick", "run_batch"]
