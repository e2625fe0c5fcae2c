"""Eval speed at film scale (issue 16): the points cache against UsdSkel, and eval against example count.

Two measurements, each interleaved repeat by repeat (the machines are shared and noisy, so
the figures are medians and every ratio compares numbers from the same run):

- **Points cache vs BakeSkinning** at 13k and 100k points (the LBS bench rig, 8 examples,
  CACHE_FRAMES frames): ``api.points_cache_layer`` against ``UsdSkel.BakeSkinning`` of the same
  stack ASSET + CORRECTIVES + ANIM + WEIGHTS onto an in-memory layer, each including its own
  composition, with every input layer held open so neither side pays for parsing, after one
  untimed run of each side (one-time set-up: USD's plug-ins and registries). ms per
  frame and their ratio; the two must agree within float32 round-off (max |cache - bake| /
  diagonal) and every cached extent must be the exact [min, max] of its points.
- **Eval vs example count**: ``psdbake eval`` of a EVAL_FRAMES-frame shot with CORRECTIVES of
  8, 32 and 128 examples (13k points), as ``.usda`` and ``.usdc``. Each eval runs in a fresh
  process with an empty crate-probe verdict cache (``PSDBAKE_CACHE_DIR``) of its own, so no
  layer or probe result carries over (a ``.usdc`` is a first read: hashed, probed and
  remembered; ``benchmarks.fitspeed`` shows a verified read beside it), after a warm-up eval of the arm
  fixture in the same process (interpreter, imports, USD's plug-ins): 'command' is the eval
  alone; 'wall' is a plain ``psdbake eval`` process, start-up included. The issue's target is
  the eval time independent of the example count within 20%: the wall column is that time as a
  user or a farm job pays it; the command column shows what grows with the examples.

Run: ``python -m benchmarks.evalspeed`` (part of ``make bench``); ``--quick`` for a smoke test,
``--folder DIR`` keeps the generated rigs and reuses them, ``--profile`` adds a cProfile of
one points cache at the largest size.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

from psdbake import api
from psdbake import tolerances as tol

from . import results, rigs

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DEFAULT_JSON = results.path_of("evalspeed")
#: Points cache: frames per measurement and rig sizes.
CACHE_FRAMES, CACHE_SIZES = 48, ("13k", "100k")
#: Eval: frames of the shot, example counts, CORRECTIVES formats, rig size.
EVAL_FRAMES, EVAL_COUNTS, EVAL_FORMATS, EVAL_SIZE = 1000, (8, 32, 128), (".usda", ".usdc"), "13k"
#: The warm-up eval each child runs first (files the measured eval never reads).
WARM = (os.path.join(ROOT, "fixtures", "arm_lbs.usda"), os.path.join(ROOT, "fixtures", "arm_anim.usda"))


def log(msg: str) -> None:
    print(f"[evalspeed] {msg}", file=sys.stderr, flush=True)


# --- points cache vs BakeSkinning ----------------------------------------------------------

def _cache_case(folder: str, size: str, frames: int) -> dict[str, Any]:
    """Rig, CORRECTIVES, a frames-long shot and its WEIGHTS for one size (made once, reused)."""
    sub = os.path.join(folder, f"cache_{size}")
    os.makedirs(sub, exist_ok=True)
    poses_layer, poses = rigs.write_poses(sub)
    rig = rigs.build(sub, "lbs", size, poses, poses_layer)
    corr = os.path.join(sub, "correctives.usdc")
    if not os.path.exists(corr):
        api.write_correctives(api.fit(rig.asset, [rig.examples]), corr)
    anim = rigs.write_shot(sub, frames)
    weights = api.evaluate(rig.asset, corr, anim)
    weights_path = api.write_weights(weights, os.path.join(sub, "weights.usda"))
    layers = [weights_path, anim, corr, rig.asset]  # strongest first
    return {"size": size, "points": rig.points, "weights": weights, "layers": layers,
            "held": [Sdf.Layer.FindOrOpen(p) for p in layers]}


def _bake(layers: list[str], frames: int) -> Usd.Stage:
    """UsdSkel.BakeSkinning of the stack onto an in-memory root layer."""
    root = Sdf.Layer.CreateAnonymous("bake.usda")
    for path in layers:
        root.subLayerPaths.append(path)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    if not UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath(rigs.generate.ROOT)), Gf.Interval(1.0, frames)):
        raise RuntimeError("UsdSkel.BakeSkinning failed")
    return stage


def _agreement(cache: Sdf.Layer, stage: Usd.Stage, frames: int) -> tuple[float, bool]:
    """(max |cache - bake| / diagonal over the frames, every cached extent == [min, max] of its points)."""
    attr = UsdGeom.Mesh(stage.GetPrimAtPath(rigs.MESH)).GetPointsAttr()
    points, extent = (Sdf.Path(rigs.MESH).AppendProperty(n) for n in ("points", "extent"))
    worst, exact = 0.0, True
    for f in range(1, frames + 1):
        ours = np.asarray(cache.QueryTimeSample(points, float(f)))
        theirs = np.asarray(attr.Get(Usd.TimeCode(f)), dtype=np.float64)
        worst = max(worst, float(np.abs(ours - theirs).max() / tol.bbox_diagonal(theirs)))
        box = np.asarray(cache.QueryTimeSample(extent, float(f)))
        exact &= bool(np.array_equal(box, np.stack([ours.min(axis=0), ours.max(axis=0)])))
    return worst, exact


def measure_cache(folder: str, sizes: tuple[str, ...], frames: int, repeats: int) -> list[dict[str, Any]]:
    """Points cache vs BakeSkinning per size, interleaved (sizes and sides alternate every repeat)."""
    cases = []
    for size in sizes:
        log(f"points cache: building the lbs {size} rig, its CORRECTIVES and a {frames}-frame shot")
        cases.append(_cache_case(folder, size, frames))
    for case in cases:  # a warm-up of each side, untimed: first runs paid 1.34-1.41x where later ones paid 1.1-1.2x
        api.points_cache_layer(case["weights"])
        _bake(case["layers"], frames)
    seconds: dict[tuple[str, str], list[float]] = {}
    for rep in range(repeats):
        log(f"points cache vs BakeSkinning: repeat {rep + 1}/{repeats}")
        for case in cases:
            sides = [("cache", lambda c=case: api.points_cache_layer(c["weights"])),
                     ("bake", lambda c=case: _bake(c["layers"], frames))]
            for side, fn in sides if rep % 2 == 0 else sides[::-1]:
                started = time.perf_counter()
                fn()
                seconds.setdefault((case["size"], side), []).append(time.perf_counter() - started)
    out = []
    for case in cases:
        worst, exact = _agreement(api.points_cache_layer(case["weights"]), _bake(case["layers"], frames), frames)
        cache, bake = (seconds[(case["size"], s)] for s in ("cache", "bake"))
        out.append({
            "size": case["size"], "points": case["points"], "frames": frames, "repeats": repeats,
            "cache_ms_per_frame": 1e3 * statistics.median(cache) / frames,
            "bake_ms_per_frame": 1e3 * statistics.median(bake) / frames,
            "ratio": statistics.median(cache) / statistics.median(bake),
            "ratio_per_repeat": [c / b for c, b in zip(cache, bake, strict=True)],
            "cache_vs_bake_max_rel": worst, "extents_exact": exact,
        })
    return out


def profile_cache(folder: str, size: str, frames: int, top: int = 14) -> str:
    """cProfile of one points cache of the size's rig, top entries by own time."""
    case = _cache_case(folder, size, frames)
    prof = cProfile.Profile()
    prof.runcall(api.points_cache_layer, case["weights"])
    out = io.StringIO()
    pstats.Stats(prof, stream=out).strip_dirs().sort_stats("tottime").print_stats(top)
    return out.getvalue()


