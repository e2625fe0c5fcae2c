"""Fit speed at film scale (issue 16): what a whole ``psdbake fit`` costs against UsdSkel's own skinning.

Two measurements, each on ``.usda`` and on ``.usdc`` inputs (the output in the same format):

- **100k points, one example**: the fit end to end (``psdbake fit`` as the command runs it:
  the input checks and crate probe, reading, the inverse, the RBF, writing CORRECTIVES),
  excluding process start-up, divided by one ``UsdSkel.SkinningQuery.ComputeSkinnedPoints``
  call of the same mesh at the example's pose, timed in the same process just before the fit
  (the median of 15 calls; the median of 15 just after it is printed too, see ``child``). The
  ratio is in *skinning-equivalents*: the inverse itself needs 5 black-box calls, the rest is
  reading, checking and writing.
- **1M points, 8 examples**: seconds (the fit, and the whole process: start-up and a warm-up
  fit of the small arm fixture included) and peak
  resident memory: the psdbake process's own high-water mark (``VmHWM``) and its children's
  (the crate probe, ``resource.getrusage(RUSAGE_CHILDREN)``).

Both show the time spent waiting for the crate probe (``psdbake.usd.integrity``: binary
inputs are read whole in a child process before psdbake opens them), whose Python and USD
start-up alone is ~0.17 s, about 100 skinnings of the 100k mesh, and each is measured in the
two states a binary input can be in, side by side:

- **first read**: the probe's verdict cache (``PSDBAKE_CACHE_DIR``) empty, so the inputs are
  hashed, probed, hashed again and their verdicts stored (the first fit of a new asset);
- **verified**: the same cache folder again, so the inputs are found (what every farm chunk
  and batch job after the first sees): by their settled identity without hashing, or hashed
  and found by content when they changed less than ``integrity.SETTLED_SECONDS`` before. The
  cache look-ups that hash are timed and shown.

Every fit runs in a fresh process (so no layer or in-process probe result is reused), after a
warm-up fit of the small arm fixture in the same format (process start-up: imports, USD's
plug-ins; it shares no file with the measured fit); each repeat gets an empty cache folder of
its own for its first read, and its verified fit follows with that folder. Formats are
interleaved repeat by repeat: the machines are shared and noisy, so the figures quoted are
medians, and ratios come from the same process.

Run: ``python -m benchmarks.fitspeed`` (part of ``make bench``); ``--folder DIR`` keeps the
generated rigs there and reuses them on the next run; ``--profile`` prints each format's
cProfile of one extra fit at each size.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

from . import processes, results, rigs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: (size, examples, default repeats): the two rigs of the issue's targets.
CASES = (("100k", 1, 5), ("1M", 8, 3))
FORMATS = (".usda", ".usdc")
#: ComputeSkinnedPoints calls per timing (their median is the unit).
SKIN_CALLS = 15
#: The inputs' probe verdicts not yet cached (an empty cache folder), then cached (the same folder).
STATES = ("first read", "verified")


def skinning_seconds(asset: str, examples: str, time_code: float, calls: int = SKIN_CALLS) -> list[float]:
    """Seconds of ``calls`` ``ComputeSkinnedPoints`` of the rig's mesh at time_code (copies of
    the rest points made beforehand: the call skins in place). The stage is its own and dies
    on return, so nothing it opened is left for a fit to find."""
    from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths.append(examples)
    root.subLayerPaths.append(asset)
    stage = Usd.Stage.Open(root)
    cache = UsdSkel.Cache()
    skel_root = UsdSkel.Root(stage.GetPrimAtPath(rigs.generate.ROOT))
    cache.Populate(skel_root, Usd.PrimDefaultPredicate)
    query = cache.GetSkinningQuery(stage.GetPrimAtPath(rigs.MESH))
    skel_query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath(rigs.generate.SKEL)))
    tc = Usd.TimeCode(time_code)
    xforms = skel_query.ComputeSkinningTransforms(tc)
    rest = UsdGeom.Mesh(stage.GetPrimAtPath(rigs.MESH)).GetPointsAttr().Get()
    copies = [Vt.Vec3fArray(rest) for _ in range(calls + 1)]
    query.ComputeSkinnedPoints(xforms, copies[-1], tc)  # warm UsdSkel's worker threads
    seconds = []
    for points in copies[:-1]:
        started = time.perf_counter()
        if not query.ComputeSkinnedPoints(xforms, points, tc):
            raise RuntimeError("ComputeSkinnedPoints failed")
        seconds.append(time.perf_counter() - started)
    return seconds


def _fit(asset: str, examples: str, out: str) -> None:
    """``psdbake fit ASSET EXAMPLES -o OUT -q``, as the command runs it."""
    from psdbake.cli import main as psdbake_main

    try:
        psdbake_main(["fit", asset, examples, "-o", out, "-q"])
    except SystemExit as exc:  # the command's exit, as from the shell
        if exc.code:
            raise


def _time_crate_probes() -> list[float]:
    """Seconds of each crate probe run from now on in this process: psdbake reads binary
    inputs whole in a child process first (``psdbake.usd.integrity``), whose Python and USD
    start-up alone is ~0.17 s; recorded around ``subprocess.run`` of ``_crate_probe.py``."""
    spent: list[float] = []
    run = subprocess.run

    def timed(argv: Any, *args: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        try:
            return run(argv, *args, **kwargs)
        finally:
            if any("_crate_probe" in str(a) for a in argv):
                spent.append(time.perf_counter() - started)

    subprocess.run = timed
    return spent


def _time_cache_lookups() -> list[float]:
    """Seconds of each look-up of a probe verdict from now on in this process (hashing the
    file: ``psdbake.usd.integrity._verdict_entry``; a first read hashes twice, around the probe)."""
    from psdbake.usd import integrity

    spent: list[float] = []
    entry = integrity._verdict_entry

    def timed(path: str) -> str | None:
        started = time.perf_counter()
        try:
            return entry(path)
        finally:
            spent.append(time.perf_counter() - started)

    integrity._verdict_entry = timed
    return spent


def child(asset: str, examples: str, out: str, warm: list[str], skin_time: float | None, profile: bool) -> None:
    """One fit in this (fresh) process, timed after process start-up; prints one JSON line.

    Start-up is the interpreter, the imports (psdbake loads fit's modules when a fit first
    runs) and USD's one-time set-up (plug-in registry, file formats): a warm-up fit of the
    small arm fixture in the same format, warm = (asset, examples, out), pays it first. It
    shares no file with the measured fit, so no layer or crate-probe result carries over."""
    _fit(*warm)
    # The unit: UsdSkel's skinning timed just before the fit, in the same process. Calls timed
    # just after it are printed too but not used: they depend on the fit's own allocations (its
    # multi-MB temporaries raised glibc's mmap threshold, which spared UsdSkel's later
    # allocations their page faults: 1.05 ms after the fit against 1.23 before, at 100k points)
    skins = skinning_seconds(asset, examples, skin_time) if skin_time is not None else []
    probes, lookups = _time_crate_probes(), _time_cache_lookups()
    started = time.perf_counter()
    if profile:
        import cProfile
        import pstats

        prof = cProfile.Profile()
        prof.runcall(_fit, asset, examples, out)
        seconds = time.perf_counter() - started
        pstats.Stats(prof, stream=sys.stderr).sort_stats("cumulative").print_stats(45)
    else:
        _fit(asset, examples, out)
        seconds = time.perf_counter() - started
    import resource

    record = {"seconds": seconds, "probe_seconds": sum(probes), "lookup_seconds": sum(lookups),
              "rss_mib": processes.peak_rss_mib(),
              "children_rss_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0}
    if skin_time is not None:
        record["skin_seconds"] = statistics.median(skins)
        record["skin_after_seconds"] = statistics.median(skinning_seconds(asset, examples, skin_time))
    print(json.dumps(record), flush=True)


def _run_child(asset: str, examples: str, out: str, warm: list[str], skin_time: float | None, cache: str,
               profile: bool = False) -> dict:
    """One measured fit in a fresh process whose probe-verdict cache is the folder cache."""
    argv = [sys.executable, "-m", "benchmarks.fitspeed", "--child", asset, examples, out, "--warm", *warm]
    if skin_time is not None:
        argv += ["--skin-time", repr(skin_time)]
    if profile:
        argv.append("--profile")
    started = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=False, cwd=ROOT,
                          env={**os.environ, "PSDBAKE_CACHE_DIR": cache})
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"fit of {examples} failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    if profile:
        print(done.stderr, file=sys.stderr)
    record = json.loads(done.stdout.strip().splitlines()[-1])
    record["wall"] = wall
    return record


def _with_usdc(paths: list[str]) -> None:
    """A .usdc copy beside each .usda (USD's own crate writer, values unchanged)."""
    from pxr import Sdf

    for path in paths:
        if not Sdf.Layer.FindOrOpen(path).Export(os.path.splitext(path)[0] + ".usdc"):
            raise SystemExit(f"cannot write {path} as .usdc")


def build(folder: str, size: str, count: int) -> dict[str, tuple[str, str]]:
    """The lbs rig of size with count examples (times 1..count), as .usda and .usdc
    ({format: (asset, examples)}); reused when already in folder."""
    here = os.path.join(folder, f"{size}_{count}")
    os.makedirs(here, exist_ok=True)
    tag = f"lbs_{size.replace('.', '_')}"
    files = {ext: (os.path.join(here, tag + ext), os.path.join(here, f"{tag}_examples{ext}")) for ext in FORMATS}
    if not all(os.path.exists(p) for pair in files.values() for p in pair):
        poses_layer, poses = rigs.write_poses(here, count)
        rig = rigs.build(here, "lbs", size, poses, poses_layer)
        _with_usdc([rig.asset, rig.examples])
    return files


def warm_up_files(folder: str) -> dict[str, list[str]]:
    """{format: [asset, examples, output]} of the small arm fixture, for each child's warm-up."""
    here = os.path.join(folder, "warm")
    os.makedirs(here, exist_ok=True)
    names = ("arm_lbs", "arm_lbs_examples")
    for name in names:
        shutil.copy(os.path.join(ROOT, "fixtures", f"{name}.usda"), here)
    _with_usdc([os.path.join(here, f"{name}.usda") for name in names])
    return {ext: [*(os.path.join(here, name + ext) for name in names), os.path.join(here, f"out{ext}")]
            for ext in FORMATS}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", help="keep the rigs here (reused when present); default: a temporary folder")
    parser.add_argument("--repeats-100k", type=int, default=CASES[0][2])
    parser.add_argument("--repeats-1m", type=int, default=CASES[1][2])
    parser.add_argument("--only", choices=[c[0] for c in CASES], help="one size only")
    parser.add_argument("--profile", action="store_true", help="cProfile one extra fit per size and format (stderr)")
    parser.add_argument("--child", nargs=3, metavar=("ASSET", "EXAMPLES", "OUT"), help=argparse.SUPPRESS)
    parser.add_argument("--warm", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--skin-time", type=float, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--json", default=results.path_of("fitspeed"), help="where to write the results record")
    args = parser.parse_args(argv)
    if args.child:
        child(*args.child, args.warm, args.skin_time, args.profile)
        return
    repeats = {"100k": args.repeats_100k, "1M": args.repeats_1m}
    lines, medians = [], []
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.folder or scratch
        os.makedirs(folder, exist_ok=True)
        warm = warm_up_files(scratch)
        for size, count, _ in CASES:
            if args.only and size != args.only:
                continue
            files = build(folder, size, count)
            skin = 1.0 if size == "100k" else None  # the first example's time
            runs: dict[str, dict[str, list[dict]]] = {ext: {state: [] for state in STATES} for ext in FORMATS}
            for _ in range(repeats[size]):
                for ext in FORMATS:  # interleaved: a slow spell of the machine hits both formats
                    out = os.path.join(scratch, f"corr_{size}{ext}")
                    cache = tempfile.mkdtemp(prefix="cache-", dir=scratch)  # empty: the first read fills it
                    for state in STATES:
                        runs[ext][state].append(_run_child(*files[ext], out, warm[ext], skin, cache))
                    if runs[ext]["verified"][-1]["probe_seconds"]:
                        raise SystemExit(f"{files[ext]}: probed again with its verdicts in {cache}")
            if args.profile:
                for ext in FORMATS:
                    print(f"--- profile: {size}, {count} example(s), {ext}, first read ---", file=sys.stderr)
                    _run_child(*files[ext], os.path.join(scratch, f"corr_{size}{ext}"), warm[ext], None,
                               tempfile.mkdtemp(prefix="cache-", dir=scratch), profile=True)
            lines += [_row(size, count, ext, runs[ext]) for ext in FORMATS]
            medians += [_medians(size, count, ext, runs[ext]) for ext in FORMATS]
    print("psdbake fit end to end (the command, after process start-up), lbs rig; medians of fresh processes, "
          "formats interleaved; first read (probe verdicts not cached) | verified (cached):")
    print("\n".join(lines))
    results.write("fitspeed", argv, ABOUT, tables(medians), raw=medians, path=args.json)


ABOUT = (
    "`psdbake fit` in fresh processes, timed after start-up (a warm-up fit of the arm fixture pays the imports), "
    "`.usda` and `.usdc` interleaved repeat by repeat, medians. \"First read\": the crate probe's verdict cache "
    "empty; \"verified\": the inputs' verdicts cached (every farm chunk and batch job after the first). At 100k "
    "points, one example: the whole command divided by one `ComputeSkinnedPoints` of the same mesh timed just "
    "before the fit in the same process (skinning-equivalents). At 1M points, 8 examples: seconds and peak "
    "resident memory (the psdbake process's high-water mark; the crate probe's child separately)."
)


def _medians(size: str, count: int, ext: str, runs: dict[str, list[dict]]) -> dict[str, Any]:
    """The medians a table row shows, per state (first read, verified)."""
    med: dict[str, Any] = {state: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for state, rs in runs.items()}
    if "skin_seconds" in runs["first read"][0]:
        med["ratio"] = {state: statistics.median(r["seconds"] / r["skin_seconds"] for r in rs) for state, rs in runs.items()}
        med["skin_seconds"] = statistics.median(r["skin_seconds"] for rs in runs.values() for r in rs)
    return {"size": size, "examples": count, "format": ext, "repeats": len(runs["verified"]), **med}


def tables(medians: list[dict[str, Any]]) -> list[dict]:
    """The 100k and 1M tables of the results record."""
    out = []
    small = [m for m in medians if "ratio" in m]
    if small:
        rows = [[f"`{m['format']}` in/out",
                 f"{m['first read']['seconds']:.3f} s (probe {m['first read']['probe_seconds']:.3f} s)",
                 f"{m['verified']['seconds']:.3f} s (hash {m['verified']['lookup_seconds']:.3f} s)",
                 f"{1000 * m['skin_seconds']:.2f} ms", f"{m['ratio']['first read']:.0f} / {m['ratio']['verified']:.0f}"]
                for m in small]
        out.append(results.table(f"{small[0]['size']}, {small[0]['examples']} example ({small[0]['repeats']} repeats)",
                                 ["format", "fit, first read", "verified", "one `ComputeSkinnedPoints`",
                                  "skinning-equivalents, first read / verified"], rows))
    large = [m for m in medians if "ratio" not in m]
    if large:
        rows = [[f"`{m['format']}` in/out", f"{m['first read']['seconds']:.2f} / {m['verified']['seconds']:.2f} s "
                 f"(probe {m['first read']['probe_seconds']:.2f} s / hash {m['verified']['lookup_seconds']:.2f} s)",
                 f"{m['first read']['wall']:.2f} / {m['verified']['wall']:.2f} s",
                 f"{m['first read']['rss_mib']:.0f} MiB (probe child {m['first read']['children_rss_mib']:.0f} MiB)"]
                for m in large]
        out.append(results.table(f"{large[0]['size']}, {large[0]['examples']} examples ({large[0]['repeats']} repeats)",
                                 ["format", "fit, first read / verified", "whole process", "peak RSS"], rows))
    return out


def _row(size: str, count: int, ext: str, runs: dict[str, list[dict]]) -> str:
    med = {state: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for state, rs in runs.items()}
    first, verified = med["first read"], med["verified"]
    head = (f"  {size:>4} x{count} {ext}  fit {first['seconds']:6.3f} s (probe {first['probe_seconds']:5.3f} s, "
            f"hash {first['lookup_seconds']:5.3f} s) | {verified['seconds']:6.3f} s (hash {verified['lookup_seconds']:5.3f} s)")
    n = f"(n={len(runs['verified'])})"
    if "skin_seconds" in first:  # ratios per process, then their median
        ratio = {state: statistics.median(r["seconds"] / r["skin_seconds"] for r in rs) for state, rs in runs.items()}
        bare = statistics.median((r["seconds"] - r["probe_seconds"]) / r["skin_seconds"] for r in runs["first read"])
        skin = statistics.median(r["skin_seconds"] for rs in runs.values() for r in rs)
        after = statistics.median(r["skin_after_seconds"] for rs in runs.values() for r in rs)
        return (f"{head}  ComputeSkinnedPoints {1000 * skin:5.2f} ms before the fit ({1000 * after:4.2f} after): "
                f"{ratio['first read']:4.0f} | "
                f"{ratio['verified']:4.0f} skinning-equivalents ({bare:4.0f} first read without the probe)  {n}")
    return (f"{head}  the whole process {first['wall']:6.2f} | {verified['wall']:6.2f} s  peak RSS "
            f"{first['rss_mib']:5.0f} | {verified['rss_mib']:5.0f} MiB (probe child {first['children_rss_mib']:4.0f} MiB)  {n}")


if __name__ == "__main__":
    main()
