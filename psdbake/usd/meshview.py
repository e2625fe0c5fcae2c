"""What ``psdbake compare``'s report needs from USD beyond the comparison, as plain numpy data.

The report draws faces, places the mesh in the world, and asks which bone carries each
vertex; it reads those here so that ``psdbake.report`` never touches ``pxr``. Matrices
keep Gf's row-vector convention (``p' = p · M``), as everywhere in psdbake.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Usd, UsdGeom, UsdSkel

from ..model import posespace
from .compose import open_layer
from .read import Scene

#: customLayerData key an input layer may carry to be credited on the report page
#: (e.g. ``customLayerData = {string attribution = "Model: CC-BY 4.0, its author"}``).
ATTRIBUTION_KEY = "attribution"


@dataclass(frozen=True)
class MeshView:
    """Faces, transforms and bones of one compared mesh."""

    triangles: NDArray[np.int64]  # (F, 3) fan-triangulated faces; (0, 3) when the prim has none
    to_world: NDArray[np.float64]  # (f, 4, 4) row-vector local-to-world per compared frame
    up: str  # stage up axis, "Y" or "Z"
    joints: tuple[str, ...]  # skeleton joint order
    dominant: NDArray[np.int64]  # (n,) skeleton joint with the largest skinning weight per point
    joint_rotations: NDArray[np.float64]  # (f, joints, 4) skeleton-space rotations (scipy quats)
    mesh_to_skel: NDArray[np.float64]  # (f, 3, 3) row-vector linear map, mesh-local -> skeleton space
    handed: float  # +1 when right-handed face winding gives outward normals in the plot frame, else -1


def read_mesh_view(files: Sequence[str], label: str, mesh: str, times: NDArray[np.float64], point_count: int
                   ) -> MeshView:
    """Compose files (strongest first) and read mesh's faces, world and skeleton transforms
    at times, and the joint that carries each of its point_count points."""
    scene = Scene(list(files), label=label)
    prim = scene.prim(mesh)
    skin, skel = scene.query(mesh)
    to_world = _world(prim, times)
    skel_world = _world(skel.GetSkeleton().GetPrim(), times)
    mesh_to_skel = (to_world @ np.linalg.inv(skel_world))[:, :3, :3]
    joints = tuple(str(j) for j in skel.GetJointOrder())
    quats = np.empty((len(times), len(joints), 4))
    for i, t in enumerate(times):
        mats = np.array([np.array(x) for x in skel.ComputeJointSkelTransforms(Usd.TimeCode(float(t)))])
        quats[i] = posespace.rotations(mats).as_quat()
    up = str(UsdGeom.GetStageUpAxis(scene.stage))
    handed = -1.0 if _orientation(prim) == "leftHanded" else 1.0
    if len(to_world) and np.linalg.det(to_world[0][:3, :3]) < 0:
        handed = -handed
    return MeshView(_triangles(prim, point_count), to_world, "Z" if up == "Z" else "Y", joints,
                    _dominant_joints(skin, joints, point_count), quats, mesh_to_skel, handed)


def layer_attribution(paths: Sequence[str]) -> tuple[str, ...]:
    """The ``attribution`` strings the given layers carry in their customLayerData, in
    order, each once: credit for a model comes from the files, not from psdbake."""
    out: list[str] = []
    for path in paths:
        value = open_layer(path).customLayerData.get(ATTRIBUTION_KEY)
        if isinstance(value, str) and value.strip() and value.strip() not in out:
            out.append(value.strip())
    return tuple(out)


def _world(prim: Usd.Prim, times: NDArray[np.float64]) -> NDArray[np.float64]:
    xform = UsdGeom.Xformable(prim)
    return np.array([np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode(float(t)))) for t in times])


def _triangles(prim: Usd.Prim, n: int) -> NDArray[np.int64]:
    """Fan-triangulated faces of a Mesh; none for other prims or inconsistent topology
    (the report then draws points)."""
    tris = np.zeros((0, 3), dtype=np.int64)
    if not prim.IsA(UsdGeom.Mesh):
        return tris
    mesh = UsdGeom.Mesh(prim)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if counts.sum() == len(indices) and (len(indices) == 0 or (indices.min() >= 0 and indices.max() < n)):
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        rows = [np.stack([indices[s] * np.ones(c - 2, dtype=np.int64), indices[s + 1:s + c - 1], indices[s + 2:s + c]], 1)
                for s, c in zip(starts, counts, strict=True) if c >= 3]
        if rows:
            tris = np.concatenate(rows)
    return tris


def _dominant_joints(skin: UsdSkel.SkinningQuery, joints: tuple[str, ...], n: int) -> NDArray[np.int64]:
    """Per point, the skeleton joint with the largest skinning weight (-1: none)."""
    order = skin.GetJointOrder()
    remap = np.array([joints.index(str(j)) if str(j) in joints else -1 for j in order]) if order else np.arange(len(joints))
    dominant = np.full(n, -1, dtype=np.int64)
    influences = skin.ComputeJointInfluences()
    if influences:
        k = max(skin.GetNumInfluencesPerComponent(), 1)
        idx = np.array(influences[0], dtype=np.int64).reshape(-1, k)
        w = np.array(influences[1], dtype=np.float64).reshape(-1, k)
        best = idx[np.arange(len(idx)), np.argmax(w, axis=1)]
        best = np.where((best >= 0) & (best < len(remap)), remap[np.clip(best, 0, len(remap) - 1)], -1)
        dominant[:] = best[0] if len(best) == 1 else best[:n]
    return dominant


def _orientation(prim: Usd.Prim) -> str:
    return str(UsdGeom.Mesh(prim).GetOrientationAttr().Get()) if prim.IsA(UsdGeom.Mesh) else "rightHanded"
