"""A skinned mesh's faces and UVs for its OBJ files (``pose --obj-dir``, ``sculpts``).

Why here: the faces are ``faceVertexCounts``/``faceVertexIndices`` and the UVs a primvar,
both USD data; ``psdbake/obj`` gets them as numpy (``MeshFaces``, in OBJ winding). The UVs
are ``primvars:st``, else the first primvar (by name) whose role is texture coordinates,
read through ``UsdGeom.PrimvarsAPI`` with their interpolation and indices: ``vertex`` and
``varying`` give one ``vt`` per point, ``faceVarying`` one per corner, indexed primvars keep
their values and indices. ``constant``/``uniform`` UVs, or UVs that do not fit the mesh,
are left out with a note (the OBJ is for sculpting; its UVs only help the artist).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdGeom

from ..errors import InputError, where
from ..normals import Topology
from ..sculpting.obj.faces import MeshFaces, obj_corner_order


def read_mesh_faces(prim: Usd.Prim, label: str) -> tuple[MeshFaces, str]:
    """(faces and UVs of the prim at its rest topology, a note when UVs were left out)."""
    path = str(prim.GetPath())
    points = UsdGeom.PointBased(prim).GetPointsAttr().Get(Usd.TimeCode.Default())
    n = len(points) if points is not None else 0
    if not prim.IsA(UsdGeom.Mesh):
        empty = np.zeros(0, dtype=np.int64)
        return MeshFaces(n, empty, empty), ""
    mesh = UsdGeom.Mesh(prim)
    counts = mesh.GetFaceVertexCountsAttr().Get(Usd.TimeCode.Default())
    indices = mesh.GetFaceVertexIndicesAttr().Get(Usd.TimeCode.Default())
    try:  # the same checks as the normals' topology: an OBJ face needs 3 corners and real points
        topology = Topology(np.array(counts if counts is not None else [], dtype=np.int64),
                            np.array(indices if indices is not None else [], dtype=np.int64), n)
    except ValueError as exc:
        raise InputError(f"{where(label, path)}: {exc}") from None
    left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    order = obj_corner_order(topology.face_vertex_counts, left)
    uvs, uv_corners, name, note = _uvs(prim, topology, label)
    return MeshFaces(n, topology.face_vertex_counts, topology.face_vertex_indices[order], uvs,
                     uv_corners[order] if uv_corners is not None else None, name, left), note


def _texcoord_primvar(prim: Usd.Prim) -> UsdGeom.Primvar | None:
    api = UsdGeom.PrimvarsAPI(prim)
    st = api.GetPrimvar("st")
    if st and st.HasAuthoredValue():
        return st
    for pv in sorted(api.GetPrimvarsWithAuthoredValues(), key=lambda p: p.GetPrimvarName()):
        if pv.GetTypeName().role == Sdf.ValueRoleNames.TextureCoordinate and pv.GetTypeName().isArray:
            return pv
    return None


def _uvs(prim: Usd.Prim, topology: Topology, label: str
         ) -> tuple[NDArray[np.float32] | None, NDArray[np.int64] | None, str, str]:
    """(vt values, vt index per corner in USD order, primvar name, note)."""
    pv = _texcoord_primvar(prim)
    if pv is None:
        return None, None, "", ""
    name, interpolation = str(pv.GetName()), str(pv.GetInterpolation())
    skip = f"{where(label, str(prim.GetPath()), name)}: OBJs written without UVs"
    value = pv.Get(Usd.TimeCode.Default())
    try:
        values = np.array(value if value is not None else [], dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        return None, None, "", f"{skip}: not two numbers per value"
    if values.size and not np.all(np.isfinite(values)):
        return None, None, "", f"{skip}: NaN or inf values"
    per = {"vertex": topology.point_count, "varying": topology.point_count,
           "faceVarying": int(topology.face_vertex_indices.size)}
    if interpolation not in per:
        return None, None, "", f"{skip}: {interpolation} interpolation has no value per point or corner"
    raw = pv.GetIndices(Usd.TimeCode.Default()) if pv.IsIndexed() else None
    slots = np.array(raw, dtype=np.int64) if raw is not None else np.arange(len(values), dtype=np.int64)
    if len(slots) != per[interpolation] or (slots.size and (slots.min() < 0 or slots.max() >= len(values))):
        return None, None, "", (f"{skip}: {len(slots)} {'indices' if raw is not None else 'values'} for "
                                f"{per[interpolation]} {'corners' if interpolation == 'faceVarying' else 'points'}")
    corners = slots if interpolation == "faceVarying" else slots[topology.face_vertex_indices]
    return values.astype(np.float32), corners, name, ""
