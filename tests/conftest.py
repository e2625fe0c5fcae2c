"""Shared helpers: fixture paths, the in-process CLI runner (``run_cli``; fixtures ``cli``
and ``run``), Pixar's bake of a stack (``bake``, read with ``points``)."""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import io
import os
import re
import shutil
import signal
import sys
import tempfile
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIXTURES = os.path.join(ROOT, "fixtures")
sys.path[:0] = [ROOT, FIXTURES]
# The crate probe's verdict cache (psdbake.usd.integrity) in a folder of the session's own,
# set for this process and every psdbake it starts: tests never write to the user's home
# and never inherit verdicts from other runs. Tests of the cache itself monkeypatch it.
os.environ["PSDBAKE_CACHE_DIR"] = tempfile.mkdtemp(prefix="psdbake-test-cache-")
atexit.register(shutil.rmtree, os.environ["PSDBAKE_CACHE_DIR"], ignore_errors=True)
# The signal tests play a user at a terminal: the commands they start must see Ctrl-C. A suite
# started as a background job (``make test &``, some CI runners) has SIGINT ignored, which every
# child would inherit and psdbake, like Python, keeps (tests/test_bounded.py); Python's own
# handler here makes the children's SIGINT the default again (a caught signal resets on exec).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        signal.signal(signal.SIGINT, signal.default_int_handler)


import generate  # noqa: E402  (fixtures/generate.py, re-exported for the tests)

from psdbake.cli import main  # noqa: E402


def fixture(*parts: str) -> str:
    return os.path.join(FIXTURES, *parts)


def tube_with_edges(rings: int, segments: int) -> tuple[np.ndarray, Any]:
    """The generated tube's rest points and its edge adjacency (sparse, n x n)."""
    from psdbake.normals import Topology
    from psdbake.solver.smoothbasis import edge_adjacency

    counts, indices = generate.tube_faces(rings, segments)
    rest = generate.tube_points(rings, segments)
    return rest, edge_adjacency(Topology(np.array(counts), np.array(indices), len(rest)))


def smoothing_chain(rest: np.ndarray, adjacency: Any, steps: int, twist: float) -> Callable[[np.ndarray], np.ndarray]:
    """A linear coupling chain: a per-vertex rotation growing to ``twist`` radians along the
    tube (skinning's part), then ``steps`` uniform smoothing steps of 1/2 along the edges (Delta
    Mush's smoothing, without its detail frames)."""
    import scipy.sparse as sp

    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    walk = (0.5 * sp.identity(len(rest)) + 0.5 * sp.diags(1.0 / degree) @ adjacency).tocsr()
    angle = twist * rest[:, 0] / rest[:, 0].max()
    c, s = np.cos(angle), np.sin(angle)

    def chain(points: np.ndarray) -> np.ndarray:
        out = np.stack([c * points[:, 0] - s * points[:, 1], s * points[:, 0] + c * points[:, 1], points[:, 2]], axis=1)
        for _ in range(steps):
            out = walk @ out
        return out

    return chain


CESIUM = fixture("cesiumman", "CesiumMan.usdz")
CESIUM_EXAMPLES = fixture("cesiumman", "cesiumman_examples.usda")


def run_cli(*args) -> tuple[int, str, str]:
    """Run the CLI in-process: (exit code, stdout, stderr) as file descriptors 1 and 2 saw
    them, USD's C++ output included (USD prints from C++ straight to fd 2, so capturing
    ``sys.stderr`` alone, as ``capsys`` does, misses lines users see). This is what
    ``capfd`` captures, done here so that module-scoped fixtures can run the CLI too: fds 1
    and 2 point at temporary files and ``sys.stdout``/``sys.stderr`` write through to them
    for the call. The one CLI runner of the tests (the ``cli`` and ``run`` fixtures)."""
    sys.stdout.flush()
    sys.stderr.flush()
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        saved_fds, saved_streams = (os.dup(1), os.dup(2)), (sys.stdout, sys.stderr)
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        sys.stdout, sys.stderr = (io.TextIOWrapper(io.FileIO(fd, "w", closefd=False), encoding="utf-8",
                                                   errors="replace", newline="", write_through=True) for fd in (1, 2))
        try:
            with pytest.raises(SystemExit) as exc:
                main([str(a) for a in args])
        finally:
            for stream in (sys.stdout, sys.stderr):
                stream.close()  # flushes; the fd stays open (closefd=False)
            sys.stdout, sys.stderr = saved_streams
            for fd, saved in zip((1, 2), saved_fds, strict=True):
                os.dup2(saved, fd)
                os.close(saved)
        out.seek(0)
        err.seek(0)
        return exc.value.code, out.read().decode("utf-8", "replace"), err.read().decode("utf-8", "replace")


@pytest.fixture(autouse=True)
def fixtures_stay_as_on_disk():
    """No test may edit a bundled fixture's layer in memory: USD keeps an open layer for every
    later FindOrOpen in this process, so such an edit changes what later tests read (a points
    cache once came out in another space, depending on test order). Edit a copy instead."""
    yield
    dirty = [layer.identifier for layer in Sdf.Layer.GetLoadedLayers()
             if not layer.anonymous and layer.dirty and os.path.realpath(layer.realPath).startswith(FIXTURES + os.sep)]
    assert not dirty, f"a test edited fixture layers in memory: {dirty}"


