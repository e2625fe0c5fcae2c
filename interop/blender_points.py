"""Blender's view of a file: import it with Blender's default importer and record, per frame, every
mesh object's evaluated vertices in world space and its shape keys' values.

Runs INSIDE the bpy virtual environment (``make interop`` creates ``.venv-blender``)::

    .venv-blender/bin/python interop/blender_points.py FILE --frames 1,2,3 -o OUT.npz [--importer usd|gltf|blend]

FILE is a USD stack (.usd/.usda/.usdc/.usdz: ``bpy.ops.wm.usd_import`` with its defaults plus
``import_skeletons`` and ``import_blendshapes``, what a rigger ticks for a skinned character),
a .glb/.gltf (``bpy.ops.import_scene.gltf`` with its defaults), or a .blend (``psdbake
export-blender``'s live rig), opened as a user opens a file with Blender's defaults: Python
auto-run off (``open_mainfile(use_scripts=False)`` after factory settings, whose preference is
off too). Nothing is changed after the import or open: no slider ranges, no modifiers, no
transforms. The scene starts empty (``read_factory_settings(use_empty=True)``).

OUT.npz holds ``meta`` (a JSON string: Blender version, importer and every operator option as
used, scene frame range and fps, frames, and one entry per object: name, type, data name, parent
chain, modifiers, custom properties, shape keys with slider ranges) and, for mesh object ``i``
(its index in ``meta["objects"]``):

- ``rest_i``   (n, 3) the mesh data's own vertices (object space, the basis shape) as imported;
- ``world_i``  (F, n, 3) the evaluated mesh's vertices (shape keys, modifiers) times ``matrix_world``;
- ``keys_i``   (F, K) each shape key's value as Blender applies it (after clamping to its slider range);
- ``curves_i`` (F, K) each shape key's animation curve evaluated at the frame (what the file asked
  for, before clamping; NaN where a key has no curve);

and, for every object ``j``, ``matrix_j`` (F, 4, 4) its ``matrix_world`` per frame. For a .blend,
``meta["drivers"]`` also says how its drivers ran: how many, how many are simple expressions and
valid, and whether Blender blocked any Python (``bpy.app.autoexec_fail``) while sampling.
Blender's conversions are not undone here: the caller compares in a common frame.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import bpy
import numpy as np

USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")
GLTF_EXTENSIONS = (".glb", ".gltf")
BLEND_EXTENSIONS = (".blend",)
# The only USD importer options set: a rigger's ticks for a skinned character (both are on by
# default in Blender 5.0 too; set explicitly so a changed default cannot drop them silently).
USD_OPTIONS = {"import_skeletons": True, "import_blendshapes": True}


def operator_options(op, overrides: dict) -> dict:
    """Every option of an import operator as it is used: the operator's default, or the override."""
    options = {}
    for prop in op.get_rna_type().properties:
        name = prop.identifier
        if name in ("rna_type", "filepath", "directory", "files") or name.startswith("filter_"):
            continue
        if prop.type == "ENUM":
            value = sorted(prop.default_flag) if prop.is_enum_flag else prop.default
        elif getattr(prop, "is_array", False):
            value = list(prop.default_array)
        elif prop.type in ("POINTER", "COLLECTION"):
            continue
        else:
            value = prop.default
        options[name] = overrides.get(name, value)
    return options


def open_blend(path: str) -> dict:
    """Open a .blend as a user does with Blender's defaults: Python auto-run off."""
    if bpy.context.preferences.filepaths.use_scripts_auto_execute:
        raise SystemExit("blender_points: factory settings have Python auto-run on; expected off")
    bpy.ops.wm.open_mainfile(filepath=os.path.abspath(path), use_scripts=False)
    return {"use_scripts": False, "use_scripts_auto_execute": bpy.context.preferences.filepaths.use_scripts_auto_execute}


