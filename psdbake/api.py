"""The pipeline in plain sight.

fit:   read USD -> pose space -> black-box skinning -> inverse (Powell) -> RBF -> CORRECTIVES
eval:  CORRECTIVES + ANIM -> pose space -> RBF weights -> WEIGHTS (+ points cache)
pose:  ASSET + POSES -> plain UsdSkel skinning per time code -> EXAMPLES to sculpt on

Every function returns data (frozen dataclasses or in-memory layers); nothing here
prints. ``write_*`` export layers atomically.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import multiprocessing
import os
import re
import time as _time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from . import atomic, posespace, rbf
from . import tolerances as tol
from .deformers import Factory, deformer_files, load_deformers
from .errors import FitError, InputError, PsdWarning, where
from .inverse import InverseResult, SculptOutOfRangeError, invert_example
from .normals import CorrectiveNormals, PosedNormals, corrective_normals
from .usd import write as usdwrite
from .usd.blackbox import FLOAT32_MAX, SkinningBlackBox
from .usd.diagnostics import usd_diagnostics, usd_errors
from .usd.normalbox import NormalBlackBox, read_mesh_shading
from .usd.read import (
    DEFAULT_GROUP,
    Scene,
    animation_components,
    check_corrective_indices,
    check_examples_binding,
    compose,
    existing_blend_shapes,
    open_layer,
    psd_prims,
    read_corrective_shapes,
    read_driver_groups,
    require_finite_time_samples,
    require_psd_prims_skinned,
    stray_point_prims,
    validate_animation,
    validate_skinning,
)

Progress = Callable[[int, int, str], None]  # (done, total, what)

__all__ = [  # noqa: RUF022 - grouped: results, then functions
    "DEFAULT_GROUP",
    "load_deformers",
    "usd_diagnostics",
    "usd_errors",
    "Example",
    "FitResult",
    "FitSettings",
    "MeshFit",
    "WeightsResult",
    "evaluate",
    "fit",
    "pose",
    "read_correctives",
    "write_correctives",
    "write_weights",
]


@dataclass(frozen=True)
class FitSettings:
    """Options of ``psdbake fit``; defaults are the documented ones."""

    drivers: tuple[str, ...] = ()  # empty: every joint rotated in any example
    kernel: str = "gaussian"
    sigma: float | None = None  # None: automatic (rbf.auto_sigma)
    degree: int | None = None  # None: rbf.default_degree(kernel)
    smoothing: float = 0.0
    rest_example: bool = True
    pose_space: str = "rotationVector"  # posespace.POSE_SPACES
    twist_axis: tuple[float, float, float] | None = None  # swingTwist: axis in each driver's bind frame
    clamp_weights: bool = False  # clamp b(x) to [0, 1] at eval time (stored, off by default)
    normalize_weights: bool = False  # divide b(x) by max(1, sum) at eval time (stored, off by default)
    rtol: float = tol.INVERSE_RTOL
    meshes: tuple[str, ...] = ()  # empty: every mesh with examples
    deformers: tuple[str, ...] = ()
    group: str = DEFAULT_GROUP  # correctives group: its own examples, drivers, kernel and sigma

    def __post_init__(self) -> None:
        def positive(name: str, value: float | None, allow_zero: bool = False) -> None:
            if value is None:
                return
            ok = np.isfinite(value) and (value >= 0 if allow_zero else value > 0)
            if not ok:
                raise InputError(f"--{name} {value!r}: must be a {'non-negative' if allow_zero else 'positive'} number")

        positive("sigma", self.sigma)
        positive("smoothing", self.smoothing, allow_zero=True)
        positive("tolerance", self.rtol)
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", self.group) or self.group in ("version", "groups"):
            raise InputError(
                f"--group {self.group!r}: must be an identifier (letters, digits, _; not 'version' or 'groups')"
            )
        if self.twist_axis is not None and not (
            np.all(np.isfinite(self.twist_axis)) and np.linalg.norm(self.twist_axis) > 0
        ):
            raise InputError(f"--twist-axis {self.twist_axis!r}: must be a non-zero finite vector")


@dataclass(frozen=True)
class Example:
    """One sculpted example of one mesh."""

    label: str  # "file.usda@t" for messages and reports
    source: str  # EXAMPLES file path
    time: float
    pose: NDArray[np.float64]  # (j, 4) every joint's rotation away from the bind pose, quaternions xyzw


@dataclass(frozen=True)
class MeshFit:
    """Everything fitted for one mesh."""

    mesh: str
    skeleton: str
    point_count: int
    examples: tuple[Example, ...]
    inverses: tuple[InverseResult, ...]
    channels: tuple[str, ...]  # blend-shape channel per example ("" when it has no corrective)
    drivers: tuple[str, ...]
    driver_data: usdwrite.DriverData
    existing_channels: tuple[str, ...]
    existing_targets: tuple[str, ...]
    group: str = DEFAULT_GROUP
    joints: tuple[str, ...] = ()  # skeleton order, as the example poses
    normals: tuple[CorrectiveNormals | None, ...] = ()  # per example, when the mesh authors normals


@dataclass(frozen=True)
class FitResult:
    asset: str
    example_files: tuple[str, ...]
    settings: FitSettings
    meshes: tuple[MeshFit, ...]
    warnings: tuple[str, ...] = field(default_factory=tuple)
    seconds: float = 0.0

    @property
    def missed(self) -> int:
        return int(sum(len(inv.missed) for m in self.meshes for inv in m.inverses))


# --- fit ---------------------------------------------------------------------------------

def _safe_token(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", text).strip("_") or "mesh"


def _resolve_drivers(requested: Sequence[str], joints: Sequence[str], label: str) -> list[int]:
    """Joint indices for --driver names: a full joint path or an unambiguous leaf name."""
    out = []
    for name in requested:
        hits = [i for i, j in enumerate(joints) if j == name]
        if not hits:
            hits = [i for i, j in enumerate(joints) if j.split("/")[-1] == name]
        if len(hits) != 1:
            what = "is not a joint of" if not hits else "is ambiguous in"
            raise InputError(f"{label}: --driver {name!r} {what} the skeleton")
        out.append(hits[0])
    return sorted(set(out))


def _gather_examples(
    asset_scene: Scene, example_files: Sequence[str], meshes: Sequence[str]
) -> dict[str, list[tuple[Scene, str, float, NDArray[np.float64]]]]:
    """mesh path -> [(scene, file, time, sculpt)], in file order then time order."""
    found: dict[str, list] = {m: [] for m in meshes}
    for path in example_files:
        layer = open_layer(path)
        scene = _scene((path, asset_scene.files[0]))  # the same stage the serial solves use
        stray = stray_point_prims(layer, {m.path for m in scene.skinned_meshes()})
        if stray:
            raise InputError(
                f"{where(path, stray[0], 'points')}: sculpted points on a prim that is not a skinned mesh "
                f"of {asset_scene.label}"
            )
        for mesh in meshes:
            for t in scene.authored_point_samples(layer, mesh):
                found[mesh].append((scene, path, t, scene.point_sample(layer, mesh, t)))
    return found


@dataclass(frozen=True)
class _InverseTask:
    """One example's inverse, described by file names only so it can run in any process."""

    asset: str
    source: str
    mesh: str
    time: float
    deformers: tuple[str, ...]
    rtol: float
    points: int


