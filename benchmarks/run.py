"""psdbake benchmark suite: the lockstep Powell inverse against its references, side by side.

Run ``python -m benchmarks.run`` from the repository root (``make bench``); ``--quick``
keeps only the 1.3k and 13k rigs. Every rig is generated on the fly into a temporary
folder (``benchmarks.rigs``), so the numbers always describe the code in this checkout.

Per rig and example, on the same black box (UsdSkel skinning, plus a user deformer on
the non-linear chain):

- psdbake: ``psdbake.inverse.invert_example`` (and one full ``psdbake.api.fit``);
- literal: the paper's method, scipy Powell per vertex with a whole-mesh black-box
  call per evaluation, timed on a sample of vertices and extrapolated;
- one-shot: a forward-difference Jacobian and one linear solve per vertex;
- closed form (LBS only): blend each vertex's matrices and solve, the practical floor;
- Powell alone: ``invert_example_with(..., quasi_newton=False)``, the solver without the
  Broyden refresh (before issue 15), interleaved per example with psdbake's own solve so
  the "solver" table compares calls and seconds from the same run.

Then the eval side: RBF weights over a long shot and the points cache against
``UsdSkel.BakeSkinning``. A fixed-width table goes to stdout, the full record to
``benchmarks/results/run.json`` (``benchmarks.results``: docs/benchmarks.md is made from it).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import itertools
import os
import platform
import pstats
import resource
import shutil
import sys
import tempfile
import time
import tracemalloc
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import scipy
from numpy.typing import NDArray
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

import psdbake
from psdbake import api
from psdbake import tolerances as tol
from psdbake.results import FitResult
from psdbake.settings import FitSettings
from psdbake.solver.inverse import InverseResult, invert_example, invert_example_with
from psdbake.usd.read import Scene

from . import references, results, rigs

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_JSON = results.path_of("run")

#: Literal-method sample: vertices per rig, spread over the examples (it is ~1000x slower).
LITERAL_VERTICES = {"1.3k": 10, "13k": 10, "100k": 3}
#: The eval benchmark: RBF weights over a long shot, points cache over a short one.
EVAL_FRAMES, CACHE_FRAMES, EVAL_RIG = 10_000, 48, ("lbs", "13k")

_T0 = time.perf_counter()


def log(msg: str) -> None:
    """Progress on stderr, so stdout holds only the table."""
    print(f"[{time.perf_counter() - _T0:7.1f}s] {msg}", file=sys.stderr, flush=True)


# --- machine ----------------------------------------------------------------------------

def machine_info() -> dict[str, Any]:
    """What the numbers depend on: cores, CPU, library versions, thread settings."""
    threads = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "PXR_WORK_THREAD_LIMIT")
    return {
        "nproc": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu_model": results.cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "usd": ".".join(map(str, Usd.GetVersion())),
        "psdbake": psdbake.__version__,
        "git": results.git_revision(),
        "thread_env": {k: os.environ[k] for k in threads if k in os.environ},
    }


# --- memory -----------------------------------------------------------------------------

def _status_kb(field: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM) so a block's own peak can be read."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return _status_kb("VmHWM") is not None
    except OSError:
        return False


class PeakRss:
    """Resident memory of a block: the process peak during it and that peak above its start, MB.

    Uses VmHWM after resetting it (Linux >= 4.0); otherwise ``ru_maxrss``, which only
    sees new process-wide highs. ``method`` says which. The delta under-reports when
    the allocator reuses memory freed earlier, so tracemalloc is reported as well.
    """

    def __enter__(self) -> PeakRss:
        self.exact = _reset_peak_rss()
        self.method = "VmHWM reset per call" if self.exact else "ru_maxrss (process high-water)"
        self.before = _status_kb("VmRSS") if self.exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return self

    def __exit__(self, *exc: object) -> None:
        after = _status_kb("VmHWM") if self.exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        self.peak_mb = (after or 0) / 1024.0
        self.mb = max((after or 0) - (self.before or 0), 0) / 1024.0


# --- helpers ----------------------------------------------------------------------------

def residual_through(box: Callable, rest: NDArray, sculpt: NDArray, idx: NDArray, d: NDArray) -> NDArray:
    """|sculpt - blackbox(rest + d)| at idx: every method is judged by the same black box."""
    moved = rest.copy()
    moved[idx] += d
    return np.linalg.norm(sculpt[idx] - box(moved)[idx], axis=1)


def _stats(residual: NDArray, diagonal: float) -> dict[str, float]:
    if len(residual) == 0:
        return {"max_rel": 0.0, "rms_rel": 0.0}
    return {"max_rel": float(residual.max() / diagonal), "rms_rel": float(np.sqrt(np.mean(residual**2)) / diagonal)}


def _mean(rows: Sequence[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows])) if rows else float("nan")


def _offset_error(d: NDArray, truth: NDArray, idx: NDArray, diagonal: float) -> float:
    """Max distance of the solved offsets from the ground truth, relative to the diagonal."""
    return float(np.linalg.norm(d - truth[idx], axis=1).max() / diagonal) if len(idx) else 0.0


# --- measurements -----------------------------------------------------------------------

def measure_psdbake(rig: rigs.Rig, scene: Scene) -> tuple[dict, list[InverseResult]]:
    """invert_example per example: time, evaluations, residuals, memory."""
    rows, results, rss_method = [], [], ""
    for t in rig.times:
        box = rig.blackbox(scene, t)
        with PeakRss() as mem:
            started = time.perf_counter()
            res = invert_example(box, rig.rest, rig.sculpts[t])
            seconds = time.perf_counter() - started
        rss_method = mem.method
        results.append(res)
        rows.append({
            "time": t, "seconds": seconds, "evaluations": res.evaluations, "sculpted": len(res.indices),
            "missed": len(res.missed), "atol_rel": res.atol / res.diagonal, "max_rel": res.max_residual / res.diagonal,
            "rms_rel": res.rms_residual / res.diagonal, "peak_rss_mb": mem.peak_mb, "peak_rss_delta_mb": mem.mb,
            "offset_error_rel": _offset_error(res.offsets, rig.truth[t], res.indices, res.diagonal),
        })
    # numpy's allocations are traced by tracemalloc; an extra run keeps the timings untraced.
    t = rig.times[-1]
    tracemalloc.start()
    try:
        invert_example(rig.blackbox(scene, t), rig.rest, rig.sculpts[t])
        traced_peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()
    summary = {
        "seconds": _mean(rows, "seconds"), "evaluations": _mean(rows, "evaluations"),
        "sculpted": _mean(rows, "sculpted"), "max_rel": _mean(rows, "max_rel"), "rms_rel": _mean(rows, "rms_rel"),
        "worst_max_rel": max(r["max_rel"] for r in rows), "missed": sum(r["missed"] for r in rows),
        "atol_rel": _mean(rows, "atol_rel"),
        "peak_rss_mb": max(r["peak_rss_mb"] for r in rows),
        "peak_rss_delta_mb": max(r["peak_rss_delta_mb"] for r in rows), "peak_rss_method": rss_method,
        "tracemalloc_peak_mb": traced_peak, "tracemalloc_example": t,
        "offset_error_rel": max(r["offset_error_rel"] for r in rows), "examples": rows,
    }
    return summary, results


def measure_solver(rig: rigs.Rig, scene: Scene) -> dict:
    """Broyden refresh (psdbake's solver) against Powell alone, example by example, interleaved
    (alternating which goes first) on fresh black boxes so both see the same machine state:
    calls, seconds, max residual."""
    sides: dict[str, list[dict]] = {"broyden": [], "powell": []}
    order = (("broyden", True), ("powell", False))
    for k, t in enumerate(rig.times):
        for side, qn in order if k % 2 == 0 else order[::-1]:  # alternate who runs first
            box = rig.blackbox(scene, t)
            started = time.perf_counter()
            res = invert_example_with(box, rig.rest, rig.sculpts[t], quasi_newton=qn)
            seconds = time.perf_counter() - started
            sides[side].append({"time": t, "seconds": seconds, "evaluations": res.evaluations,
                                "qn_steps": res.qn_steps, "cycles": res.cycles, "missed": len(res.missed),
                                "max_rel": res.max_residual / res.diagonal})
    out: dict[str, Any] = {}
    for side, rows in sides.items():
        out[side] = {"seconds": _mean(rows, "seconds"), "evaluations": _mean(rows, "evaluations"),
                     "max_evaluations": max(r["evaluations"] for r in rows), "max_rel": _mean(rows, "max_rel"),
                     "worst_max_rel": max(r["max_rel"] for r in rows), "missed": sum(r["missed"] for r in rows),
                     "examples": rows}
    new, old = out["broyden"], out["powell"]
    out["calls_ratio"] = old["evaluations"] / new["evaluations"]
    out["seconds_ratio"] = old["seconds"] / new["seconds"]
    out["worst_residual_ratio"] = new["worst_max_rel"] / old["worst_max_rel"] if old["worst_max_rel"] else None
    return out


def measure_fit(rig: rigs.Rig) -> tuple[dict, FitResult]:
    """One full ``api.fit`` of the rig from its EXAMPLES file (read, invert, RBF)."""
    settings = FitSettings(deformers=tuple(spec for spec, _ in rig.deformers))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        started = time.perf_counter()
        result = api.fit(rig.asset, [rig.examples], settings)
        seconds = time.perf_counter() - started
    inverse_seconds = sum(inv.seconds for m in result.meshes for inv in m.inverses)
    return {
        "seconds": seconds, "inverse_seconds": inverse_seconds, "missed": result.missed,
        "warnings": [str(w.message) for w in caught],
    }, result


def measure_literal(rig: rigs.Rig, scene: Scene, results: list[InverseResult], count: int, seed: int = 0) -> dict:
    """scipy Powell per vertex on ``count`` vertices spread over the examples, extrapolated."""
    rng = np.random.default_rng(seed)
    picks = np.unique(np.round(np.linspace(0, len(rig.times) - 1, count)).astype(int), return_counts=True)
    rows = []
    for k, n in zip(*picks, strict=True):
        t, res = rig.times[k], results[k]
        if len(res.indices) == 0:
            continue
        box = rig.blackbox(scene, t)
        for v in rng.choice(res.indices, size=min(n, len(res.indices)), replace=False):
            started = time.perf_counter()
            d, nfev = references.literal_powell(box, rig.rest, rig.sculpts[t], int(v))
            seconds = time.perf_counter() - started
            r = residual_through(box, rig.rest, rig.sculpts[t], np.array([v]), d[None])
            rows.append({"time": t, "vertex": int(v), "seconds": seconds, "evaluations": nfev,
                         "rel": float(r[0] / res.diagonal)})
    per_vertex = _mean(rows, "seconds")
    sculpted = float(np.mean([len(r.indices) for r in results]))
    return {
        "sampled_vertices": len(rows), "sampled_examples": len({r["time"] for r in rows}),
        "seconds_per_vertex": per_vertex, "evaluations_per_vertex": _mean(rows, "evaluations"),
        "seconds": per_vertex * sculpted, "evaluations": _mean(rows, "evaluations") * sculpted,
        "extrapolated": True, "max_rel": max(r["rel"] for r in rows), "rms_rel": float(
            np.sqrt(np.mean([r["rel"] ** 2 for r in rows]))), "vertices": rows,
    }


def measure_one_shot(rig: rigs.Rig, scene: Scene, results: list[InverseResult]) -> dict:
    """3 + 1 black-box calls and one 3x3 solve per vertex, judged through the black box."""
    rows = []
    for t, res in zip(rig.times, results, strict=True):
        box = rig.blackbox(scene, t)
        step = tol.JACOBIAN_STEP_RTOL * res.diagonal  # psdbake's own Jacobian step
        started = time.perf_counter()
        d, calls = references.one_shot_linearisation(box, rig.rest, rig.sculpts[t], res.indices, step)
        seconds = time.perf_counter() - started
        r = residual_through(box, rig.rest, rig.sculpts[t], res.indices, d)
        rows.append({"time": t, "seconds": seconds, "evaluations": calls, **_stats(r, res.diagonal),
                     "offset_error_rel": _offset_error(d, rig.truth[t], res.indices, res.diagonal)})
    return {"seconds": _mean(rows, "seconds"), "evaluations": _mean(rows, "evaluations"),
            "max_rel": _mean(rows, "max_rel"), "rms_rel": _mean(rows, "rms_rel"),
            "worst_max_rel": max(r["max_rel"] for r in rows),
            "offset_error_rel": max(r["offset_error_rel"] for r in rows), "examples": rows}


def measure_closed_form(rig: rigs.Rig, scene: Scene, results: list[InverseResult]) -> dict | None:
    """Exact LBS inverse: matrix blend (reads UsdSkel's weights and transforms) + solve."""
    if not rig.linear_skinning:
        return None
    rows = []
    for t, res in zip(rig.times, results, strict=True):
        started = time.perf_counter()
        matrices = references.lbs_matrices(scene.stage, rigs.MESH, t)
        blended = time.perf_counter()
        d = references.closed_form_lbs(matrices, rig.rest, rig.sculpts[t], res.indices)
        solved = time.perf_counter()
        r = residual_through(rig.blackbox(scene, t), rig.rest, rig.sculpts[t], res.indices, d)
        rows.append({"time": t, "seconds": solved - started, "blend_seconds": blended - started,
                     "solve_seconds": solved - blended, **_stats(r, res.diagonal),
                     "offset_error_rel": _offset_error(d, rig.truth[t], res.indices, res.diagonal)})
    return {"seconds": _mean(rows, "seconds"), "blend_seconds": _mean(rows, "blend_seconds"),
            "solve_seconds": _mean(rows, "solve_seconds"), "max_rel": _mean(rows, "max_rel"),
            "rms_rel": _mean(rows, "rms_rel"), "worst_max_rel": max(r["max_rel"] for r in rows),
            "offset_error_rel": max(r["offset_error_rel"] for r in rows), "examples": rows}


def blackbox_call_seconds(rig: rigs.Rig, scene: Scene, repeats: int = 5) -> float:
    """Median wall time of one whole-mesh black-box call: the unit every method pays in."""
    box = rig.blackbox(scene, rig.times[-1])
    box(rig.rest)  # first call warms caches
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        box(rig.rest)
        times.append(time.perf_counter() - started)
    return float(np.median(times))


def bench_rig(rig: rigs.Rig) -> tuple[dict, FitResult]:
    """Every method on one rig; returns the JSON record and the fit (for the eval benchmark)."""
    scene = rig.scene()
    log(f"{rig.name}: psdbake invert_example x{len(rig.times)}")
    psd, results = measure_psdbake(rig, scene)
    log(f"{rig.name}: Broyden refresh vs Powell alone")
    solver = measure_solver(rig, scene)
    log(f"{rig.name}: api.fit")
    fit, fit_result = measure_fit(rig)
    log(f"{rig.name}: one-shot linearisation")
    one_shot = measure_one_shot(rig, scene, results)
    closed = None
    if rig.linear_skinning:
        log(f"{rig.name}: closed-form LBS")
        closed = measure_closed_form(rig, scene, results)
    count = LITERAL_VERTICES[rig.size]
    log(f"{rig.name}: literal scipy Powell on {count} vertices")
    literal = measure_literal(rig, scene, results, count)
    ratios = {
        "psdbake_over_closed_form_time": psd["seconds"] / closed["seconds"] if closed else None,
        "literal_over_psdbake_time": literal["seconds"] / psd["seconds"],
        "psdbake_over_one_shot_max_residual": psd["max_rel"] / one_shot["max_rel"] if one_shot["max_rel"] else None,
    }
    record = {
        "rig": rig.name, "variant": rig.variant, "size": rig.size, "points": rig.points,
        "examples": len(rig.times), "build_seconds": rig.build_seconds,
        "blackbox_call_seconds": blackbox_call_seconds(rig, scene),
        "psdbake": psd, "solver": solver, "fit": fit, "literal": literal, "one_shot": one_shot, "closed_form": closed,
        "ratios": ratios,
    }
    return record, fit_result


def _stack_stage(layers: Sequence[str]) -> Usd.Stage:
    root = Sdf.Layer.CreateAnonymous("bench_stack.usda")
    for path in layers:
        root.subLayerPaths.append(path)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    return stage


def measure_eval(folder: str, rig: rigs.Rig, fit_result: FitResult) -> dict:
    """RBF weights over EVAL_FRAMES frames; points cache vs UsdSkel.BakeSkinning over CACHE_FRAMES."""
    corr = os.path.join(folder, "eval_correctives.usda")
    api.write_correctives(fit_result, corr)
    started = time.perf_counter()
    anim = rigs.write_shot(folder, EVAL_FRAMES)
    write_seconds = time.perf_counter() - started
    log(f"eval: weights over {EVAL_FRAMES} frames")
    started = time.perf_counter()
    weights = api.evaluate(rig.asset, corr, anim)
    eval_seconds = time.perf_counter() - started
    frames = len(weights.animations[0].times)
    channels = weights.animations[0].psd_channels

    log(f"eval: points cache vs BakeSkinning over {CACHE_FRAMES} frames")
    short = api.evaluate(rig.asset, corr, anim, frames=(1.0, float(CACHE_FRAMES)))
    weights_path = api.write_weights(short, os.path.join(folder, "eval_weights.usda"))
    # Hold every input layer open so neither side pays for parsing the long shot.
    held = [Sdf.Layer.FindOrOpen(p) for p in (weights_path, anim, corr, rig.asset)]
    started = time.perf_counter()
    cache = api.points_cache_layer(short)
    cache_seconds = time.perf_counter() - started
    started = time.perf_counter()
    stage = _stack_stage([weights_path, anim, corr, rig.asset])
    UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath(rigs.generate.ROOT)), Gf.Interval(1.0, CACHE_FRAMES))
    bake_seconds = time.perf_counter() - started
    # Both must describe the same deformation, or the ratio means nothing.
    attr = UsdGeom.Mesh(stage.GetPrimAtPath(rigs.MESH)).GetPointsAttr()
    spec = Sdf.Path(rigs.MESH).AppendProperty("points")
    worst = 0.0
    for f in range(1, CACHE_FRAMES + 1):
        ours = np.array(cache.QueryTimeSample(spec, float(f)), dtype=np.float64)
        theirs = np.array(attr.Get(Usd.TimeCode(f)), dtype=np.float64)
        worst = max(worst, float(np.abs(ours - theirs).max() / tol.bbox_diagonal(theirs)))
    return {
        "rig": rig.name, "points": rig.points, "correctives": channels,
        "anim_frames": frames, "anim_write_seconds": write_seconds,
        "weights_seconds": eval_seconds, "weights_us_per_frame": 1e6 * eval_seconds / frames,
        "cache_frames": CACHE_FRAMES, "points_cache_seconds": cache_seconds,
        "points_cache_ms_per_frame": 1e3 * cache_seconds / CACHE_FRAMES,
        "bake_seconds": bake_seconds, "bake_ms_per_frame": 1e3 * bake_seconds / CACHE_FRAMES,
        "cache_over_bake": cache_seconds / bake_seconds, "cache_vs_bake_max_rel": worst,
        "layers_held_open": len(held),
    }