# --- eval vs example count -----------------------------------------------------------------

def _eval_cases(folder: str, counts: tuple[int, ...], size: str, frames: int) -> tuple[str, dict[int, tuple[str, str]]]:
    """(the shot, count -> (asset, CORRECTIVES without extension)): one fit per count, written in each format."""
    shot = rigs.write_shot(folder, frames)
    cases = {}
    for count in counts:
        sub = os.path.join(folder, f"eval_{count}")
        os.makedirs(sub, exist_ok=True)
        base = os.path.join(sub, "correctives")
        poses_layer, poses = rigs.write_poses(sub, count)
        rig = rigs.build(sub, "lbs", size, poses, poses_layer)
        if not all(os.path.exists(base + ext) for ext in EVAL_FORMATS):
            log(f"eval: fitting {count} examples at {size}")
            fit = api.fit(rig.asset, [rig.examples])
            for ext in EVAL_FORMATS:
                api.write_correctives(fit, base + ext)
        cases[count] = (rig.asset, base)
    return shot, cases


def _eval(asset: str, corr: str, anim: str, out: str) -> None:
    """``psdbake eval ASSET CORR --anim ANIM -o OUT -q``, as the command runs it."""
    from psdbake.cli import main as psdbake_main

    try:
        psdbake_main(["eval", asset, corr, "--anim", anim, "-o", out, "-q"])
    except SystemExit as exc:
        if exc.code:
            raise