@pytest.fixture
def cli():
    """The in-process CLI runner (``run_cli``) as a fixture."""
    return run_cli


@pytest.fixture
def run():
    """Another name for the ``cli`` fixture (the same runner), used by many tests."""
    return run_cli


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


_KEEP: list = []  # anonymous layers live as long as the session


def stage_of(layers: list) -> Usd.Stage:
    """A stage over layers (paths or identifiers, strongest first) with an anonymous root as
    its edit target, so baking writes nowhere on disk."""
    root = Sdf.Layer.CreateAnonymous(".usda")
    for path in layers:
        root.subLayerPaths.append(str(path))
    _KEEP.append(root)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    return stage


def bake(layers: list | Usd.Stage, first: float, last: float | None = None) -> Usd.Stage:
    """Pixar's ``UsdSkel.BakeSkinning`` of the stack ``layers`` (strongest first; or a stage
    already open) over the frames first..last (last defaults to first), the one way the
    tests bake: the whole stage at once (``stage.Traverse()``), which is how UsdSkel itself
    bakes a stage, nested SkelRoots included. Returns the baked stage (``points`` reads it)."""
    stage = layers if isinstance(layers, Usd.Stage) else stage_of(layers)
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(first, first if last is None else last))
    return stage


def points(stage: Usd.Stage, mesh: str, time: float, dtype=np.float64) -> np.ndarray:
    """The points of a (baked) mesh at time, (n, 3)."""
    prim = stage.GetPrimAtPath(mesh)
    assert prim.IsA(UsdGeom.PointBased), f"no mesh at <{mesh}>"
    return np.array(UsdGeom.PointBased(prim).GetPointsAttr().Get(time), dtype=dtype)


def sculpt(path: str, mesh: str, time: float) -> np.ndarray:
    layer = Sdf.Layer.FindOrOpen(path)
    return np.array(layer.QueryTimeSample(Sdf.Path(mesh).AppendProperty("points"), time), dtype=np.float64)


def diagonal(points: np.ndarray) -> float:
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def pose_only(examples: str) -> str:
    """An EXAMPLES layer without its sculpted points: the pose alone, usable as ANIM
    (else its points samples would be skinned again)."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(examples))
    found: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath, lambda p: found.append(p) if p.IsPropertyPath() and p.name == "points" else None)
    for path in found:
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

    stage = stage_of(layers)
    shading = read_mesh_shading(stage.GetPrimAtPath(mesh))
    assert shading.normals is not None, shading.why_not
    bake(stage, time)
    baked = np.array(UsdGeom.Mesh(stage.GetPrimAtPath(mesh)).GetNormalsAttr().Get(time), dtype=np.float64)
    shape = points(stage, mesh, time) if sculpt_points is None else sculpt_points
    return angle_between(baked, vertex_normals(shape, shading.topology))


def corrective_weights(asset: str, correctives: str, weights: str, anim_prim: str, times) -> dict[str, np.ndarray]:
    """Each corrective's weight b_s over times (psd:shapes name -> (f,)), from WEIGHTS as
    written: its client-safe channels' weights times their scales, summed (channels.py)."""
    from psdbake.fitting.groups import read_correctives
    from psdbake.model.channels import column_weights

    layer = Sdf.Layer.FindOrOpen(str(weights))
    names = list(layer.GetAttributeAtPath(Sdf.Path(anim_prim).AppendProperty("blendShapes")).default)
    path = Sdf.Path(anim_prim).AppendProperty("blendShapeWeights")
    w = np.array([layer.QueryTimeSample(path, float(t)) for t in times], dtype=np.float64)
    out = {}
    for groups in read_correctives(str(asset), str(correctives)).values():
        for data, _ in groups.values():
            channels = list(data.channels) or list(data.shapes)
            b = column_weights(data, w[:, [names.index(c) for c in channels]])
            out.update({name: b[:, s] for s, name in enumerate(data.shapes)})
    return out


def without_provenance(path) -> str:
    """A layer's text without the provenance psdbake records in it (its command line and
    inputs), for comparing what two differently invoked commands wrote."""
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    custom = dict(layer.customLayerData)
    custom.pop("psdbake", None)
    layer.customLayerData = custom
    return layer.ExportToString()


def stitched_chunks(manifest) -> list[str]:
    """The chunk files a chunked eval's manifest stitches (its clips' asset paths; every clipped
    prim names the same)."""
    layer = Sdf.Layer.OpenAsAnonymous(str(manifest))
    found: list[list[str]] = []

    def visit(path) -> None:
        spec = layer.GetPrimAtPath(path) if path.IsPrimPath() else None
        if spec is not None and spec.HasInfo("clips"):
            found.append([a.path for a in spec.GetInfo("clips")["psdbake"]["assetPaths"]])

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    assert found and all(f == found[0] for f in found), found
    return found[0]
