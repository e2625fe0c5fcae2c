"""What ``export-gltf`` needs from the composed stack, as plain numpy (no glTF here).

Why this shape: glTF skins with v_world = sum_j w_j (jointWorld_j . inverseBind_j) v_mesh
and ignores the skinned mesh node's own transform, while UsdSkel skins
p . geomBind . bind_j^-1 . joint_j (skeleton space) and then places the skeleton in the
world. So the glTF mesh holds the rest points *through geomBindTransform* (skeleton bind
space), the inverse bind matrices are the Skeleton's ``bindTransforms`` inverted, and the
joints hang under a node carrying the Skeleton prim's world transform: the skinned glTF
point is then exactly ``UsdSkel.BakeSkinning``'s world-space point. Blend shapes act
before skinning in the mesh's rest space, so their offsets go through geomBindTransform's
linear part too. Inbetweens are UsdSkel sub-shapes: each becomes a morph target whose
per-frame weight UsdSkel itself computes (``BlendShapeQuery.ComputeSubShapeWeights``), so
the piecewise-linear inbetween blend is reproduced exactly.

Every matrix here is column-vector (glTF's convention, v' = M v): USD's row-vector
matrices are transposed on the way out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

from ..errors import InputError, where
from ..normals import Topology, vertex_normals
from .normalbox import read_mesh_shading
from .read import Scene, matrices

#: (channels, times (f,), weights (f, c)) of one SkelAnimation, keyed by its path: what
#: ``api.evaluate`` computed (AnimWeights), matched to each mesh's channels by name.
ChannelWeights = Mapping[str, tuple[Sequence[str], NDArray[np.float64], NDArray[np.float64]]]


@dataclass(frozen=True)
class SkeletonSource:
    """One Skeleton: its joint tree, bind pose and pose per frame."""

    path: str
    joints: tuple[str, ...]  # UsdSkel joint paths, skeleton order
    parents: NDArray[np.int64]  # (j,) parent index, -1 for a root joint
    bind: NDArray[np.float64]  # (j, 4, 4) skeleton-space bindTransforms
    times: NDArray[np.float64]  # (f,) time codes of the animation (empty: not animated)
    to_world: NDArray[np.float64]  # (max(f, 1), 4, 4) the Skeleton prim's local-to-world per frame
    local: NDArray[np.float64]  # (max(f, 1), j, 4, 4) joint local transforms per frame (UsdSkel's)
    animation: str | None  # the bound SkelAnimation's path


@dataclass(frozen=True)
class MorphTarget:
    """One UsdSkel sub-shape (a BlendShape's offsets, or one of its inbetweens)."""

    name: str  # the channel, or ``channel:inbetween``
    indices: NDArray[np.int64]  # (k,) sorted points it moves
    offsets: NDArray[np.float64]  # (k, 3) in the glTF mesh's space (skeleton bind space)
    normal_indices: NDArray[np.int64]  # (m,) sorted points whose normal it turns
    normal_offsets: NDArray[np.float64]  # (m, 3)


@dataclass(frozen=True)
class MeshSource:
    """One skinned prim as glTF wants it: bind-space points, triangles, influences, shapes."""

    path: str
    skeleton: str  # SkeletonSource.path
    points: NDArray[np.float64]  # (n, 3) rest points through geomBindTransform
    triangles: NDArray[np.int64] | None  # (t, 3) counter-clockwise; None: not a Mesh (drawn as points)
    normals: NDArray[np.float64] | None  # (n, 3) unit, bind space
    skin_joints: NDArray[np.int64]  # (s,) skeleton joint index of each skin joint (the mesh's skel:joints order)
    joint_indices: NDArray[np.int64]  # (n, k) index into skin_joints
    joint_weights: NDArray[np.float64]  # (n, k) as authored
    skinning_method: str
    targets: tuple[MorphTarget, ...]
    target_weights: NDArray[np.float64]  # (f, len(targets)) per frame of the skeleton's times


@dataclass(frozen=True)
class GltfSource:
    label: str  # the file messages name (CORRECTIVES: the stack's psdbake layer)
    skeletons: tuple[SkeletonSource, ...]
    meshes: tuple[MeshSource, ...]
    fps: float  # timeCodesPerSecond
    meters_per_unit: float
    up_axis: str  # "Y" or "Z"


def read_gltf_source(scene: Scene, asset: str, weights: ChannelWeights) -> GltfSource:
    """Everything the glTF export needs from a composed ASSET + CORRECTIVES + ANIM stage
    (units and up axis: the asset's own; times: the composed stage's time codes)."""
    infos = scene.skinned_meshes()
    skeletons: dict[str, SkeletonSource] = {}
    meshes = []
    for info in infos:
        scene.require_not_instanced(info.path)
        if info.skeleton not in skeletons:
            skeletons[info.skeleton] = _skeleton(scene, info.path, weights)
        meshes.append(_mesh(scene, info.path, skeletons[info.skeleton], weights))
    own = Usd.Stage.Open(Sdf.Layer.FindOrOpen(asset), Usd.Stage.LoadNone)  # the composed root authors no metadata
    meters = float(UsdGeom.GetStageMetersPerUnit(own))
    if not (np.isfinite(meters) and meters > 0):
        raise InputError(f"{asset}: metersPerUnit {meters!r} is not a positive number")
    fps = float(scene.stage.GetTimeCodesPerSecond())
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"{scene.label}: timeCodesPerSecond {fps!r} is not a positive number")
    return GltfSource(scene.label, tuple(skeletons[k] for k in sorted(skeletons)), tuple(meshes), fps, meters,
                      str(UsdGeom.GetStageUpAxis(own)))


