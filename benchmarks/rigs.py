"""Benchmark rigs made on the fly with ``fixtures/generate.py``: asset, poses, sculpts.

The sculpts are ground truth made independently of psdbake's solver: for the
skinning-only variants Pixar's ``UsdSkel.BakeSkinning`` of rest + a known rest-space
offset (``generate.bake_sculpt``); for the non-linear chains the same UsdSkel black
box followed by the chain's deformer (``benchmarks.deformers.bulge``, or psdbake's reference
Delta Mush for ``lbs+deltamush``) evaluated at rest + offset, i.e.
sculpt = deformer(skinning(rest + offset)).
"""

from __future__ import annotations

import math
import os
import sys
import time as _time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import UsdSkel

from psdbake.deformers import DeformerFactory, load_deformers
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.read import Scene

from . import deformers

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if os.path.join(ROOT, "fixtures") not in sys.path:
    sys.path.insert(0, os.path.join(ROOT, "fixtures"))

import generate  # noqa: E402  (fixtures/generate.py)

MESH = generate.MESH
DEFORMER_SPEC = "benchmarks.deformers:bulge"
#: The coupling chain's deformer: psdbake's reference Delta Mush (10 iterations, step 0.5).
DELTA_MUSH_SPEC = "psdbake.delta_mush:delta_mush"
#: Sizes (rings, segments): about 1.3k, 3k, 13k, 100k and 1M points (1M: benchmarks/fitspeed.py only).
SIZES = {"1.3k": (82, 16), "3k": (130, 24), "13k": (260, 50), "100k": (625, 160), "1M": (2500, 400)}
#: Variant -> (UsdSkel skinning method, user deformer chain).
VARIANTS = {"lbs": ("classicLinear", False), "dqs": ("dualQuaternion", False), "lbs+bulge": ("classicLinear", True)}
#: Chains whose deformer couples vertices (benchmarks/coupled.py), kept out of VARIANTS, which
#: benchmarks/run.py and benchmarks/outputs.py loop over: variant -> (skinning, deformer spec).
COUPLED_VARIANTS = {"lbs+deltamush": ("classicLinear", DELTA_MUSH_SPEC)}
#: The sculpted band: x in [BAND_LO, BAND_HI] of the 5-unit tube, a third of its length.
BAND_LO, BAND_HI = 0.9, 0.9 + generate.LENGTH / 3.0


def example_poses(count: int = 8) -> dict[float, dict]:
    """Example poses at times 1..count: elbow 20..160 degrees, a varying wrist twist."""
    poses = {}
    for i in range(count):
        elbow = 20.0 + 140.0 * i / max(count - 1, 1)
        wrist = 60.0 * math.sin(1.3 * i)
        poses[float(i + 1)] = {"Elbow": ((0, 0, 1), elbow), "Wrist": ((1, 0, 0), wrist)}
    return poses


def shot_poses(frames: int) -> dict[float, dict]:
    """A long shot (frames 1..frames): smooth elbow swing and wrist twist, a few cycles."""
    poses = {}
    for f in range(1, frames + 1):
        s = (f - 1) / max(frames - 1, 1)
        poses[float(f)] = {
            "Elbow": ((0, 0, 1), 80.0 + 70.0 * math.sin(2 * math.pi * 7.0 * s)),
            "Wrist": ((1, 0, 0), 60.0 * math.sin(2 * math.pi * 11.0 * s)),
        }
    return poses


def band_offsets(bind_pts: NDArray[np.float64], pose: dict) -> NDArray[np.float64]:
    """Rest-space (skeleton bind space) corrective: a bulge and a twist on the elbow band.

    Smooth (sin^2 window) in x over a third of the tube; zero outside it.
    """
    elbow = pose.get("Elbow", ((0, 0, 1), 0.0))[1]
    wrist = pose.get("Wrist", ((1, 0, 0), 0.0))[1]
    x, y, z = bind_pts[:, 0], bind_pts[:, 1], bind_pts[:, 2]
    u = np.clip((x - BAND_LO) / (BAND_HI - BAND_LO), 0.0, 1.0)
    window = np.sin(math.pi * u) ** 2
    amount = 0.2 * math.sin(math.radians(elbow)) * window * (1.0 + 0.5 * y / generate.RADIUS)
    twist = 0.12 * math.sin(math.radians(wrist)) * window
    off = np.zeros_like(bind_pts)
    off[:, 1] = amount * y / generate.RADIUS - twist * z
    off[:, 2] = amount * z / generate.RADIUS + twist * y
    return off