def driver_facts() -> dict:
    """Every driver of every datablock: counts, simple expressions, validity, blocked Python."""
    drivers = [fc.driver for coll in (bpy.data.objects, bpy.data.shape_keys, bpy.data.meshes, bpy.data.armatures)
               for idblock in coll if idblock.animation_data for fc in idblock.animation_data.drivers]
    return {"drivers": len(drivers), "simple": sum(d.is_simple_expression for d in drivers),
            "valid": sum(d.is_valid for d in drivers), "autoexec_fail": bool(bpy.app.autoexec_fail),
            "autoexec_fail_message": bpy.app.autoexec_fail_message,
            "longest_expression": max((len(d.expression) for d in drivers), default=0)}


def import_file(path: str, importer: str) -> dict:
    """Import path into the (empty) scene; returns the options used."""
    if importer == "blend":
        return open_blend(path)
    if importer == "usd":
        op, overrides = bpy.ops.wm.usd_import, dict(USD_OPTIONS)
    else:
        op, overrides = bpy.ops.import_scene.gltf, {}
    missing = [name for name in overrides if name not in {p.identifier for p in op.get_rna_type().properties}]
    if missing:
        raise SystemExit(f"blender_points: {op.idname_py()} has no option(s) {missing} in Blender {bpy.app.version_string}")
    options = operator_options(op, overrides)
    result = op(filepath=os.path.abspath(path), **overrides)
    if "FINISHED" not in result:
        raise SystemExit(f"blender_points: import of {path} returned {sorted(result)}")
    return options


def parent_chain(obj) -> list[str]:
    chain = []
    while obj is not None:
        chain.append(obj.name)
        obj = obj.parent
    return chain[::-1]


def shape_key_curves(key) -> dict:
    """data path -> F-curve of the shape-key datablock's action (Blender 5 slotted actions)."""
    ad = key.animation_data if key is not None else None
    if ad is None or ad.action is None:
        return {}
    from bpy_extras import anim_utils

    bag = anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot)
    return {fc.data_path: fc for fc in bag.fcurves} if bag is not None else {}


def custom_properties(idblock) -> dict:
    out = {}
    for name in idblock.keys():
        value = idblock[name]
        out[name] = value if isinstance(value, (str, int, float, bool)) else repr(value)
    return out


def describe(objects) -> list[dict]:
    out = []
    for obj in objects:
        entry = {
            "name": obj.name, "type": obj.type, "data": obj.data.name if obj.data is not None else None,
            "parents": parent_chain(obj), "parent_type": obj.parent_type,
            "modifiers": [[m.type, m.name, getattr(getattr(m, "object", None), "name", None)]
                          for m in getattr(obj, "modifiers", [])],
            "properties": custom_properties(obj),
            "matrix_basis": [list(row) for row in obj.matrix_basis],
        }
        if obj.type == "MESH":
            mesh = obj.data
            entry["vertices"] = len(mesh.vertices)
            entry["polygons"] = len(mesh.polygons)
            entry["data_properties"] = custom_properties(mesh)
            entry["vertex_groups"] = [g.name for g in obj.vertex_groups]
            key = mesh.shape_keys
            if key is not None:
                entry["reference_key"] = key.reference_key.name
                entry["shape_keys"] = [{"name": kb.name, "slider_min": kb.slider_min, "slider_max": kb.slider_max,
                                        "mute": kb.mute, "relative_key": kb.relative_key.name}
                                       for kb in key.key_blocks]
                entry["curves"] = sorted(shape_key_curves(key))
            else:
                entry["shape_keys"], entry["curves"] = [], []
        out.append(entry)
    return out


def frame_set(scene, frame: float) -> None:
    whole = math.floor(frame)
    scene.frame_set(int(whole), subframe=float(frame - whole))