def profile_invert(rig: rigs.Rig, top: int = 15) -> str:
    """cProfile of one invert_example (the rig's first example), top entries by own time."""
    scene = rig.scene()
    t = rig.times[0]
    box = rig.blackbox(scene, t)
    prof = cProfile.Profile()
    prof.enable()
    invert_example(box, rig.rest, rig.sculpts[t])
    prof.disable()
    out = io.StringIO()
    pstats.Stats(prof, stream=out).strip_dirs().sort_stats("tottime").print_stats(top)
    return out.getvalue()


# --- report -----------------------------------------------------------------------------

def _s(x: float | None) -> str:
    """Seconds, readable at any scale."""
    if x is None or not np.isfinite(x):
        return "-"
    if x < 1e-3:
        return f"{x * 1e6:.0f}us"
    if x < 1.0:
        return f"{x * 1e3:.1f}ms"
    return f"{x:.2f}s"


def _e(x: float | None) -> str:
    return "-" if x is None else f"{x:.1e}"


def _r(x: float | None) -> str:
    return "-" if x is None else f"{x:.3g}"


def _n(x: float | None) -> str:
    return "-" if x is None else f"{x:,.0f}"


COLUMNS: list[tuple[str, str, Callable[[dict], str]]] = [
    # (group, header, formatter of one rig record)
    ("", "rig", lambda r: r["rig"]),
    ("", "points", lambda r: _n(r["points"])),
    ("", "moved", lambda r: _n(r["psdbake"]["sculpted"])),
    ("", "bb call", lambda r: _s(r["blackbox_call_seconds"])),
    ("psdbake", "s/ex", lambda r: _s(r["psdbake"]["seconds"])),
    ("psdbake", "evals", lambda r: f"{r['psdbake']['evaluations']:.0f}"),
    ("psdbake", "max/diag", lambda r: _e(r["psdbake"]["max_rel"])),
    ("psdbake", "rms/diag", lambda r: _e(r["psdbake"]["rms_rel"])),
    ("psdbake", "py MB", lambda r: f"{r['psdbake']['tracemalloc_peak_mb']:.1f}"),
    ("psdbake", "rss MB", lambda r: f"{r['psdbake']['peak_rss_mb']:.0f}"),
    ("psdbake", "+rss", lambda r: f"{r['psdbake']['peak_rss_delta_mb']:.1f}"),
    ("psdbake", "fit", lambda r: _s(r["fit"]["seconds"])),
    ("literal*", "s/ex", lambda r: _s(r["literal"]["seconds"])),
    ("literal*", "evals", lambda r: _n(r["literal"]["evaluations"])),
    ("literal*", "N", lambda r: str(r["literal"]["sampled_vertices"])),
    ("literal*", "max/diag", lambda r: _e(r["literal"]["max_rel"])),
    ("one-shot", "s/ex", lambda r: _s(r["one_shot"]["seconds"])),
    ("one-shot", "max/diag", lambda r: _e(r["one_shot"]["max_rel"])),
    ("LBS closed", "s/ex", lambda r: _s(r["closed_form"]["seconds"]) if r["closed_form"] else "-"),
    ("LBS closed", "solve", lambda r: _s(r["closed_form"]["solve_seconds"]) if r["closed_form"] else "-"),
    ("LBS closed", "max/diag", lambda r: _e(r["closed_form"]["max_rel"]) if r["closed_form"] else "-"),
    ("ratios", "psd/cf", lambda r: _r(r["ratios"]["psdbake_over_closed_form_time"])),
    ("ratios", "lit/psd", lambda r: _r(r["ratios"]["literal_over_psdbake_time"])),
    ("ratios", "res psd/1s", lambda r: _r(r["ratios"]["psdbake_over_one_shot_max_residual"])),
]


