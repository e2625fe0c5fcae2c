"""What a frame costs in Blender: the plain rig, the baked corrected shot and the live rig,
measured side by side in one Blender process.

Runs INSIDE the bpy virtual environment (``make interop`` creates ``.venv-blender``)::

    .venv-blender/bin/python interop/blender_speed.py --frames 1,2,3 -o OUT.json NAME=FILE [NAME=FILE ...]

Each FILE is a USD stack (imported with Blender's USD importer as interop/blender_points.py
imports it) or a .blend (opened with Python auto-run off). Per round, every variant is loaded in
turn into an empty scene, played once to warm up, then played ``--repeat`` times over the shot's
frames with ``scene.frame_set`` (the depsgraph: animation, drivers, armature deform of every
mesh), timed with ``time.perf_counter``. Rounds interleave the variants, so a busy machine slows
them alike; the report gives each variant's per-frame seconds per round and their median.
Loading is not timed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from blender_points import frame_set, import_file, parse_frames  # beside this file; it imports bpy too


def load(path: str) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ext = os.path.splitext(path)[1].lower()
    import_file(path, "blend" if ext == ".blend" else "usd")


def drivers() -> int:
    return sum(len(idblock.animation_data.drivers) for coll in (bpy.data.objects, bpy.data.shape_keys)
               for idblock in coll if idblock.animation_data)


def play(frames: list[float], repeat: int) -> float:
    """Seconds per frame over ``repeat`` passes of the frames."""
    scene = bpy.context.scene
    start = time.perf_counter()
    for _ in range(repeat):
        for f in frames:
            frame_set(scene, f)
    return (time.perf_counter() - start) / (repeat * len(frames))


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", metavar="NAME=FILE")
    parser.add_argument("--frames", required=True, help="comma-separated frames, or A:B")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeat", type=int, default=3, help="passes over the frames per timing")
    parser.add_argument("-o", "--out", required=True, help="output .json")
    args = parser.parse_args(argv)
    frames = parse_frames(args.frames)
    variants = dict(v.split("=", 1) for v in args.variants)
    seconds: dict[str, list[float]] = {name: [] for name in variants}
    counts: dict[str, dict] = {}
    for _ in range(args.rounds):
        for name, path in variants.items():
            load(path)
            play(frames[:2], 1)  # warm-up: first evaluations build the depsgraph and caches
            seconds[name].append(play(frames, args.repeat))
            counts[name] = {"drivers": drivers(), "objects": len(bpy.data.objects),
                            "vertices": sum(len(o.data.vertices) for o in bpy.data.objects if o.type == "MESH")}
    report = {"blender": bpy.app.version_string, "frames": len(frames), "rounds": args.rounds, "repeat": args.repeat,
              "variants": {name: {"file": variants[name], "seconds_per_frame": seconds[name],
                                  "median": statistics.median(seconds[name]), **counts[name]} for name in variants}}
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
