"""Conditioning as examples grow: default fits of 8, 32, 128 and 500 examples on the 13k bench rig.

Per example count: the bench rig (``benchmarks.rigs.build``, LBS, 13k points) with examples
from ``rigs.example_poses(count)`` (elbow 20..160 degrees, varying wrist twist), one
``psdbake.api.fit`` with default settings, then the written stack evaluated at the example
poses themselves: ``api.evaluate`` + ``api.points_cache_layer`` for every example and Pixar's
``UsdSkel.BakeSkinning`` of ASSET + CORRECTIVES + POSES + WEIGHTS for the first few, both
compared with the sculpts. An example is reproduced when its worst vertex is within the
round-trip guarantee (1e-5 of the diagonal).

Columns: examples; the RBF system's 2-norm condition number (largest over the fit's groups)
and sigma (radians; a range when there are several groups); fit seconds per example; max
residual / diagonal over every example (points cache) and over the baked ones; exact-at-examples.

Run: ``python -m benchmarks.conditioning [--counts 8 32 128 500] [--jobs N]`` (``make bench``).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

from psdbake import api
from psdbake import tolerances as tol
from psdbake.errors import PsdWarning
from psdbake.fitting import rbf_fit as rbf
from psdbake.settings import FitSettings

from . import results, rigs

#: The round-trip guarantee: every example reproduced to this fraction of the diagonal.
ROUND_TRIP_RTOL = 1e-5
#: Examples checked by BakeSkinning of the written stack (the points cache checks all).
BAKED = 4


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _conditions(result) -> tuple[float, list[float]]:
    """Largest condition number over the fit's RBF groups and their sigmas (re-planned from the
    stored driver data: same centres, kernel, sigma, degree, smoothing, hence the same system)."""
    conds, sigmas = [], []
    for m in result.meshes:
        d = m.driver_data
        if len(d.centers) < 2 and d.degree >= 0:
            sigmas.append(d.sigma)
            continue  # a one-example combination: the constant 1, no system
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PsdWarning)
            plan = rbf.plan_rbf(d.centers, None, list(d.center_labels), kernel=d.kernel, sigma=d.sigma,
                                degree=d.degree, smoothing=d.smoothing, raise_problem=False)
        conds.append(plan.condition)
        sigmas.append(d.sigma)
    return (max(conds) if conds else float("nan")), sigmas


def _stage(layers: list[str]) -> Usd.Stage:
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths = layers
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    return stage


def measure(folder: str, count: int, jobs: int | None) -> dict:
    sub = os.path.join(folder, f"n{count}")
    os.makedirs(sub)
    log(f"{count} examples: building the 13k rig")
    poses_layer, poses = rigs.write_poses(sub, count)
    rig = rigs.build(sub, "lbs", "13k", poses, poses_layer)
    log(f"{count} examples: api.fit (rig built in {rig.build_seconds:.1f} s)")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PsdWarning)
        started = time.perf_counter()
        result = api.fit(rig.asset, [rig.examples], FitSettings(), jobs=jobs)
        fit_seconds = time.perf_counter() - started
    cond, sigmas = _conditions(result)
    inverse_worst = max(float(inv.residual.max() / inv.diagonal) if len(inv.residual) else 0.0
                        for m in result.meshes for inv in m.inverses)

    log(f"{count} examples: the written stack at the example poses")
    corr = os.path.join(sub, "correctives.usda")
    api.write_correctives(result, corr)
    weights = api.evaluate(rig.asset, corr, poses_layer)
    cache = api.points_cache_layer(weights)
    spec = Sdf.Path(rigs.MESH).AppendProperty("points")
    diag = tol.bbox_diagonal(rig.sculpts[rig.times[0]])
    worst = max(float(np.abs(np.array(cache.QueryTimeSample(spec, t), dtype=np.float64) - rig.sculpts[t]).max())
                for t in rig.times) / diag
    short = api.evaluate(rig.asset, corr, poses_layer, frames=(rig.times[0], rig.times[min(BAKED, count) - 1]))
    weights_path = api.write_weights(short, os.path.join(sub, "weights.usda"))
    stage = _stage([weights_path, poses_layer, corr, rig.asset])
    UsdSkel.BakeSkinning(UsdSkel.Root(stage.GetPrimAtPath(rigs.generate.ROOT)),
                         Gf.Interval(rig.times[0], rig.times[min(BAKED, count) - 1]))
    attr = UsdGeom.Mesh(stage.GetPrimAtPath(rigs.MESH)).GetPointsAttr()
    baked = max(float(np.abs(np.array(attr.Get(Usd.TimeCode(t)), dtype=np.float64) - rig.sculpts[t]).max())
                for t in rig.times[:BAKED]) / diag
    return {
        "examples": count, "condition": cond, "sigmas": sigmas, "groups": len(result.meshes),
        "fit_seconds": fit_seconds, "seconds_per_example": fit_seconds / count, "inverse_max_rel": inverse_worst,
        "cache_max_rel": worst, "baked_max_rel": baked,
        "exact": worst <= ROUND_TRIP_RTOL and baked <= ROUND_TRIP_RTOL,
        "warnings": [str(w.message) for w in caught if issubclass(w.category, PsdWarning)],
    }


def table(rows: list[dict]) -> str:
    lines = [f"{'examples':>8} {'groups':>6} {'condition':>10} {'sigma (rad)':>15} {'s/example':>10} "
             f"{'max res/diag':>13} {'baked/diag':>11} {'exact':>6}"]
    for r in rows:
        lo, hi = min(r["sigmas"]), max(r["sigmas"])
        sig = f"{lo:.4g}" if lo == hi else f"{lo:.3g}..{hi:.3g}"
        lines.append(f"{r['examples']:>8} {r['groups']:>6} {r['condition']:>10.2e} {sig:>15} "
                     f"{r['seconds_per_example']:>10.3f} {r['cache_max_rel']:>13.2e} {r['baked_max_rel']:>11.2e} "
                     f"{'yes' if r['exact'] else 'NO':>6}")
    return "\n".join(lines)


ABOUT = (
    "Default fits of many examples on the 13k bench rig (lbs; one global group, since every bench example bends "
    "the elbow and the wrist together). sigma is the largest sigma_0 * 2^(-j/4) whose system has a condition number ≤ "
    f"{tol.RBF_COND_TARGET:.0e}. \"max residual\" is the points cache of the written stack at every example; "
    f"\"baked\" is `UsdSkel.BakeSkinning` of the stack at the first {BAKED}; exact = both within "
    f"{ROUND_TRIP_RTOL:g} of the diagonal."
)


def tables(rows: list[dict]) -> list[dict]:
    """The conditioning table of the results record."""
    cells = []
    for r in rows:
        lo, hi = min(r["sigmas"]), max(r["sigmas"])
        cells.append([str(r["examples"]), f"{r['condition']:.2e}", f"{lo:.4g}" if lo == hi else f"{lo:.3g}..{hi:.3g}",
                      f"{r['seconds_per_example']:.3f}", f"{r['cache_max_rel']:.2e}", f"{r['baked_max_rel']:.2e}",
                      "yes" if r["exact"] else "NO"])
    return [results.table("Many examples: conditioning, time, exactness",
                          ["examples", "condition number", "sigma (rad)", "s / example", "max residual / diag",
                           "baked / diag", "exact"], cells)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Default fits of many examples: conditioning, time, exactness.")
    parser.add_argument("--counts", type=int, nargs="+", default=[8, 32, 128, 500])
    parser.add_argument("--jobs", type=int, default=None, help="worker processes for api.fit (default: 1)")
    parser.add_argument("--json", default=results.path_of("conditioning"), help="where to write the results record")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for count in args.counts:
            rows.append(measure(folder, count, args.jobs))
            log(f"{count} examples: done, fit {rows[-1]['fit_seconds']:.1f} s")
            for w in rows[-1]["warnings"]:
                log(f"  warning: {w}")
    print(f"Default fits on the 13k bench rig (lbs), examples from rigs.example_poses(count); "
          f"condition-number target {tol.RBF_COND_TARGET:.0e}, exact = every example within "
          f"{ROUND_TRIP_RTOL:g} of the diagonal (points cache; BakeSkinning for the first {BAKED}).")
    print(table(rows))
    results.write("conditioning", argv, ABOUT, tables(rows), raw=rows, path=args.json)
    return 0 if all(r["exact"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
