"""A mesh's shading normals as UsdSkel sees them, and UsdSkel's normal skinning as a black box.

What usd-core 26.11 does with normals (``UsdSkel.BakeSkinning``; measured in
tests/test_normals.py, OpenUSD pxr/usd/usdSkel/bakeSkinning.cpp, blendShapeQuery.cpp,
utils.cpp):

* it skins the ``normals`` attribute (``vertex``, ``varying`` and ``faceVarying``), never
  ``primvars:normals``, which, when authored, takes precedence over ``normals`` for
  renderers: baked normals would then never be seen;
* BlendShape ``normalOffsets`` are added at ``pointIndices`` (same length as ``offsets``,
  else UsdSkel warns and drops every shape's normal offsets), then normalised, before
  skinning; they are ignored for ``faceVarying`` normals and when no normals are authored;
* skinning is ``UsdSkel.SkinNormals`` (LBS: the weight-blended inverse transposes of the
  joints' 3x3 skinning matrices; DQS: the blended rotation) after the geomBindTransform's
  inverse transpose, normalised, then skeleton -> mesh local space by that transform's
  inverse transpose (so baked normals are not unit length under scaling transforms).

``NormalBlackBox`` calls that very code; only ``normal_maps`` looks at its outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

from ..errors import InputError, where
from ..normals import PER_POINT_INTERPOLATIONS, Topology, check_faces, normal_maps_from_probes
from .inplace import numbers
from .read import Scene


@dataclass(frozen=True)
class MeshShading:
    """What a corrective needs to carry normal offsets for one mesh."""

    topology: Topology | None  # None: not a polygon mesh, or not asked for (read_mesh_shading's normals_only)
    normals: NDArray[np.float64] | None  # authored rest ``normals`` UsdSkel offsets and skins, else None
    interpolation: str | None
    why_not: str  # "" when normals is set, else why no normalOffsets should be written


def read_mesh_shading(prim: Usd.Prim, label: str = "", *, normals_only: bool = False) -> MeshShading:
    """Topology and authored rest normals of a mesh (default time), read-only, the faces checked.
    normals_only: the topology only for a mesh with normals to offset (None for the others, whose
    faces are checked in place: fit reads every mesh's, and the int64 copies of a 100k-point
    mesh's faces cost more than the check)."""
    path = str(prim.GetPath())
    if not prim.IsA(UsdGeom.Mesh):
        return MeshShading(None, None, None, "not a Mesh: no faces to compute normals from")
    mesh = UsdGeom.Mesh(prim)
    counts = mesh.GetFaceVertexCountsAttr().Get(Usd.TimeCode.Default())
    indices = mesh.GetFaceVertexIndicesAttr().Get(Usd.TimeCode.Default())
    points = mesh.GetPointsAttr().Get(Usd.TimeCode.Default())
    point_count = len(points) if points is not None else 0

    def read_topology() -> Topology:
        try:
            return Topology(
                np.array(counts if counts is not None else [], dtype=np.int64),
                np.array(indices if indices is not None else [], dtype=np.int64),
                point_count,
                left_handed=mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded,
            )
        except ValueError as exc:
            raise InputError(f"{where(label, path)}: {exc}") from None

    if normals_only:
        try:
            check_faces(numbers(counts, np.int64), numbers(indices, np.int64), point_count)
        except ValueError as exc:
            raise InputError(f"{where(label, path)}: {exc}") from None
    topology = None if normals_only else read_topology()
    if UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals").HasAuthoredValue():
        return MeshShading(topology, None, None, "primvars:normals is authored: UsdSkel skins only the normals attribute, "
                           "and primvars:normals overrides it for renderers")
    attr = mesh.GetNormalsAttr()
    value = attr.Get(Usd.TimeCode.Default()) if attr.HasAuthoredValue() else None
    if value is None or len(value) == 0:
        return MeshShading(topology, None, None, "no authored normals: renderers compute them from the posed points, "
                           "which already carry the correction")
    interpolation = str(mesh.GetNormalsInterpolation())
    if interpolation not in PER_POINT_INTERPOLATIONS:
        return MeshShading(topology, None, interpolation, f"{interpolation} normals: normalOffsets are indexed by point "
                           "and UsdSkel does not apply them")
    normals = np.array(value, dtype=np.float64).reshape(-1, 3)
    if normals.shape[0] != point_count:
        raise InputError(f"{where(label, path, 'normals')}: {normals.shape[0]} {interpolation} normals for "
                         f"{point_count} points")
    if not np.all(np.isfinite(normals)):
        raise InputError(f"{where(label, path, 'normals')}: contains NaN or inf")
    return MeshShading(topology or read_topology(), normals, interpolation, "")


class NormalBlackBox:
    """UsdSkel's normal skinning of one mesh at one time: rest normals (n, 3) -> posed unit
    normals (n, 3) in mesh local space, as ``UsdSkel.BakeSkinning`` writes them (up to
    length). The mesh's own blend shapes are not applied (their ``normalOffsets`` add to
    the rest normals before this map)."""

    def __init__(self, scene: Scene, mesh: str, time: float) -> None:
        self._scene = scene  # queries die with their stage
        self.mesh, self.time, self.label = mesh, float(time), scene.label
        tc = Usd.TimeCode(time)
        query, skel_query = scene.query(mesh)
        xforms = skel_query.ComputeSkinningTransforms(tc)
        if xforms is None:
            raise InputError(f"{where(scene.label, mesh)}: UsdSkel cannot compute skinning transforms at time {time:g}")
        mapper = query.GetJointMapper()  # the mesh's own skel:joints order, as BakeSkinning remaps
        if mapper is not None and not mapper.IsIdentity():
            xforms = mapper.RemapTransforms(xforms, Vt.Matrix4dArray())
        self._method = query.GetSkinningMethod()
        self._joints = Vt.Matrix3dArray([m.ExtractRotationMatrix().GetInverse().GetTranspose() for m in xforms])
        self._bind = query.GetGeomBindTransform(tc).ExtractRotationMatrix().GetInverse().GetTranspose()
        count = scene.point_count(mesh)
        influences = query.ComputeVaryingJointInfluences(count, tc)
        if influences is None:
            raise InputError(f"{where(scene.label, mesh)}: UsdSkel cannot compute joint influences at time {time:g}")
        self._indices, self._weights = influences
        self._per_point = len(self._indices) // max(count, 1)
        skel_to_world = UsdGeom.Xformable(skel_query.GetPrim()).ComputeLocalToWorldTransform(tc)
        mesh_to_world = UsdGeom.Xformable(scene.prim(mesh)).ComputeLocalToWorldTransform(tc)
        to_local: Gf.Matrix4d = skel_to_world * mesh_to_world.GetInverse()
        self._to_local = np.array(to_local.ExtractRotationMatrix().GetInverse().GetTranspose(), dtype=np.float64)

    def __call__(self, normals: NDArray[np.float64]) -> NDArray[np.float64]:
        vt = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32))
        if not UsdSkel.SkinNormals(self._method, self._bind, self._joints, self._indices, self._weights,
                                   self._per_point, vt):
            raise InputError(f"{where(self.label, self.mesh)}: UsdSkel failed to skin normals at time {self.time:g}")
        posed = np.asarray(vt, dtype=np.float64).reshape(-1, 3)
        lin = self._to_local  # element-wise, not BLAS (see blackbox.SkinningBlackBox.skin)
        local = posed[:, 0:1] * lin[0] + posed[:, 1:2] * lin[1] + posed[:, 2:3] * lin[2]
        return local / np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-300)

    def normal_maps(self) -> NDArray[np.float64]:
        """Per-vertex maps M (n, 3, 3), posed ~ rest @ M, from four calls (``normal_maps_from_probes``)."""
        n = self._scene.point_count(self.mesh)
        probes = [self(np.tile(v, (n, 1))) for v in np.vstack([np.eye(3), np.ones(3)])]
        return normal_maps_from_probes(*probes)
