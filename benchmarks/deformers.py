"""A smooth, non-linear user deformer for the benchmarks' non-linear chain.

``bulge`` is a psdbake ``--deformer`` factory (``benchmarks.deformers:bulge``): it
runs after UsdSkel skinning, in the mesh's local space, and makes the black box
non-affine per vertex so the one-shot linearisation is no longer exact while the
chain stays smooth and locally invertible (Powell must still reach the sculpt).

The warp is a fixed field in mesh local space, built from the rest mesh: a twist
about the rest tube's long axis by an angle that varies sinusoidally along the
axis, and a radial bulge that does too. Each output point depends on its own
input point only, as psdbake's per-vertex formulation assumes.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from pxr import Usd, UsdGeom

Points = NDArray[np.float64]

#: Largest twist angle (radians) along the axis; enough to make the chain clearly non-affine.
TWIST = 0.35
#: Relative radial bulge amplitude.
BULGE = 0.08


def _axis_frame(rest: Points) -> tuple[Points, Points, float]:
    """Centroid, unit long axis and half length of the rest points (principal axis)."""
    centre = rest.mean(axis=0)
    _, _, vt = np.linalg.svd(rest - centre, full_matrices=False)
    axis = vt[0] / np.linalg.norm(vt[0])
    along = (rest - centre) @ axis
    return centre, axis, max(float(np.abs(along).max()), 1e-12)


def bulge(stage: Usd.Stage, mesh_path: str, time: float) -> Callable[[Points], Points]:
    """psdbake deformer factory: twist + sinusoidal bulge about the mesh's rest long axis.

    The amplitude varies smoothly with ``time`` so every example sees a different chain.
    """
    attr = UsdGeom.PointBased(stage.GetPrimAtPath(mesh_path)).GetPointsAttr()
    rest = np.array(attr.Get(Usd.TimeCode.Default()), dtype=np.float64).reshape(-1, 3)
    centre, axis, half = _axis_frame(rest)
    gain = 1.0 + 0.25 * math.sin(0.7 * float(time))

    def deform(points: Points) -> Points:
        # Component-wise on purpose: tall-skinny ``@`` goes to multithreaded BLAS, which
        # contends with USD's worker threads and costs more than the arithmetic.
        rel = points - centre
        s = rel[:, 0] * axis[0] + rel[:, 1] * axis[1] + rel[:, 2] * axis[2]
        radial = rel - s[:, None] * axis
        around = np.stack(
            [
                axis[1] * radial[:, 2] - axis[2] * radial[:, 1],
                axis[2] * radial[:, 0] - axis[0] * radial[:, 2],
                axis[0] * radial[:, 1] - axis[1] * radial[:, 0],
            ],
            axis=1,
        )  # axis x radial
        angle = gain * TWIST * np.sin(math.pi * s / half)
        scale = 1.0 + gain * BULGE * np.sin(2.0 * math.pi * s / half) ** 2
        cos, sin = (np.cos(angle) * scale)[:, None], (np.sin(angle) * scale)[:, None]
        return centre + s[:, None] * axis + radial * cos + around * sin

    return deform
