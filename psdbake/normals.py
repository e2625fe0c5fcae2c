"""Vertex normals of polygon meshes and the BlendShape ``normalOffsets`` of a corrective.

Why: a mesh that authors ``normals`` is shaded with them, and UsdSkel moves them only
by BlendShape ``normalOffsets`` and skinning, never from the points. Without offsets
the corrected shape is lit like the uncorrected one. ``UsdSkel.BakeSkinning`` adds
``weight * normalOffsets`` at the BlendShape's ``pointIndices`` to the rest normals,
renormalises, then skins them (LBS: the weighted sum of each joint's inverse-transpose
applied to the normal; DQS: the blended rotation), so

* ``normalOffsets`` share ``pointIndices`` with ``offsets`` and have the same length, and
* a sculpt changes the normals of every vertex sharing a face with a sculpted vertex
  (its 1-ring), so ``pointIndices`` grow to that ring, with zero point offsets there.

Which offset: skinned normals are not the normals of the skinned mesh (LBS ignores how
the weights vary over the surface; at a bent elbow they differ by radians). A rest-space
offset (normal of the corrected rest shape minus rest normal) therefore leaves errors
that are not skinning's own. With the example's pose, ``corrective_normals`` instead
inverts UsdSkel's normal skinning: the baked normal becomes the plain-skinned normal
turned by exactly the rotation the sculpt gives the surface normal. The baked normals
then differ from the sculpt's normals by exactly the angle plain skinning already has
at that vertex, with no seam at the ring's edge (see tests/test_normals.py for figures).

Pure numpy, float64, vectorised over the mesh.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Normal interpolations UsdSkel offsets: one normal per point. ``normalOffsets`` are
#: indexed by ``pointIndices``; UsdSkel ignores them for ``faceVarying`` normals (measured
#: with usd-core 26.11) and does not skin ``uniform``/``constant`` ones.
PER_POINT_INTERPOLATIONS = ("vertex", "varying")

#: A ring vertex (not itself sculpted) joins ``pointIndices`` only when its normal turns by
#: more than this (radians): a float32 unit normal carries ~1e-7 of noise, so a smaller
#: turn is no shading change.
RING_ANGLE_ATOL = 1e-6

#: A posed normal map M with |det M| below this fraction of |M|_F^3 is singular (LBS
#: blending opposite rotations: a candy wrapper): it cannot be inverted, and that vertex
#: gets the pose-free rest-space offset. (For a rotation the ratio is 3^-1.5 ~ 0.19.)
NORMAL_MAP_RCOND = 1e-6


def check_faces(counts: NDArray[np.integer], indices: NDArray[np.integer], point_count: int) -> None:
    """Refuse faces a polygon mesh cannot have (ValueError): fewer than 3 corners, counts that
    do not add up to the indices, an index outside the points. Any integer arrays: 1-D views of
    USD's own int32 ones give the same answers as int64 copies (sums are taken in int64)."""
    if counts.size and counts.min() < 3:
        raise ValueError(f"faceVertexCounts: a face has {int(counts.min())} vertices (at least 3 needed)")
    total = int(counts.sum(dtype=np.int64))
    if total != indices.size:
        raise ValueError(f"faceVertexCounts sum to {total}, faceVertexIndices has {indices.size} entries")
    if indices.size and (indices.min() < 0 or indices.max() >= point_count):
        raise ValueError(f"faceVertexIndices: an index is out of range for {point_count} points")


