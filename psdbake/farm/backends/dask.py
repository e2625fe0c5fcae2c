"""The Dask back end, ``psdbake batch --scheduler tcp://HOST:PORT``: an existing cluster.

Each task is submitted once, with the futures of what it waits for as arguments, so the
scheduler runs it only after them and hands it their results (``run_job`` skips a task whose
inputs failed). Worker loss is the scheduler's business: it reruns the tasks that were on the
lost worker elsewhere, up to ``distributed.scheduler.allowed-failures`` times (default 3),
after which the task is reported lost. Rerunning is safe: a killed worker's job process dies
with it (``psdbake.farm.job``), its outputs are atomic and the commands deterministic, so the
results are byte-identical to a local run.

Workers need psdbake installed and the jobs file's folder at the same path (shared storage).
``distributed`` is imported only when a batch runs here: it is an optional dependency.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time
from typing import Any

from ...errors import BatchUsageError, InputError
from ..runner import make_output_folders, run_job
from ..tasks import Batch, BatchResult, JobResult, OnDone, Task
from .base import Backend

#: Seconds to connect to the scheduler and get its handshake: a scheduler answers in
#: milliseconds, a busy one in well under this; something that accepts the connection but never
#: answers (not a Dask scheduler, a hung one) is refused after it. PSDBAKE_SCHEDULER_TIMEOUT
#: (seconds) overrides it.
CONNECT_TIMEOUT = 10.0

ACCEPTED = "tcp://HOST:PORT (or HOST:PORT)"


def connect_timeout() -> float:
    """CONNECT_TIMEOUT, or PSDBAKE_SCHEDULER_TIMEOUT when set (refused unless 0 < seconds < a day)."""
    text = os.environ.get("PSDBAKE_SCHEDULER_TIMEOUT")
    if not text:
        return CONNECT_TIMEOUT
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < 86400:
        raise BatchUsageError(f"PSDBAKE_SCHEDULER_TIMEOUT={text!r}: expected seconds, more than 0")
    return value


def check_address(address: str) -> None:
    """Only plain TCP addresses of a Dask scheduler: an http(s) dashboard URL, TLS (needs
    certificates psdbake does not take), ucx, ws or inproc are refused here, before a
    Client is made (a Client half-built from one hangs on clean-up)."""
    from distributed.comm import parse_address, parse_host_port
    from distributed.comm.registry import backends

    try:
        scheme, location = parse_address(address, strict=False)
    except (ValueError, TypeError):
        scheme, location = "", ""
    if scheme != "tcp" or not location:
        what = f"address scheme '{scheme}'" if scheme else "address"
        kind = "unsupported" if scheme in backends else "unknown"
        raise BatchUsageError(f"--scheduler {address}: {kind} {what}: psdbake batch connects to a Dask scheduler at "
                              f"{ACCEPTED} (no http, https, tls, ws, ucx or inproc)")
    try:
        host, port = parse_host_port(location)
    except (ValueError, TypeError):
        host, port = "", 0
    if not host or not isinstance(port, int) or not 0 < port < 65536:
        raise BatchUsageError(f"--scheduler {address}: expected {ACCEPTED} with a port 1..65535")


def _probe(address: str, timeout: float) -> None:
    """Connect and read the scheduler's handshake within timeout seconds (distributed's own
    connect waits for the handshake without a limit), then hang up."""
    from distributed.comm import connect

    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:  # a plain TCP connect first: distributed retries a refused connection until its timeout
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except TimeoutError:
        raise InputError(f"--scheduler {address}: no answer within {timeout:g} s (not a Dask scheduler, "
                         "or a hung one)") from None
    except OSError as exc:
        raise InputError(f"--scheduler {address}: cannot connect ({exc.strerror or exc})") from None

    async def attempt() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=timeout), timeout)
        with contextlib.suppress(Exception):
            await asyncio.wait_for(comm.close(), 1.0)

    try:
        asyncio.run(attempt())
    except TimeoutError:  # asyncio.TimeoutError is TimeoutError since 3.11
        raise InputError(f"--scheduler {address}: no answer within {timeout:g} s "
                         "(not a Dask scheduler, or a hung one)") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"--scheduler {address}: cannot connect ({_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]


def _client(address: str, timeout: float) -> Any:
    """A connected Client that, when its constructor fails, is not closed again from ``__del__``
    (that waits twice the timeout and prints a traceback long after psdbake's error line)."""
    from distributed import Client

    class _Client(Client):
        _psdbake_failed = False

        def __del__(self) -> None:
            if self._psdbake_failed:
                return
            with contextlib.suppress(Exception):
                super().__del__()

    client = _Client.__new__(_Client)
    try:
        _Client.__init__(client, address, timeout=timeout, set_as_default=False)
    except Exception as exc:
        client._psdbake_failed = True
        with contextlib.suppress(Exception):
            client.status = "closed"
        raise InputError(f"--scheduler {address}: cannot connect ({_first_line(exc)})") from None
    return client


def _result(future: Any, t: Task, futures: dict[str, Any], tasks: dict[str, Task]) -> JobResult:
    """The task's own result, or why the scheduler gave up on it (its workers kept dying), or on
    something it waits for."""
    if future.status == "finished":
        result: JobResult = future.result()
        return result
    upstream = [futures[k] for k in (*t.needs, *t.after) if futures[k].status != "finished"]
    if upstream:
        return JobResult(t.key, t.label, "skipped", None, 0.0, 0, f"waits for {tasks[upstream[0].key].label}, which was lost")
    exc = future.exception() if future.status == "error" else None
    why = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}" if exc else future.status
    return JobResult(t.key, t.label, "lost", None, 0.0, 0, why)


class Dask(Backend):
    """An existing dask.distributed cluster, reached at its scheduler's address."""

    name = "dask"

    def run(self, batch: Batch, address: str | None, *, workers: int | None, signal_retries: int,
            on_done: OnDone | None) -> BatchResult:
        """Run the batch on the cluster whose scheduler listens at address."""
        if workers is not None:
            raise BatchUsageError("--workers sizes the local pool; with --scheduler the cluster's workers run the jobs")
        try:
            from distributed import as_completed
        except ImportError:
            raise BatchUsageError("--scheduler needs dask.distributed: pip install 'psdbake[dask]'") from None
        assert address is not None
        started = time.perf_counter()
        check_address(address)
        timeout = connect_timeout()
        _probe(address, timeout)
        with _client(address, timeout) as client:
            make_output_folders(batch)
            n_workers = len(client.scheduler_info(n_workers=-1).get("workers", {}))
            futures: dict[str, Any] = {}
            for t in batch.tasks:  # topological order: every dependency is already submitted
                deps = [futures[k] for k in (*t.needs, *t.after)]
                futures[t.key] = client.submit(run_job, t, *deps, signal_retries=signal_retries, key=t.key, pure=False)
            tasks = {t.key: t for t in batch.tasks}
            results: dict[str, JobResult] = {}
            try:
                for future in as_completed(list(futures.values()), loop=client.loop):
                    r = results[future.key] = _result(future, tasks[future.key], futures, tasks)
                    if on_done:
                        on_done(r, len(results), len(batch.tasks))
            except BaseException:
                client.cancel(list(futures.values()))
                raise
        return BatchResult(batch, address, n_workers, tuple(results[t.key] for t in batch.tasks),
                           time.perf_counter() - started)
