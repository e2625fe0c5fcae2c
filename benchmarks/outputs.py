"""Digests of every output psdbake writes for the demo, the character batch and the bench rigs.

A change that must not change behaviour (a restructuring, a speed-up) is checked by running
this before and after and comparing the two listings, byte for byte::

    python -m benchmarks.outputs OUT_DIR > before.txt   # on the old revision
    python -m benchmarks.outputs OUT_DIR > after.txt    # on the new one
    diff before.txt after.txt                            # empty: every output identical

Each line is ``sha256  relative/path``. The runs are the commands users type (``python -m
psdbake``): the demo's pose / fit / eval --points-cache / stack on the arm, the character's
batch file (three correctives groups, a chunked eval with points caches, a stack), and a fit
plus an eval with a points cache on the 13k bench rig in LBS, dual-quaternion and LBS + the
non-linear bulge deformer. JSON reports are left out (they carry timings).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import subprocess
import sys

from . import rigs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIX = os.path.join(ROOT, "fixtures")


def _psdbake(*args: str, cwd: str = ROOT) -> None:
    subprocess.run([sys.executable, "-m", "psdbake", *args, "-q"], cwd=cwd, check=True, stdout=subprocess.DEVNULL)


def demo(out: str) -> None:
    """The demo's commands on copies of its fixtures inside out (so the stack's relative
    paths do not depend on where the checkout is)."""
    d, inputs = os.path.join(out, "demo"), os.path.join(out, "inputs")
    os.makedirs(d)
    os.makedirs(inputs)
    for name in ("arm_lbs.usda", "arm_anim.usda", "arm_poses.usda", "arm_lbs_examples.usda"):
        shutil.copy(os.path.join(FIX, name), inputs)
    arm, anim = os.path.join(inputs, "arm_lbs.usda"), os.path.join(inputs, "arm_anim.usda")
    _psdbake("pose", arm, "--anim", os.path.join(inputs, "arm_poses.usda"), "-o", os.path.join(d, "to_sculpt.usda"))
    _psdbake("fit", arm, os.path.join(inputs, "arm_lbs_examples.usda"), "-o", os.path.join(d, "correctives.usda"))
    _psdbake("eval", arm, os.path.join(d, "correctives.usda"), "--anim", anim, "-o", os.path.join(d, "weights.usda"),
             "--points-cache", os.path.join(d, "points_cache.usda"))
    _psdbake("stack", arm, os.path.join(d, "correctives.usda"), anim, os.path.join(d, "weights.usda"),
             "-o", os.path.join(d, "shot.usda"))


def character_batch(out: str) -> None:
    """fixtures/batch/character_jobs.toml, run from a copy whose outputs land in out/batch."""
    jobs = os.path.join(out, "jobs")
    os.makedirs(os.path.join(jobs, "batch"))
    shutil.copytree(os.path.join(FIX, "character"), os.path.join(jobs, "character"))
    with open(os.path.join(FIX, "batch", "character_jobs.toml"), encoding="utf-8") as fh:
        text = fh.read().replace("../../out/batch/", "../../batch/")
    path = os.path.join(jobs, "batch", "character_jobs.toml")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    os.makedirs(os.path.join(out, "batch"))
    subprocess.run([sys.executable, "-m", "psdbake", "batch", path, "-q"], cwd=ROOT, check=True)
    shutil.rmtree(jobs)


def bench_rigs(out: str) -> None:
    folder = os.path.join(out, "rigs")
    os.makedirs(folder)
    poses_layer, poses = rigs.write_poses(folder)
    shot = rigs.write_shot(folder, 24)
    for variant in rigs.VARIANTS:
        rig = rigs.build(folder, variant, "13k", poses, poses_layer)
        tag = os.path.splitext(os.path.basename(rig.asset))[0]
        chain = ["--deformer", rigs.DEFORMER_SPEC] if rig.deformers else []
        corr, weights, cache = (os.path.join(folder, f"{tag}_{k}.usda") for k in ("corr", "weights", "cache"))
        _psdbake("fit", rig.asset, rig.examples, "-o", corr, *chain)
        _psdbake("eval", rig.asset, corr, "--anim", shot, "-o", weights, "--points-cache", cache, *chain)


def digests(out: str) -> list[str]:
    lines = []
    for here, _, files in sorted(os.walk(out)):
        for name in sorted(files):
            path = os.path.join(here, name)
            if name.endswith(".json"):
                continue
            with open(path, "rb") as fh:
                lines.append(f"{hashlib.sha256(fh.read()).hexdigest()}  {os.path.relpath(path, out)}")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="an empty or new folder to write into")
    args = parser.parse_args(argv)
    if os.path.exists(args.out) and os.listdir(args.out):
        parser.error(f"{args.out} is not empty")
    os.makedirs(args.out, exist_ok=True)
    demo(args.out)
    character_batch(args.out)
    bench_rigs(args.out)
    print("\n".join(digests(args.out)))


if __name__ == "__main__":
    main()
