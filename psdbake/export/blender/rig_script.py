"""Blender's half of ``psdbake export-blender``: import the character, add the drivers, save.

Run by psdbake, never imported by it (it imports ``bpy`` and nothing of psdbake), in either
form:

    blender --background --factory-startup --python rig_script.py -- PLAN.json
    python-with-bpy rig_script.py PLAN.json

PLAN.json (written by ``psdbake.blender.export``) names the USD stack to import (ASSET +
CORRECTIVES [+ ANIM]), the .blend to save, and per corrected mesh its skeleton's joints with
their bind transforms and the drivers to add (``graph.Driver``: target, expression and what
each variable reads). The script:

1. starts from factory settings and imports the stack with Blender's own USD importer and
   its defaults plus skeletons and blend shapes, as ``make interop`` checks it;
2. finds each mesh's object (its prim's name, point count, a shape key per channel) and the
   armature deforming it, and maps every joint to its bone (skeleton order, the joint's name),
   checking that the bone rests at the joint's bind transform: the drivers read a bone's
   rotation away from its rest pose as the joint's rotation away from its bind pose;
3. adds the drivers to the mesh's shape-key datablock (nodes as its custom properties), each
   a simple expression (checked: ``is_simple_expression``, valid after one evaluation);
4. saves the .blend, and writes REPORT (JSON) with what it made, or the error.

Any failure is reported as ``{"error": "..."}`` in REPORT and a non-zero exit.
"""

from __future__ import annotations

import json
import math
import sys
import time
import traceback

import bpy

#: A bone's rest must sit at its joint's bind transform within these (the importer converts
#: bindTransforms to float32 matrices: measured up to 2.6e-7 rad on CesiumMan).
REST_ROTATION_ATOL = 1e-5  # radians
REST_POSITION_RTOL = 1e-5  # of the skeleton's extent


class RigError(Exception):
    """Something in the imported scene is not what the plan expects."""


def strip_suffix(name: str) -> str:
    """Blender's de-duplicated name ``Body.001`` -> ``Body``."""
    head, dot, tail = name.rpartition(".")
    return head if dot and tail.isdigit() and len(tail) == 3 else name


def blender_name(name: str) -> str:
    """A name as Blender keeps it: at most 63 bytes (psdbake's channel names fit; a pre-v4
    layer's psd:shapes might not, and the importer names their shape keys cut so)."""
    return name.encode()[:63].decode(errors="ignore")


def import_stack(stack: str, options: dict) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    result = bpy.ops.wm.usd_import(filepath=stack, **options)
    if "FINISHED" not in result:
        raise RigError(f"Blender's USD import of {stack} returned {sorted(result)}")


def find_mesh(entry: dict):
    """The imported object of one USD mesh: its prim's name, point count and channels."""
    name = blender_name(entry["path"].rsplit("/", 1)[-1])
    found = [o for o in bpy.data.objects if o.type == "MESH" and strip_suffix(o.name) == name
             and len(o.data.vertices) == entry["points"]]
    keyed = [o for o in found if o.data.shape_keys is not None
             and all(blender_name(c) in o.data.shape_keys.key_blocks for c in entry["channels"])]
    if len(keyed) != 1:
        what = "no" if not found else f"{len(found)}" if not keyed else f"{len(keyed)} matching"
        raise RigError(f"<{entry['path']}>: {what} Blender mesh object(s) named {name!r} with {entry['points']} "
                       f"vertices and a shape key per channel ({len(entry['channels'])}) after the USD import")
    return keyed[0]


def find_armature(obj, entry: dict):
    arms = [m.object for m in obj.modifiers if m.type == "ARMATURE" and m.object is not None]
    if len(arms) != 1:
        raise RigError(f"<{entry['path']}>: Blender object {obj.name!r} has {len(arms)} armature modifiers, not 1")
    return arms[0]


def _angle(a, b) -> float:
    """Angle (radians) between the rotations of two 3x3 matrices (columns normalised)."""
    def unit(m):
        cols = [[m[r][c] for r in range(3)] for c in range(3)]
        cols = [[v / math.sqrt(sum(x * x for x in col)) for v in col] for col in cols]
        return [[cols[c][r] for c in range(3)] for r in range(3)]

    a, b = unit(a), unit(b)
    trace = sum(a[r][c] * b[r][c] for r in range(3) for c in range(3))  # trace(a^T b)
    return math.acos(max(-1.0, min(1.0, (trace - 1.0) / 2.0)))


