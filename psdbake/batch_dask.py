"""``psdbake batch --scheduler tcp://HOST:PORT``: the same tasks on an existing Dask cluster.

Each task is submitted once, with the futures of what it waits for as arguments, so the
scheduler runs it only after them and hands it their results (``run_job`` skips a task whose
inputs failed). Worker loss is the scheduler's business: it reruns the tasks that were on the
lost worker elsewhere, up to ``distributed.scheduler.allowed-failures`` times (default 3),
after which the task is reported lost. Rerunning is safe: a killed worker's job process dies
with it (``psdbake._job``), its outputs are atomic and the commands deterministic, so the
results are byte-identical to a local run.

Workers need psdbake installed and the jobs file's folder at the same path (shared storage).
"""

from __future__ import annotations

import time

from .batch import Batch, BatchResult, BatchUsageError, JobResult, OnDone, make_output_folders, run_job
from .errors import InputError

CONNECT_TIMEOUT = 10.0  # seconds: a scheduler answers in milliseconds, a busy one in well under this


def run_dask(batch: Batch, address: str, *, signal_retries: int = 2, on_done: OnDone | None = None) -> BatchResult:
    """Run the batch on the cluster whose scheduler listens at address."""
    try:
        from distributed import Client, as_completed
        from distributed.comm import parse_address
        from distributed.comm.registry import get_backend
    except ImportError:
        raise BatchUsageError("--scheduler needs dask.distributed: pip install 'psdbake[dask]'") from None
    started = time.perf_counter()
    try:  # a malformed address is refused here: a Client half-built from one hangs on clean-up
        scheme, location = parse_address(address)
        get_backend(scheme)
        if ":" not in location:
            raise ValueError("expected tcp://HOST:PORT")
    except ValueError as exc:
        raise BatchUsageError(f"--scheduler {address}: {exc}") from None
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"--scheduler {address}: cannot connect ({str(exc).strip().splitlines()[0]})") from None
    with client:
        make_output_folders(batch)
        workers = len(client.scheduler_info(n_workers=-1).get("workers", {}))
        futures = {}
        for t in batch.tasks:  # topological order: every dependency is already submitted
            deps = [futures[k] for k in (*t.needs, *t.after)]
            futures[t.key] = client.submit(run_job, t, *deps, signal_retries=signal_retries, key=t.key, pure=False)
        tasks = {t.key: t for t in batch.tasks}
        results: dict[str, JobResult] = {}
        try:
            for future in as_completed(list(futures.values()), loop=client.loop):
                t = tasks[future.key]
                if future.status == "finished":
                    r = future.result()
                else:  # the scheduler gave up on it (its workers kept dying), or on something it waits for
                    upstream = [futures[k] for k in (*t.needs, *t.after) if futures[k].status != "finished"]
                    if upstream:
                        r = JobResult(t.key, t.label, "skipped", None, 0.0, 0,
                                      f"waits for {tasks[upstream[0].key].label}, which was lost")
                    else:
                        exc = future.exception() if future.status == "error" else None
                        why = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}" if exc else future.status
                        r = JobResult(t.key, t.label, "lost", None, 0.0, 0, why)
                results[t.key] = r
                if on_done:
                    on_done(r, len(results), len(batch.tasks))
        except BaseException:
            client.cancel(list(futures.values()))
            raise
    return BatchResult(batch, address, workers, tuple(results[t.key] for t in batch.tasks), time.perf_counter() - started)