def _column(m) -> NDArray[np.float64]:
    """USD row-vector matrices -> column-vector (..., 4, 4)."""
    return np.swapaxes(matrices(m), -1, -2)


def _skeleton(scene: Scene, mesh: str, weights: ChannelWeights) -> SkeletonSource:
    _, skel_query = scene.query(mesh)
    skel = skel_query.GetSkeleton()
    path = str(skel.GetPrim().GetPath())
    anim = scene.animation_prim(mesh)
    if anim is not None and anim in weights:
        times = np.asarray(weights[anim][1], dtype=np.float64)
    else:
        times = np.asarray(scene.animation_times(mesh), dtype=np.float64)
    joints = tuple(str(j) for j in skel_query.GetJointOrder())
    bind = _column(skel.GetBindTransformsAttr().Get() or [])
    if len(bind) != len(joints):
        raise InputError(f"{where(scene.label, path, 'bindTransforms')}: {len(bind)} matrices for {len(joints)} joints")
    sampled = [float(t) for t in times] or [_first_time(scene)]
    local = np.stack([_column(scene.joint_local_transforms(mesh, t)) for t in sampled])
    xformable = UsdGeom.Xformable(skel.GetPrim())
    to_world = np.stack([_column([xformable.ComputeLocalToWorldTransform(Usd.TimeCode(t))])[0] for t in sampled])
    for name, values in (("joint transforms", local), ("world transform", to_world)):
        if not np.all(np.isfinite(values)):
            raise InputError(f"{where(scene.label, path)}: its {name} are not finite (NaN or inf) at some frame")
    parents = np.array(skel_query.GetTopology().GetParentIndices(), dtype=np.int64)
    return SkeletonSource(path, joints, parents, bind, times, to_world, local, anim)


def _first_time(scene: Scene) -> float:
    """Where an unanimated skeleton is posed: the stage's start (its pose never changes)."""
    start = scene.stage.GetStartTimeCode()
    return float(start) if np.isfinite(start) else 0.0