@functools.lru_cache(maxsize=8)
def _scene(files: tuple[str, ...]) -> Scene:
    return Scene(list(files), label=files[0])


def _invert(task: _InverseTask) -> tuple[InverseResult, CorrectiveNormals | None]:
    """Solve one example: the same code whether it runs here or in a worker process."""
    scene = _scene((task.source, task.asset))
    rest = _scene((task.asset,)).rest_points(task.mesh)
    sculpt = scene.point_sample(open_layer(task.source), task.mesh, task.time)
    box = SkinningBlackBox(scene, task.mesh, task.time, load_deformers(task.deformers))
    try:
        inverse = invert_example(box, rest, sculpt, rtol=task.rtol)
    except SculptOutOfRangeError as exc:
        raise InputError(f"{where(task.source, task.mesh, 'points')}: example at time {task.time:g}: {exc}") from None
    return inverse, _normal_offsets(task, scene, box, rest, sculpt, inverse)


def _normal_offsets(task: _InverseTask, scene: Scene, box: SkinningBlackBox, rest, sculpt, inverse: InverseResult
                    ) -> CorrectiveNormals | None:
    """BlendShape normalOffsets so shading follows the sculpt, for meshes that author
    per-point ``normals`` (else None: renderers derive normals from the posed points,
    which already carry the correction). Inverts UsdSkel's normal skinning at the
    example's pose, as the points are inverted (``psdbake.normals.corrective_normals``)."""
    shading = read_mesh_shading(_scene((task.asset,)).prim(task.mesh), task.asset)
    if shading.normals is None or not len(inverse.indices):
        return None
    posed = PosedNormals(box(rest), sculpt, NormalBlackBox(scene, task.mesh, task.time).normal_maps())
    return corrective_normals(rest, shading.topology, inverse.indices, inverse.offsets, shading.normals,
                              shading.interpolation, posed)


def _auto_jobs(tasks: Sequence[_InverseTask], jobs: int | None) -> int:
    """Worker processes. Default 1: UsdSkel already skins on every core, and on the 2-core
    machines measured (benchmarks/jobs.py, 20 examples x 100k points) two workers were
    0.56x as fast as one. ``--jobs N`` is there for machines where examples outnumber
    what UsdSkel's threads can use."""
    if jobs is None:
        return 1
    return max(1, min(int(jobs), len(tasks)))


def _solve_all(tasks: Sequence[_InverseTask], jobs: int | None, progress: Progress | None
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
            pool.shutdown(wait=False, cancel_futures=True)
            _end_workers(workers.values())
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


def _invert_tracked(i: int, task: _InverseTask):
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


def _worker_died(tasks: Sequence[_InverseTask], running, workers: dict) -> Exception:
    """A worker process ended abruptly (a deformer calling os._exit, a segfault, the OOM killer):
    name the example it was solving and the deformers, rather than BrokenProcessPool."""
    import signal

    from .errors import DeformerError, PsdError

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
    return PsdError(f"a fit worker process died{how}{doing} (out of memory?)")


def open_asset(asset: str, notes: list[str] | None = None) -> Scene:
    """The asset on its own, with every skinned mesh's influences and skeleton validated."""
    scene = Scene([asset])
    scene.require_skinned()
    for info in scene.skinned_meshes():
        for msg in validate_skinning(scene, info.path):
            if notes is not None:
                notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=3)
    return scene