def sample(frames: list[float]) -> tuple[dict, list[dict]]:
    scene = bpy.context.scene
    objects = sorted(bpy.data.objects, key=lambda o: o.name)
    meta = describe(objects)
    arrays: dict[str, np.ndarray] = {}
    meshes = [(i, o) for i, o in enumerate(objects) if o.type == "MESH"]
    for i, obj in meshes:
        arrays[f"rest_{i}"] = read_coords(obj.data.vertices)
    worlds: dict[int, list] = {i: [] for i, _ in meshes}
    keys: dict[int, list] = {i: [] for i, _ in meshes}
    curves: dict[int, list] = {i: [] for i, _ in meshes}
    matrices: dict[int, list] = {i: [] for i in range(len(objects))}
    for frame in frames:
        frame_set(scene, frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        for j, obj in enumerate(objects):
            matrices[j].append(np.array(obj.evaluated_get(depsgraph).matrix_world, dtype=np.float64))
        for i, obj in meshes:
            evaluated = obj.evaluated_get(depsgraph)
            mesh = evaluated.to_mesh()
            try:
                local = read_coords(mesh.vertices)
            finally:
                evaluated.to_mesh_clear()
            m = np.array(evaluated.matrix_world, dtype=np.float64)
            worlds[i].append(local @ m[:3, :3].T + m[:3, 3])
            key = obj.data.shape_keys
            if key is None:
                keys[i].append(np.zeros(0))
                curves[i].append(np.zeros(0))
                continue
            fcurves = shape_key_curves(key)
            ekey = key.evaluated_get(depsgraph)
            keys[i].append(np.array([kb.value for kb in ekey.key_blocks], dtype=np.float64))
            curves[i].append(np.array([fcurves[p].evaluate(frame) if p in fcurves else np.nan
                                       for p in (f'key_blocks["{kb.name}"].value' for kb in key.key_blocks)],
                                      dtype=np.float64))
    for i, _ in meshes:
        counts = {w.shape[0] for w in worlds[i]}
        if len(counts) != 1:
            meta[i]["evaluated_vertex_counts"] = sorted(counts)
            worlds[i] = [w[: min(counts)] for w in worlds[i]]
        arrays[f"world_{i}"] = np.stack(worlds[i])
        arrays[f"keys_{i}"] = np.stack(keys[i])
        arrays[f"curves_{i}"] = np.stack(curves[i])
        meta[i]["evaluated_vertices"] = int(arrays[f"world_{i}"].shape[1])
    for j in matrices:
        arrays[f"matrix_{j}"] = np.stack(matrices[j])
    return arrays, meta


def read_coords(vertices) -> np.ndarray:
    flat = np.empty(len(vertices) * 3, dtype=np.float32)
    vertices.foreach_get("co", flat)
    return flat.reshape(-1, 3).astype(np.float64)


def parse_frames(text: str) -> list[float]:
    frames: list[float] = []
    for part in text.split(","):
        if ":" in part:
            a, b = part.split(":")
            frames += [float(f) for f in range(int(a), int(b) + 1)]
        elif part:
            frames.append(float(part))
    return frames


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file")
    parser.add_argument("--frames", required=True, help="comma-separated frames, or A:B for every whole frame A..B")
    parser.add_argument("-o", "--out", required=True, help="output .npz")
    parser.add_argument("--importer", choices=("usd", "gltf", "blend"), help="default: from the file's extension")
    args = parser.parse_args(argv)
    ext = os.path.splitext(args.file)[1].lower()
    importer = args.importer or ("gltf" if ext in GLTF_EXTENSIONS else "usd" if ext in USD_EXTENSIONS
                                 else "blend" if ext in BLEND_EXTENSIONS else None)
    if importer is None:
        parser.error(f"cannot tell the importer from {args.file!r}: use --importer")
    frames = parse_frames(args.frames)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    options = import_file(args.file, importer)
    scene = bpy.context.scene
    arrays, objects = sample(frames)
    meta = {
        "blender": bpy.app.version_string, "file": os.path.abspath(args.file), "importer": importer,
        "operator": {"usd": "wm.usd_import", "gltf": "import_scene.gltf", "blend": "wm.open_mainfile"}[importer],
        "options": options,
        "scene": {"frame_start": scene.frame_start, "frame_end": scene.frame_end, "fps": scene.render.fps,
                  "fps_base": scene.render.fps_base, "unit_scale": scene.unit_settings.scale_length},
        "frames": frames, "objects": objects,
    }
    if importer == "blend":
        meta["drivers"] = driver_facts()
    np.savez_compressed(args.out, meta=np.array(json.dumps(meta)), **arrays)


if __name__ == "__main__":
    main(sys.argv[1:])
