"""The sculptor's loop through OBJ, read top to bottom: ``pose --obj-dir`` writes one OBJ per
skinned mesh and pose beside EXAMPLES; ``sculpts`` reads the edited OBJs back into an
EXAMPLES layer ``fit`` reads.

Why OBJ: every sculpting application imports and exports it keeping the vertex order, and
psdbake needs nothing else to put a sculpt back on its mesh. The OBJ holds the mesh exactly
as the EXAMPLES ``points`` sample holds it (mesh local space, float32-exact digits), so an
unedited file reads back bit for bit; every file read back is checked (vertex count,
faces, finite values, near its posed mesh) before anything is written.
"""

from __future__ import annotations

import math
import os
import re
import time as _time
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import __version__
from ..errors import InputError, PsdWarning, SettingError, where
from ..lookup import did_you_mean
from ..outputs import EXAMPLES
from ..results import PoseResult, SculptFile, SculptsResult
from ..usd import write as usdwrite
from ..usd.author import Layer
from ..usd.meshfaces import read_mesh_faces
from ..usd.read import Scene
from ..usd.sculpted import layer_points, sculpted_layer
from .obj.check import check_placement, check_topology, displacement, up_rotation
from .obj.faces import MeshFaces
from .obj.folder import Manifest, ObjEntry, obj_name, read_manifest, sha256_file, time_of_name, unlisted_objs, write_obj_dir
from .obj.read import read_obj
from .obj.text import obj_text

UP_AXES = ("Y", "Z")


def _warn(msg: str, notes: list[str] | None = None) -> None:
    if notes is not None:
        notes.append(msg)
    warnings.warn(msg, PsdWarning, stacklevel=3)


# --- pose --obj-dir: EXAMPLES -> one OBJ per mesh and time code -------------------------------

def obj_files(result: PoseResult) -> list[str]:
    """The OBJ file names ``pose --obj-dir`` writes for result, sorted by mesh and time code."""
    return [obj_name(m, t) for m in sorted(result.meshes) for t in result.times]


def pose_objs(result: PoseResult) -> list[tuple[ObjEntry, str]]:
    """(manifest entry, OBJ text) per mesh and time code: the posed points exactly as the
    EXAMPLES layer holds them, with the asset's faces and UVs."""
    scene = Scene([result.asset])
    posed = layer_points(result.layer)  # PoseResult.layer is the in-memory Sdf.Layer
    out = []
    for mesh in sorted(result.meshes):
        faces, note = read_mesh_faces(scene.prim(mesh), result.asset)
        if note:
            _warn(note)
        for t in result.times:
            pts = posed[(mesh, float(t))]
            comments = [f"psdbake {__version__} pose --obj-dir: <{mesh}> at time code {t:g}, plain-skinned, in the "
                        "mesh's local space",
                        "Sculpt it keeping the vertex order and the faces, save it under the same name, then run "
                        "psdbake sculpts."]
            text = obj_text(pts, faces, mesh.rsplit("/", 1)[-1], comments)
            out.append((ObjEntry(obj_name(mesh, t), mesh, float(t), len(pts), faces.face_count), text))
    return out


def write_pose_objs(result: PoseResult, examples: str, obj_dir: str, inputs: list[str]) -> list[str]:
    """EXAMPLES, the OBJs and the manifest in one commit; returns the OBJ names."""
    objs = pose_objs(result)
    sources = {"asset": result.asset, "poses": result.poses, "examples": examples,
               "asset_sha256": sha256_file(result.asset)}

    def write_examples(tmp: str) -> None:
        usdwrite.export_layer(result.layer, tmp, examples)

    return write_obj_dir(obj_dir, examples, write_examples, EXAMPLES, objs, sources, inputs)


# --- sculpts: DIR's OBJs -> EXAMPLES with the sculpted points ------------------------------

