"""Every example's black-box inverse, serially or on a process pool.

One example is one task, described by file names only, so the same code solves it here
or in a spawned worker (USD is multithreaded: never forked). A worker that dies, or a
signal, ends the pool at once and names the example and the deformer that was running.
"""

from __future__ import annotations

import concurrent.futures
import functools
import multiprocessing
import os
import sys
import time as _time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ..arrays import Progress
from ..deformers import load_deformers
from ..errors import InputError, SculptOutOfRangeError, where
from ..normals import CorrectiveNormals, PosedNormals, corrective_normals
from ..usd.blackbox import ChainSkinning, SkinningBlackBox
from ..usd.compose import open_layer
from ..usd.normalbox import MeshShading, NormalBlackBox, read_mesh_shading
from ..usd.read import Scene
from . import coupled
from .inverse import InverseResult
from .smoothbasis import edge_adjacency


@dataclass(frozen=True)
class InverseTask:
    """One example's inverse, described by file names only so it can run in any process."""

    asset: str
    source: str
    mesh: str
    time: float
    deformers: tuple[str, ...]
    rtol: float
    points: int


#: Scenes the fit has composed already, by their files (``share_scene``): ``cached_scene``
#: hands them out rather than composing the same files again.
_shared: dict[tuple[str, ...], Scene] = {}


def share_scene(scene: Scene) -> None:
    """Let ``cached_scene`` use scene for its files until ``clear_caches``: the asset the fit
    opened and validated first is the stage its rest points and shading are read from (a
    second composition of the asset cost ~1 ms at 100k points)."""
    if all(isinstance(f, str) for f in scene.files) and scene.label == scene.files[0]:
        _shared[tuple(scene.files)] = scene


@functools.lru_cache(maxsize=8)
def cached_scene(files: tuple[str, ...]) -> Scene:
    return _shared.get(files) or Scene(list(files), label=files[0])


@functools.lru_cache(maxsize=8)
def cached_rest(asset: str, mesh: str) -> NDArray[np.float64]:
    """The mesh's rest points, read once per fit rather than once per example (read-only:
    every example of the mesh shares them)."""
    rest = cached_scene((asset,)).rest_points(mesh)
    rest.flags.writeable = False
    return rest


@functools.lru_cache(maxsize=8)
def cached_shading(asset: str, mesh: str) -> MeshShading:
    """The mesh's shading (``read_mesh_shading``, faces checked), read once per fit: at 1M
    points its topology took 0.13 s an example. Only a mesh with authored normals uses the
    topology, so without them it is not read (the faces are checked in place)."""
    return read_mesh_shading(cached_scene((asset,)).prim(mesh), asset, normals_only=True)


@functools.lru_cache(maxsize=8)
def cached_adjacency(asset: str, mesh: str) -> sp.csr_matrix | None:
    """The mesh's edge adjacency for the coupled inverse's smooth start, read only when a
    coupled example needs it, once per fit; None for a prim with no faces to read."""
    topology = read_mesh_shading(cached_scene((asset,)).prim(mesh), asset).topology
    return edge_adjacency(topology) if topology is not None else None


def clear_caches() -> None:
    """Forget the stages and meshes read for a fit (they die with it)."""
    _shared.clear()
    cached_scene.cache_clear()
    cached_rest.cache_clear()
    cached_shading.cache_clear()
    cached_adjacency.cache_clear()


def _invert(task: InverseTask) -> tuple[InverseResult, CorrectiveNormals | None]:
    """Solve one example: the same code whether it runs here or in a worker process."""
    scene = cached_scene((task.source, task.asset))
    rest = cached_rest(task.asset, task.mesh)
    sculpt = scene.point_sample(open_layer(task.source), task.mesh, task.time)
    box = SkinningBlackBox(scene, task.mesh, task.time, load_deformers(task.deformers))
    try:
        # probes the chain: per-vertex (Powell in lockstep) or coupled (Newton-Krylov), see InverseResult.regime
        inverse = coupled.invert(box, rest, sculpt, rtol=task.rtol,
                                 neighbours=functools.partial(cached_adjacency, task.asset, task.mesh),
                                 skinning=ChainSkinning(box))  # the skinning the chain's own calls did, read back
    except SculptOutOfRangeError as exc:
        raise InputError(f"{where(task.source, task.mesh, 'points')}: example at time {task.time:g}: {exc}") from None
    return inverse, _normal_offsets(task, scene, box, rest, sculpt, inverse)


