"""The local back end: a pool of threads on this machine, each waiting on one job process.

At most ``workers`` jobs at once (default one per core: a job's start-up, ~1 s of imports, is
single-threaded), each as soon as what it waits for is done. Ctrl-C or SIGTERM stops new
attempts and SIGTERMs the running jobs, which unwind and remove their temporary files.
"""

from __future__ import annotations

import concurrent.futures
import os
import time

from ..runner import allow_running, run_job, stop_running
from ..tasks import Batch, BatchResult, JobResult, OnDone, Task
from .base import Backend


def default_workers() -> int:
    """Local jobs at once: one per core (a job's start-up, ~1 s of imports, is single-threaded)."""
    return max(1, os.cpu_count() or 1)


class Local(Backend):
    """This machine's processes."""

    name = "local"

    def run(self, batch: Batch, address: str | None, *, workers: int | None, signal_retries: int,
            on_done: OnDone | None) -> BatchResult:
        """Run the batch here, at most `workers` jobs at once, each as soon as what it waits for is done."""
        workers = workers or default_workers()
        started = time.perf_counter()
        results: dict[str, JobResult] = {}
        pending = list(batch.tasks)
        running: dict[concurrent.futures.Future[JobResult], Task] = {}
        position = {t.key: i for i, t in enumerate(batch.tasks)}
        allow_running()
        with concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="psdbake-batch") as pool:
            try:
                while pending or running:
                    for t in list(pending):
                        if len(running) >= workers:
                            break
                        if all(k in results for k in (*t.needs, *t.after)):
                            pending.remove(t)
                            deps = [results[k] for k in (*t.needs, *t.after)]
                            running[pool.submit(run_job, t, *deps, signal_retries=signal_retries)] = t
                    done, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
                    for future in sorted(done, key=lambda f: position[running[f].key]):
                        del running[future]
                        r = future.result()
                        results[r.key] = r
                        if on_done:
                            on_done(r, len(results), len(batch.tasks))
            except BaseException:
                stop_running()
                raise
        return BatchResult(batch, "local", workers, tuple(results[t.key] for t in batch.tasks),
                           time.perf_counter() - started)