def read_sculpts(asset: str, examples: str, obj_dir: str, *, scale: float | None = None,
                 up_axis: str | None = None, fixes: Mapping[str, Mapping[str, Any]] | None = None) -> SculptsResult:
    """Every OBJ the manifest of obj_dir lists, read and checked against the asset's mesh and
    its posed points in EXAMPLES (``pose``'s layer); --scale and --up-axis applied first, for every
    file or, in ``fixes`` (OBJ file name -> {"scale": S, "up_axis": "Z"}), for one file (an export
    made with other settings than the rest). Every file is checked before any refusal, which
    names each bad file and what is wrong with it."""
    started = _time.perf_counter()
    fixes = dict(fixes or {})
    for value in (scale, *(f.get("scale") for f in fixes.values())):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise SettingError("scale", value, "must be a positive, finite number")
    for value in (up_axis, *(f.get("up_axis") for f in fixes.values())):
        if value is not None and value not in UP_AXES:
            raise SettingError("up_axis", value, "must be Y or Z")
    notes: list[str] = []
    scene = Scene([asset])
    scene.require_skinned()
    skinned = {m.path for m in scene.skinned_meshes()}
    asset_up = str(usdwrite.asset_metadata(asset)["upAxis"])
    posed = layer_points(examples)
    manifest = read_manifest(obj_dir)
    listed = [e.file for e in manifest.entries]
    unknown = sorted(set(fixes) - set(listed))
    if unknown:
        raise SettingError("scale" if "scale" in fixes[unknown[0]] else "up_axis", unknown[0],
                           f"names no OBJ file of {obj_dir}/manifest.json{did_you_mean(unknown[0], listed)}")
    _check_sources(asset, examples, obj_dir, manifest, notes)
    _check_unlisted(obj_dir, manifest, examples, {t for _, t in posed}, notes)
    faces: dict[str, MeshFaces] = {}
    files, refused = [], []
    entries = sorted(manifest.entries, key=lambda e: (e.mesh, e.time))
    for entry in entries:
        fix = fixes.get(entry.file, {})
        try:
            files.append(_read_one(entry, obj_dir, asset, examples, scene, skinned, posed, faces, asset_up,
                                   fix.get("scale", scale), fix.get("up_axis", up_axis)))
        except InputError as exc:
            refused.append((entry, str(exc)))
    if refused:
        raise InputError(_refusal(obj_dir, refused, len(entries)))
    return SculptsResult(asset, examples, obj_dir, tuple(files),
                         tuple([*(f.file for f in files), os.path.join(obj_dir, "manifest.json")]),
                         scale, up_axis, tuple(notes), _time.perf_counter() - started)


def _refusal(obj_dir: str, refused: Sequence[tuple[ObjEntry, str]], total: int) -> str:
    """One line for every refused OBJ: alone, its own message; when every file fails for the
    same reason (an export setting), that reason once, with the flag for all of them."""
    if len(refused) == 1:
        return refused[0][1]
    alone = re.compile(r" \(for this file alone: [^)]*\)$")
    kinds = {re.sub(r"\d[\d.e+-]*", "#", alone.sub("", msg.split(" at time code ", 1)[-1])) for _, msg in refused}
    if len(refused) == total and len(kinds) == 1:  # an export setting of every file: its flag for all of them
        return f"{obj_dir}: all {total} sculpts refused alike, e.g. {alone.sub('', refused[0][1])}"
    return f"{obj_dir}: {len(refused)} of {total} sculpts refused: " + " | ".join(msg for _, msg in refused)