def _mesh(scene: Scene, path: str, skeleton: SkeletonSource, weights: ChannelWeights) -> MeshSource:
    query, _ = scene.query(path)
    prim = scene.prim(path)
    rest = scene.rest_points(path)
    n = len(rest)
    if n == 0:
        raise InputError(f"{where(scene.label, path, 'points')}: no points: nothing to export")
    geom_bind = _column([query.GetGeomBindTransform()])[0]
    linear = geom_bind[:3, :3]
    points = rest @ linear.T + geom_bind[:3, 3]
    influences = query.ComputeVaryingJointInfluences(n)
    if influences is None:
        raise InputError(f"{where(scene.label, path)}: UsdSkel cannot compute its joint influences")
    k = len(influences[0]) // max(n, 1)
    joint_indices = np.array(influences[0], dtype=np.int64).reshape(n, k)
    joint_weights = np.array(influences[1], dtype=np.float64).reshape(n, k)
    order = query.GetJointOrder()
    index = {j: i for i, j in enumerate(skeleton.joints)}
    skin_joints = np.array([index[str(j)] for j in order] if order else range(len(skeleton.joints)), dtype=np.int64)
    if joint_indices.size and (joint_indices.min() < 0 or joint_indices.max() >= len(skin_joints)):
        raise InputError(f"{where(scene.label, path, 'primvars:skel:jointIndices')}: an index is out of range for "
                         f"{len(skin_joints)} joints")
    shading = read_mesh_shading(prim, scene.label)
    topology = shading.topology
    triangles = None
    normals = None
    normal_map = np.linalg.inv(linear).T  # how UsdSkel carries normals through geomBindTransform
    if topology is not None:
        holes = set(int(h) for h in (UsdGeom.Mesh(prim).GetHoleIndicesAttr().Get() or []))
        tris = topology.triangles
        if holes:
            tris = tris[[int(f) not in holes for f in topology._triangle_face]]
        triangles = (tris[:, ::-1] if topology.left_handed else tris) if len(tris) else None  # no faces: points
        if shading.normals is not None:
            normals = _unit(shading.normals @ normal_map.T)
        else:
            normals = _unit(vertex_normals(points, topology))
    targets, target_weights = _targets(scene, path, points, linear, normal_map, topology, shading.normals is not None,
                                       skeleton, weights)
    return MeshSource(path, skeleton.path, points, triangles, normals, skin_joints, joint_indices, joint_weights,
                      str(query.GetSkinningMethod()), targets, target_weights)


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit rows; a zero row (a point no face uses) gets +Z, since glTF normals must be unit."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    out = np.where(length > 0, v / np.where(length > 0, length, 1.0), 0.0)
    out[length[:, 0] == 0] = (0.0, 0.0, 1.0)
    return out


