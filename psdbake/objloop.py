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
import time as _time
import warnings

import numpy as np
from numpy.typing import NDArray

from . import __version__
from .errors import InputError, PsdWarning, SettingError, where
from .obj.check import check_placement, check_topology, displacement, up_rotation
from .obj.faces import MeshFaces
from .obj.folder import (
    Manifest,
    ObjEntry,
    obj_name,
    read_manifest,
    sha256_file,
    time_of_name,
    unlisted_objs,
    write_obj_dir,
)
from .obj.read import read_obj
from .obj.text import obj_text
from .outputs import EXAMPLES
from .results import PoseResult, SculptFile, SculptsResult
from .usd import write as usdwrite
from .usd.author import Layer
from .usd.meshfaces import read_mesh_faces
from .usd.read import Scene
from .usd.sculpted import layer_points, sculpted_layer

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
                 up_axis: str | None = None) -> SculptsResult:
    """Every OBJ the manifest of obj_dir lists, read and checked against the asset's mesh and
    its posed points in EXAMPLES (``pose``'s layer); --scale and --up-axis applied first."""
    started = _time.perf_counter()
    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise SettingError("scale", scale, "must be a positive, finite number")
    if up_axis is not None and up_axis not in UP_AXES:
        raise SettingError("up_axis", up_axis, "must be Y or Z")
    notes: list[str] = []
    scene = Scene([asset])
    scene.require_skinned()
    skinned = {m.path for m in scene.skinned_meshes()}
    asset_up = str(usdwrite.asset_metadata(asset)["upAxis"])
    posed = layer_points(examples)
    manifest = read_manifest(obj_dir)
    _check_sources(asset, examples, obj_dir, manifest, notes)
    _check_unlisted(obj_dir, manifest, examples, {t for _, t in posed}, notes)
    faces: dict[str, MeshFaces] = {}
    files = []
    for entry in sorted(manifest.entries, key=lambda e: (e.mesh, e.time)):
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
                        flags_given=scale is not None or up_axis is not None)
        moved, largest, mean, diag = displacement(sculpt.astype(np.float64), target)
        files.append(SculptFile(path, entry.mesh, entry.time, sculpt, moved, largest, mean, diag,
                                edited=sha256_file(path) != entry.sha256))
    return SculptsResult(asset, examples, obj_dir, tuple(files),
                         tuple([*(f.file for f in files), os.path.join(obj_dir, "manifest.json")]),
                         scale, up_axis, tuple(notes), _time.perf_counter() - started)


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