def render(report: dict) -> str:
    """The fixed-width table plus the eval block and footnotes."""
    rows = [[fmt(r) for _, _, fmt in COLUMNS] for r in report["rigs"]]
    heads = [h for _, h, _ in COLUMNS]
    widths = [max([len(h), *(len(row[i]) for row in rows)]) for i, h in enumerate(heads)]
    groups, i = [], 0  # group titles centred over their columns
    for group, members in itertools.groupby(COLUMNS, key=lambda c: c[0]):
        n = len(list(members))
        span = sum(widths[i:i + n]) + 2 * (n - 1)
        groups.append(group.center(span, "-") if group else " " * span)
        i += n
    line = "  ".join(groups)
    out = []
    m = report["machine"]
    out.append(f"psdbake {m['psdbake']} ({m['git']}) benchmarks, {report['mode']} mode, "
               f"total {report['total_seconds']:.0f} s")
    out.append(f"machine: {m['nproc']} cores, {m['cpu_model']}; python {m['python']}, numpy {m['numpy']}, "
               f"scipy {m['scipy']}, usd {m['usd']}" + (f"; env {m['thread_env']}" if m["thread_env"] else ""))
    out.append("")
    out.append(line)
    for row in [heads, ["-" * w for w in widths], *rows]:
        out.append("  ".join(c.rjust(w) if k else c.ljust(w) for k, (c, w) in enumerate(zip(row, widths, strict=True))))
    ex = report["rigs"][0]["examples"] if report["rigs"] else 0
    sample = sorted({(r["literal"]["sampled_vertices"], r["literal"]["sampled_examples"]) for r in report["rigs"]})
    sample_text = "; ".join(f"{n} vertices over {e} examples" for n, e in sample)
    rss = report["rigs"][0]["psdbake"]["peak_rss_method"] if report["rigs"] else ""
    atol = [r["psdbake"]["atol_rel"] for r in report["rigs"]] or [float("nan")]
    missed = sum(r["psdbake"]["missed"] for r in report["rigs"])
    out += [
        "",
        f"Per-example means over {ex} examples; residuals |sculpt - blackbox(rest + d)| / bbox diagonal, mean of",
        "  per-example maxima, every method judged through the same black box. 'moved': sculpted vertices per example.",
        f"  psdbake stops each vertex at its tolerance, atol/diag {min(atol):.1e}..{max(atol):.1e} (1e-6 or the float32",
        f"  floor); vertices that missed it: {missed}. The literal method runs scipy to xtol 1e-10, hence its lower residual.",
        "  'bb call': one whole-mesh black-box call (median). 'fit': one api.fit of the whole rig (all examples).",
        "* literal (scipy Powell per vertex, whole-mesh call per evaluation): s/ex and evals EXTRAPOLATED FROM N",
        f"  VERTICES sampled across the examples ({sample_text}) to all sculpted vertices.",
        "  Its max/diag is over the sampled vertices only.",
        "one-shot: 3-call forward-difference Jacobian (psdbake's step) + one solve. LBS closed: matrix blend + solve",
        "  (total; 'solve' alone). Ratios: psd/cf = psdbake time / closed-form time; lit/psd = literal / psdbake",
        "  time; res psd/1s = psdbake max residual / one-shot max residual.",
        "Memory: 'py MB' tracemalloc peak of one extra invert_example (numpy + Python heap, not USD's C++);",
        "  'rss MB' process peak RSS during invert_example, '+rss' that peak above the RSS at the call's start",
        f"  (max over examples; {rss}; freed memory the allocator reuses is not counted).",
    ]
    out += render_solver(report)
    ev = report.get("eval")
    if ev:
        out += [
            "",
            f"eval on {ev['rig']} ({ev['correctives']} correctives): weights for {ev['anim_frames']:,} frames "
            f"{_s(ev['weights_seconds'])} ({ev['weights_us_per_frame']:.0f} us/frame)",
            f"  points cache {ev['cache_frames']} frames: psdbake points_cache_layer {ev['points_cache_ms_per_frame']:.2f}"
            f" ms/frame, UsdSkel.BakeSkinning {ev['bake_ms_per_frame']:.2f} ms/frame (both incl. composing), ratio "
            f"{ev['cache_over_bake']:.2f}; max |cache - bake| / diag {ev['cache_vs_bake_max_rel']:.1e}",
            "  (at 13k and 100k side by side, and eval time vs example count: python -m benchmarks.evalspeed)",
        ]
    for name, text in report.get("profiles", {}).items():
        out += ["", f"cProfile of invert_example on {name} (first example), top by own time:", text.rstrip()]
    return "\n".join(out)


