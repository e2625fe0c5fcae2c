"""Start-up cost: ``psdbake --help`` and a small ``psdbake eval`` against the interpreter's own.

Every farm chunk and batch job is a fresh process, so what the command loads before its
first frame is paid once per task (issue 16). Four commands, timed wall-clock as a user
starts them (a new process each run):

- ``python -c pass``: the interpreter alone, the floor nothing can go below;
- ``python -c "import pxr.Usd"``: USD alone, what any command that reads a layer pays;
- ``psdbake --help``: click and psdbake's option names, no numerics and no USD;
- ``psdbake eval`` on the arm fixture (fixtures/arm_lbs.usda, its 8-example correctives
  fitted once beforehand, untimed, over fixtures/arm_anim.usda): a whole small command.

The runs are interleaved (one of each per round, the order rotated every round) after one
untimed warm-up round, and the table gives medians, so the load of a shared machine falls
on every command alike; the ratio to the floor is the figure to compare between machines.

Run: ``python -m benchmarks.startup [--runs N]`` (part of ``make bench``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIX = os.path.join(ROOT, "fixtures")

#: Issue 16's targets, in seconds of wall time.
TARGETS = {"psdbake --help": 0.25, "psdbake eval (arm)": 0.6}


def _psdbake() -> list[str]:
    """The console script beside this interpreter (what users run), else ``python -m psdbake``."""
    script = os.path.join(os.path.dirname(sys.executable), "psdbake")
    return [script] if os.path.exists(script) else [sys.executable, "-m", "psdbake"]


def commands(folder: str) -> dict[str, list[str]]:
    """The timed commands, by label; fits the arm's correctives into folder first (untimed)."""
    arm, anim = os.path.join(FIX, "arm_lbs.usda"), os.path.join(FIX, "arm_anim.usda")
    correctives = os.path.join(folder, "correctives.usda")
    subprocess.run([*_psdbake(), "fit", arm, os.path.join(FIX, "arm_lbs_examples.usda"), "-o", correctives, "-q"],
                   check=True)
    return {
        "python -c pass": [sys.executable, "-c", "pass"],
        "python -c 'import pxr.Usd'": [sys.executable, "-c", "import pxr.Usd"],
        "psdbake --help": [*_psdbake(), "--help"],
        "psdbake eval (arm)": [*_psdbake(), "eval", arm, correctives, "--anim", anim, "-o",
                               os.path.join(folder, "weights.usda"), "-q"],
    }


def _wall(argv: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - started


def measure(cmds: dict[str, list[str]], runs: int) -> dict[str, list[float]]:
    """Wall seconds of each command, runs times, interleaved (round r starts at command r mod 4)."""
    labels = list(cmds)
    for label in labels:  # warm-up: page cache, .pyc files
        _wall(cmds[label])
    seconds: dict[str, list[float]] = {label: [] for label in labels}
    for r in range(runs):
        for label in labels[r % len(labels):] + labels[: r % len(labels)]:
            seconds[label].append(_wall(cmds[label]))
    return seconds


def table(seconds: dict[str, list[float]]) -> list[str]:
    floor = statistics.median(seconds["python -c pass"])
    lines = [f"{'command':<28} {'median s':>9} {'min s':>7} {'x floor':>8}  target",
             f"{'-' * 28} {'-' * 9} {'-' * 7} {'-' * 8}  {'-' * 14}"]
    for label, values in seconds.items():
        median = statistics.median(values)
        target = TARGETS.get(label)
        verdict = f"<= {target} s: {'yes' if median <= target else 'NO'}" if target else ""
        lines.append(f"{label:<28} {median:>9.3f} {min(values):>7.3f} {median / floor:>8.1f}  {verdict}")
    return lines


ABOUT = (
    "Every farm chunk and batch job is a fresh process, so what the command loads before its first frame is "
    "paid once per task. `--help`, option parsing and usage errors load only click and the option names; each "
    "command imports the library it runs; `eval` loads numpy and USD but not SciPy. Wall time of a new process "
    "per run, the commands interleaved, medians; the ratio to `python -c pass` is the figure to compare "
    "between machines."
)


def tables(seconds: dict[str, list[float]], runs: int) -> list[dict]:
    """The start-up table of the results record."""
    from . import results

    floor = statistics.median(seconds["python -c pass"])
    rows = []
    for label, values in seconds.items():
        median = statistics.median(values)
        target = TARGETS.get(label)
        rows.append([f"`{label}`", f"{median:.3f} s", f"{median / floor:.1f}", f"{target} s" if target else ""])
    return [results.table(f"Start-up ({runs} runs of each command, interleaved)",
                          ["command", "median", "x `python -c pass`", "target"], rows)]


def main(argv: list[str] | None = None) -> None:
    from . import results

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15, help="timed runs of each command (default 15)")
    parser.add_argument("--json", default=results.path_of("startup"), help="where to write the results record")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        seconds = measure(commands(folder), args.runs)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"start-up, {args.runs} interleaved runs each, {os.cpu_count()} cores, load average {load:.2f} "
          f"at the end (python {sys.version.split()[0]})")
    print("\n".join(table(seconds)))
    results.write("startup", argv, ABOUT, tables(seconds, args.runs), raw=seconds, path=args.json)


if __name__ == "__main__":
    main()