def _warm_correctives(folder: str) -> str:
    """The arm fixture's CORRECTIVES for the children's warm-up eval (written once per folder)."""
    path = os.path.join(folder, "warm_correctives.usda")
    if not os.path.exists(path):
        api.write_correctives(api.fit(WARM[0], [os.path.join(ROOT, "fixtures", "arm_lbs_examples.usda")]), path)
    return path


def child(asset: str, corr: str, anim: str, out: str, warm_corr: str) -> None:
    """One eval in this fresh process, timed after a warm-up eval of the arm fixture (the
    interpreter, the imports and USD's plug-ins paid first): prints one JSON line."""
    _eval(WARM[0], warm_corr, WARM[1], os.path.join(os.path.dirname(out), "warm_weights.usda"))
    started = time.perf_counter()
    _eval(asset, corr, anim, out)
    print(json.dumps({"seconds": time.perf_counter() - started}), flush=True)


def _run(argv: list[str], what: str) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="psdbake-cache-") as cache:  # nothing remembered from earlier runs
        done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, check=False, stdin=subprocess.DEVNULL,
                              env={**os.environ, "PSDBAKE_CACHE_DIR": cache})
    if done.returncode != 0:
        raise SystemExit(f"{what} failed (exit {done.returncode}):\n{done.stderr}")
    return done