def _check_pose(scene: Scene, mesh: str, local: NDArray[np.float64], t: float, joints: Sequence[str]) -> None:
    """A joint whose local transform has a zero-scale axis has no rotation: no pose, and
    skinning through it cannot be inverted."""
    bad = np.nonzero(posespace.undefined_rotations(local))[0]
    if len(bad):
        raise FitError(
            f"{where(scene.label, mesh)}: joint {joints[bad[0]]!r} has zero scale (or NaN) at time {t:g}: "
            "its pose is undefined and skinning through it cannot be inverted"
        )


def _bind_quaternions(bind_local: NDArray[np.float64]) -> NDArray[np.float64]:
    return posespace.rotations(bind_local).as_quat()


def fit(
    asset: str,
    example_files: Sequence[str],
    settings: FitSettings = FitSettings(),
    *,
    jobs: int | None = None,
    progress: Progress | None = None,
) -> FitResult:
    """Fit rest-space correctives and their RBF drivers from sculpted examples.

    jobs: worker processes for the per-example inverses (None: 1, see ``_auto_jobs``). The
    output does not depend on it.
    """
    started = _time.perf_counter()
    if not example_files:
        raise InputError("fit needs at least one EXAMPLES file")
    notes: list[str] = []
    load_deformers(settings.deformers)  # fail fast on a bad spec; each solve loads its own chain
    asset_scene = open_asset(asset, notes)
    infos = asset_scene.skinned_meshes()
    all_meshes = [m.path for m in infos]
    for wanted in settings.meshes:
        if wanted not in all_meshes:
            raise InputError(f"{where(asset, wanted)}: --mesh is not a skinned mesh of the asset")
    meshes = [m for m in all_meshes if not settings.meshes or m in settings.meshes]
    try:
        return _fit_examples(asset, asset_scene, infos, meshes, example_files, settings, jobs, progress, notes, started)
    finally:
        _scene.cache_clear()  # the example stages die with the fit


def _fit_examples(asset, asset_scene, infos, meshes, example_files, settings, jobs, progress, notes, started
                  ) -> FitResult:
    """fit() once the asset is open: gather and validate the examples, solve, fit the RBFs."""
    for path in example_files:  # the skinning fit inverts must be the one eval and UsdSkel apply
        check_examples_binding(asset_scene, _scene((path, asset)), path)
    found = _gather_examples(asset_scene, example_files, meshes)
    work = [(m, ex) for m in meshes for ex in found[m]]
    for mesh in sorted({m for m, _ in work}):
        asset_scene.require_not_instanced(mesh)  # before any worker starts
    if not work:
        raise InputError(
            f"{', '.join(example_files)}: no examples: no points time samples on the skinned meshes "
            f"{', '.join(f'<{m}>' for m in meshes)}"
        )
    # Validate every example (cheap) before solving any (expensive).
    tasks: list[_InverseTask] = []
    checked: set[tuple[int, str]] = set()
    per_mesh: dict[str, list[Example]] = {}
    for mesh_info in infos:
        mesh = mesh_info.path
        if mesh not in meshes or not found[mesh]:
            continue
        rest = asset_scene.rest_points(mesh)
        bind_local = asset_scene.bind_local_transforms(mesh)
        for scene, source, t, sculpt in found[mesh]:
            if not np.isfinite(t):
                raise InputError(f"{where(source, mesh, 'points')}: example at time code {t!r}: USD accepts a time "
                                 "sample at inf, but an example needs a finite time code (its pose is there)")
            if sculpt.shape != rest.shape:
                raise InputError(
                    f"{where(source, mesh, 'points')}: example at time {t:g} has {len(sculpt)} points, "
                    f"the asset's mesh has {len(rest)}"
                )
            if not np.all(np.isfinite(sculpt)):
                raise InputError(f"{where(source, mesh, 'points')}: example at time {t:g} contains NaN or inf")
            if scene.animation_prim(mesh) is None:
                raise InputError(
                    f"{where(source, mesh_info.skeleton)}: no SkelAnimation bound (skel:animationSource), "
                    f"so the example at time {t:g} has no pose"
                )
            if (id(scene), mesh) not in checked:
                validate_animation(scene, mesh)
                require_finite_time_samples(scene, scene.animation_prim(mesh), source)
                checked.add((id(scene), mesh))
            local = scene.joint_local_transforms(mesh, t)
            _check_pose(scene, mesh, local, t, mesh_info.joints)
            pose_x = posespace.relative_rotations(bind_local, local).as_quat().reshape(-1, 4)
            label = f"{os.path.basename(source)}@{t:g}"
            per_mesh.setdefault(mesh, []).append(Example(label=label, source=source, time=t, pose=pose_x))
            tasks.append(_InverseTask(asset, source, mesh, t, settings.deformers, settings.rtol, len(rest)))
    solved = _solve_all(tasks, jobs, progress)
    fits = []
    k = 0
    for mesh_info in infos:
        if mesh_info.path not in per_mesh:
            continue
        examples = per_mesh[mesh_info.path]
        mine = solved[k : k + len(examples)]
        k += len(examples)
        bind_local = asset_scene.bind_local_transforms(mesh_info.path)
        fitted = _fit_rbf(asset, asset_scene, mesh_info, examples, [s[0] for s in mine], bind_local, settings, notes)
        fits.append(dataclasses.replace(fitted, normals=tuple(s[1] for s in mine)))
        why_not = read_mesh_shading(asset_scene.prim(mesh_info.path), asset).why_not
        if why_not and not why_not.startswith(("no authored normals", "not a Mesh")):
            msg = f"{where(asset, mesh_info.path)}: no normalOffsets written: {why_not}"
            notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=2)
    return FitResult(
        asset=asset,
        example_files=tuple(example_files),
        settings=settings,
        meshes=tuple(fits),
        warnings=tuple(notes),
        seconds=_time.perf_counter() - started,
    )


