"""A mesh's authored rest points and polygon topology, for deformers that need its faces
(``psdbake.delta_mush``): the only USD they read, at the default time."""

from __future__ import annotations

import numpy as np
from pxr import Usd, UsdGeom

from ..arrays import Points
from ..normals import Topology
from .normalbox import read_mesh_shading


def rest_mesh(stage: Usd.Stage, mesh_path: str) -> tuple[Points, Topology]:
    """(authored points (n, 3) float64 in mesh local space, topology); ValueError for a prim
    that is not a polygon mesh with points."""
    prim = stage.GetPrimAtPath(mesh_path)
    if not prim or not prim.IsA(UsdGeom.Mesh):
        raise ValueError(f"{mesh_path} is not a Mesh: the deformer needs its faces")
    value = UsdGeom.Mesh(prim).GetPointsAttr().Get(Usd.TimeCode.Default())
    points = np.array(value if value is not None else [], dtype=np.float64).reshape(-1, 3)
    topology = read_mesh_shading(prim, str(stage.GetRootLayer().identifier)).topology
    if topology is None:
        raise ValueError(f"{mesh_path} has no faces")
    return points, topology
