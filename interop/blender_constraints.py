"""Does a bone turned by a constraint drive the live rig's correctives as the same turn keyed
directly? (An animator's IK or Copy Rotation must count, not only the bone's own channels.)

Runs INSIDE the bpy virtual environment (``make interop`` creates ``.venv-blender``)::

    .venv-blender/bin/python interop/blender_constraints.py LIVE.blend -o OUT.json

Opens the rig with Python auto-run off, drops the shot's action, and for every bone the
drivers read and a few turns q (fixed seed): (a) the bone's own rotation set to q; (b) the bone
at rest and a Copy Rotation constraint (world space to the bone's local space) copying an empty
turned by q (outside the rig: no driver reads it, no dependency cycle). Writes the largest
difference of any shape-key value between (a) and (b), and the largest value reached (so a
rig whose drivers ignore the pose cannot pass unnoticed).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys

import bpy
import mathutils


def key_values(key) -> list[float]:
    bpy.context.view_layer.update()
    evaluated = key.evaluated_get(bpy.context.evaluated_depsgraph_get())
    return [kb.value for kb in evaluated.key_blocks]


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file")
    parser.add_argument("-o", "--out", required=True)
    args = parser.parse_args(argv)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=os.path.abspath(args.file), use_scripts=False)
    rng = random.Random(0)
    worst, reached, checked = 0.0, 0.0, []
    handle = bpy.data.objects.new("psdbake_constraint_target", None)
    bpy.context.scene.collection.objects.link(handle)
    handle.rotation_mode = "QUATERNION"
    for key in bpy.data.shape_keys:
        if not key.animation_data:
            continue
        bones = sorted({(v.targets[0].id.name, v.targets[0].bone_target) for fc in key.animation_data.drivers
                        for v in fc.driver.variables if v.type == "TRANSFORMS"})
        for arm_name, bone in bones:
            arm = bpy.data.objects[arm_name]
            if arm.animation_data:
                arm.animation_data.action = None
            for _ in range(3):
                axis = mathutils.Vector([rng.uniform(-1, 1) for _ in range(3)]).normalized()
                q = mathutils.Quaternion(axis, rng.uniform(0.2, 2.5))
                for pb in arm.pose.bones:
                    pb.rotation_mode = "QUATERNION"
                    pb.rotation_quaternion = (1.0, 0.0, 0.0, 0.0)
                arm.pose.bones[bone].rotation_quaternion = q
                direct = key_values(key)
                arm.pose.bones[bone].rotation_quaternion = (1.0, 0.0, 0.0, 0.0)
                handle.rotation_quaternion = q
                c = arm.pose.bones[bone].constraints.new("COPY_ROTATION")
                c.target, c.target_space, c.owner_space = handle, "WORLD", "LOCAL"
                constrained = key_values(key)
                arm.pose.bones[bone].constraints.remove(c)
                worst = max(worst, max(abs(a - b) for a, b in zip(direct, constrained, strict=True)))
                reached = max(reached, max(direct))
            checked.append(bone)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump({"blender": bpy.app.version_string, "bones": checked, "turns_per_bone": 3,
                   "max_abs_dw": worst, "max_value": reached}, fh)


if __name__ == "__main__":
    main(sys.argv[1:])