@dataclass
class Rig:
    """One benchmark rig on disk plus what the measurements need in memory."""

    name: str  # e.g. "lbs 13k"
    variant: str
    size: str
    asset: str
    poses_layer: str
    examples: str  # EXAMPLES file (poses + sculpted points) for api.fit
    times: list[float]
    rest: NDArray[np.float64]  # (n, 3) authored mesh points
    sculpts: dict[float, NDArray[np.float64]]  # float32-rounded, as read back from USD
    truth: dict[float, NDArray[np.float64]]  # ground-truth mesh-space offsets per example
    deformers: tuple[tuple[str, DeformerFactory], ...]
    build_seconds: float = 0.0

    @property
    def points(self) -> int:
        return len(self.rest)

    @property
    def linear_skinning(self) -> bool:
        """True when the closed-form LBS inverse applies (LBS and no user deformer)."""
        return self.variant == "lbs"

    def scene(self) -> Scene:
        return Scene([self.poses_layer, self.asset], label=self.poses_layer)

    def blackbox(self, scene: Scene, time: float) -> SkinningBlackBox:
        return SkinningBlackBox(scene, MESH, time, self.deformers)


def geom_bind_linear(asset: str) -> NDArray[np.float64]:
    """The 3x3 linear part of the mesh's geomBindTransform (row-vector convention)."""
    scene = Scene([asset])
    g = UsdSkel.BindingAPI(scene.prim(MESH)).GetGeomBindTransformAttr().Get()
    return np.array(g, dtype=np.float64).reshape(4, 4)[:3, :3]


def build(folder: str, variant: str, size: str, poses: dict[float, dict], poses_layer: str) -> Rig:
    """Write asset + examples for one (variant, size) into folder and return the Rig."""
    started = _time.perf_counter()
    if variant in COUPLED_VARIANTS:
        method, spec = COUPLED_VARIANTS[variant]
        chain: tuple[tuple[str, DeformerFactory], ...] = tuple(load_deformers([spec]))
    else:
        method, nonlinear = VARIANTS[variant]
        chain = ((DEFORMER_SPEC, deformers.bulge),) if nonlinear else ()
    rings, segments = SIZES[size]
    tag = f"{variant.replace('+', '_')}_{size.replace('.', '_')}"
    asset = generate.build_arm(
        os.path.join(folder, f"{tag}.usda"), generate.ArmSpec(rings=rings, segments=segments, method=method)
    )
    bind_pts = generate.tube_points(rings, segments)
    times = sorted(poses)
    offsets: Callable[[float], NDArray[np.float64]] = lambda t: band_offsets(bind_pts, poses[t])  # noqa: E731
    to_mesh = np.linalg.inv(geom_bind_linear(asset))  # bind-space offset -> authored mesh space
    truth = {t: offsets(t) @ to_mesh for t in times}
    if not chain:
        sculpts = generate.bake_sculpt(asset, poses_layer, times, offsets)
    else:
        # sculpt = deformer(BakeSkinning(rest + offset)), through psdbake's black box with the same chain
        scene = Scene([poses_layer, asset])
        rest = scene.rest_points(MESH)
        sculpts = {}
        for t in times:
            moved = (rest + truth[t]).astype(np.float32).astype(np.float64)
            sculpts[t] = SkinningBlackBox(scene, MESH, t, chain)(moved)
    examples = generate.write_examples(os.path.join(folder, f"{tag}_examples.usda"), poses_layer, sculpts)
    rounded = {t: s.astype(np.float32).astype(np.float64) for t, s in sculpts.items()}
    rest = Scene([asset]).rest_points(MESH)
    return Rig(
        name=f"{variant} {size}", variant=variant, size=size, asset=asset, poses_layer=poses_layer,
        examples=examples, times=times, rest=rest, sculpts=rounded, truth=truth, deformers=chain,
        build_seconds=_time.perf_counter() - started,
    )


def write_poses(folder: str, count: int = 8) -> tuple[str, dict[float, dict]]:
    """The POSES layer shared by every rig (all rigs have the same skeleton)."""
    poses = example_poses(count)
    return generate.write_animation(os.path.join(folder, "poses.usda"), poses), poses


def write_shot(folder: str, frames: int) -> str:
    """ANIM layer with ``frames`` frames for the eval benchmark."""
    return generate.write_animation(os.path.join(folder, f"shot_{frames}.usda"), shot_poses(frames))
