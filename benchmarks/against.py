"""Fit and eval time against an earlier psdbake, side by side in one run.

The earlier psdbake is this repository's ``psdbake/`` at ``--rev`` (default: the commit before
per-joint terms and combinations, the default fit's layout until issue 26), unpacked with
``git archive`` into a temporary folder; both run on the same installed numpy, SciPy and USD.
Each measurement is a fresh process importing one or the other (``PYTHONPATH``), and the two
alternate, ``--rounds`` times, so a shared machine's load falls on both alike:

- **fit**: ``psdbake.api.fit`` with default settings of the 100k-point LBS bench arm's ten
  single-joint sculpts (``sculptspeed.single_poses``), the median of ``FITS`` after a warm-up;
- **eval**: ``psdbake.api.evaluate`` of the humanoid's default fit (fitted by the same psdbake)
  over its 100-frame shot, the median of ``EVALS`` after a warm-up, per frame.

Reported: medians over every round, and this psdbake's over the earlier one's.

Run: ``python -m benchmarks.against`` (part of ``make bench``; needs the repository's git history).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import tarfile
import tempfile
import time

from . import processes, results, rigs, sculptspeed

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
BEFORE = "7d0c24c"  # main before per-joint terms (issue 26)
FITS = 3
EVALS = 5
ROUNDS = 3
HUMANOID = os.path.join(ROOT, "fixtures", "humanoid")


def child(asset: str, examples: str, folder: str) -> None:
    """In a fresh process: fit times, then eval seconds per frame; prints one JSON line."""
    from psdbake import api

    api.fit(asset, [examples])
    fits = []
    for _ in range(FITS):
        t0 = time.perf_counter()
        api.fit(asset, [examples])
        fits.append(time.perf_counter() - t0)
    humanoid = os.path.join(HUMANOID, "humanoid.usda")
    anim = os.path.join(HUMANOID, "humanoid_anim.usda")
    correctives = os.path.join(folder, f"humanoid_{os.getpid()}.usda")
    api.write_correctives(api.fit(humanoid, [os.path.join(HUMANOID, "humanoid_examples.usda")]), correctives)
    frames = len(api.evaluate(humanoid, correctives, anim).animations[0].times)
    evals = []
    for _ in range(EVALS):
        t0 = time.perf_counter()
        api.evaluate(humanoid, correctives, anim)
        evals.append((time.perf_counter() - t0) / frames)
    print(json.dumps({"fit": fits, "eval_per_frame": evals, "frames": frames, "psdbake": os.path.dirname(api.__file__)}))


def unpack(rev: str, folder: str) -> str:
    """``psdbake/`` at rev, in folder: the folder to put on PYTHONPATH."""
    archive = os.path.join(folder, "before.tar")
    with open(archive, "wb") as out:
        subprocess.run(["git", "-C", ROOT, "archive", rev, "psdbake"], stdout=out, check=True)
    target = os.path.join(folder, "before")
    with tarfile.open(archive) as tar:
        tar.extractall(target, filter="data")
    return target


def measure(path: str, asset: str, examples: str, folder: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([path, ROOT]))  # psdbake from path, benchmarks from ROOT
    return processes.in_child("against", [asset, examples, folder], env=env, cwd=folder)


ABOUT = (
    "This psdbake against an earlier one (its `psdbake/` at a git revision, on the same libraries), side by side: "
    "fresh processes alternating between the two. Fit: the default fit of the 100k-point LBS bench arm's ten "
    "single-joint sculpts (median after a warm-up). Eval: the humanoid's default fit (fitted by the same psdbake, "
    "24 channels both) over its 100-frame shot, seconds per frame."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Fit and eval time against an earlier psdbake, side by side.")
    parser.add_argument("--rev", default=BEFORE, help="the earlier psdbake's git revision")
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--record", default=results.path_of("against"), help="where to write the results record")
    args = parser.parse_args(argv)
    runs: dict[str, list[dict]] = {"before": [], "now": []}
    with tempfile.TemporaryDirectory() as folder:
        before = unpack(args.rev, folder)
        poses = sculptspeed.single_poses()
        layer = rigs.generate.write_animation(os.path.join(folder, "poses.usda"), poses)
        rig = rigs.build(folder, "lbs", sculptspeed.SIZE, poses, layer)
        for r in range(args.rounds):
            for name, path in (("before", before), ("now", ROOT)) if r % 2 == 0 else (("now", ROOT), ("before", before)):
                runs[name].append(measure(path, rig.asset, rig.examples, folder))
                print(f"round {r + 1} {name}: fit {statistics.median(runs[name][-1]['fit']):.3f} s, eval "
                      f"{statistics.median(runs[name][-1]['eval_per_frame']) * 1e3:.3f} ms/frame", flush=True)
    fit = {n: statistics.median(s for run in v for s in run["fit"]) for n, v in runs.items()}
    per_frame = {n: statistics.median(s for run in v for s in run["eval_per_frame"]) for n, v in runs.items()}
    print(f"fit: {fit['now']:.3f} s against {fit['before']:.3f} s ({fit['now'] / fit['before']:.2f}x); eval: "
          f"{per_frame['now'] * 1e3:.3f} against {per_frame['before'] * 1e3:.3f} ms per frame "
          f"({per_frame['now'] / per_frame['before']:.2f}x)")
    rows = [["fit, 10 single-joint sculpts, 100k points (s)", f"{fit['before']:.3f}", f"{fit['now']:.3f}",
             f"{fit['now'] / fit['before']:.2f}x"],
            ["eval, humanoid, 24 channels (ms per frame)", f"{per_frame['before'] * 1e3:.3f}",
             f"{per_frame['now'] * 1e3:.3f}", f"{per_frame['now'] / per_frame['before']:.2f}x"]]
    table = results.table(f"This psdbake against {args.rev}", ["measure", args.rev, "now", "now / before"], rows,
                          f"{args.rounds} rounds alternating, {FITS} fits and {EVALS} evals each after a warm-up; "
                          "medians over every round.")
    results.write("against", argv, ABOUT, [table], raw={"rev": args.rev, "runs": runs}, path=args.record)


if __name__ == "__main__":
    main()