def measure_eval(folder: str, counts: tuple[int, ...], size: str, frames: int, repeats: int) -> list[dict[str, Any]]:
    """Per (count, format): the eval command's own seconds (a child process, after a warm-up)
    and the wall time of a plain ``psdbake eval`` process; interleaved repeat by repeat."""
    shot, cases = _eval_cases(folder, counts, size, frames)
    warm = _warm_correctives(folder)
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    timings: dict[tuple[int, str], list[tuple[float, float]]] = {}
    for rep in range(repeats):
        log(f"eval vs example count: repeat {rep + 1}/{repeats}")
        order = [(c, e) for c in counts for e in EVAL_FORMATS]
        for count, ext in order if rep % 2 == 0 else order[::-1]:
            asset, base = cases[count]
            out = os.path.join(folder, f"eval_{count}", f"weights{ext}.usda")
            done = _run([sys.executable, "-m", "benchmarks.evalspeed", "--child", asset, base + ext, shot, out, warm],
                        f"eval of {base + ext}")
            seconds = json.loads(done.stdout.strip().splitlines()[-1])["seconds"]
            started = time.perf_counter()
            _run([exe, "eval", asset, base + ext, "--anim", shot, "-o", out, "-q"], f"psdbake eval of {base + ext}")
            timings.setdefault((count, ext), []).append((seconds, time.perf_counter() - started))
    out = []
    for (count, ext), runs in sorted(timings.items()):
        corr = cases[count][1] + ext
        out.append({"examples": count, "format": ext, "frames": frames, "size": size,
                    "correctives_mb": os.path.getsize(corr) / 1e6,
                    "command_seconds": statistics.median(s for s, _ in runs),
                    "wall_seconds": statistics.median(w for _, w in runs), "repeats": len(runs)})
    for row in out:
        first = next(r for r in out if r["format"] == row["format"] and r["examples"] == min(counts))
        row["command_over_fewest"] = row["command_seconds"] / first["command_seconds"]
        row["wall_over_fewest"] = row["wall_seconds"] / first["wall_seconds"]
    return out


# --- report -----------------------------------------------------------------------------