def _fit_rbf(asset, asset_scene, mesh_info, examples, inverses, bind_local, settings, notes) -> MeshFit:
    mesh, joints = mesh_info.path, mesh_info.joints
    poses = np.array([e.pose for e in examples])
    if settings.drivers:
        driver_idx = _resolve_drivers(settings.drivers, joints, where(asset, mesh_info.skeleton))
    else:
        driver_idx = list(np.nonzero(posespace.rotated_joints(poses, tol.DRIVER_ANGLE_ATOL))[0])
        if not driver_idx:
            files = ", ".join(sorted({e.source for e in examples}))
            raise FitError(
                f"{files} {where(None, mesh)}: every example is at the bind pose, so no joint drives the correctives "
                "(name joints with --driver)"
            )
    if settings.pose_space not in posespace.POSE_SPACES:
        raise FitError(f"unknown pose space {settings.pose_space!r}: choose one of {', '.join(posespace.POSE_SPACES)}")
    if settings.pose_space == "swingTwist" and settings.twist_axis is None:
        raise FitError("--pose-space swingTwist needs --twist-axis (the twist axis in each driver's bind frame)")

    def coordinates(pose: NDArray[np.float64]) -> NDArray[np.float64]:
        delta = Rotation.from_quat(pose[driver_idx])
        return posespace.features(delta, settings.pose_space, settings.twist_axis)

    centers, labels, outputs = [], [], []
    if settings.rest_example:
        centers.append(coordinates(np.tile([0.0, 0.0, 0.0, 1.0], (len(joints), 1))))
        labels.append("bind")
    base = mesh_info.path.split("/")[-1]
    root_rel = os.path.relpath(mesh, mesh_info.skel_root) if mesh != mesh_info.skel_root else base
    prefix = f"psd_{settings.group}_{_safe_token(root_rel)}"
    channels = []
    for k, (example, inverse) in enumerate(zip(examples, inverses, strict=True)):
        if len(inverse.indices) == 0:
            msg = (
                f"{where(example.source, mesh)}: example at time {example.time:g} equals plain skinning; "
                "it is kept as a zero example"
            )
            notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=2)
            channels.append("")
        else:
            outputs.append(len(centers))
            channels.append(f"{prefix}_{k:02d}")
        centers.append(coordinates(example.pose))
        labels.append(example.label)
    if not outputs:
        files = ", ".join(sorted({e.source for e in examples}))
        raise FitError(f"{files} {where(None, mesh)}: no example differs from plain skinning: nothing to correct")
    full_centers = np.array(centers)
    model = rbf.fit_cardinal(
        full_centers, outputs, labels,
        kernel=settings.kernel, sigma=settings.sigma, degree=settings.degree, smoothing=settings.smoothing,
    )
    self_weights = model.weights(full_centers[outputs])
    for col, row in enumerate(outputs):
        if self_weights[col, col] < tol.SELF_WEIGHT_MIN:
            msg = (f"{where(asset, mesh)}: example {labels[row]} reaches a weight of only "
                   f"{self_weights[col, col]:.3f} at its own pose (smoothing {settings.smoothing:g})")
            notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=2)
    near = rbf.check_distinct(full_centers, labels)
    for a, b, d in near:
        msg = f"{where(asset, mesh)}: examples {a} and {b} are only {d:.3g} rad apart in pose space"
        notes.append(msg)
        warnings.warn(msg, PsdWarning, stacklevel=2)
    data = usdwrite.DriverData(
        drivers=[joints[j] for j in driver_idx],
        bind_rotations=_bind_quaternions(bind_local[driver_idx]),
        pose_space=settings.pose_space,
        twist_axis=settings.twist_axis,
        clamp_weights=settings.clamp_weights,
        normalize_weights=settings.normalize_weights,
        kernel=model.kernel,
        sigma=model.sigma,
        degree=model.degree,
        smoothing=model.smoothing,
        centers=model.centers,
        center_labels=labels,
        shapes=[c for c in channels if c],
        coefficients=model.coefficients,
        powers=model.powers,
        shift=model.shift,
        scale=model.scale,
        dims=model.dims,
        example_times=[e.time for e in examples],
        example_sources=[os.path.basename(e.source) for e in examples],
    )
    existing, targets = existing_blend_shapes(asset_scene, mesh)
    return MeshFit(
        mesh=mesh,
        skeleton=mesh_info.skeleton,
        point_count=mesh_info.point_count,
        examples=tuple(examples),
        inverses=tuple(inverses),
        channels=tuple(channels),
        drivers=tuple(data.drivers),
        driver_data=data,
        existing_channels=tuple(existing),
        existing_targets=tuple(targets),
        group=settings.group,
        joints=tuple(joints),
    )


