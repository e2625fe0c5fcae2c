"""After a fit: the product at every example, through the composition a client uses.

What a client shows is UsdSkel evaluating ASSET + CORRECTIVES + ANIM + WEIGHTS. So each
example is checked through exactly that: its pose (its EXAMPLES layer without the sculpted
points) as ANIM, the fitted CORRECTIVES, the weights ``eval`` computes at its time code, and
the asset; every mesh is posed by the black box from the points the composed stage holds at
that time, as a client takes them, and compared with the sculpt. This catches what the
inverse cannot see, because it works on the rest it was given: an input where UsdSkel
applies the product differently from how it was fitted. An example the product misses by
more than ``tol.ROUNDTRIP_RTOL`` of its diagonal is *degraded*: ``fit`` fails on it (exit 7)
unless ``--allow-degraded``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..deformers import DeformerFactory
from ..results import ExampleCheck, FitResult
from ..shot.evaluation import animation_weights, correctives_by_animation
from ..usd import write as usdwrite
from ..usd.author import Layer
from ..usd.blackbox import SkinningBlackBox
from ..usd.posedpoints import RestPoints
from ..usd.read import Scene
from ..usd.sculpted import layer_points, pose_only_layer


def check_product(result: FitResult, correctives: Layer, chain: Sequence[tuple[str, DeformerFactory]]
                  ) -> tuple[ExampleCheck, ...]:
    """Every fitted example of result, through ASSET + correctives + its pose + its weights."""
    wanted: dict[str, dict[tuple[str, float], str]] = {}  # EXAMPLES file -> (mesh, time) -> label
    for m in result.meshes:
        for ex in m.examples:
            wanted.setdefault(ex.source, {})[(m.mesh, ex.time)] = ex.label
    out = []
    for source in sorted(wanted):
        pose = pose_only_layer(source)
        scene = Scene([pose, correctives, result.asset], label=source)
        per_anim = correctives_by_animation(scene, Scene([pose, result.asset], label=source), source, source)
        times = np.array(sorted({t for _, t in wanted[source]}), dtype=np.float64)
        drive = usdwrite.weights_layer("psdbake fit: weights at the examples", [
            (a.animation, a.channels, a.times, a.weights)
            for a in (animation_weights(scene, anim, per_anim[anim], times, source, source, lambda _: None)
                      for anim in sorted(per_anim))
        ], scene.stage.GetTimeCodesPerSecond())
        stack = Scene([drive, pose, correctives, result.asset], label=source)
        sculpts = layer_points(source)
        for (mesh, t), label in sorted(wanted[source].items()):
            rest = np.array(stack.prim(mesh).GetAttribute("points").Get(t), dtype=np.float64).reshape(-1, 3)
            posed = np.array(SkinningBlackBox(stack, mesh, t, chain).posed(RestPoints(rest)).points,
                             dtype=np.float64).reshape(-1, 3)
            target = sculpts[(mesh, t)].astype(np.float64)
            diagonal = float(np.linalg.norm(np.ptp(target, axis=0))) or 1.0
            if posed.shape != target.shape:
                out.append(ExampleCheck(mesh, label, source, t, float("inf"), 0))
                continue
            distance = np.linalg.norm(posed - target, axis=1)
            worst = int(np.argmax(distance))
            out.append(ExampleCheck(mesh, label, source, t, float(distance[worst]) / diagonal, worst))
    return tuple(out)