SOLVER_COLUMNS: list[tuple[str, Callable[[dict], str]]] = [
    ("rig", lambda r: r["rig"]),
    ("calls/ex", lambda r: f"{r['solver']['broyden']['evaluations']:.2f}"),
    ("max", lambda r: f"{r['solver']['broyden']['max_evaluations']}"),
    ("old calls/ex", lambda r: f"{r['solver']['powell']['evaluations']:.2f}"),
    ("calls old/new", lambda r: f"{r['solver']['calls_ratio']:.2f}"),
    ("s/ex", lambda r: _s(r["solver"]["broyden"]["seconds"])),
    ("old s/ex", lambda r: _s(r["solver"]["powell"]["seconds"])),
    ("s old/new", lambda r: f"{r['solver']['seconds_ratio']:.2f}"),
    ("worst max/diag", lambda r: _e(r["solver"]["broyden"]["worst_max_rel"])),
    ("old worst", lambda r: _e(r["solver"]["powell"]["worst_max_rel"])),
    ("missed", lambda r: f"{r['solver']['broyden']['missed']}/{r['solver']['powell']['missed']}"),
]


def render_solver(report: dict) -> list[str]:
    """The solver table: Broyden-refreshed lockstep Powell against Powell alone, same run."""
    recs = [r for r in report["rigs"] if r.get("solver")]
    if not recs:
        return []
    heads = [h for h, _ in SOLVER_COLUMNS]
    rows = [[fmt(r) for _, fmt in SOLVER_COLUMNS] for r in recs]
    widths = [max([len(h), *(len(row[i]) for row in rows)]) for i, h in enumerate(heads)]
    out = ["", "solver: Broyden refresh (psdbake) vs Powell alone after the linearised start (quasi_newton=False),",
           "  interleaved per example in this run; calls = black-box calls per example (mean; 'max' the worst example)."]
    for row in [heads, ["-" * w for w in widths], *rows]:
        out.append("  ".join(c.rjust(w) if k else c.ljust(w) for k, (c, w) in enumerate(zip(row, widths, strict=True))))
    out.append("  worst max/diag: largest per-example max residual / diagonal; missed: vertices above tolerance (new/old).")
    return out