def _shapes_of(m: MeshFit) -> list[usdwrite.BlendShapeData]:
    """The corrective BlendShapes of one fitted mesh (examples equal to plain skinning have none)."""
    out = []
    for k, (ch, inv) in enumerate(zip(m.channels, m.inverses, strict=True)):
        if not ch:
            continue
        name = f"psd_{m.group}_{k:02d}"
        cn = m.normals[k] if m.normals else None
        if cn is None:
            out.append(usdwrite.BlendShapeData(name=name, channel=ch, indices=inv.indices, offsets=inv.offsets))
        else:  # pointIndices grown to the sculpt's 1-ring: normals change there too
            out.append(usdwrite.BlendShapeData(name=name, channel=ch, indices=cn.indices, offsets=cn.offsets,
                                               normal_offsets=cn.normal_offsets))
    return out


_Groups = dict[str, dict[str, tuple[usdwrite.DriverData, list[usdwrite.BlendShapeData]]]]  # mesh -> group -> data


def read_correctives(asset: str, correctives: str) -> _Groups:
    """Every group of an existing CORRECTIVES layer over asset: its driver data and BlendShapes."""
    owners = psd_prims(open_layer(correctives))
    scene = Scene([correctives, asset], label=correctives)
    skinned = {m.path: m for m in scene.skinned_meshes()}
    if not owners:
        raise InputError(f"{correctives}: holds no psd: correctives (not a CORRECTIVES layer written by psdbake fit)")
    out: _Groups = {}
    for mesh in owners:
        if mesh not in skinned:
            raise InputError(f"{where(correctives, mesh)}: has correctives but is not a skinned mesh of {asset}")
        for group, data in read_driver_groups(scene, mesh):
            shapes = read_corrective_shapes(scene, mesh, data.shapes)
            for shape in shapes:
                if len(shape.indices) and (shape.indices.min() < 0 or shape.indices.max() >= skinned[mesh].point_count):
                    raise InputError(
                        f"{where(correctives, mesh + '/' + shape.name, 'pointIndices')}: indices outside the "
                        f"{skinned[mesh].point_count} points of the asset's mesh"
                    )
            out.setdefault(mesh, {})[group] = (data, shapes)
    return out


def _cross_talk(result: FitResult, others: _Groups) -> list[str]:
    """Groups are fitted independently, so another group's correctives must be (nearly) off
    at this group's examples: its weight times its largest offset, relative to the mesh's
    diagonal, must stay under the fit tolerance, or that sculpt is not reproduced."""
    notes = []
    for m in result.meshes:
        infos = dict(others.get(m.mesh, {}))
        infos.pop(m.group, None)
        for group, (data, shapes) in sorted(infos.items()):
            reach = np.array([np.abs(s.offsets).max() if len(s.offsets) else 0.0 for s in shapes])
            idx = [m.joints.index(d) for d in data.drivers if d in m.joints]
            if len(idx) != len(data.drivers):
                continue  # eval refuses such a layer with its own message
            for ex, inv in zip(m.examples, m.inverses, strict=True):
                w = weights_of_rotations(data, Rotation.from_quat(ex.pose[idx]), 1)[0]
                spill = float(np.max(np.abs(w) * reach)) / (inv.diagonal or 1.0)
                if spill > result.settings.rtol:
                    notes.append(
                        f"{where(result.asset, m.mesh)}: group {group!r} moves points by {spill:.2g} of the diagonal "
                        f"at example {ex.label} of group {m.group!r}: the two groups' drivers overlap, so that sculpt "
                        "is not reproduced exactly"
                    )
    return notes


def correctives_layer(result: FitResult, update: str | None = None):
    """CORRECTIVES as an in-memory layer: BlendShapes, bindings and psd: driver data.

    update: an existing CORRECTIVES layer whose other groups are carried over unchanged;
    this fit's group replaces its namesake on the fitted meshes (on every mesh when the
    fit was not restricted with ``--mesh``). Groups are written sorted by name, so the
    layer does not depend on the order the groups were fitted in.
    """
    from . import __version__

    groups: _Groups = read_correctives(result.asset, update) if update else {}
    for note in _cross_talk(result, groups):
        warnings.warn(note, PsdWarning, stacklevel=2)
    group = result.settings.group
    fitted = {m.mesh for m in result.meshes}
    for mesh, per_group in groups.items():
        if not result.settings.meshes or mesh in fitted:
            per_group.pop(group, None)
    for m in result.meshes:
        groups.setdefault(m.mesh, {})[group] = (m.driver_data, _shapes_of(m))
    asset_scene = Scene([result.asset])
    layer = usdwrite.new_layer(
        f"psdbake {__version__} fit: rest-space correctives (inverse PSD)", metadata=usdwrite.asset_metadata(result.asset)
    )
    for mesh in sorted(groups):
        names = sorted(groups[mesh])
        if not names:
            continue
        existing, targets = existing_blend_shapes(asset_scene, mesh)
        ours = {s.channel for g in names for s in groups[mesh][g][1]}
        keep = [(c, t) for c, t in zip(existing, targets, strict=True) if c not in ours]
        shapes = [s for g in names for s in groups[mesh][g][1]]
        usdwrite.author_blend_shapes(layer, mesh, shapes, [c for c, _ in keep], [t for _, t in keep])
        usdwrite.author_driver_data(layer, mesh, [(g, groups[mesh][g][0]) for g in names])
    return layer