def _targets(scene: Scene, path: str, points: NDArray[np.float64], linear: NDArray[np.float64],
             normal_map: NDArray[np.float64], topology: Topology | None, authored_normals: bool,
             skeleton: SkeletonSource, weights: ChannelWeights) -> tuple[tuple[MorphTarget, ...], NDArray[np.float64]]:
    """Every sub-shape with offsets, and its weight per frame (UsdSkel's own sub-shape weights)."""
    query, _ = scene.query(path)
    frames = max(len(skeleton.times), 1)
    if not query.HasBlendShapes():
        return (), np.zeros((frames, 0))
    channels = [str(c) for c in query.GetBlendShapeOrder()]
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(scene.prim(path)))
    if shapes.GetNumBlendShapes() != len(channels):
        raise InputError(f"{where(scene.label, path, 'skel:blendShapeTargets')}: {shapes.GetNumBlendShapes()} valid "
                         f"BlendShape targets for {len(channels)} skel:blendShapes")
    point_indices = shapes.ComputeBlendShapePointIndices()
    sub_offsets = shapes.ComputeSubShapePointOffsets()
    n = len(points)
    targets, subs = [], []
    for s in range(shapes.GetNumSubShapes()):
        b = int(shapes.GetBlendShapeIndex(s))
        inbetween = shapes.GetInbetween(s)
        offsets = np.array(sub_offsets[s], dtype=np.float64).reshape(-1, 3)
        is_primary = not inbetween and (s + 1 == shapes.GetNumSubShapes() or int(shapes.GetBlendShapeIndex(s + 1)) != b)
        if not inbetween and not is_primary:
            continue  # the null shape at weight 0
        indices = np.array(point_indices[b], dtype=np.int64) if len(point_indices[b]) else np.arange(n)
        shape_prim = shapes.GetBlendShape(b)
        label = where(scene.label, str(shape_prim.GetPrim().GetPath()), "offsets")
        if len(offsets) != len(indices) or (indices.size and (indices.min() < 0 or indices.max() >= n)) \
                or len(np.unique(indices)) != len(indices):
            raise InputError(f"{label}: {len(offsets)} offsets for {len(indices)} point indices (each once, of {n} "
                             "points) expected")
        if not np.all(np.isfinite(offsets)):
            raise InputError(f"{label}: contains NaN or inf")
        offsets = offsets @ linear.T
        order = np.argsort(indices, kind="stable")
        indices, offsets = indices[order], offsets[order]
        raw_normals = inbetween.GetNormalOffsets() if inbetween else shape_prim.GetNormalOffsetsAttr().Get()
        normal_idx, normal_off = _normal_offsets(raw_normals, indices, offsets, points, normal_map, topology,
                                                 authored_normals, order)
        name = channels[b] + (f":{inbetween.GetAttr().GetBaseName()}" if inbetween else "")
        targets.append(MorphTarget(name, indices, offsets, normal_idx, normal_off))
        subs.append(s)
    mesh_weights = _channel_weights(scene, path, channels, skeleton, weights)
    per_frame = np.zeros((frames, shapes.GetNumSubShapes()))
    for f in range(frames):
        values, _, sub_index = shapes.ComputeSubShapeWeights(Vt.FloatArray([float(w) for w in mesh_weights[f]]))
        np.add.at(per_frame[f], np.array(sub_index, dtype=np.int64), np.array(values, dtype=np.float64))
    return tuple(targets), per_frame[:, subs]


def _normal_offsets(raw, indices: NDArray[np.int64], offsets: NDArray[np.float64], points: NDArray[np.float64],
                    normal_map: NDArray[np.float64], topology: Topology | None, authored_normals: bool,
                    order: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """A shape's normal deltas: its authored normalOffsets when the mesh has per-point
    normals (what UsdSkel adds), else the change of the area-weighted normals the shape
    makes (what a renderer deriving normals from the deformed points would see)."""
    empty = (np.zeros(0, dtype=np.int64), np.zeros((0, 3)))
    if topology is None:
        return empty
    if authored_normals:
        if raw is None or len(raw) != len(indices):
            return empty  # UsdSkel applies no normal offsets then
        values = np.array(raw, dtype=np.float64).reshape(-1, 3)[order] @ normal_map.T
        keep = np.any(values != 0, axis=1)
        return indices[keep], values[keep]
    moved = indices[np.any(offsets != 0, axis=1)]
    if moved.size == 0:
        return empty
    ring = topology.ring(moved)
    shaped = points.copy()
    shaped[indices] += offsets
    delta = _unit(vertex_normals(shaped, topology, ring)) - _unit(vertex_normals(points, topology, ring))
    keep = np.linalg.norm(delta, axis=1) > 1e-6  # below a float32 unit normal's noise: no shading change
    return ring[keep], delta[keep]


def _channel_weights(scene: Scene, path: str, channels: Sequence[str], skeleton: SkeletonSource,
                     weights: ChannelWeights) -> NDArray[np.float64]:
    """(f, c) weight of each of the mesh's channels per frame, matched by name; 0 when unanimated."""
    frames = max(len(skeleton.times), 1)
    if skeleton.animation is None:
        return np.zeros((frames, len(channels)))
    if skeleton.animation in weights:
        names, _, values = weights[skeleton.animation]
    else:
        names, values = scene.blend_shape_weights(path, skeleton.times)
    column = {c: i for i, c in enumerate(names)}
    out = np.zeros((frames, len(channels)))
    values = np.asarray(values, dtype=np.float64).reshape(len(skeleton.times), len(names))
    for i, channel in enumerate(channels):
        if channel in column and len(skeleton.times):
            out[:, i] = values[:, column[channel]]
    return out
