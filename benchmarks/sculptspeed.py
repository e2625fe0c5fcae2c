"""Fit time by kind of sculpt, side by side on the 100k bench rig: single joints against shot frames.

The rig is ``benchmarks/rigs.py``'s LBS arm at 100k points. Two EXAMPLES sets of ten sculpts
each, of the same ground truth (``rigs.band_offsets``: a bulge growing with the elbow's bend and
a twist fix following the wrist's):

- **single joints**: five poses bending the elbow alone (30 to 150 degrees) and five twisting
  the wrist alone (-60 to 60 degrees);
- **shot frames**: ten frames of a shot where both move at once (``rigs.shot_poses``, frames
  spread over it).

Each fit (``psdbake.api.fit``, default settings, one worker) runs ``REPEATS`` times in this
process after a warm-up fit of each set; the median seconds and the ratio shot / single are
printed (one run: ratios taken side by side on a shared machine).

Run: ``python -m benchmarks.sculptspeed`` (part of ``make bench``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

import numpy as np

from . import results, rigs

REPEATS = 3
SIZE = "100k"


def single_poses() -> dict[float, dict]:
    poses = {}
    for i, elbow in enumerate(np.linspace(30.0, 150.0, 5)):
        poses[float(i + 1)] = {"Elbow": ((0, 0, 1), float(elbow))}
    for i, wrist in enumerate((-60.0, -30.0, 20.0, 45.0, 60.0)):
        poses[float(i + 6)] = {"Wrist": ((1, 0, 0), wrist)}
    return poses


def shot_frames(count: int = 10, frames: int = 200) -> dict[float, dict]:
    shot = rigs.shot_poses(frames)
    picks = np.linspace(7, frames - 7, count).round()
    return {float(i + 1): shot[float(f)] for i, f in enumerate(picks)}


def run(folder: str, repeats: int = REPEATS) -> dict:
    from psdbake import api

    sets = {"single joints": single_poses(), "shot frames": shot_frames()}
    built = {}
    for name, poses in sets.items():
        tag = name.replace(" ", "_")
        sub = os.path.join(folder, tag)
        os.makedirs(sub, exist_ok=True)
        layer = rigs.generate.write_animation(os.path.join(sub, "poses.usda"), poses)
        built[name] = rigs.build(sub, "lbs", SIZE, poses, layer)
    seconds: dict[str, list[float]] = {name: [] for name in sets}
    groups: dict[str, list[str]] = {}
    for name, rig in built.items():  # warm-up
        groups[name] = [m.group for m in api.fit(rig.asset, [rig.examples]).meshes]
    for _ in range(repeats):
        for name, rig in built.items():
            t0 = time.perf_counter()
            api.fit(rig.asset, [rig.examples])
            seconds[name].append(time.perf_counter() - t0)
    medians = {name: statistics.median(s) for name, s in seconds.items()}
    return {"points": built["single joints"].points, "seconds": seconds, "medians": medians, "groups": groups,
            "ratio": medians["shot frames"] / medians["single joints"]}


ABOUT = (
    "Fit time by kind of sculpt, side by side on the 100k-point LBS bench arm: ten single-joint sculpts (five elbow "
    "bends, five wrist twists) against ten frames of a shot where both move, of the same ground truth; default "
    "settings, one worker, the median of three fits each after a warm-up, in one process."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Fit time: single-joint sculpts against shot frames (100k rig).")
    parser.add_argument("--repeats", type=int, default=REPEATS)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--record", default=results.path_of("sculptspeed"), help="where to write the results record")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        report = run(folder, args.repeats)
    if args.json:
        print(json.dumps(report, indent=2, sort_keys=True))
    else:
        for name, m in report["medians"].items():
            print(f"{name}: {m:.2f} s (median of {len(report['seconds'][name])}), groups {', '.join(report['groups'][name])}")
        print(f"shot frames / single joints: {report['ratio']:.2f}")
    rows = [[name, f"{m:.2f}", ", ".join(report["groups"][name])] for name, m in report["medians"].items()]
    rows.append(["shot frames / single joints", f"{report['ratio']:.2f}", ""])
    table = results.table("Fit time by kind of sculpt (100k points, ten sculpts)", ["sculpts", "fit s", "groups"],
                          rows, f"{report['points']} points.")
    results.write("sculptspeed", argv, ABOUT, [table], raw=report, path=args.record)


if __name__ == "__main__":
    main()