def files_read(paths: Sequence[str], deformers: Sequence[str] = ()) -> list[str]:
    """Every file a command reads: the given layers, every layer they reach (sublayers,
    references, payloads, clips) and the ``--deformer`` source files. No output may be
    one of them (``atomic.check_output``); layer files that are not regular files
    (a FIFO would block USD) are refused here, before anything is composed."""
    return sorted(set(usdwrite.files_read(paths)) | set(deformer_files(deformers)))


def write_correctives(result: FitResult, path: str, *, update: bool = False,
                      side_files: Sequence[tuple[str, str]] = ()) -> str:
    """Export CORRECTIVES atomically; inputs are never overwritten.

    update: when path exists, keep its other groups (``fit --group``); the read, merge and
    rename happen under a lock, so concurrent group fits into one layer all land.
    side_files: (path, text) written in the same commit (``fit --report``): both land or neither.
    """
    inputs = files_read([result.asset, *result.example_files], result.settings.deformers)
    if not update:
        usdwrite.export_all([(path, correctives_layer(result)), *side_files], inputs)
        return path
    atomic.check_output(path, inputs, usdwrite.FORMATS)
    with atomic.updating(path):
        base = path if os.path.exists(path) else None
        layer = correctives_layer(result, update=base)
        usdwrite.export_all([(path, layer), *side_files], inputs)
        return path


# --- eval --------------------------------------------------------------------------------

@dataclass(frozen=True)
class AnimWeights:
    """Blend-shape channels and weights to author on one SkelAnimation."""

    animation: str
    channels: tuple[str, ...]  # existing channels first, then psdbake's
    times: NDArray[np.float64]  # (f,)
    weights: NDArray[np.float64]  # (f, c)
    psd_channels: int  # how many of the channels are psdbake's


@dataclass(frozen=True)
class WeightsResult:
    asset: str
    correctives: str
    anim: str
    animations: tuple[AnimWeights, ...]
    fps: float | None
    seconds: float = 0.0


def parse_frames(text: str | None) -> tuple[float, float] | None:
    """'A:B' -> (A, B), inclusive whole frames; at most ``tol.MAX_FRAMES`` of them
    (checked by arithmetic: nothing is allocated for a refused range)."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(-?\d{1,30}(?:\.\d{0,30})?)\s*:\s*(-?\d{1,30}(?:\.\d{0,30})?)\s*", text)
    if not m or float(m.group(1)) > float(m.group(2)):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise InputError(f"--frames {shown!r}: expected START:END with START <= END (e.g. 1:240)")
    span = float(m.group(1)), float(m.group(2))
    frame_count(span, text.strip())
    return span


def frame_count(frames: tuple[float, float], text: str | None = None) -> int:
    """How many whole frames A..B holds, refusing a range past ``tol.MAX_FRAMES`` frames or
    bounds past ``tol.MAX_FRAME_MAGNITUDE`` (and a range with none) before anything is allocated."""
    start, end = (float(f) for f in frames)
    shown = text if text is not None and len(text) <= 60 else f"{start:g}:{end:g}"
    if not (np.isfinite(start) and np.isfinite(end)) or max(abs(start), abs(end)) > tol.MAX_FRAME_MAGNITUDE:
        raise InputError(f"--frames {shown}: frame numbers must be finite and within "
                         f"+-{tol.MAX_FRAME_MAGNITUDE:.0f} (2**53, where whole frames stop being distinct)")
    count = int(np.floor(end) - np.ceil(start)) + 1
    if count < 1:
        raise InputError(f"--frames {shown}: no whole frame in that range")
    if count > tol.MAX_FRAMES:
        raise InputError(f"--frames {shown}: {count} frames, more than the limit of {tol.MAX_FRAMES} "
                         "(a typo? evaluate a long range in parts)")
    return count


def frames_of(scene: Scene, mesh: str, frames: tuple[float, float] | None, label: str | None = None
              ) -> NDArray[np.float64]:
    """Whole frames A..B when given, else the animation's authored time samples."""
    if frames is not None:
        count = frame_count(frames)  # refuses a huge range before allocating it
        return np.ceil(float(frames[0])) + np.arange(count, dtype=np.float64)
    times = scene.animation_times(mesh)
    if not times:
        anim = scene.animation_prim(mesh) or mesh
        raise InputError(f"{where(label or scene.label, anim)}: the animation has no time samples; give --frames")
    return np.array(times, dtype=np.float64)


def rbf_from_driver_data(data: usdwrite.DriverData) -> rbf.CardinalRbf:
    if data.kernel not in rbf.KERNELS:
        raise InputError(f"psd:kernel {data.kernel!r} is unknown")
    return rbf.CardinalRbf(
        centers=data.centers, kernel=data.kernel, sigma=data.sigma, degree=data.degree,
        smoothing=data.smoothing, coefficients=data.coefficients, powers=data.powers,
        shift=data.shift, scale=data.scale, dims=data.dims,
    )


def check_driver_transforms(local: NDArray[np.float64], times, drivers: Sequence[str], label: str) -> None:
    """Driver transforms (f, d, 4, 4) must be finite with no zero-scale axis: else no pose."""
    bad = posespace.undefined_rotations(local)
    if bad.any():
        f, d = (int(i[0]) for i in np.nonzero(bad))
        raise InputError(
            f"{label}: joint {drivers[d]!r} has a NaN, infinite or zero-scale transform at time {float(times[f]):g}"
        )