def _normal_offsets(task: InverseTask, scene: Scene, box: SkinningBlackBox, rest, sculpt, inverse: InverseResult
                    ) -> CorrectiveNormals | None:
    """BlendShape normalOffsets so shading follows the sculpt, for meshes that author
    per-point ``normals`` (else None: renderers derive normals from the posed points,
    which already carry the correction). Inverts UsdSkel's normal skinning at the
    example's pose, as the points are inverted (``psdbake.normals.corrective_normals``)."""
    shading = cached_shading(task.asset, task.mesh)
    if shading.normals is None or shading.topology is None or shading.interpolation is None or not len(inverse.indices):
        return None
    posed = PosedNormals(box(rest), sculpt, NormalBlackBox(scene, task.mesh, task.time).normal_maps())
    return corrective_normals(rest, shading.topology, inverse.indices, inverse.offsets, shading.normals,
                              shading.interpolation, posed)


def _auto_jobs(tasks: Sequence[InverseTask], jobs: int | None) -> int:
    """Worker processes. Default 1: UsdSkel already skins on every core, and on the 2-core
    machines measured (benchmarks/jobs.py, 20 examples x 100k points) two workers were
    0.56x as fast as one. ``--jobs N`` is there for machines where examples outnumber
    what UsdSkel's threads can use."""
    if jobs is None:
        return 1
    return max(1, min(int(jobs), len(tasks)))


def solve_all(tasks: Sequence[InverseTask], jobs: int | None, progress: Progress | None
               ) -> list[tuple[InverseResult, CorrectiveNormals | None]]:
    """Every example's inverse, in task order, serially or on a process pool."""
    n = _auto_jobs(tasks, jobs)
    results: list[tuple[InverseResult, CorrectiveNormals | None] | None] = [None] * len(tasks)
    if n == 1:
        for i, task in enumerate(tasks):
            results[i] = _invert(task)
            if progress:
                progress(i + 1, len(tasks), f"{task.mesh} {os.path.basename(task.source)}@{task.time:g}")
    else:
        from concurrent.futures.process import BrokenProcessPool

        ctx = multiprocessing.get_context("spawn")  # USD is multithreaded: never fork it
        running = ctx.RawArray("q", len(tasks))  # pid of the worker solving task i, 0 when none
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_worker_init,
                                                      initargs=(running,))
        workers: dict = {}
        try:
            with _ignoring_sigint():  # workers spawned now inherit SIG_IGN: Ctrl-C is the parent's to handle
                futures = {pool.submit(_invert_tracked, i, task): i for i, task in enumerate(tasks)}
            workers = dict(getattr(pool, "_processes", None) or {})  # spawned by the submits
            for done, future in enumerate(concurrent.futures.as_completed(futures), start=1):
                try:
                    results[futures[future]] = future.result()
                except BrokenProcessPool:
                    raise _worker_died(tasks, running, workers) from None
                if progress:
                    task = tasks[futures[future]]
                    progress(done, len(tasks), f"{task.mesh} {os.path.basename(task.source)}@{task.time:g}")
        except BaseException:
            # Ctrl-C, SIGTERM (KeyboardInterrupt, see cli.main) or a failure: stop now, not after every
            # queued example (a stuck deformer would never finish): cancel the queue, end the workers.
            workers |= dict(getattr(pool, "_processes", None) or {})
            manager = getattr(pool, "_executor_manager_thread", None)  # shutdown forgets it
            pool.shutdown(wait=False, cancel_futures=True)
            _end_workers(workers.values())
            _join_manager(manager)
            raise
        pool.shutdown(wait=True)
    return [r for r in results if r is not None]


_RUNNING = None  # in a worker: the shared array of which worker solves which task


