"""Reference inverses that psdbake is measured against (tests use them as oracles).

Unlike psdbake's solver these look *inside* the skinning on purpose:

- ``closed_form_lbs``: blend each vertex's joint matrices and solve its affine
  system exactly (vectorised numpy): the practical floor, LBS only.
- ``one_shot_linearisation``: 3 whole-mesh black-box calls, a 3x3 Jacobian per vertex,
  one solve (what Maya-side tools such as cvShapeInverter do); exact only when the
  black box is affine per vertex.
- ``literal_powell``: ``scipy.optimize.minimize(method="Powell")`` per vertex, every
  evaluation running the whole-mesh black box (what the paper describes).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from pxr import Usd, UsdGeom, UsdSkel
from scipy.optimize import minimize

Points = NDArray[np.float64]


def lbs_matrices(stage: Usd.Stage, mesh: str, time: float) -> NDArray[np.float64]:
    """Per-vertex affine matrices A_v (n, 4, 4), row-vector: posed_local = [p, 1] . A_v.

    A_v = G . (sum_j w_vj S_j) . skel_to_local, with G the geomBindTransform and S_j the
    skeleton-space skinning transforms at time (classicLinear skinning).
    """
    cache = UsdSkel.Cache()
    prim = stage.GetPrimAtPath(mesh)
    root = UsdSkel.Root.Find(prim)
    cache.Populate(root, Usd.TraverseInstanceProxies())
    query = cache.GetSkinningQuery(prim)
    binding = UsdSkel.BindingAPI(prim)
    skel = binding.GetInheritedSkeleton()
    skel_query = cache.GetSkelQuery(skel)
    tc = Usd.TimeCode(time)
    xforms = np.array([np.array(m) for m in skel_query.ComputeSkinningTransforms(tc)])
    mapper = query.GetJointMapper()
    if mapper is not None and not mapper.IsNull() and not mapper.IsIdentity():
        xforms = np.array([np.array(m) for m in mapper.RemapTransforms(skel_query.ComputeSkinningTransforms(tc))])
    indices, weights = query.ComputeVaryingJointInfluences(len(UsdGeom.PointBased(prim).GetPointsAttr().Get()), tc)
    k = query.GetNumInfluencesPerComponent()
    idx = np.array(indices, dtype=np.int64).reshape(-1, k)
    w = np.array(weights, dtype=np.float64).reshape(-1, k)
    blended = np.einsum("nk,nkab->nab", w, xforms[idx])
    geom_bind = np.array(query.GetGeomBindTransform(tc), dtype=np.float64)
    skel_w = np.array(UsdGeom.Xformable(skel.GetPrim()).ComputeLocalToWorldTransform(tc))
    mesh_w = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(tc))
    to_local = skel_w @ np.linalg.inv(mesh_w)
    return geom_bind[None] @ blended @ to_local[None]


def closed_form_lbs(matrices: NDArray[np.float64], rest: Points, sculpt: Points, indices=None) -> Points:
    """Exact LBS inverse: d = sculpt . A_v^-1 - rest for the given vertices."""
    idx = np.arange(len(rest)) if indices is None else np.asarray(indices)
    a = matrices[idx]
    target = np.c_[sculpt[idx], np.ones(len(idx))]
    # solve x . A = target  <=>  A^T x^T = target^T
    x = np.linalg.solve(np.transpose(a, (0, 2, 1)), target[..., None])[..., 0]
    return x[:, :3] / x[:, 3:4] - rest[idx]


def one_shot_linearisation(blackbox: Callable[[Points], Points], rest: Points, sculpt: Points,
                           indices: Sequence[int], step: float) -> tuple[Points, int]:
    """Forward-difference Jacobian per vertex (3 calls + 1), one linear solve."""
    idx = np.asarray(indices)
    base = blackbox(rest)[idx]
    jac = np.empty((len(idx), 3, 3))
    for axis in range(3):
        moved = rest.copy()
        moved[idx, axis] += step
        jac[:, :, axis] = (blackbox(moved)[idx] - base) / step
    d = np.linalg.solve(jac, (sculpt[idx] - base)[..., None])[..., 0]
    return d, 4


def literal_powell(blackbox: Callable[[Points], Points], rest: Points, sculpt: Points, vertex: int,
                   *, xtol: float = 1e-10, ftol: float = 1e-16) -> tuple[NDArray[np.float64], int]:
    """One vertex: scipy Powell, each evaluation a whole-mesh black-box call."""
    target = sculpt[vertex]

    def f(d: NDArray[np.float64]) -> float:
        moved = rest.copy()
        moved[vertex] += d
        r = target - blackbox(moved)[vertex]
        return float(r @ r)

    res = minimize(f, np.zeros(3), method="Powell", options={"xtol": xtol, "ftol": ftol, "maxfev": 20000})
    return res.x, int(res.nfev)