def driver_weights(data: usdwrite.DriverData, local: NDArray[np.float64]) -> NDArray[np.float64]:
    """Weights (f, s) of the stored correctives for driver local transforms (f, d, 4, 4):
    pose coordinates, cardinal RBF, then the stored clamp/normalise options."""
    f = len(local)
    delta = posespace.relative_from_quaternions(np.tile(data.bind_rotations, (f, 1)), local.reshape(-1, 4, 4))
    return weights_of_rotations(data, delta, f)


def weights_of_rotations(data: usdwrite.DriverData, delta: Rotation, f: int) -> NDArray[np.float64]:
    """Weights (f, s) for the drivers' rotations away from their bind pose (f * d rotations)."""
    width = posespace.WIDTH[data.pose_space]
    x = posespace.features(delta, data.pose_space, data.twist_axis).reshape(f, width * len(data.drivers))
    w = rbf_from_driver_data(data).weights(x)
    if data.clamp_weights:
        w = np.clip(w, 0.0, 1.0)
    if data.normalize_weights:
        w = w / np.maximum(1.0, w.sum(axis=1, keepdims=True))
    return w


def evaluate(
    asset: str,
    correctives: str,
    anim: str,
    *,
    frames: tuple[float, float] | None = None,
    progress: Progress | None = None,
) -> WeightsResult:
    """RBF weights of every corrective at every frame of ANIM."""
    started = _time.perf_counter()
    open_asset(asset)
    scene = Scene([anim, correctives, asset], label=correctives)
    scene.require_skinned()
    require_psd_prims_skinned(scene, correctives, asset)
    per_anim: dict[str, list] = {}
    anim_scene = Scene([anim, asset], label=anim)
    for info in scene.skinned_meshes():
        groups = read_driver_groups(scene, info.path)
        if not groups:
            continue
        for _, data in groups:
            check_corrective_indices(scene, info.path, data.shapes, info.point_count)
        anim_prim = scene.animation_prim(info.path)
        if anim_prim is None:
            raise InputError(f"{where(anim, info.skeleton)}: no SkelAnimation bound (skel:animationSource)")
        validate_animation(anim_scene, info.path)
        require_finite_time_samples(scene, anim_prim, anim)
        per_anim.setdefault(anim_prim, []).append((info, groups))
    if not per_anim:
        raise InputError(f"{correctives}: no psd: driver data on any skinned mesh of {asset}")
    results = []
    planned = {a: frames_of(scene, per_anim[a][0][0].path, frames, label=anim) for a in sorted(per_anim)}
    total, done = sum(len(planned[a]) * len(per_anim[a]) for a in planned), 0
    for anim_prim in sorted(per_anim):
        entries = per_anim[anim_prim]
        first = entries[0][0].path
        times = planned[anim_prim]
        existing_channels, existing_weights = _existing_channels(scene, first, times)
        psd_channels, columns = [], []
        for info, groups in entries:
            local = np.empty((len(times), len(info.joints), 4, 4))
            for f, t in enumerate(times):  # UsdSkel's pose per frame: the slow part, so progress per frame
                local[f] = scene.joint_local_transforms(info.path, float(t))
                done += 1
                if progress:
                    progress(done, total, info.path)
            for group, data in groups:
                idx = [info.joints.index(d) for d in data.drivers]
                check_driver_transforms(local[:, idx], times, data.drivers, where(anim, anim_prim))
                w = driver_weights(data, local[:, idx])
                bad = ~(np.abs(w) <= FLOAT32_MAX)  # NaN fails the comparison
                if bad.any():  # finite psd: values can still overflow: refuse rather than write inf
                    f, s = (int(i[0]) for i in np.nonzero(bad))
                    raise InputError(
                        f"{where(correctives, info.path)}: group {group!r} gives channel {data.shapes[s]} the weight "
                        f"{float(w[f, s]):.3g} at time {float(times[f]):g}: beyond float32's range (the psd: values "
                        "are corrupt or absurdly large)"
                    )
                columns.append(w)
                psd_channels += list(data.shapes)
        ours = np.concatenate(columns, axis=1)
        keep = [i for i, c in enumerate(existing_channels) if c not in set(psd_channels)]
        channels = tuple([existing_channels[i] for i in keep] + psd_channels)
        weights = np.concatenate([existing_weights[:, keep], ours], axis=1)
        results.append(AnimWeights(anim_prim, channels, times, weights, len(psd_channels)))
    fps = scene.stage.GetTimeCodesPerSecond()
    return WeightsResult(asset, correctives, anim, tuple(results), fps, _time.perf_counter() - started)


def _existing_channels(scene: Scene, mesh: str, times: NDArray[np.float64]) -> tuple[list[str], NDArray[np.float64]]:
    """The animation's own blend-shape channels and their weights at times (kept in WEIGHTS)."""
    _, skel_query = scene.query(mesh)
    anim = skel_query.GetAnimQuery()
    order = [str(c) for c in anim.GetBlendShapeOrder()] if anim else []
    weights = np.zeros((len(times), len(order)))
    if order:
        for f, t in enumerate(times):
            w = anim.ComputeBlendShapeWeights(float(t))
            if w is not None and len(w) == len(order):
                weights[f] = np.array(w, dtype=np.float64)
    return order, weights


def weights_layer(result: WeightsResult):
    """WEIGHTS as an in-memory layer."""
    from . import __version__

    return usdwrite.weights_layer(
        f"psdbake {__version__} eval: corrective blend-shape weights",
        [(a.animation, a.channels, a.times, a.weights) for a in result.animations],
        result.fps,
        usdwrite.asset_metadata(result.asset),
    )