def render(report: dict[str, Any]) -> str:
    lines = [f"psdbake eval speed, {report['mode']} mode, total {report['total_seconds']:.0f} s", ""]
    if report.get("cache"):
        lines += ["points cache vs UsdSkel.BakeSkinning (lbs rig, 8 examples; medians, interleaved in this run)",
                  f"{'size':>5} {'points':>7} {'frames':>6} {'cache ms/f':>10} {'bake ms/f':>9} {'ratio':>6} "
                  f"{'ratios min..max':>15} {'max|c-b|/diag':>13} {'extents':>8}"]
        for r in report["cache"]:
            lo, hi = min(r["ratio_per_repeat"]), max(r["ratio_per_repeat"])
            lines.append(f"{r['size']:>5} {r['points']:>7,} {r['frames']:>6} {r['cache_ms_per_frame']:>10.2f} "
                         f"{r['bake_ms_per_frame']:>9.2f} {r['ratio']:>6.2f} {f'{lo:.2f}..{hi:.2f}':>15} "
                         f"{r['cache_vs_bake_max_rel']:>13.1e} {'exact' if r['extents_exact'] else 'WRONG':>8}")
        lines += ["  each side includes composing its stack; ratio = median cache / median bake (target <= 1.25)", ""]
    if report.get("eval"):
        rows = report["eval"]
        lines += [f"eval of {rows[0]['frames']:,} frames vs example count ({rows[0]['size']} points; fresh process per "
                  "eval, medians, interleaved)",
                  f"{'examples':>8} {'format':>6} {'MB':>6} {'command s':>9} {'vs fewest':>9} {'wall s':>7} {'vs fewest':>9}"]
        for r in rows:
            lines.append(f"{r['examples']:>8} {r['format']:>6} {r['correctives_mb']:>6.1f} {r['command_seconds']:>9.3f} "
                         f"{r['command_over_fewest']:>9.2f} {r['wall_seconds']:>7.2f} {r['wall_over_fewest']:>9.2f}")
        lines += ["  command: psdbake eval after process start-up and a warm-up eval; wall: a psdbake eval process",
                  "  (issue 16's target: eval time within 20% from the fewest to the most examples; the wall column",
                  "  is a whole eval as a user or a farm runs it, the command column the part after start-up)"]
    if report.get("profile"):
        lines += ["", f"cProfile of one points cache ({report['profile_size']}), top by own time:", report["profile"].rstrip()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.evalspeed", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="13k only, 8 and 32 examples, fewer repeats")
    parser.add_argument("--repeats", type=int, default=None, help="repeats per measurement (default 7 cache, 3 eval)")
    parser.add_argument("--folder", default=None, help="generate the rigs here and reuse them on the next run")
    parser.add_argument("--json", default=DEFAULT_JSON, help=f"where to write the JSON (default {DEFAULT_JSON})")
    parser.add_argument("--profile", action="store_true", help="also cProfile one points cache at the largest size")
    parser.add_argument("--child", nargs=5, metavar=("ASSET", "CORRECTIVES", "ANIM", "OUT", "WARM"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    started = time.perf_counter()
    sizes = CACHE_SIZES[:1] if args.quick else CACHE_SIZES
    counts = EVAL_COUNTS[:2] if args.quick else EVAL_COUNTS
    folder = args.folder or tempfile.mkdtemp(prefix="psdbake-evalspeed-")
    os.makedirs(folder, exist_ok=True)
    report: dict[str, Any] = {"mode": "quick" if args.quick else "full"}
    try:
        report["cache"] = measure_cache(folder, sizes, CACHE_FRAMES, args.repeats or (3 if args.quick else 7))
        report["eval"] = measure_eval(folder, counts, EVAL_SIZE, EVAL_FRAMES, args.repeats or (1 if args.quick else 3))
        if args.profile:
            report["profile_size"] = sizes[-1]
            report["profile"] = profile_cache(folder, sizes[-1], CACHE_FRAMES)
    finally:
        if args.folder is None:
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
    report["total_seconds"] = time.perf_counter() - started
    print(render(report))
    results.write("evalspeed", argv, ABOUT, tables(report), raw=report, path=args.json)
    return 0


ABOUT = (
    "Two measurements, each interleaved repeat by repeat, medians. **Points cache against "
    "`UsdSkel.BakeSkinning`**: the LBS bench rig with 8 correctives, each side composing its own stack "
    "ASSET + CORRECTIVES + ANIM + WEIGHTS with every input layer held open, after one untimed run of each; "
    "the two must agree within float32 round-off and every cached extent must be its points' exact min/max. "
    "**`eval` against example count**: `psdbake eval` of a 1,000-frame shot, 13k points, in a fresh process "
    "per eval with an empty crate-probe cache (a `.usdc` CORRECTIVES is a first read: hashed, probed by a "
    "child process and remembered); \"command\" is the eval after start-up and a warm-up eval of the arm, "
    "\"whole\" a plain `psdbake eval` process."
)


def tables(report: dict[str, Any]) -> list[dict]:
    """The points-cache and eval tables of the results record."""
    out = []
    if report.get("cache"):
        rows = []
        for r in report["cache"]:
            lo, hi = min(r["ratio_per_repeat"]), max(r["ratio_per_repeat"])
            rows.append([r["size"], f"{r['cache_ms_per_frame']:.2f} ms/frame", f"{r['bake_ms_per_frame']:.2f} ms/frame",
                         f"{r['ratio']:.2f} ({lo:.2f}-{hi:.2f})", f"{r['cache_vs_bake_max_rel']:.1e}",
                         "exact min/max" if r["extents_exact"] else "WRONG"])
        out.append(results.table(f"Points cache against UsdSkel.BakeSkinning ({report['cache'][0]['frames']} frames)",
                                 ["points", "psdbake cache", "BakeSkinning", "ratio (range over repeats)",
                                  "max |cache - bake| / diag", "extents"], rows))
    if report.get("eval"):
        rows = [[str(r["examples"]), f"`{r['format']}`, {r['correctives_mb']:.1f} MB", f"{r['command_seconds']:.3f} s",
                 f"{r['command_over_fewest']:.2f}", f"{r['wall_seconds']:.2f} s", f"{r['wall_over_fewest']:.2f}"]
                for r in report["eval"]]
        first = report["eval"][0]
        out.append(results.table(f"`eval` against example count ({first['frames']:,} frames, {first['size']} points)",
                                 ["examples", "CORRECTIVES", "command", "vs fewest", "whole process", "vs fewest"], rows))
    return out


if __name__ == "__main__":
    sys.exit(main())