def _read_one(entry: ObjEntry, obj_dir: str, asset: str, examples: str, scene: Scene, skinned: set[str],
              posed: Mapping[tuple[str, float], NDArray[np.float32]], faces: dict[str, MeshFaces], asset_up: str,
              scale: float | None, up_axis: str | None) -> SculptFile:
    """One listed OBJ read back, checked and brought to the asset's units and up axis."""
    path = os.path.join(obj_dir, entry.file)
    label = f"{where(path, entry.mesh)} at time code {entry.time:g}"
    if entry.mesh not in skinned:
        raise InputError(f"{label}: not a skinned mesh of {asset}")
    if (entry.mesh, entry.time) not in posed:
        raise InputError(f"{label}: {examples} has no pose at time code {entry.time:g} (no points sample of the "
                         "mesh there)")
    obj = read_obj(path, label)
    if entry.mesh not in faces:
        faces[entry.mesh] = read_mesh_faces(scene.prim(entry.mesh), asset)[0]
    check_topology(obj, faces[entry.mesh], label)
    target = posed[(entry.mesh, entry.time)].astype(np.float64)
    if target.shape != obj.points.shape:
        raise InputError(f"{where(examples, entry.mesh, 'points')}: time {entry.time:g} has {len(target)} points, "
                         f"the asset's mesh has {faces[entry.mesh].point_count}")
    sculpt = _fixed(obj.points, scale, up_axis, asset_up, label)
    check_placement(sculpt.astype(np.float64), obj.points.astype(np.float64), target, asset_up, label,
                    flags_given=scale is not None or up_axis is not None, file_name=entry.file)
    moved, largest, mean, diag = displacement(sculpt.astype(np.float64), target)
    return SculptFile(path, entry.mesh, entry.time, sculpt, moved, largest, mean, diag,
                      edited=sha256_file(path) != entry.sha256)


def _fixed(points: NDArray[np.float32], scale: float | None, up_axis: str | None, asset_up: str,
           label: str) -> NDArray[np.float32]:
    """The OBJ points in the asset's units and up axis (unchanged, bit for bit, without flags)."""
    if scale is None and (up_axis is None or up_axis == asset_up):
        return points
    fixed = (points.astype(np.float64) @ up_rotation(up_axis or asset_up, asset_up)) * (scale or 1.0)
    if not np.all(np.abs(fixed) <= float(np.finfo(np.float32).max)):
        raise InputError(f"{label}: --scale {scale:g} takes coordinates beyond float32's range")
    return fixed.astype(np.float32)


def _check_sources(asset: str, examples: str, obj_dir: str, manifest: Manifest, notes: list[str]) -> None:
    """Warn when ASSET or EXAMPLES are not the files pose wrote the folder from (their bytes
    differ from the manifest's sha256): the checks below still compare every sculpt with them."""
    for name, path in (("asset", asset), ("examples", examples)):
        recorded = manifest.sources.get(f"{name}_sha256")
        if recorded and os.path.isfile(path) and sha256_file(path) != recorded:
            _warn(f"{path}: not the {name.upper()} file psdbake pose wrote {obj_dir} from (its bytes differ from "
                  "manifest.json's); each sculpt is checked against it all the same", notes)


def _check_unlisted(obj_dir: str, manifest: Manifest, examples: str, posed_times: set[float], notes: list[str]) -> None:
    """An OBJ in the folder that the manifest does not list: refused when its name says a
    time code (a sculpt someone expects to be used), ignored with a warning otherwise."""
    for name in unlisted_objs(obj_dir, manifest):
        path = os.path.join(obj_dir, name)
        t = time_of_name(name)
        if t is None:
            _warn(f"{path}: ignored: not listed in manifest.json (psdbake sculpts reads the files psdbake pose "
                  "listed there)", notes)
        elif t not in posed_times:
            raise InputError(f"{path}: time code {t:g}: {examples} has no pose there (and manifest.json does not list "
                             "the file)")
        else:
            raise InputError(f"{path}: not listed in manifest.json: psdbake sculpts reads only the files psdbake pose "
                             "listed there (a sculpt saved under another mesh's name?)")


def sculpts_layer(result: SculptsResult) -> Layer:
    """SCULPTED_EXAMPLES: EXAMPLES with each file's points sample replaced by its sculpt."""
    return sculpted_layer(result.examples, f"psdbake {__version__} sculpts: psdbake pose's examples with their sculpted points",
                          [(f.mesh, f.time, f.points) for f in result.files])
