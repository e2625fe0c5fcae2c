"""Real characters behind LBS + the reference Delta Mush (10 iterations, step 0.5), for
``benchmarks.coupled``: CesiumMan (``fixtures/cesiumman``, 3,273 points) and the whole
character fixture (``fixtures/character``: the body's three 168-point tubes and the sleeve).

Two kinds of sculpt:

* **through the chain**: rest + a known smooth rest-space offset, put through the whole chain
  (UsdSkel, then Delta Mush) by psdbake's own black box and rounded to float32, so an exact
  answer exists. The offsets are the fixtures' own: CesiumMan's chest-and-shoulder swelling
  (``fixtures/generate.cesium_examples``) and the character's elbow and neck correctives
  (``fixtures/character.offsets``);
* **shipped**: CesiumMan's own EXAMPLES, sculpted on the plain-skinned mesh as an artist
  sculpts; no offset need reproduce them through Delta Mush.
"""

from __future__ import annotations

import importlib
import os
import tempfile
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from pxr import Sdf

from psdbake.deformers import load_deformers
from psdbake.solver.smoothbasis import edge_adjacency
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.meshrest import rest_mesh
from psdbake.usd.read import Scene

from . import rigs

character = importlib.import_module("character")  # fixtures/character.py, on the path rigs puts fixtures/ on

FIXTURES = os.path.join(rigs.ROOT, "fixtures")
CHAIN = tuple(load_deformers([rigs.DELTA_MUSH_SPEC]))


@dataclass
class Case:
    """One example: its black box (the whole chain), rest points, sculpt, mesh edges, and for a
    sculpt made through the chain the offsets it was made from (rounded to float32 as stored)."""

    name: str
    box: SkinningBlackBox
    rest: NDArray[np.float64]
    sculpt: NDArray[np.float64]
    adjacency: sp.csr_matrix
    offsets: NDArray[np.float64] | None = None


def _case(name: str, scene: Scene, mesh: str, time: float, offsets: NDArray[np.float64] | None,
          sculpt: NDArray[np.float64] | None = None) -> Case:
    box = SkinningBlackBox(scene, mesh, time, CHAIN)
    rest = scene.rest_points(mesh)
    moved = None
    if offsets is not None:
        moved = (rest + offsets).astype(np.float32).astype(np.float64)
        sculpt = box(moved).astype(np.float32).astype(np.float64)
    assert sculpt is not None
    return Case(name, box, rest, sculpt, edge_adjacency(rest_mesh(scene.stage, mesh)[1]),
                None if moved is None else moved - rest)


def cesium_swelling(rest: NDArray[np.float64], example: int) -> NDArray[np.float64]:
    """CesiumMan's example offsets (``generate.cesium_examples``): a chest and shoulder
    swelling, outward from the body's axis, larger at the second example."""
    centre = np.array([0.0, 0.1, 1.2])
    bump = np.exp(-((np.linalg.norm(rest - centre, axis=1) / 0.18) ** 2))
    outward = rest - [0.0, 0.0, 1.2]
    outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-9)
    return np.asarray((0.02 + 0.015 * example) * bump[:, None] * outward, dtype=np.float64)


def cesium(shipped: bool = False) -> list[Case]:
    """CesiumMan at its two example frames: through the chain, or its shipped sculpts."""
    asset = os.path.join(FIXTURES, "cesiumman", rigs.generate.CESIUM)
    examples = os.path.join(FIXTURES, "cesiumman", "cesiumman_examples.usda")
    scene = Scene([examples, asset], label=examples)
    mesh = rigs.generate.CESIUM_MESH
    rest = scene.rest_points(mesh)
    cases = []
    for k, t in enumerate(rigs.generate.CESIUM_FRAMES):
        if shipped:
            sculpt = scene.point_sample(Sdf.Layer.FindOrOpen(examples), mesh, t)
            cases.append(_case(f"CesiumMan@{t:g} shipped", scene, mesh, t, None, sculpt))
        else:
            cases.append(_case(f"CesiumMan@{t:g}", scene, mesh, t, cesium_swelling(rest, k)))
    return cases


def whole_character(folder: str | None = None) -> list[Case]:
    """The character fixture's sculpted meshes at each example of each set, through the chain."""
    folder = folder or tempfile.mkdtemp(prefix="psdbake_character_")
    asset = os.path.join(FIXTURES, "character", "character.usda")
    cases = []
    for name, spec in character.EXAMPLE_SETS.items():
        poses = spec["poses"]
        assert isinstance(poses, dict)
        poses_layer = character.write_animation(os.path.join(folder, f"{name}_poses.usda"), poses)
        scene = Scene([poses_layer, asset], label=poses_layer)
        for mesh in spec["meshes"]:  # type: ignore[attr-defined]
            rest = scene.rest_points(mesh)
            for t, pose in sorted(poses.items()):
                angle = next(iter(pose.values()))[1]
                cases.append(_case(f"character {name} {mesh.split('/')[-1]}@{t:g} ({abs(angle):g} deg)", scene, mesh, t,
                                   character.offsets(mesh, name, pose, rest)))
    return cases


def reach_pattern(adjacency: sp.csr_matrix, idx: NDArray[np.int64], rings: int) -> sp.csr_matrix:
    """Which offsets (3 per vertex) can move which outputs: vertices within ``rings`` edges of
    each other (Delta Mush's 10 smoothing steps, its normals' faces and its tangent's first
    neighbour reach 12), for the reference optimiser's coloured finite differences."""
    n = adjacency.shape[0]
    step = (adjacency + sp.identity(n, format="csr")).tocsr()
    step.data[:] = 1.0
    reach = sp.identity(n, format="csr")
    for _ in range(rings):
        reach = (reach @ step).tocsr()
        reach.data[:] = 1.0
    return sp.kron(reach[idx][:, idx], np.ones((3, 3)), format="csr")


#: Delta Mush's reach in edges (10 smoothing steps, 1 for the normals' faces, 1 for the tangent).
DELTA_MUSH_RINGS = 12