def write_weights(result: WeightsResult, path: str, *, points_cache: tuple[str, object] | None = None,
                  deformers: Sequence[str] = ()) -> str:
    """Export WEIGHTS (and, given as (path, layer), the points cache in the same commit:
    both land or neither)."""
    outputs = [(path, weights_layer(result)), *([points_cache] if points_cache else [])]
    usdwrite.export_all(outputs, files_read([result.asset, result.correctives, result.anim], deformers))
    return path


def points_cache_layer(result: WeightsResult, deformers: Sequence[str] = (), *, progress: Progress | None = None):
    """Final posed points per frame (correctives, existing shapes, skinning, deformers),
    as a layer that needs no UsdSkel: the SkelRoots become Xforms, like BakeSkinning.
    The asset's authored shading normals are blocked (they are rest normals), so renderers
    derive normals from the cached points.

    The points come from UsdSkel evaluating the stack ASSET + CORRECTIVES + ANIM + WEIGHTS
    (the correctives are ordinary blend shapes there), then the deformer chain.
    """
    from . import __version__

    chain = load_deformers(deformers)
    wl = weights_layer(result)
    scene = Scene([wl, result.anim, result.correctives, result.asset], label=result.correctives)
    times = sorted({float(t) for a in result.animations for t in a.times})
    meshes = scene.skinned_meshes()
    return usdwrite.points_layer(
        f"psdbake {__version__} eval: points cache (no UsdSkel needed)",
        scene.skel_roots, _posed_points(scene, scene, meshes, times, chain, progress), times, result.fps,
        usdwrite.asset_metadata(result.asset),
        blocked=[(m.path, name) for m in meshes for name in ("normals", "primvars:normals")
                 if scene.prim(m.path).GetAttribute(name).HasAuthoredValue()],
    )


def describe(path: str) -> dict:
    """What a USD file holds (``psdbake inspect``): JSON-ready, sorted."""
    from .usd.describe import describe as _describe

    return _describe(path)


def _posed_points(rest_scene: Scene, scene: Scene, meshes, times, chain, progress: Progress | None):
    """(mesh, time, points) for every mesh and time: the black box applied to the rest points."""
    total, done = len(meshes) * len(times), 0
    for info in meshes:
        rest = rest_scene.rest_points(info.path)
        for t in times:
            yield info.path, t, SkinningBlackBox(scene, info.path, t, chain)(rest)
            done += 1
            if progress:
                progress(done, total, info.path)


def write_points_cache(result: WeightsResult, path: str, deformers: Sequence[str] = (), *, progress=None) -> str:
    return usdwrite.export_atomic(
        points_cache_layer(result, deformers, progress=progress), path,
        files_read([result.asset, result.correctives, result.anim], deformers),
    )


# --- pose --------------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseResult:
    asset: str
    poses: str
    times: tuple[float, ...]
    meshes: tuple[str, ...]
    layer: object  # Sdf.Layer
    deformers: tuple[str, ...] = ()


def pose(asset: str, poses: str, deformers: Sequence[str] = (), *, progress: Progress | None = None) -> PoseResult:
    """EXAMPLES to sculpt on: skinned points per time code of POSES, with the pose itself."""
    from . import __version__

    chain: list[tuple[str, Factory]] = load_deformers(deformers)
    asset_scene = open_asset(asset)
    scene = Scene([poses, asset], label=poses)
    meshes = scene.skinned_meshes()
    for info in meshes:
        validate_animation(scene, info.path)
        if (anim_path := scene.animation_prim(info.path)) is not None:
            require_finite_time_samples(scene, anim_path, poses)
    anims = sorted({a for m in meshes if (a := scene.animation_prim(m.path))})
    if not anims:
        raise InputError(f"{poses}: no SkelAnimation is bound to the skeleton (skel:animationSource)")
    times = sorted({t for m in meshes for t in scene.animation_times(m.path)})
    if not times:
        raise InputError(f"{where(poses, anims[0])}: the animation has no time samples: nothing to pose")
    fps = scene.stage.GetTimeCodesPerSecond()
    animations, seen = [], set()
    for info in meshes:
        anim_path = scene.animation_prim(info.path)
        if anim_path is None or info.skeleton in seen:
            continue
        seen.add(info.skeleton)
        path, joints, channels, anim_samples = animation_components(scene, info.path, times)
        animations.append((info.skeleton, path, joints, channels, anim_samples))
    layer = usdwrite.examples_layer(
        f"psdbake {__version__} pose: skinned examples to sculpt on", animations,
        _posed_points(asset_scene, scene, meshes, times, chain, progress), times, fps,
        usdwrite.asset_metadata(asset),
    )
    return PoseResult(asset, poses, tuple(times), tuple(m.path for m in meshes), layer, tuple(deformers))


def write_pose(result: PoseResult, path: str) -> str:
    return usdwrite.export_atomic(result.layer, path, files_read([result.asset, result.poses], result.deformers))


def write_stack(path: str, layers: Sequence[str]) -> str:
    """A viewable stack: sublayers ``layers`` (weakest first: ASSET, CORRECTIVES, ANIM, WEIGHTS)."""
    compose(list(reversed(layers)))  # refuse what no viewer could compose (cycles, unreadable sublayers)
    return usdwrite.export_atomic(usdwrite.stack_layer(path, layers), path, files_read(layers))
