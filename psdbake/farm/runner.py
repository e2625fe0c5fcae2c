"""One task as one psdbake process, on whatever machine calls ``run_job``.

Every task runs as its own process, ``psdbake.farm.job`` (= ``python -m psdbake``): USD's
global state stays per job, a crashing job cannot take its worker down, and exit codes come
for free. The process runs in the jobs file's folder but never imports from it (``job_argv``).
The commands write their outputs atomically, so a job killed mid-way leaves no partial file and
is simply run again (they are deterministic). Back ends decide where and when ``run_job``
runs; this module decides how.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from .tasks import JobResult, Task

_KILLED = (130, 143)  # psdbake's exit after SIGINT/SIGTERM (unwound, temporary file removed)
_STOP = threading.Event()  # set on Ctrl-C/SIGTERM of a local batch: no new attempts
_RUNNING: set[subprocess.Popen[bytes]] = set()
_RUNNING_LOCK = threading.Lock()


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


#: A job's first code, run as ``python -I -c _BOOT PATH_JSON PARENT_PID COMMAND ARGS...``: ``-I`` keeps
#: the working folder (the jobs file's, where anyone may have left a ``click.py``, ``numpy.py`` or
#: ``pxr/``) and ``PYTHON*`` variables off ``sys.path``; the path the job imports from is then
#: set explicitly, before any import of psdbake or its dependencies, to this process's own
#: (``import_path``), with the user site's ``.pth`` files read again when this process used it.
_BOOT = ("import json, site, sys\n"
         "path, user_site = json.loads(sys.argv.pop(1))\n"
         "sys.path[:] = path\n"
         "if user_site:\n"
         "    site.addsitedir(user_site)\n"
         "from psdbake.farm.job import main\n"
         "main()\n")


def import_path(folder: str) -> tuple[list[str], str | None]:
    """(sys.path for a job run in folder, the user site to read ``.pth`` files from, or None):
    this process's absolute entries except folder itself, which is data, never code."""
    import site

    here = os.path.realpath(folder)
    path = [p for p in sys.path if p and os.path.isabs(p) and os.path.realpath(p) != here]
    user = site.getusersitepackages() if site.ENABLE_USER_SITE else None
    return path, user if user in path else None


def job_argv(task: Task) -> list[str]:
    """The command line of one job process (see ``_BOOT``): isolated from its working folder."""
    return [sys.executable, "-I", "-c", _BOOT, json.dumps(import_path(task.cwd)), str(os.getpid()), task.command,
            *task.args]


def _attempts(task: Task, signal_retries: int, started: float) -> tuple[int, int | None, str] | JobResult:
    """(attempts, exit code, stderr) of the last run, rerun while killed by a signal; or the
    failed result when the process cannot start."""
    argv = job_argv(task)
    attempts, code, err = 0, None, ""
    while attempts <= signal_retries and not _STOP.is_set():
        attempts += 1
        try:
            proc = subprocess.Popen(argv, cwd=task.cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE, start_new_session=True)
        except OSError as exc:
            return JobResult(task.key, task.label, "failed", None, time.perf_counter() - started, attempts,
                             f"cannot start in {task.cwd}: {exc.strerror or exc}", worker=_worker_name())
        with _RUNNING_LOCK:
            _RUNNING.add(proc)
            if _STOP.is_set():  # stopped between the check above and the start: no job outlives the batch
                proc.send_signal(signal.SIGTERM)
        try:
            _, raw = proc.communicate()
        finally:
            with _RUNNING_LOCK:
                _RUNNING.discard(proc)
        code, err = proc.returncode, raw.decode("utf-8", "replace")
        if code >= 0 and code not in _KILLED:
            break
    return attempts, code, err


def run_job(task: Task, *deps: JobResult, signal_retries: int = 2) -> JobResult:
    """Run one task as a psdbake process in task.cwd (on whatever machine calls this).

    deps: the results of task.needs and task.after; the task is skipped when a writer of a
    file it reads did not succeed (``JobResult.failed_writes``). A process killed by a signal (or
    psdbake's own exit after SIGINT/SIGTERM) is run again, up to signal_retries times: its
    outputs are atomic and the commands deterministic. A psdbake exit code is final.
    """
    reads, writes, needs, after = set(task.reads), set(task.writes), set(task.needs), set(task.after)
    blocked = [label for d in deps if d.key in needs for p, label in d.failed_writes if p in reads]
    earlier: dict[str, str] = {}  # written file -> the first earlier writer of it that did not succeed
    for d in deps:
        if d.key in after:
            for p, label in d.failed_writes:
                if p in writes:
                    earlier.setdefault(p, label)

    def failed(status: str) -> tuple[tuple[str, str], ...]:
        if status == "ok":
            return tuple(sorted(earlier.items()))
        return tuple((p, earlier.get(p, task.label)) for p in task.writes)

    if blocked:
        return JobResult(task.key, task.label, "skipped", None, 0.0, 0, f"needs {blocked[0]}, which did not succeed",
                         worker=_worker_name(), failed_writes=failed("skipped"))
    started = time.perf_counter()
    ran = _attempts(task, signal_retries, started)
    if isinstance(ran, JobResult):
        return dataclasses.replace(ran, failed_writes=failed(ran.status))
    attempts, code, err = ran
    seconds = time.perf_counter() - started
    lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
    warns = tuple(ln.removeprefix("psdbake: warning: ") for ln in lines if ln.startswith("psdbake: warning: "))
    if code == 0:
        return JobResult(task.key, task.label, "ok", 0, seconds, attempts, "", warns, _worker_name(), failed("ok"))
    if code is None:
        message = "interrupted before it started"
    elif code < 0:
        message = f"killed by {signal.Signals(-code).name}" + (f" after: {lines[-1]}" if lines else "")
    else:
        message = lines[-1].removeprefix("psdbake: error: ") if lines else f"exit {code} with no message"
    return JobResult(task.key, task.label, "failed", code, seconds, attempts, message, warns, _worker_name(),
                     failed("failed"))


def stop_running() -> None:
    """No new attempts; SIGTERM the running jobs, which unwind and remove their temporary files."""
    _STOP.set()
    with _RUNNING_LOCK:
        for proc in _RUNNING:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)


def allow_running() -> None:
    """A new local batch starts: attempts are allowed again after an earlier one was stopped."""
    _STOP.clear()
