"""Shared helpers: fixture paths, an in-process CLI runner, Pixar's bake of a stack."""

from __future__ import annotations

import hashlib
import os
import re
import sys
from collections.abc import Iterable

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
def cli(capfd):
    """Run the CLI in-process: (exit code, stdout, stderr), USD's C++ output included
    (``capfd``, not ``capsys``: USD prints from C++ straight to file descriptor 2)."""

    def _run(*args) -> tuple[int, str, str]:
        capfd.readouterr()
        with pytest.raises(SystemExit) as exc:
            main([str(a) for a in args])
        out, err = capfd.readouterr()
        return exc.value.code, out, err

    return _run


def no_leftovers(outputs: Iterable) -> None:
    """No output and no temporary file beside where an output would have gone."""
    for path in outputs:
        assert not os.path.exists(path), f"{path} was written by a failed run"
        folder = os.path.dirname(str(path))
        if os.path.isdir(folder):
            temps = [f for f in os.listdir(folder) if ".tmp" in f]
            assert not temps, f"temporary files left in {folder}: {temps}"


def digest(paths: Iterable) -> dict[str, str]:
    """sha256 of each regular file (to show inputs are byte-identical after a run)."""
    out = {}
    for p in paths:
        p = str(p)
        if os.path.isfile(p):
            with open(p, "rb") as fh:
                out[p] = hashlib.sha256(fh.read()).hexdigest()
    return out


def refused(result, code: int, *, names=(), says: str = "", outputs=(), inputs: dict[str, str] | None = None) -> str:
    """Assert the one-line refusal contract: exit code, exactly one ``psdbake: error:`` line
    naming ``names`` and matching ``says``, no traceback, no C++ internals, no output or temp
    file left; with ``inputs`` (a ``digest`` taken before the run), inputs byte-identical.
    Returns the line."""
    rc, out, err = result
    assert "Traceback" not in out + err, err
    lines = err.splitlines()
    assert len(lines) == 1, f"stderr must be exactly one line, got {len(lines)}:\n{err}"
    line = lines[0]
    assert line.startswith("psdbake: error:"), line
    assert "pxrInternal" not in line and ".cpp" not in line, f"USD's C++ internals leak into the message: {line}"
    for name in names:
        # a prim may be named with its attribute: </Prim.attr>
        alternatives = (name, name[:-1] + ".") if name.startswith("</") and name.endswith(">") else (name,)
        assert any(a in line for a in alternatives), f"{name!r} not named in: {line}"
    if says:
        assert re.search(says, line, re.IGNORECASE), f"/{says}/ not in: {line}"
    assert rc == code, f"exit {rc}, expected {code}: {line}"
    no_leftovers(outputs)
    if inputs is not None:
        assert digest(inputs) == inputs, f"an input was modified: {line}"
    return line


def warned(result, *, names=(), says: str = "", outputs=()) -> str:
    """Assert success with a psdbake: warning: line; returns the warning."""
    rc, out, err = result
    assert "Traceback" not in out + err, err
    assert rc == 0, err
    found = [ln for ln in err.splitlines() if ln.startswith("psdbake: warning:")]
    assert found, f"no psdbake: warning: line in stderr:\n{err}"
    others = [ln for ln in err.splitlines() if not ln.startswith("psdbake: warning:")]
    assert not others, f"stderr has lines that are not psdbake warnings:\n{err}"
    hits = [w for w in found if all(n in w for n in names) and (not says or re.search(says, w, re.IGNORECASE))]
    assert hits, f"no warning naming {names} and saying /{says}/:\n{err}"
    for path in outputs:
        assert os.path.exists(path)
    return hits[0]


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
