"""``psdbake batch JOBS.toml``: many pose/fit/eval/stack runs described in one file.

A job is one table of JOBS.toml (``[[fit]]``, ``[[eval]]``, ...): the command's arguments and
long options by name (``points_cache`` or ``points-cache`` for ``--points-cache``), with
``[defaults]`` merged under every job whose command takes the key. Relative paths are left as
written and each job runs in the jobs file's folder, so a job file is portable and a job's
outputs are byte-identical to the same command typed in that folder.

Every job runs as its own process, ``python -m psdbake._job`` (= ``python -m psdbake``):
USD's global state stays per job, a crashing job cannot take its worker down, and exit codes
come for free. The commands write their outputs atomically, so a job killed mid-way leaves no
partial file and is simply run again (they are deterministic).

Order comes from the files: a job that reads a file other jobs write runs after all of them
(and is skipped if one fails); jobs writing the same file run in file order (``fit --group``
updates of one CORRECTIVES layer are read-modify-write). Independent jobs run in parallel, on a
local pool of processes (here) or a Dask cluster (``batch_dask``).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import heapq
import json
import os
import shlex
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .errors import InputError, OutputError, PsdError

COMMANDS = ("pose", "fit", "eval", "stack")
_READS = frozenset({"asset", "examples", "poses", "anim", "correctives", "layers"})  # click parameter names
_WRITES = frozenset({"output", "report", "points_cache"})
_BATCH_OWNS = frozenset({"quiet", "verbose", "as_json"})  # the batch decides what its jobs print
_KILLED = (130, 143)  # psdbake's exit after SIGINT/SIGTERM (unwound, temporary file removed)


class BatchUsageError(PsdError):
    """A batch option that cannot be honoured here (e.g. ``--scheduler`` without dask)."""

    exit_code = 2


class BatchError(PsdError):
    """Some jobs failed; the exit code is the first failed job's (file order)."""

    def __init__(self, message: str, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code


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


# --- parse ------------------------------------------------------------------------------------


def _commands() -> dict[str, Any]:
    from .cli import cli  # the command-line interface is the schema of a job

    return {name: cli.commands[name] for name in COMMANDS}


def _long(option: Any) -> str:
    return next((o for o in option.opts if o.startswith("--")), option.opts[0])


def _key_of(param: Any) -> str:
    import click

    return _long(param).lstrip("-").replace("-", "_") if isinstance(param, click.Option) else param.name


def _schema(command: Any) -> dict[str, Any]:
    """TOML key -> click parameter: arguments by name, options by long name."""
    return {_key_of(p): p for p in command.params if p.name not in _BATCH_OWNS}


def _scalar(kind: Any, value: Any, where: str, key: str) -> str:
    import click

    if isinstance(kind, click.types.IntParamType):
        ok, want = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(kind, click.types.FloatParamType):
        ok, want = isinstance(value, int | float) and not isinstance(value, bool), "a number"
    elif isinstance(kind, click.types.BoolParamType):
        ok, want = isinstance(value, bool), "true or false"
    else:
        ok, want = isinstance(value, str), "a string"
    if not ok:
        raise InputError(f"{where}: {key} must be {want}, got {value!r}")
    return repr(value) if isinstance(value, float) else str(value).lower() if isinstance(value, bool) else str(value)


def _values(param: Any, value: Any, where: str, key: str) -> list[str]:
    """A TOML value as the strings click will parse (one per value, nargs/multiple flattened)."""
    many = getattr(param, "multiple", False) or param.nargs == -1
    if param.nargs > 1:
        if not isinstance(value, list) or len(value) != param.nargs:
            raise InputError(f"{where}: {key} must be a list of {param.nargs} values, got {value!r}")
        return [_scalar(kind, v, where, key) for kind, v in zip(param.type.types, value, strict=True)]
    if many:
        items = value if isinstance(value, list) else [value]
        return [_scalar(param.type, v, where, key) for v in items]
    return [_scalar(param.type, value, where, key)]


def _arguments(command: Any, values: Mapping[str, Any], where: str) -> list[str]:
    """The command line of one job (after the command name), checked by click itself."""
    import click

    schema = _schema(command)
    for key, param in schema.items():
        if param.required and key not in values:
            raise InputError(f"{where}: missing required key {key!r}")
    positional, options = [], []
    for key, param in schema.items():
        if key not in values:
            continue
        value = values[key]
        if isinstance(param, click.Argument):
            positional += _values(param, value, where, key)
        elif param.is_flag and not param.count:
            if not isinstance(value, bool):
                raise InputError(f"{where}: {key} must be true or false, got {value!r}")
            options += [_long(param)] if value else param.secondary_opts[:1]
        elif param.nargs > 1:
            options += [_long(param), *_values(param, value, where, key)]
        else:
            options += [f"{_long(param)}={v}" for v in _values(param, value, where, key)]
    if any(p.startswith("-") for p in positional):
        args = [*options, "--", *positional]
    else:
        args = [*positional, *options]
    try:
        command.make_context(command.name, list(args))
    except click.ClickException as exc:
        raise InputError(f"{where}: {exc.format_message()}") from None
    return args


def eval_chunks(output: str, points_cache: str | None, frames: str, chunk_size: int) -> list[tuple[int, tuple[str, ...]]]:
    """The tasks of ``eval --frames A:B --chunk-size N``: (K, the files ``--chunk K`` writes, as
    paths written like output), cut as ``psdbake.chunks`` cuts them. Every chunk task also writes
    the manifests, identically, so they are listed with each chunk."""
    from . import api
    from . import chunks as ch

    span = api.parse_frames(frames)
    assert span is not None
    plan = ch.plan_frames(span, chunk_size)  # by arithmetic: bounded (MAX_FRAMES, MAX_CHUNKS), no frame list
    manifests = [output, ch.clip_manifest_path(output)]
    if points_cache:
        manifests += [points_cache, ch.clip_manifest_path(points_cache)]
    return [
        (c.index, (ch.chunk_path(output, plan, c), *([ch.chunk_path(points_cache, plan, c)] if points_cache else []),
                   *manifests))
        for c in plan.chunks
    ]


#: Largest jobs file read. A job is a few hundred bytes, so 1 MiB is thousands of jobs (more
#: than a farm queue takes from one file); the cap keeps a wrong path (a huge log, a disk image)
#: from being read into memory whole.
MAX_JOBS_FILE_BYTES = 1 << 20


def _read_toml(path: str) -> dict[str, Any]:
    """The jobs file, if it is a regular file of at most MAX_JOBS_FILE_BYTES: a FIFO, a socket
    or a device (``/dev/zero``, ``/dev/urandom``) would block or never end."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))  # a FIFO must not block the open
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            kind = "a folder" if stat.S_ISDIR(info.st_mode) else "a FIFO" if stat.S_ISFIFO(info.st_mode) else \
                "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode) else "not a regular file"
            raise InputError(f"{path}: a jobs file must be a regular file, this is {kind}")
        if info.st_size > MAX_JOBS_FILE_BYTES:
            raise InputError(f"{path}: {info.st_size} bytes, more than a jobs file may hold "
                             f"({MAX_JOBS_FILE_BYTES} bytes): is this the jobs file?")
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            data = fh.read(MAX_JOBS_FILE_BYTES + 1)  # the file may grow after the fstat
        if len(data) > MAX_JOBS_FILE_BYTES:
            raise InputError(f"{path}: more than a jobs file may hold ({MAX_JOBS_FILE_BYTES} bytes)")
        return tomllib.loads(data.decode("utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None
    finally:
        if fd >= 0:
            os.close(fd)


def _norm(table: Mapping[str, Any]) -> dict[str, Any]:
    return {k.replace("-", "_"): v for k, v in table.items()}


def load_jobs(path: str) -> Batch:
    """Parse, check and expand a jobs file; refuse it whole (InputError) if any job is wrong."""
    commands = _commands()
    doc = _read_toml(path)
    folder = os.path.dirname(os.path.abspath(path))
    unknown = sorted(set(doc) - {"defaults", *commands})
    if unknown:
        raise InputError(f"{path}: unknown table [{unknown[0]}] (expected [defaults] or [[{']], [['.join(commands)}]])")
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError(f"{path} [defaults]: must be a table")
    defaults = _norm(defaults)
    schemas = {name: _schema(cmd) for name, cmd in commands.items()}
    for key in sorted(defaults):
        if not any(key in s for s in schemas.values()):
            raise InputError(f"{path} [defaults]: unknown key {key!r}")

    jobs: list[tuple[str, str, tuple[str, ...], list[tuple[str, str, list[str], tuple[str, ...]]]]] = []
    kept: list[tuple[str, str]] = [(os.path.abspath(path), "the jobs file itself")]  # read, never written by a job
    written: list[tuple[str, str]] = []
    for name in doc:  # tables in order of first appearance, jobs in file order
        if name == "defaults":
            continue
        entries = doc[name]
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise InputError(f"{path} [{name}]: jobs are an array of tables: write [[{name}]]")
        schema = schemas[name]
        for n, entry in enumerate(entries, start=1):
            where = f"{path} [[{name}]] #{n}"
            job = _norm(entry)
            for key in job:
                if key not in schema:
                    owned = " (psdbake batch sets it)" if key in ("quiet", "verbose", "json") else ""
                    raise InputError(f"{where}: unknown key {key!r} for psdbake {name}{owned}")
            values = {k: v for k, v in defaults.items() if k in schema} | job
            args = _arguments(commands[name], values, where)
            paths = {key: _values(schema[key], values[key], where, key) for key in values
                     if schema[key].name in _READS | _WRITES}
            reads = tuple(p for k, ps in paths.items() if schema[k].name in _READS for p in ps)
            writes = tuple(p for k, ps in paths.items() if schema[k].name in _WRITES for p in ps)
            for k in values:
                if schema[k].name == "deformers":
                    specs = _values(schema[k], values[k], where, k)
                    kept += [(spec.rpartition(":")[0], f"a --deformer file of {where}") for spec in specs
                             if spec.rpartition(":")[0].endswith(".py")]
            written += [(p, where) for p in writes]
            label = f"[[{name}]] #{n}"
            subtasks = [(label, f"{name}-{n}", args, writes)]
            if "chunk_size" in values and "chunk" in schema and "chunk" not in values:
                if "frames" not in values:
                    raise InputError(f"{where}: chunk_size needs frames = \"START:END\" to cut the job into tasks "
                                     "(psdbake batch does not read the animation to count its samples)")
                try:
                    parts = eval_chunks(values["output"], values.get("points_cache"), values["frames"], values["chunk_size"])
                except PsdError as exc:
                    raise InputError(f"{where}: {exc}") from None
                subtasks = [(f"{label} chunk {k}/{len(parts)}", f"{name}-{n}-chunk{k}", [*args, f"--chunk={k}"], files)
                            for k, files in parts]
            jobs.append((label, name, reads, subtasks))
    _refuse_overwrites(folder, kept, written)
    return Batch(path, folder, _order(path, folder, jobs))


def _same_file(a: str, b: str) -> bool:
    """Same path once links are resolved, or the same file under two names (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _refuse_overwrites(folder: str, kept: Sequence[tuple[str, str]], written: Sequence[tuple[str, str]]) -> None:
    """No job may write a file the batch reads but never produces: the jobs file itself (a job's
    ``report = "jobs.toml"``) or a ``--deformer`` source file. Refused at load, before any job runs."""
    for out, where in written:
        target = os.path.join(folder, out)
        for src, what in kept:
            if _same_file(target, os.path.join(folder, src)):
                raise InputError(f"{where}: output {out} is {what}: a job may not overwrite it")


def _order(path: str, folder: str, jobs: Sequence[tuple]) -> tuple[Task, ...]:
    """Tasks with their dependencies, topologically sorted, file order among the free ones."""

    def real(p: str) -> str:
        return os.path.realpath(os.path.join(folder, p))

    digest = hashlib.sha256(json.dumps([folder, [s[2] for j in jobs for s in j[3]]]).encode()).hexdigest()[:12]
    tasks: list[Task] = []
    for label, name, reads, subtasks in jobs:
        for sub_label, slug, args, writes in subtasks:
            tasks.append(Task(
                key=f"psdbake-{slug}-{digest}", label=sub_label, job=label, command=name, args=tuple(args), cwd=folder,
                reads=tuple(dict.fromkeys(real(p) for p in reads)), writes=tuple(dict.fromkeys(real(p) for p in writes)),
                outputs=writes,
            ))
    writers: dict[str, list[Task]] = {}
    for t in tasks:
        for p in t.writes:
            first = writers.setdefault(p, [t])[0]
            if first.command != t.command:
                raise InputError(f"{path} {t.job}: writes {os.path.relpath(p, folder)}, as {first.job} does: "
                                 "only jobs of one command may write the same file")
            if t is not first:
                writers[p].append(t)
    linked = []
    for t in tasks:
        needs = {w.key for p in t.reads for w in writers.get(p, ()) if w.job != t.job}
        after = set()
        for p in t.writes:
            ws = writers[p]
            mine = next(i for i, w in enumerate(ws) if w.job == t.job)
            after |= {w.key for w in ws[:mine]}
        linked.append(dataclasses.replace(t, needs=tuple(needs), after=tuple(after - needs)))
    position = {t.key: i for i, t in enumerate(linked)}
    waiting = {t.key: set(t.needs) | set(t.after) for t in linked}
    users: dict[str, list[str]] = {}
    for key, deps in waiting.items():
        for d in deps:
            users.setdefault(d, []).append(key)
    ready = [position[k] for k, deps in waiting.items() if not deps]
    heapq.heapify(ready)
    ordered = []
    while ready:
        t = linked[heapq.heappop(ready)]
        ordered.append(t)
        for u in users.get(t.key, ()):
            waiting[u].discard(t.key)
            if not waiting[u]:
                heapq.heappush(ready, position[u])
    if len(ordered) < len(linked):
        stuck = sorted({linked[position[k]].job for k, deps in waiting.items() if deps})
        raise InputError(f"{path}: jobs read each other's outputs in a cycle: {', '.join(stuck)}")
    final = {t.key: i for i, t in enumerate(ordered)}
    return tuple(dataclasses.replace(t, needs=tuple(sorted(t.needs, key=final.get)), after=tuple(sorted(t.after, key=final.get)))
                 for t in ordered)


# --- run ------------------------------------------------------------------------------------


_STOP = threading.Event()  # set on Ctrl-C/SIGTERM of a local batch: no new attempts
_RUNNING: set[subprocess.Popen] = set()
_RUNNING_LOCK = threading.Lock()


def default_workers() -> int:
    """Local jobs at once: one per core (a job's start-up, ~1 s of imports, is single-threaded)."""
    return max(1, os.cpu_count() or 1)


def _worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def run_job(task: Task, *deps: JobResult, signal_retries: int = 2) -> JobResult:
    """Run one task as a psdbake process in task.cwd (on whatever machine calls this).

    deps: the results of task.needs and task.after. A process killed by a signal (or
    psdbake's own exit after SIGINT/SIGTERM) is run again, up to signal_retries times: its
    outputs are atomic and the commands deterministic. A psdbake exit code is final.
    """
    blocked = [d.label for d in deps if d.key in task.needs and d.status != "ok"]
    if blocked:
        return JobResult(task.key, task.label, "skipped", None, 0.0, 0, f"needs {blocked[0]}, which did not succeed",
                         worker=_worker_name())
    argv = [sys.executable, "-m", "psdbake._job", str(os.getpid()), task.command, *task.args]
    started = time.perf_counter()
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
    lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
    warns = tuple(ln.removeprefix("psdbake: warning: ") for ln in lines if ln.startswith("psdbake: warning: "))
    if code == 0:
        return JobResult(task.key, task.label, "ok", 0, time.perf_counter() - started, attempts, "", warns, _worker_name())
    if code is None:
        message = "interrupted before it started"
    elif code < 0:
        message = f"killed by {signal.Signals(-code).name}" + (f" after: {lines[-1]}" if lines else "")
    else:
        message = lines[-1].removeprefix("psdbake: error: ") if lines else f"exit {code} with no message"
    return JobResult(task.key, task.label, "failed", code, time.perf_counter() - started, attempts, message, warns,
                     _worker_name())


OnDone = Callable[[JobResult, int, int], None]  # (result, finished so far, total)


def run_local(batch: Batch, workers: int | None = None, *, signal_retries: int = 2,
              on_done: OnDone | None = None) -> BatchResult:
    """Run the batch here, at most `workers` jobs at once, each as soon as what it waits for is done."""
    workers = workers or default_workers()
    make_output_folders(batch)
    started = time.perf_counter()
    results: dict[str, JobResult] = {}
    pending = list(batch.tasks)
    running: dict[concurrent.futures.Future, Task] = {}
    position = {t.key: i for i, t in enumerate(batch.tasks)}
    _STOP.clear()
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
            _stop_running()
            raise
    return BatchResult(batch, "local", workers, tuple(results[t.key] for t in batch.tasks), time.perf_counter() - started)


def make_output_folders(batch: Batch) -> None:
    """Create the outputs' folders before the first job starts: a farm writes into new shot
    folders, and the commands themselves refuse a missing one."""
    for folder in sorted({os.path.dirname(p) for t in batch.tasks for p in t.writes}):
        try:
            os.makedirs(folder, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{batch.path}: cannot create output folder {folder} ({exc.strerror or exc})") from None


def _stop_running() -> None:
    """No new attempts; SIGTERM the running jobs, which unwind and remove their temporary files."""
    _STOP.set()
    with _RUNNING_LOCK:
        for proc in _RUNNING:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)


def run_batch(batch: Batch, *, scheduler: str | None = None, workers: int | None = None, signal_retries: int = 2,
              on_done: OnDone | None = None) -> BatchResult:
    """Run on the local pool, or on the Dask cluster at `scheduler` (tcp://HOST:PORT)."""
    if scheduler is None:
        return run_local(batch, workers, signal_retries=signal_retries, on_done=on_done)
    if workers is not None:
        raise BatchUsageError("--workers sizes the local pool; with --scheduler the cluster's workers run the jobs")
    from .batch_dask import run_dask

    return run_dask(batch, scheduler, signal_retries=signal_retries, on_done=on_done)
