"""The glTF 2.0 binary (.glb) of a shot: skinned meshes, joint animation, corrective morph targets.

Why glTF: game engines and Blender read it natively, and it has everything the stack
ASSET + CORRECTIVES + ANIM + WEIGHTS needs at run time: morph targets added before
linear-blend skinning, their weights animated, joints animated by TRS. What UsdSkel
computes in between (the RBF) is baked into those weights, one keyframe per time code.

Layout (``usd.gltf_source`` explains why the glTF then skins exactly as UsdSkel does):
per Skeleton one node carrying the Skeleton prim's world transform (times the
Y-up / meters conversion glTF prescribes), its joints below it; per skinned prim one mesh
node at the scene root (glTF ignores a skinned mesh node's transform) with one skin whose
joints are the prim's own joint order. Accessors are float32 (glTF's only float type);
a morph target is stored sparse whenever that is smaller. The same source gives the same
bytes: no time stamps, no hash-ordered containers.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pygltflib as gl
from numpy.typing import NDArray

from .. import atomic
from ..errors import InputError, where
from ..outputs import GLTF
from ..usd.gltf_source import GltfSource, MeshSource, MorphTarget, SkeletonSource

#: A matrix whose rotation part is off orthonormal by more than this (after taking the
#: scales out) has shear, which glTF's TRS nodes cannot hold.
SHEAR_TOLERANCE = 1e-5

#: Z-up -> Y-up: a -90 degree turn about X (glTF is Y-up; USD may be either).
_Z_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])

_FLOAT, _UBYTE, _USHORT, _UINT = gl.FLOAT, gl.UNSIGNED_BYTE, gl.UNSIGNED_SHORT, gl.UNSIGNED_INT
_COMPONENTS = {gl.SCALAR: 1, gl.VEC3: 3, gl.VEC4: 4, gl.MAT4: 16}
_DTYPES = {_FLOAT: np.float32, _UBYTE: np.uint8, _USHORT: np.uint16, _UINT: np.uint32}


def world_conversion(up_axis: str, meters_per_unit: float) -> NDArray[np.float64]:
    """(4, 4) column-vector map from the stage's world to glTF's (Y up, meters)."""
    axes = _Z_TO_Y_UP if up_axis.upper() == "Z" else np.eye(4)
    return np.diag([meters_per_unit] * 3 + [1.0]) @ axes


@dataclass(frozen=True)
class Glb:
    data: bytes
    morph_targets: int
    sparse_targets: int  # morph target POSITION accessors stored sparse


def build_glb(source: GltfSource, animation_name: str, generator: str) -> Glb:
    """The .glb of source (one glTF animation named animation_name over every skeleton)."""
    builder = _Builder(source, animation_name, generator)
    data = builder.glb()
    return Glb(data, sum(len(m.targets) for m in source.meshes), builder.sparse_targets)


def write_glb(data: bytes, path: str, inputs: Iterable[str] = ()) -> str:
    """Write the .glb atomically (temp file + rename); an input is never overwritten."""
    with atomic.replacing(path, inputs, kind=GLTF) as tmp, open(tmp, "wb") as fh:  # OSError -> OutputError
        fh.write(data)
    return path


def differences(source: GltfSource, label: str) -> list[str]:
    """Warnings: where engines will show something other than UsdSkel (label: the asset)."""
    notes = []
    for mesh in source.meshes:
        at = where(label, mesh.path)
        if mesh.skinning_method != "classicLinear":
            notes.append(f"{at}: skinned with {mesh.skinning_method} in USD; glTF skins linearly, so engines will show "
                         "linear-blend skinning")
        off = int(np.sum(np.abs(mesh.joint_weights.sum(axis=1) - 1.0) > 1e-3))
        if off:
            notes.append(f"{at}: jointWeights of {off} point(s) do not sum to 1: glTF requires it, so they are "
                         "normalised (UsdSkel uses them as they are)")
        if int((mesh.joint_weights > 0).sum(axis=1).max(initial=0)) > 4:
            notes.append(f"{at}: more than 4 joint influences per point: written as several JOINTS_n/WEIGHTS_n sets "
                         "(engines reading only the first set drop the rest)")
    return notes


# --- transforms ----------------------------------------------------------------------------

def decompose(m: NDArray[np.float64], label: str) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Column-vector matrices (..., 4, 4) -> translation (..., 3), rotation quaternion
    (..., 4) as glTF's (x, y, z, w), scale (..., 3), such that M = T . R . S. A negative
    determinant goes into the x scale; shear (not TRS) is refused, naming label."""
    t = m[..., :3, 3]
    linear = m[..., :3, :3]
    s = np.linalg.norm(linear, axis=-2)
    s[..., 0] *= np.where(np.linalg.det(linear) < 0, -1.0, 1.0)
    if np.any(s == 0):
        raise InputError(f"{label}: a zero scale: not representable as a glTF node transform")
    r = linear / s[..., None, :]
    off = np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max(initial=0.0)
    if off > SHEAR_TOLERANCE or np.any(m[..., 3, :3] != 0):
        raise InputError(f"{label}: a transform with shear or projection (off rotation by {off:.2g}): glTF nodes hold "
                         "translation, rotation and scale only")
    return t, _quaternion(r), s


