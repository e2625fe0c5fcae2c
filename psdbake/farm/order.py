"""The order of a batch's tasks, from the files they read and write.

A task that reads a file other jobs write runs after all of them (and is skipped if one
fails: ``needs``); tasks writing the same file run in file order (``after``: ``fit --group``
updates of one CORRECTIVES layer are read-modify-write; the chunks of a shot share its
manifests); any other file two jobs write is refused, as the later would replace the earlier's
output; otherwise file order. Edges are
linear in the jobs (``_link``): 25,000 jobs writing one file make a chain, not 312 million
pairs. Keys are
deterministic (a digest of the folder and every command line), so a rerun of the same jobs
file has the same Dask keys.
"""

from __future__ import annotations

import dataclasses
import hashlib
import heapq
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass

from ..errors import InputError
from .tasks import Batch, Task

#: The commands that read-modify-write a CORRECTIVES layer under its update lock.
UPDATERS = frozenset({"fit", "mirror", "groups"})


@dataclass(frozen=True)
class Part:
    """One task of a job, before ordering: the job itself, or one chunk of it."""

    label: str
    slug: str  # names the task's key
    args: list[str]
    writes: tuple[str, ...]  # as written in the jobs file


@dataclass(frozen=True)
class Job:
    """One checked table of the jobs file."""

    label: str  # "[[fit]] #2"
    command: str
    reads: tuple[str, ...]  # as written in the jobs file
    writes: tuple[str, ...]
    parts: list[Part]


def _tasks(folder: str, jobs: Sequence[Job]) -> list[Task]:
    """One task per part, with real paths for ordering and a key unique to this jobs file."""

    def real(p: str) -> str:
        return os.path.realpath(os.path.join(folder, p))

    digest = hashlib.sha256(json.dumps([folder, [p.args for j in jobs for p in j.parts]]).encode()).hexdigest()[:12]
    return [
        Task(key=f"psdbake-{p.slug}-{digest}", label=p.label, job=j.label, command=j.command, args=tuple(p.args),
             cwd=folder, reads=tuple(dict.fromkeys(real(r) for r in j.reads)),
             writes=tuple(dict.fromkeys(real(w) for w in p.writes)), outputs=p.writes)
        for j in jobs for p in j.parts
    ]


def _link(path: str, folder: str, tasks: Sequence[Task]) -> list[Task]:
    """Each task with what it needs and what it waits for, in edges linear in the jobs: a task
    waits for the tasks of the job that wrote each of its files just before it (``after``: one
    chain per file, in file order) and needs the tasks of the last job writing each file it
    reads (``needs``). An earlier writer's failure reaches the readers along the chain
    (``JobResult.failed_writes``), so a reader is still skipped when any writer of what it reads
    failed. Only jobs of one command may write the same file, but for the commands that update a
    CORRECTIVES layer (``UPDATERS``: ``fit``, ``mirror`` and ``groups`` into one file run in file
    order, each on the one before's result)."""
    writers: dict[str, list[list[Task]]] = {}  # file -> the tasks of each job writing it, in file order
    before: dict[tuple[str, str], list[Task]] = {}  # (file, job) -> the tasks of the job writing it just before
    for t in tasks:
        for p in t.writes:
            jobs = writers.setdefault(p, [])
            if jobs and jobs[0][0].command != t.command and not {jobs[0][0].command, t.command} <= UPDATERS:
                raise InputError(f"{path} {t.job}: writes {os.path.relpath(p, folder)}, as {jobs[0][0].job} does: "
                                 "only jobs of one command may write the same file")
            if jobs and jobs[-1][0].job != t.job and t.command not in UPDATERS and os.path.splitext(p)[1] and not (
                    _is_chunk(t) and _is_chunk(jobs[-1][0])):  # (an --obj-dir folder is shared file by file)
                raise InputError(f"{path} {t.job}: writes {os.path.relpath(p, folder)}, as {jobs[-1][0].job} does: the "
                                 "later would replace the earlier's output (write each to its own file; the chunks of "
                                 "one shot are one job with chunk_size, or jobs with chunk = K)")
            if not jobs or jobs[-1][0].job != t.job:
                if jobs:
                    before[(p, t.job)] = jobs[-1]
                jobs.append([])
            jobs[-1].append(t)
    linked = []
    for t in tasks:
        # a job that reads the file it also writes (mirror in place) reads the writer's just before it
        needs = {w.key for p in t.reads
                 for w in (before.get((p, t.job), ()) if p in t.writes else writers.get(p, [()])[-1])
                 if w.job != t.job}
        after = {w.key for p in t.writes for w in before.get((p, t.job), ())}
        linked.append(dataclasses.replace(t, needs=tuple(needs), after=tuple(after - needs)))
    return linked


def _is_chunk(task: Task) -> bool:
    """A chunk of a chunked eval: its manifest is shared with the shot's other chunks by design."""
    return any(a == "--chunk" or a.startswith("--chunk=") for a in task.args)


def _sort(path: str, linked: Sequence[Task]) -> list[Task]:
    """Topological order, file order among the tasks free to run."""
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
    return ordered


def check_reads(batch: Batch) -> None:
    """Refuse, before anything runs, a job that reads a file no job writes and that is not
    there (a typo in a path would otherwise fail that job, and skip its readers, hours into a
    farm run), or that reads its own output (only the commands updating a CORRECTIVES layer
    may: ``mirror`` and ``groups`` in place). ``psdbake batch`` checks this before it runs or
    prints a dry run; ``load_jobs`` does not, so a jobs file can be planned before its inputs exist."""
    path, folder = batch.path, batch.folder
    written = {p for t in batch.tasks for p in t.writes}
    for t in batch.tasks:
        for p in t.reads:
            if p in t.writes and t.command not in UPDATERS:
                raise InputError(f"{path} {t.job}: reads {os.path.relpath(p, folder)}, which it also writes: inputs "
                                 "are never overwritten; write to another file")
            if p not in written and not os.path.exists(p):
                raise InputError(f"{path} {t.job}: reads {os.path.relpath(p, folder)}, which is not there and no job "
                                 f"writes (paths are relative to the jobs file's folder, {folder})")


def order(path: str, folder: str, jobs: Sequence[Job]) -> tuple[Task, ...]:
    """Tasks with their dependencies, topologically sorted, file order among the free ones."""
    ordered = _sort(path, _link(path, folder, _tasks(folder, jobs)))
    final = {t.key: i for i, t in enumerate(ordered)}
    return tuple(dataclasses.replace(t, needs=tuple(sorted(t.needs, key=final.__getitem__)),
                                     after=tuple(sorted(t.after, key=final.__getitem__)))
                 for t in ordered)