ABOUT = (
    "The tube/arm rig at 1.3k, 13k and 100k points (a third of the vertices sculpted, 8 examples) in LBS, "
    "dual-quaternion and a non-linear chain (LBS followed by a position-dependent twist-and-bulge "
    "`--deformer`); psdbake against the reference methods side by side in one run: the closed-form LBS inverse "
    "(blend each vertex's matrices and solve), the paper's literal method (scipy `minimize(method=\"Powell\")` "
    "per vertex, each evaluation a whole-mesh black-box call, timed on a few sampled vertices and extrapolated "
    "to all sculpted vertices) and the one-shot linearisation. Seconds vary ±30-50% between runs on shared "
    "machines: read the ratios, taken in the same run."
)
SOLVER_ABOUT = (
    "`python -m benchmarks.run --solver-only`: the solver (Broyden-refreshed directions) against Powell alone "
    "after the linearised start, alternating per example in one run, 8 examples per rig."
)


def tables(report: dict) -> list[dict]:
    """The rig table (and the solver table and the eval figures) of the results record."""
    rows = []
    for r in report["rigs"]:
        p, ratios = r["psdbake"], r["ratios"]
        closed = ratios.get("psdbake_over_closed_form_time")
        rows.append([r["rig"], f"{r['points']:,}", f"{p['evaluations']:.0f}", f"{p['max_rel']:.1e}", _s(p["seconds"]),
                     "-" if closed is None else f"{closed:.2f}x the closed form",
                     f"{ratios['literal_over_psdbake_time']:.2g}x faster",
                     f"{ratios['psdbake_over_one_shot_max_residual']:.2g}x the one-shot's {r['one_shot']['max_rel']:.1e}"])
    out = [results.table("psdbake against the reference methods",
                         ["rig", "points", "evals / example", "max residual / diag", "s / example", "vs closed-form LBS",
                          "vs literal Powell", "residual vs one-shot"], rows,
                         "Literal Powell: extrapolated from sampled vertices (see the JSON's `literal` records).")]
    if any(r.get("solver") for r in report["rigs"]):
        out.append(solver_table(report))
    ev = report.get("eval")
    if ev:
        out.append(results.table(f"eval on {ev['rig']} ({ev['correctives']} correctives)", ["measure", "value"], [
            [f"weights for {ev['anim_frames']:,} frames",
             f"{_s(ev['weights_seconds'])} ({ev['weights_us_per_frame']:.0f} us/frame)"],
            [f"points cache, {ev['cache_frames']} frames", f"{ev['points_cache_ms_per_frame']:.2f} ms/frame"],
            [f"UsdSkel.BakeSkinning, {ev['cache_frames']} frames", f"{ev['bake_ms_per_frame']:.2f} ms/frame"],
            ["max |cache - bake| / diag", f"{ev['cache_vs_bake_max_rel']:.1e}"]]))
    return out


