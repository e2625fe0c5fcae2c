"""``psdbake batch JOBS.toml --dry-run`` on large jobs files: peak memory and time by job count.

Every job writes one CORRECTIVES layer (``fit --group gN -o c.usda``), the worst case for the
ordering: each job waits for the one before it. Each dry run is a fresh ``psdbake`` process;
its peak resident memory is ``getrusage(RUSAGE_CHILDREN).ru_maxrss`` of a process that starts
only that run. The jobs file of 25,000 jobs is 614 kB, under the 1 MiB cap.

Run: ``python -m benchmarks.jobsfile`` (part of ``make bench``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

_MEASURE = """
import resource, subprocess, sys, time
started = time.perf_counter()
done = subprocess.run([sys.argv[1], "batch", sys.argv[2], "--dry-run", "-q"], capture_output=True)
print(done.returncode, time.perf_counter() - started, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
"""


def write_jobs(path: str, count: int) -> int:
    """A jobs file of count fit jobs into one output; returns its size in bytes."""
    with open(path, "w", encoding="utf-8") as fh:
        fh.write('[defaults]\nasset = "a.usda"\nexamples = ["e.usda"]\noutput = "c.usda"\n')
        fh.writelines(f'[[fit]]\ngroup = "g{i}"\n' for i in range(count))
    return os.path.getsize(path)


def dry_run(path: str) -> tuple[float, float]:
    """(seconds, peak RSS in MiB) of one ``psdbake batch --dry-run``."""
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    done = subprocess.run([sys.executable, "-c", _MEASURE, exe, path], capture_output=True, text=True, check=True)
    code, seconds, peak_kib = done.stdout.split()
    if code != "0":
        raise SystemExit(f"psdbake batch --dry-run {path} failed with exit {code}")
    return float(seconds), int(peak_kib) / 1024.0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, nargs="+", default=[1_000, 5_000, 25_000])
    args = parser.parse_args(argv)
    print("psdbake batch --dry-run, every job writing one file:")
    print(f"  {'jobs':>7} {'file':>9} {'seconds':>8} {'peak RSS':>10}")
    with tempfile.TemporaryDirectory() as folder:
        for count in args.jobs:
            path = os.path.join(folder, f"jobs{count}.toml")
            size = write_jobs(path, count)
            seconds, peak = dry_run(path)
            print(f"  {count:>7,} {size / 1000:>7.0f} kB {seconds:>8.2f} {peak:>6.0f} MiB")


if __name__ == "__main__":
    main()