@dataclass(frozen=True)
class Topology:
    """A polygon mesh's connectivity, as UsdGeomMesh stores it."""

    face_vertex_counts: NDArray[np.int64]
    face_vertex_indices: NDArray[np.int64]
    point_count: int
    left_handed: bool = False  # UsdGeomMesh ``orientation = "leftHanded"``

    def __post_init__(self) -> None:
        """Checks the faces (and stores int64 copies); what is derived from them (fan
        triangles, each triangle's and each corner's face) is made on first use: a fit reads
        every mesh's faces to check them, and only meshes with authored normals use the rest."""
        counts = np.asarray(self.face_vertex_counts, dtype=np.int64).reshape(-1)
        indices = np.asarray(self.face_vertex_indices, dtype=np.int64).reshape(-1)
        check_faces(counts, indices, self.point_count)
        object.__setattr__(self, "face_vertex_counts", counts)
        object.__setattr__(self, "face_vertex_indices", indices)

    @functools.cached_property
    def _fan(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(fan triangles (t, 3), the face of each triangle)."""
        counts, indices = self.face_vertex_counts, self.face_vertex_indices
        starts = np.cumsum(counts) - counts
        # Fan triangulation: a face with k vertices v0..v(k-1) gives (v0, vj, vj+1), j = 1..k-2.
        fan = counts - 2
        tri_face = np.repeat(np.arange(counts.size), fan)
        first = starts[tri_face]
        j = np.arange(tri_face.size) - (np.cumsum(fan) - fan)[tri_face] + 1
        tris = np.stack([indices[first], indices[first + j], indices[first + j + 1]], axis=1)
        return tris.reshape(-1, 3), tri_face

    @property
    def _triangle_face(self) -> NDArray[np.int64]:
        """The face of each fan triangle (t,)."""
        return self._fan[1]

    @functools.cached_property
    def _corner_face(self) -> NDArray[np.int64]:
        """The face of each face-vertex (corner), (len(face_vertex_indices),)."""
        return np.repeat(np.arange(self.face_vertex_counts.size), self.face_vertex_counts)

    @property
    def face_count(self) -> int:
        return int(self.face_vertex_counts.size)

    @property
    def triangles(self) -> NDArray[np.int64]:
        """Fan triangles (t, 3) of every face, in face order."""
        return self._fan[0]

    def ring(self, vertices: ArrayLike) -> NDArray[np.int64]:
        """Sorted vertices sharing a face with any of ``vertices`` (those included): exactly
        the vertices whose normal a move of ``vertices`` can change."""
        marked = np.zeros(self.point_count, dtype=bool)
        marked[np.asarray(vertices, dtype=np.int64)] = True
        faces = np.zeros(self.face_count, dtype=bool)
        np.logical_or.at(faces, self._corner_face, marked[self.face_vertex_indices])
        out = marked.copy()
        out[self.face_vertex_indices[faces[self._corner_face]]] = True
        return np.nonzero(out)[0]


def face_area_vectors(points: ArrayLike, topology: Topology, faces: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
    """Per face, its vector area (f, 3): unit normal times area, oriented by ``orientation``
    (only the faces where the mask ``faces`` is true; the others are zero).

    The sum of a polygon's fan-triangle cross products is its vector area whichever vertex
    the fan starts from, for non-planar polygons too, so the result does not depend on how
    a renderer would triangulate.
    """
    p = np.asarray(points, dtype=np.float64)
    t, tri_face = topology.triangles, topology._triangle_face
    if faces is not None:
        keep = faces[tri_face]
        t, tri_face = t[keep], tri_face[keep]
    cross = 0.5 * np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    if topology.left_handed:
        cross = -cross
    return _scatter(tri_face, cross, topology.face_count)


def vertex_normals(points: ArrayLike, topology: Topology, vertices: ArrayLike | None = None) -> NDArray[np.float64]:
    """Unit area-weighted vertex normals (n, 3): every face adds its vector area to each of
    its vertices. Points no face uses (or whose faces have no area) get (0, 0, 0).

    vertices: only these rows, (k, 3), computed from their own faces only (a vertex's normal
    depends on nothing else), for a cost that follows k rather than the mesh.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.shape != (topology.point_count, 3):
        raise ValueError(f"points: expected ({topology.point_count}, 3), got {p.shape}")
    corners = topology.face_vertex_indices
    corner_face = topology._corner_face
    if vertices is None:
        faces = face_area_vectors(p, topology)
        return _unit(_scatter(corners, faces[corner_face], topology.point_count))
    vertices = np.asarray(vertices, dtype=np.int64)
    marked = np.zeros(topology.point_count, dtype=bool)
    marked[vertices] = True
    mine = marked[corners]
    face_mask = np.zeros(topology.face_count, dtype=bool)
    face_mask[corner_face[mine]] = True
    faces = face_area_vectors(p, topology, face_mask)
    return _unit(_scatter(corners[mine], faces[corner_face[mine]], topology.point_count)[vertices])


def _scatter(index: NDArray[np.int64], values: NDArray[np.float64], size: int) -> NDArray[np.float64]:
    """Row sums of values grouped by index, (size, 3); bincount is ~10x faster than np.add.at."""
    return np.stack([np.bincount(index, weights=values[:, k], minlength=size) for k in range(3)], axis=1)


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def angle_between(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """Per-row angle (radians) between direction arrays (n, 3); accurate near 0 and pi."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def rotate_between(a: ArrayLike, b: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """Rotate each v[i] by the smallest rotation taking direction a[i] to direction b[i]
    (Rodrigues). A zero a[i] or b[i] leaves v[i] as it is; opposite a[i], b[i] have no
    smallest rotation, and v[i] becomes b[i] at the length of v[i]."""
    a, b = _unit(np.asarray(a, dtype=np.float64)), _unit(np.asarray(b, dtype=np.float64))
    v = np.asarray(v, dtype=np.float64)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1, keepdims=True)  # sin(angle)
    c = np.sum(a * b, axis=-1, keepdims=True)  # cos(angle)
    k = np.divide(axis, s, out=np.zeros_like(axis), where=s > 0)
    out = v * c + np.cross(k, v) * s + k * np.sum(k * v, axis=-1, keepdims=True) * (1.0 - c)
    zero = (np.linalg.norm(a, axis=-1) == 0) | (np.linalg.norm(b, axis=-1) == 0)
    out[zero] = v[zero]
    opposite = ~zero & (c[:, 0] < 0) & (s[:, 0] < 1e-12)
    out[opposite] = b[opposite] * np.linalg.norm(v[opposite], axis=-1, keepdims=True)
    return out


def normal_maps_from_probes(
    probe_x: ArrayLike, probe_y: ArrayLike, probe_z: ArrayLike, probe_sum: ArrayLike
) -> NDArray[np.float64]:
    """Per-vertex 3x3 maps M (n, 3, 3), row-vector (posed ~ rest @ M), up to a positive
    scale per vertex, from a normal skinning known only as a black box.

    UsdSkel's normal skinning is linear then normalised (LBS and DQS alike), so its outputs
    for the rest normals x, y, z are M's rows up to their lengths, and its output for
    x + y + z fixes those lengths up to one common factor (which normalisation ignores).
    Rows are NaN where the probes are degenerate (a singular map).
    """
    rows = np.stack([np.asarray(p, dtype=np.float64) for p in (probe_x, probe_y, probe_z)], axis=1)  # (n, 3, 3)
    total = np.asarray(probe_sum, dtype=np.float64)
    det = np.linalg.det(rows)
    good = np.abs(det) > NORMAL_MAP_RCOND * np.linalg.norm(rows, axis=(1, 2)) ** 3
    safe = np.where(good[:, None, None], rows, np.eye(3))
    lengths = np.linalg.solve(np.swapaxes(safe, 1, 2), total[:, :, None])[:, :, 0]  # lengths @ rows = total
    maps = lengths[:, :, None] * safe
    maps[~good | np.any(lengths <= 0, axis=1)] = np.nan
    return np.asarray(maps, dtype=np.float64)


@dataclass(frozen=True)
class PosedNormals:
    """One example's pose, as the normal inverse needs it (mesh local space)."""

    plain_points: NDArray[np.float64]  # (n, 3) skinning of the rest points at the pose (no corrective)
    sculpt_points: NDArray[np.float64]  # (n, 3) the sculpt
    normal_maps: NDArray[np.float64]  # (n, 3, 3) UsdSkel's posed normal ~ rest normal @ M (normal_maps_from_probes)


@dataclass(frozen=True)
class CorrectiveNormals:
    """A corrective's BlendShape arrays, sorted by point index: ``pointIndices`` (k,),
    ``offsets`` (k, 3) and ``normalOffsets`` (k, 3)."""

    indices: NDArray[np.int64]
    offsets: NDArray[np.float64]
    normal_offsets: NDArray[np.float64]
    ring_added: int  # vertices added to pointIndices for their normal only (zero point offset)
    max_turn: float  # largest turn (radians) of a surface normal the sculpt makes
    rest_space: int  # vertices given the pose-free rest-space offset (no pose, or a singular normal map)


def _checked_arrays(rest_points: ArrayLike, topology: Topology, indices: ArrayLike, offsets: ArrayLike,
                    rest_normals: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64],
                                                      NDArray[np.float64]]:
    """rest points, authored normals (n, 3), point indices and offsets, shapes checked."""
    rest = np.asarray(rest_points, dtype=np.float64)
    authored = np.asarray(rest_normals, dtype=np.float64)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    off = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    if rest.shape != (topology.point_count, 3) or authored.shape != rest.shape:
        raise ValueError(f"rest points {rest.shape} and normals {authored.shape}: expected ({topology.point_count}, 3)")
    if off.shape[0] != idx.size:
        raise ValueError(f"offsets: {off.shape[0]} rows for {idx.size} point indices")
    if idx.size and (idx.min() < 0 or idx.max() >= topology.point_count or np.unique(idx).size != idx.size):
        raise ValueError("point indices: out of range or repeated")
    return rest, authored, idx, off


def corrective_normals(
    rest_points: ArrayLike,
    topology: Topology,
    indices: ArrayLike,
    offsets: ArrayLike,
    rest_normals: ArrayLike | None,
    interpolation: str = "vertex",
    pose: PosedNormals | None = None,
) -> CorrectiveNormals | None:
    """A corrective's BlendShape arrays with ``normalOffsets``, or None when none should be
    written.

    rest_normals: the mesh's authored rest ``normals`` (n, 3) and their interpolation.
    With ``pose`` (the example the corrective was fitted from), each ring vertex's offset
    is the inverse of UsdSkel's normal skinning at that pose: the baked normal is the
    plain-skinned authored normal turned by the rotation that takes the plain-skinned
    surface's normal to the sculpt's. Without ``pose`` (and where a normal map is
    singular), the offset turns the authored normal by the rotation from the rest shape's
    normal to the corrected rest shape's (exact only where skinning moves normals as it
    moves the surface). Either way the stored rest normal keeps the authored normal's
    length, so UsdSkel's renormalisation does not change it at weight 1, and authored
    normals that deviate from computed ones (smoothed, edited) keep their deviation.

    None: no authored normals (renderers compute normals from the posed points, which
    already carry the correction, and UsdSkel ignores ``normalOffsets`` without authored
    normals), or normals not per point (``faceVarying``, ``uniform``, ``constant``).
    """
    if rest_normals is None or interpolation not in PER_POINT_INTERPOLATIONS:
        return None
    rest, authored, idx, off = _checked_arrays(rest_points, topology, indices, offsets, rest_normals)
    ring = topology.ring(idx)
    mine = authored[ring]
    target = np.empty_like(mine)
    turn = np.zeros(ring.size)
    inverted = np.zeros(ring.size, dtype=bool)
    if pose is not None:
        maps = np.asarray(pose.normal_maps, dtype=np.float64)[ring]
        plain = vertex_normals(pose.plain_points, topology, ring)
        sculpt = vertex_normals(pose.sculpt_points, topology, ring)
        turn = angle_between(plain, sculpt)
        inverted = np.all(np.isfinite(maps), axis=(1, 2))
        skinned = np.einsum("ni,nij->nj", mine[inverted], maps[inverted])  # UsdSkel's posed authored normal
        wanted = rotate_between(plain[inverted], sculpt[inverted], skinned)
        target[inverted] = np.einsum("ni,nij->nj", wanted, np.linalg.inv(maps[inverted]))
    if not inverted.all():
        # Pose-free: turn the authored normal as the rest shape's normal turns.
        rest_side = ring[~inverted]
        corrected = rest.copy()
        corrected[idx] += off
        before = vertex_normals(rest, topology, rest_side)
        after = vertex_normals(corrected, topology, rest_side)
        target[~inverted] = rotate_between(before, after, mine[~inverted])
        if pose is None:
            turn = angle_between(before, after)
    target = _unit(target) * np.linalg.norm(mine, axis=1, keepdims=True)
    keep = np.isin(ring, idx) | (turn > RING_ANGLE_ATOL)
    ring, delta = ring[keep], (target - mine)[keep]
    point_offsets = np.zeros((ring.size, 3))
    point_offsets[np.searchsorted(ring, idx)] = off
    return CorrectiveNormals(
        indices=ring,
        offsets=point_offsets,
        normal_offsets=delta,
        ring_added=int(ring.size - idx.size),
        max_turn=float(turn[keep].max()) if ring.size else 0.0,
        rest_space=int(np.count_nonzero(~inverted[keep])),
    )
