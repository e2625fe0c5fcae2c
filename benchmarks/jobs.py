"""Fitting 20 examples of the 100k-vertex rig: ``--jobs`` scaling, peak memory, identical output.

Runs ``psdbake fit`` as a separate process for each N in ``--jobs 1`` and ``--jobs <cores>``,
samples the resident memory of the whole process tree (psdbake plus its workers) every
20 ms from /proc, and compares the output layers byte for byte.

Run: ``python -m benchmarks.jobs`` (part of ``make bench``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from benchmarks import results, rigs


def _tree_rss_kb(pid: int) -> int:
    """Resident memory of pid and all its descendants, in KiB."""
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/status") as fh:
                for line in fh:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1])
            with open(f"/proc/{p}/task/{p}/children") as fh:
                todo += [int(c) for c in fh.read().split()]
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
    return total


def run_fit(asset: str, examples: str, out: str, jobs: int) -> tuple[float, float]:
    """(seconds, peak tree RSS in MiB) of one ``psdbake fit -j jobs``."""
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    started = time.perf_counter()
    proc = subprocess.Popen([exe, "fit", asset, examples, "-o", out, "-q", "-j", str(jobs)])
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _tree_rss_kb(proc.pid))
        time.sleep(0.02)
    if proc.returncode != 0:
        raise SystemExit(f"psdbake fit -j {jobs} failed with exit {proc.returncode}")
    return time.perf_counter() - started, peak / 1024.0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="100k", choices=sorted(rigs.SIZES))
    parser.add_argument("--examples", type=int, default=20)
    parser.add_argument("--json", default=results.path_of("jobs"), help="where to write the results record")
    args = parser.parse_args(argv)
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as folder:
        poses_layer, poses = rigs.write_poses(folder, args.examples)
        rig = rigs.build(folder, "lbs", args.size, poses, poses_layer)
        rows = []
        outputs = {}
        out = os.path.join(folder, "corr.usdc")  # one path: the layer records the command line that wrote it
        for jobs in sorted({1, cores}):
            if os.path.exists(out):
                os.remove(out)
            seconds, peak = run_fit(rig.asset, rig.examples, out, jobs)
            with open(out, "rb") as fh:
                outputs[jobs] = fh.read()
            rows.append((jobs, seconds, peak))
        identical = len(set(outputs.values())) == 1
    print(f"fit of {args.examples} examples, lbs {args.size} ({rig.points:,} points, a third sculpted), "
          f"{cores} cores:")
    print(f"  {'--jobs':>6} {'seconds':>8} {'peak RSS (tree)':>16} {'speed-up':>9}")
    base = rows[0][1]
    for jobs, seconds, peak in rows:
        print(f"  {jobs:>6} {seconds:>8.2f} {peak:>13.0f} MiB {base / seconds:>8.2f}x")
    print(f"  outputs byte-identical across --jobs: {'yes' if identical else 'NO'}")
    about = (f"`psdbake fit` of {args.examples} examples of the {args.size} lbs bench rig ({rig.points:,} points, a third "
             "sculpted) as a separate process with `--jobs 1` and `--jobs <cores>`; peak resident memory of the whole "
             "process tree (psdbake and its workers) sampled every 20 ms; the outputs compared byte for byte.")
    table = results.table(f"`fit --jobs`: {args.examples} examples, {args.size}", ["--jobs", "seconds", "peak RSS (tree)",
                                                                                   "speed-up"],
                          [[str(j), f"{s:.2f}", f"{p:.0f} MiB", f"{base / s:.2f}x"] for j, s, p in rows],
                          f"Outputs byte-identical across --jobs: {'yes' if identical else 'NO'}.")
    results.write("jobs", argv, about, [table], raw={"rows": rows, "identical": identical}, path=args.json)
    if not identical:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