def solver_table(report: dict) -> dict:
    """The solver table (Broyden refresh against Powell alone) as a results table."""
    recs = [r for r in report["rigs"] if r.get("solver")]
    rows = [[fmt(r) for _, fmt in SOLVER_COLUMNS] for r in recs]
    return results.table("The solver: Broyden refresh against Powell alone", [h for h, _ in SOLVER_COLUMNS], rows,
                         "calls = black-box calls per example (mean; 'max' the worst example); missed: vertices above "
                         "tolerance (new/old).")


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def solver_only(json_path: str, sizes: Sequence[str] = ("13k", "100k"),
                variants: Sequence[str] = ("lbs", "dqs", "lbs+bulge"), argv: Sequence[str] | None = None) -> int:
    """``--solver-only``: the solver table alone, written to stdout and beside ``json_path``."""
    m = machine_info()
    report: dict[str, Any] = {"mode": "solver-only", "machine": m, "rigs": []}
    folder = tempfile.mkdtemp(prefix="psdbake-bench-")
    try:
        poses_layer, poses = rigs.write_poses(folder)
        for size in sizes:
            for variant in variants:
                log(f"building {variant} {size}")
                rig = rigs.build(folder, variant, size, poses, poses_layer)
                log(f"{rig.name}: Broyden refresh vs Powell alone")
                report["rigs"].append({"rig": rig.name, "variant": variant, "size": size, "points": rig.points,
                                       "solver": measure_solver(rig, rig.scene())})
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    report["total_seconds"] = time.perf_counter() - _T0
    print(f"psdbake {m['psdbake']} ({m['git']}) solver benchmark, total {report['total_seconds']:.0f} s; "
          f"machine: {m['nproc']} cores, {m['cpu_model']}")
    print("\n".join(render_solver(report)))
    path = os.path.splitext(json_path)[0] + "_solver.json"
    results.write("run", argv, SOLVER_ABOUT, [solver_table(report)], raw=_jsonable(report), path=path)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the suite, print the table, write the JSON; exit 0."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the 1.3k and 13k rigs (smoke test)")
    parser.add_argument("--json", default=DEFAULT_JSON, help=f"where to write the JSON (default {DEFAULT_JSON})")
    parser.add_argument("--profile", action="store_true",
                        help="also cProfile one invert_example per variant at the largest size")
    parser.add_argument("--keep", action="store_true", help="keep the generated rigs (prints the folder)")
    parser.add_argument("--solver-only", action="store_true",
                        help="only the solver table (Broyden refresh vs Powell alone) on the 13k and 100k rigs")
    args = parser.parse_args(argv)

    if args.solver_only:
        return solver_only(args.json, argv=argv)
    sizes = ["1.3k", "13k"] if args.quick else ["1.3k", "13k", "100k"]
    report: dict[str, Any] = {"mode": "quick" if args.quick else "full", "machine": machine_info(), "rigs": []}
    folder = tempfile.mkdtemp(prefix="psdbake-bench-")
    try:
        poses_layer, poses = rigs.write_poses(folder)
        eval_fit = None
        largest: dict[str, rigs.Rig] = {}
        for size in sizes:
            for variant in rigs.VARIANTS:
                log(f"building {variant} {size}")
                rig = rigs.build(folder, variant, size, poses, poses_layer)
                record, fit_result = bench_rig(rig)
                report["rigs"].append(record)
                if (variant, size) == EVAL_RIG:
                    eval_fit = (rig, fit_result)
                if args.profile and size == sizes[-1]:
                    largest[variant] = rig
        if eval_fit is not None:
            report["eval"] = measure_eval(folder, *eval_fit)
        if args.profile:
            report["profiles"] = {}
            for rig in largest.values():
                log(f"profiling {rig.name}")
                report["profiles"][rig.name] = profile_invert(rig)
        report["total_seconds"] = time.perf_counter() - _T0
    finally:
        if args.keep:
            log(f"rigs kept in {folder}")
        else:
            shutil.rmtree(folder, ignore_errors=True)
    print(render(report))
    results.write("run", argv, ABOUT, tables(report), raw=_jsonable(report), path=args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
