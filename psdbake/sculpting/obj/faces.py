"""A mesh's faces and UVs as an OBJ file carries them, in OBJ's winding.

Why a module of its own: ``pose --obj-dir`` writes these faces and ``sculpts`` compares a
sculpt's faces with them, so both must agree on one convention. OBJ faces are
counter-clockwise when seen from outside (right-handed); a USD mesh authored
``orientation = "leftHanded"`` is clockwise, so its faces are reversed here (each face's
corners in the opposite order, first corner kept) and come back the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class MeshFaces:
    """Faces (OBJ winding) and optional UVs of one mesh at its rest topology."""

    point_count: int
    counts: NDArray[np.int64]  # corners per face (faceVertexCounts); empty for a prim without faces
    indices: NDArray[np.int64]  # 0-based point per corner, OBJ winding
    uvs: NDArray[np.float32] | None = None  # (k, 2) ``vt`` values, as authored
    uv_indices: NDArray[np.int64] | None = None  # 0-based ``vt`` per corner, OBJ winding
    uv_name: str = ""  # the primvar the UVs come from (``primvars:st``)
    left_handed: bool = False  # the faces were reversed from the mesh's leftHanded winding

    @property
    def face_count(self) -> int:
        return int(self.counts.size)


def obj_corner_order(counts: NDArray[np.int64], left_handed: bool) -> NDArray[np.int64]:
    """Corner permutation from USD order to OBJ order: the identity for a rightHanded mesh,
    each face reversed (corners 0, k-1, ..., 1) for a leftHanded one."""
    counts = np.asarray(counts, dtype=np.int64)
    order = np.arange(int(counts.sum()), dtype=np.int64)
    if not left_handed or not counts.size:
        return order
    starts = np.cumsum(counts) - counts
    face = np.repeat(np.arange(counts.size), counts)
    j = order - starts[face]  # corner number within its face
    return starts[face] + np.where(j == 0, 0, counts[face] - j)
