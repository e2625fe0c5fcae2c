"""Shared helpers: fixture paths, an in-process CLI runner, Pixar's bake of a stack."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIXTURES = os.path.join(ROOT, "fixtures")
sys.path[:0] = [ROOT, FIXTURES]


import generate  # noqa: E402, F401  (fixtures/generate.py, re-exported for the tests)

from psdbake.cli import main  # noqa: E402


def fixture(*parts: str) -> str:
    return os.path.join(FIXTURES, *parts)


CESIUM = fixture("cesiumman", "CesiumMan.usdz")
CESIUM_EXAMPLES = fixture("cesiumman", "cesiumman_examples.usda")


@pytest.fixture
def run(capsys):
    """Run the CLI in-process: returns (exit code, stdout, stderr)."""

    def _run(*args: str) -> tuple[int, str, str]:
        with pytest.raises(SystemExit) as exc:
            main([str(a) for a in args])
        out, err = capsys.readouterr()
        return exc.value.code, out, err

    return _run


def bake_stack(layers: list[str], time: float) -> dict[str, np.ndarray]:
    """UsdSkel.BakeSkinning of the given layers (strongest first) at time: mesh -> points."""
    root = Sdf.Layer.CreateAnonymous(".usda")
    for path in layers:
        root.subLayerPaths.append(path)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    skel_roots = [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]
    meshes = []
    for p in skel_roots:
        meshes += [m for m in Usd.PrimRange(p) if m.IsA(UsdGeom.Mesh)]
    for p in skel_roots:
        assert UsdSkel.BakeSkinning(UsdSkel.Root(p), Gf.Interval(time, time))
    return {str(m.GetPath()): np.array(UsdGeom.Mesh(m).GetPointsAttr().Get(time), dtype=np.float64) for m in meshes}


def sculpt(path: str, mesh: str, time: float) -> np.ndarray:
    layer = Sdf.Layer.FindOrOpen(path)
    return np.array(layer.QueryTimeSample(Sdf.Path(mesh).AppendProperty("points"), time), dtype=np.float64)


def diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


_KEEP: list = []  # anonymous layers live as long as the session


def pose_only(examples: str) -> str:
    """An EXAMPLES layer without its sculpted points: the pose alone, usable as ANIM
    (else its points samples would be skinned again)."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(examples))
    points: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath, lambda p: points.append(p) if p.IsPropertyPath() and p.name == "points" else None)
    for path in points:
        layer.GetPrimAtPath(path.GetPrimPath()).RemoveProperty(layer.GetPropertyAtPath(path))
    _KEEP.append(layer)
    return layer.identifier


def baked_normal_errors(layers: list[str], mesh: str, time: float, sculpt_points: np.ndarray | None = None) -> np.ndarray:
    """Per-vertex angle (radians) between the normals UsdSkel.BakeSkinning gives the stack
    ``layers`` (strongest first; the asset must author vertex ``normals``) at time and the
    area-weighted normals (psdbake.normals) of sculpt_points, or of the baked points
    themselves when None: skinning's own normal error, since skinned normals are not
    exactly the normals of the skinned mesh."""
    from psdbake.normals import angle_between, vertex_normals
    from psdbake.usd.normalbox import read_mesh_shading

    root = Sdf.Layer.CreateAnonymous(".usda")
    for path in layers:
        root.subLayerPaths.append(path)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    shading = read_mesh_shading(stage.GetPrimAtPath(mesh))
    assert shading.normals is not None, shading.why_not
    for p in [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]:
        assert UsdSkel.BakeSkinning(UsdSkel.Root(p), Gf.Interval(time, time))
    geom = UsdGeom.Mesh(stage.GetPrimAtPath(mesh))
    baked = np.array(geom.GetNormalsAttr().Get(time), dtype=np.float64)
    points = np.array(geom.GetPointsAttr().Get(time), dtype=np.float64) if sculpt_points is None else sculpt_points
    return angle_between(baked, vertex_normals(points, shading.topology))