def map_bones(arm, entry: dict) -> dict[str, str]:
    """joint path -> bone name, checking each bone rests at its joint's bind transform."""
    joints, bind = entry["joints"], entry["bind"]
    bones = list(arm.data.bones)
    by_name: dict[str, list] = {}
    for b in bones:
        by_name.setdefault(strip_suffix(b.name), []).append(b)
    extent = entry["extent"]
    out = {}
    for i, joint in enumerate(joints):
        leaf = blender_name(joint.rsplit("/", 1)[-1])
        bone = bones[i] if i < len(bones) and strip_suffix(bones[i].name) == leaf else None
        if bone is None:
            same = by_name.get(leaf, [])
            if len(same) != 1:
                raise RigError(f"<{entry['skeleton']}>: joint {joint!r} has {len(same)} bones named {leaf!r} in "
                               f"armature {arm.name!r}")
            bone = same[0]
        m = bone.matrix_local
        want = bind[i]
        offset = math.dist([m[r][3] for r in range(3)], [want[r][3] for r in range(3)])
        turn = _angle([[m[r][c] for c in range(3)] for r in range(3)], [[want[r][c] for c in range(3)] for r in range(3)])
        if offset > REST_POSITION_RTOL * extent or turn > REST_ROTATION_ATOL:
            raise RigError(f"<{entry['skeleton']}>: Blender's USD import rests bone {bone.name!r} {offset:.3g} units and "
                           f"{turn:.3g} rad away from joint {joint!r}'s bind transform; psdbake's drivers read a bone's "
                           "rotation from its rest as the joint's rotation from its bind pose")
        out[joint] = bone.name
    return out


def add_drivers(key, arm, bones: dict[str, str], drivers: list[dict]) -> dict:
    """The plan's drivers on the shape-key datablock key; returns counts."""
    esc = bpy.utils.escape_identifier
    for d in drivers:
        if d["kind"] == "node":
            key[d["target"]] = 0.0
            fc = key.driver_add(f'["{esc(d["target"])}"]')
        else:
            fc = key.key_blocks[blender_name(d["target"])].driver_add("value")
        # driver_add gives the F-Curve two Bezier keys, (0, 0) and (1, 1), through which the
        # driver's value is mapped: not the identity (5e-5 comes out as 0, measured in bpy
        # 5.0.1). Without keys or modifiers the value is written as the driver computes it.
        fc.keyframe_points.clear()
        drv = fc.driver
        drv.type = "SCRIPTED"
        for var_name, *source in d["variables"]:
            var = drv.variables.new()
            var.name = var_name
            target = var.targets[0]
            if source[0] == "bone":
                var.type = "TRANSFORMS"
                target.id = arm
                target.bone_target = bones[source[1]]
                target.transform_type = f"ROT_{source[2]}"
                target.rotation_mode = "QUATERNION"
                target.transform_space = "LOCAL_SPACE"
            else:
                var.type = "SINGLE_PROP"
                target.id_type = "KEY"
                target.id = key
                target.data_path = f'["{esc(source[1])}"]'
        drv.expression = d["expression"]
    return {"nodes": sum(d["kind"] == "node" for d in drivers), "channels": sum(d["kind"] == "channel" for d in drivers)}


def check_drivers(key) -> None:
    """Every driver of key simple, valid after an evaluation, with its whole text kept."""
    bpy.context.view_layer.update()
    bpy.context.scene.frame_set(bpy.context.scene.frame_current)
    for fc in key.animation_data.drivers:
        if len(fc.keyframe_points) or len(fc.modifiers):
            raise RigError(f"driver {fc.data_path} maps its value through keys or modifiers")
        d = fc.driver
        if not d.is_simple_expression:
            raise RigError(f"driver {fc.data_path} is not a simple expression: {d.expression}")
        if not d.is_valid:
            raise RigError(f"driver {fc.data_path} is invalid after evaluation: {d.expression}")


def build(plan: dict) -> dict:
    start = time.perf_counter()
    import_stack(plan["stack"], plan["import_options"])
    meshes = []
    for entry in plan["meshes"]:
        obj = find_mesh(entry)
        arm = find_armature(obj, entry)
        bones = map_bones(arm, entry)
        key = obj.data.shape_keys
        counts = add_drivers(key, arm, bones, entry["drivers"])
        check_drivers(key)
        meshes.append({"path": entry["path"], "object": obj.name, "armature": arm.name, **counts})
    bpy.context.preferences.filepaths.save_version = 0  # no OUTPUT.blend1 beside the output
    bpy.context.scene["psdbake"] = plan["made_by"]  # what psdbake reads to know its own earlier output
    bpy.ops.wm.save_as_mainfile(filepath=plan["output"], check_existing=False, compress=False)
    return {"blender": bpy.app.version_string, "meshes": meshes, "seconds": time.perf_counter() - start}


def main(argv: list[str]) -> int:
    args = argv[argv.index("--") + 1:] if "--" in argv else argv[1:]
    with open(args[0], encoding="utf-8") as fh:
        plan = json.load(fh)
    try:
        report = build(plan)
        code = 0
    except RigError as exc:
        report, code = {"error": str(exc)}, 3
    except Exception as exc:  # any failure inside Blender goes back to psdbake as a report
        report, code = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}, 1
    with open(plan["report"], "w", encoding="utf-8") as fh:
        json.dump(report, fh)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