class _ignoring_sigint:  # noqa: N801 - used as a context manager, like contextlib's
    """SIGINT blocked while worker processes are spawned: a blocked signal stays blocked in the
    child (the mask survives fork and exec), so Ctrl-C, which reaches the whole process group,
    never interrupts a worker still importing USD (a KeyboardInterrupt traceback of its own);
    the parent ends the workers. A Ctrl-C in this short window is delivered on unblocking."""

    def __enter__(self) -> None:
        import signal

        self._old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})

    def __exit__(self, *exc) -> None:
        import signal

        signal.pthread_sigmask(signal.SIG_SETMASK, self._old)


def _worker_init(running) -> None:
    """A fit worker: Ctrl-C is the parent's to handle (it ends the workers), so a worker
    prints no KeyboardInterrupt traceback of its own."""
    import signal

    global _RUNNING
    _RUNNING = running
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _invert_tracked(i: int, task: InverseTask) -> tuple[InverseResult, CorrectiveNormals | None]:
    assert _RUNNING is not None, "only in a worker started by solve_all"
    _RUNNING[i] = os.getpid()
    try:
        return _invert(task)
    finally:
        _RUNNING[i] = 0


def _end_workers(processes) -> None:
    """SIGTERM the worker processes (they write nothing, so nothing is left half-done), then
    SIGKILL any that has not gone within a second (stuck in C code that ignores SIGTERM)."""
    import contextlib

    processes = list(processes)
    for p in processes:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = _time.monotonic() + 1.0
    for p in processes:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - _time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)


def _join_manager(thread, timeout: float = 2.0) -> None:
    """Wait (bounded) for the pool's manager thread to close its wake-up pipe. Python 3.11's
    exit hook writes to that pipe unlocked (CPython gh-125451 gave it a lock in later 3.12 and 3.13):
    left running, the thread can close it mid-write and the interrupted run ends with an
    ``OSError: Bad file descriptor`` traceback after ``psdbake: interrupted``. Once the
    workers are gone the thread exits at once; the bound keeps Ctrl-C prompt whatever happens."""
    if thread is not None:
        thread.join(timeout)


def _worker_died(tasks: Sequence[InverseTask], running, workers: dict) -> Exception:
    """A worker process ended abruptly (a deformer calling os._exit, a segfault, the OOM killer):
    name the example it was solving and the deformers, rather than BrokenProcessPool."""
    import signal

    from ..errors import DeformerError, PsdError

    deadline = _time.monotonic() + 2.0  # the pool terminates the other workers: wait for every exit code
    while _time.monotonic() < deadline and any(p.exitcode is None for p in workers.values()):
        _time.sleep(0.01)
    dead = {pid: p.exitcode for pid, p in workers.items() if p.exitcode is not None and p.exitcode != -signal.SIGTERM}
    busy = [i for i in range(len(tasks)) if running[i]]
    culprits = [i for i in busy if running[i] in dead] or busy
    how = ""
    if culprits and running[culprits[0]] in dead:
        code = dead[running[culprits[0]]]
        how = f" (killed by {signal.Signals(-code).name})" if code < 0 else f" (exit {code})"
    examples = " or ".join(f"{where(t.source, t.mesh)} example at time {t.time:g}" for t in (tasks[i] for i in culprits))
    doing = f" while solving {examples}" if examples else ""
    specs = tasks[0].deformers if tasks else ()
    if specs:
        return DeformerError(f"deformer {', '.join(repr(s) for s in specs)}: the worker process running it "
                             f"died{how}{doing}")
    script = getattr(sys.modules.get("__main__"), "__file__", None)
    ours = script is not None and (os.path.basename(script) == "psdbake" or os.path.abspath(script).startswith(
        os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep))  # the command's own entry points
    if not examples and script and not ours:  # died starting: spawn runs the calling script again
        return PsdError(f"a fit worker process died{how} before solving anything: a script calling psdbake.fit with "
                        f"jobs > 1 must guard its top level with `if __name__ == \"__main__\":` (its workers are "
                        f"spawned, and run {script} again)")
    return PsdError(f"a fit worker process died{how}{doing} (out of memory?)")