def _quaternion(r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (x, y, z, w), w >= 0 where
    possible (Shepperd's method: the largest of the four candidates is divided by)."""
    m = r.reshape(-1, 3, 3)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = np.stack([trace, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    pick = np.argmax(cand, axis=1)
    q = np.empty((len(m), 4))
    for k in range(4):
        sel = pick == k
        a = m[sel]
        if k == 0:
            w = np.sqrt(1.0 + trace[sel]) * 2
            q[sel] = np.stack([(a[:, 2, 1] - a[:, 1, 2]) / w, (a[:, 0, 2] - a[:, 2, 0]) / w,
                               (a[:, 1, 0] - a[:, 0, 1]) / w, w / 4], axis=1)
        else:
            i, j, m_ = k - 1, k % 3, (k + 1) % 3  # (i, j, m_) cyclic, i the largest diagonal entry
            w = np.sqrt(1.0 + a[:, i, i] - a[:, j, j] - a[:, m_, m_]) * 2
            vals = np.empty((int(sel.sum()), 4))
            vals[:, i] = w / 4
            vals[:, j] = (a[:, j, i] + a[:, i, j]) / w
            vals[:, m_] = (a[:, m_, i] + a[:, i, m_]) / w
            vals[:, 3] = (a[:, m_, j] - a[:, j, m_]) / w
            q[sel] = vals
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(*r.shape[:-2], 4)


def _continuous(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Quaternions (f, ..., 4) with each frame's sign chosen nearest the previous frame's,
    so glTF's slerp between keys takes the short way."""
    if len(q) < 2:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    flips = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    out = q.copy()
    out[1:] *= flips[..., None]
    return out


# --- the document ------------------------------------------------------------------------

class _Builder:
    def __init__(self, source: GltfSource, animation_name: str, generator: str) -> None:
        self.source = source
        self.doc = gl.GLTF2(asset=gl.Asset(generator=generator, version="2.0"))
        self.blob = bytearray()
        self.animation = gl.Animation(name=animation_name)
        self.convert = world_conversion(source.up_axis, source.meters_per_unit)
        # USD's timeline: time code t at t / fps seconds, so frame numbers survive an import
        # (Blender's glTF importer keys second s at frame s * fps); glTF times cannot be
        # negative, so a shot starting before 0 is shifted to start at 0 s
        all_times = [float(t) for s in source.skeletons for t in s.times]
        self.t0 = min(0.0, min(all_times)) if all_times else 0.0
        self.inputs: dict[str, int] = {}  # skeleton -> its key times accessor
        self.joint_nodes: dict[str, list[int]] = {}
        self.skeleton_nodes: dict[str, int] = {}
        self.sparse_targets = 0

    def glb(self) -> bytes:
        roots = [self._skeleton(s) for s in self.source.skeletons]
        roots += [self._mesh(m, i) for i, m in enumerate(self.source.meshes)]
        self.doc.scenes = [gl.Scene(nodes=roots)]
        self.doc.scene = 0
        if self.animation.channels:
            self.doc.animations = [self.animation]
        self.doc.buffers = [gl.Buffer(byteLength=len(self.blob))]
        self.doc.set_binary_blob(bytes(self.blob))
        return b"".join(self.doc.save_to_bytes())

    # -- buffers and accessors --
    def _view(self, data: bytes, target: int | None = None) -> int:
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.doc.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data),
                                                  target=target))
        self.blob += data
        return len(self.doc.bufferViews) - 1

    def _accessor(self, values: NDArray, component: int, kind: str, target: int | None = None,
                  bounds: bool = False) -> int:
        array = np.ascontiguousarray(values, dtype=_DTYPES[component]).reshape(-1, _COMPONENTS[kind])
        accessor = gl.Accessor(bufferView=self._view(array.tobytes(), target), componentType=component,
                               count=len(array), type=kind)
        if bounds:
            accessor.min, accessor.max = _bounds(array)
        self.doc.accessors.append(accessor)
        return len(self.doc.accessors) - 1

    def _vectors(self, indices: NDArray[np.int64], values: NDArray[np.float64], count: int, bounds: bool) -> int:
        """A VEC3 float accessor of count rows, zero except ``values`` at ``indices`` (sorted):
        sparse when that is smaller than dense, no buffer at all when there is nothing."""
        values32 = np.ascontiguousarray(values, dtype=np.float32).reshape(-1, 3)
        accessor = gl.Accessor(componentType=_FLOAT, count=count, type=gl.VEC3, byteOffset=None)
        index_type = _UBYTE if count <= 256 else _USHORT if count <= 65536 else _UINT
        index_size = np.dtype(_DTYPES[index_type]).itemsize
        if len(indices) and len(indices) * (12 + index_size) + 4 < count * 12:
            accessor.sparse = gl.Sparse(
                count=len(indices),
                indices=gl.AccessorSparseIndices(bufferView=self._view(indices.astype(_DTYPES[index_type]).tobytes()),
                                                 componentType=index_type),
                values=gl.AccessorSparseValues(bufferView=self._view(values32.tobytes())),
            )
        elif len(indices):
            dense = np.zeros((count, 3), dtype=np.float32)
            dense[indices] = values32
            accessor.bufferView, accessor.byteOffset = self._view(dense.tobytes(), gl.ARRAY_BUFFER), 0
        if bounds:
            rows = values32 if len(indices) == count else np.vstack([values32, np.zeros((1, 3), np.float32)])
            accessor.min, accessor.max = _bounds(rows)
        self.doc.accessors.append(accessor)
        return len(self.doc.accessors) - 1

    def _node(self, node: gl.Node) -> int:
        self.doc.nodes.append(node)
        return len(self.doc.nodes) - 1

    # -- skeletons and their animation --
    def _skeleton(self, skel: SkeletonSource) -> int:
        label = where(self.source.label, skel.path)
        placed = self.convert @ skel.to_world
        root = self._node(gl.Node(name=skel.path.rsplit("/", 1)[-1], **_trs(placed[0], label)))
        self.skeleton_nodes[skel.path] = root
        leaves = [j.rsplit("/", 1)[-1] for j in skel.joints]
        names = [leaf if leaves.count(leaf) == 1 else joint for leaf, joint in zip(leaves, skel.joints, strict=True)]
        nodes = [self._node(gl.Node(name=name, **_trs(skel.local[0, j], f"{label} joint {skel.joints[j]!r}")))
                 for j, name in enumerate(names)]
        self.joint_nodes[skel.path] = nodes
        for j, parent in enumerate(skel.parents):
            (self.doc.nodes[nodes[parent]] if parent >= 0 else self.doc.nodes[root]).children.append(nodes[j])
        if len(skel.times):
            if np.abs(placed - placed[0]).max() > 0:
                self._animate_trs(skel, root, placed, label)
            for j, node in enumerate(nodes):
                self._animate_trs(skel, node, skel.local[:, j], f"{label} joint {skel.joints[j]!r}")
        return root

    def _input(self, skel: SkeletonSource) -> int:
        if skel.path not in self.inputs:
            seconds = (np.asarray(skel.times, dtype=np.float64) - self.t0) / self.source.fps
            self.inputs[skel.path] = self._accessor(seconds, _FLOAT, gl.SCALAR, bounds=True)
        return self.inputs[skel.path]

    def _sample(self, skel: SkeletonSource, node: int, path: str, values: NDArray, kind: str) -> None:
        sampler = gl.AnimationSampler(input=self._input(skel), interpolation=gl.ANIM_LINEAR,
                                      output=self._accessor(values, _FLOAT, kind))
        self.animation.samplers.append(sampler)
        self.animation.channels.append(gl.AnimationChannel(sampler=len(self.animation.samplers) - 1,
                                                           target=gl.AnimationChannelTarget(node=node, path=path)))

    def _animate_trs(self, skel: SkeletonSource, node: int, matrices: NDArray[np.float64], label: str) -> None:
        t, r, s = decompose(matrices, label)
        self._sample(skel, node, "translation", t, gl.VEC3)
        self._sample(skel, node, "rotation", _continuous(r), gl.VEC4)
        self._sample(skel, node, "scale", s, gl.VEC3)

    # -- meshes --
    def _mesh(self, mesh: MeshSource, index: int) -> int:
        n = len(mesh.points)
        attributes = gl.Attributes(POSITION=self._accessor(mesh.points, _FLOAT, gl.VEC3, gl.ARRAY_BUFFER, bounds=True))
        if mesh.normals is not None:
            attributes.NORMAL = self._accessor(mesh.normals, _FLOAT, gl.VEC3, gl.ARRAY_BUFFER)
        joints, weights = gltf_influences(mesh.joint_indices, mesh.joint_weights)
        joint_type = _UBYTE if len(mesh.skin_joints) <= 256 else _USHORT
        for k in range(joints.shape[1] // 4):
            setattr(attributes, f"JOINTS_{k}",
                    self._accessor(joints[:, 4 * k:4 * k + 4], joint_type, gl.VEC4, gl.ARRAY_BUFFER))
            setattr(attributes, f"WEIGHTS_{k}",
                    self._accessor(weights[:, 4 * k:4 * k + 4], _FLOAT, gl.VEC4, gl.ARRAY_BUFFER))
        primitive = gl.Primitive(attributes=attributes, mode=gl.POINTS if mesh.triangles is None else gl.TRIANGLES)
        if mesh.triangles is not None:
            kind = _USHORT if n < 65535 else _UINT  # 65535 is primitive restart in a ushort index buffer
            primitive.indices = self._accessor(mesh.triangles, kind, gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER)
        primitive.targets = self._targets(mesh.targets, n, mesh.normals is not None)
        name = mesh.path.rsplit("/", 1)[-1]
        gltf_mesh = gl.Mesh(name=name, primitives=[primitive])
        if mesh.targets:
            gltf_mesh.weights = [float(w) for w in mesh.target_weights[0].astype(np.float32)]
            gltf_mesh.extras = {"targetNames": [t.name for t in mesh.targets]}
        self.doc.meshes.append(gltf_mesh)
        node = self._node(gl.Node(name=name, mesh=len(self.doc.meshes) - 1, skin=self._skin(mesh, name),
                                  extras={"usdPath": mesh.path}))
        skel = next(s for s in self.source.skeletons if s.path == mesh.skeleton)
        if mesh.targets and len(skel.times):
            self._sample(skel, node, "weights", mesh.target_weights, gl.SCALAR)
        return node

    def _targets(self, targets: Sequence[MorphTarget], n: int, with_normals: bool) -> list[gl.Attributes]:
        normals = with_normals and any(len(t.normal_indices) for t in targets)
        out = []
        for target in targets:
            attributes = gl.Attributes(POSITION=self._vectors(target.indices, target.offsets, n, bounds=True))
            self.sparse_targets += self.doc.accessors[attributes.POSITION].sparse is not None
            if normals:
                attributes.NORMAL = self._vectors(target.normal_indices, target.normal_offsets, n, bounds=False)
            out.append(attributes)
        return out

    def _skin(self, mesh: MeshSource, name: str) -> int:
        skel = next(s for s in self.source.skeletons if s.path == mesh.skeleton)
        try:
            inverse = np.linalg.inv(skel.bind[mesh.skin_joints])
        except np.linalg.LinAlgError:
            raise InputError(f"{where(self.source.label, skel.path, 'bindTransforms')}: a singular bind matrix") from None
        inverse[:, 3, :] = (0.0, 0.0, 0.0, 1.0)  # affine exactly: glTF requires it of inverse bind matrices
        column_major = np.swapaxes(inverse, -1, -2)
        self.doc.skins.append(gl.Skin(name=name, inverseBindMatrices=self._accessor(column_major, _FLOAT, gl.MAT4),
                                      skeleton=self.skeleton_nodes[skel.path],
                                      joints=[self.joint_nodes[skel.path][j] for j in mesh.skin_joints]))
        return len(self.doc.skins) - 1


def _bounds(array: NDArray) -> tuple[list[float], list[float]]:
    """Per-component min and max, as glTF stores them (exactly the stored values)."""
    lo, hi = array.min(axis=0), array.max(axis=0)
    if array.dtype.kind == "f":
        return [float(v) for v in lo], [float(v) for v in hi]
    return [int(v) for v in lo], [int(v) for v in hi]


def _trs(m: NDArray[np.float64], label: str) -> dict[str, list[float]]:
    t, r, s = decompose(m, label)
    return {"translation": [float(v) for v in t], "rotation": [float(v) for v in r], "scale": [float(v) for v in s]}


def gltf_influences(joints: NDArray[np.int64], weights: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """UsdSkel influences (n, k) -> glTF's (n, 4m): a joint listed twice merged, zero weights
    dropped, the rest sorted by weight (largest first), normalised to sum 1 in float32, and
    padded with (joint 0, weight 0), as glTF requires of JOINTS_n/WEIGHTS_n."""
    n, k = weights.shape
    order = np.argsort(joints, axis=1, kind="stable")
    j = np.take_along_axis(joints, order, axis=1)
    w = np.take_along_axis(weights, order, axis=1).astype(np.float64).copy()
    for c in range(1, k):  # runs of one joint: the run's sum moves to its last entry
        same = j[:, c] == j[:, c - 1]
        w[same, c] += w[same, c - 1]
        w[same, c - 1] = 0.0
    w = np.where(w > 0, w, 0.0)
    order = np.argsort(-w, axis=1, kind="stable")
    j = np.take_along_axis(j, order, axis=1)
    w = np.take_along_axis(w, order, axis=1)
    used = int((w > 0).sum(axis=1).max(initial=0))
    width = 4 * max(1, math.ceil(used / 4))
    if width > k:
        j = np.hstack([j, np.zeros((n, width - k), dtype=j.dtype)])
        w = np.hstack([w, np.zeros((n, width - k))])
    j, w = j[:, :width], w[:, :width]
    total = w.sum(axis=1, keepdims=True)
    w = w / np.where(total > 0, total, 1.0)
    j = np.where(w > 0, j, 0)
    w32 = w.astype(np.float32)
    # float32 rounding can leave the sum a few ulps off 1: the largest weight takes the rest
    w32[:, 0] = (1.0 - w32[:, 1:].astype(np.float64).sum(axis=1)).astype(np.float32)
    w32[total[:, 0] <= 0] = 0.0
    return j, w32
