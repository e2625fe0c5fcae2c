"""The rig as the model sees it: a skinned mesh and its skeleton, and the mesh in its
skeleton's bind space (what mirroring reflects). Plain data: ``usd/read.py`` and
``usd/bindspace.py`` read them from a stage. Matrices are Gf's row-vector convention
(p' = p . M), as read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SkinnedMesh:
    """A skinned point-based prim and the skeleton that deforms it."""

    path: str
    skeleton: str
    skel_root: str
    joints: tuple[str, ...]  # skeleton joint order (full joint paths)
    point_count: int


@dataclass(frozen=True)
class BindSpace:
    """One skinned mesh and its skeleton at the bind pose, in skeleton space (row-vector matrices)."""

    mesh: str
    skeleton: str
    skel_root: str
    joints: tuple[str, ...]  # skeleton order
    parents: NDArray[np.int64]  # (J,) parent index, -1 for a root
    bind_world: NDArray[np.float64]  # (J, 4, 4) bindTransforms: each joint's skeleton-space bind transform
    bind_local: NDArray[np.float64]  # (J, 4, 4) bind local transforms (local_j = bind_j . bind_parent^-1)
    geom_bind: NDArray[np.float64]  # (4, 4) geomBindTransform: mesh points -> skeleton space
    rest: NDArray[np.float64]  # (n, 3) rest points in skeleton space (through geom_bind)


@dataclass(frozen=True)
class Skin:
    """Which joints deform each point, as UsdSkel binds them: what decides which joints can
    explain a point's corrective (``fitting.locality``)."""

    indices: NDArray[np.int64]  # (n, k) skeleton-order joint index of each influence (-1: none)
    weights: NDArray[np.float64]  # (n, k)
    parents: NDArray[np.int64]  # (J,) each joint's parent index, -1 for a root
