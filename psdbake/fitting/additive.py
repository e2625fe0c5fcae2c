"""Per-joint terms fitted from whatever sculpts exist: additive kernel ridge regression.

Model. Each joint j that can explain some sculpted point (``locality``) has a group driven by j
alone: a cardinal RBF over j's pose coordinates x_j with centres c_(j,1..L) and the bind pose
(weight 0 there), so its weights b_(j,l) vanish when j is at bind (in kernel terms: the kernel
conditioned to vanish at bind, k~(x, c) = k(x, c) - k(x, 0) k(0, c) / k(0, 0), spans the same
functions). Its BlendShape for column l holds s_(j,l), the term's value at centre l. At a pose
the additive part of the corrective of point v is

    A(x)[v] = sum_(j in J(v)) sum_l b_(j,l)(x_j) s_(j,l)[v]

Fit, per set of points sharing the same joints J (a signature: one small dense solve, every
point of it a right-hand side):

- a joint sculpted alone (some example moves it and nothing else) is taken as sculpted: its
  values are fitted to those examples only, exactly where its centres allow;
- the other joints' values minimise, over every example that moves a joint of J,
  sum_k w_k |A(x_k) - d_k|^2 + sum_j s_j^T Q_j s_j, where Q_j is the RKHS norm of the term
  (the interpolant's kernel coefficients c = C s give c^T K c), w_k = 1 / ``tol.ADDITIVE_RIDGE``
  for an example that moves two or more joints of J and 1 / ``tol.ADDITIVE_RIDGE_EXACT`` for
  one that moves a single one (there the additive part is all there is). As the ridge goes to 0
  this is the minimum-norm additive interpolant. Where the examples tell the joints apart only by
  cancellation (frames of a shot where they all move, some sculpted and some left as they
  were), that interpolant is steep through close centres and swells off the shot: the ridge is
  raised tenfold at a time (to ``tol.ADDITIVE_RIDGE_MAX``) until no term exceeds
  ``tol.ADDITIVE_AMPLIFICATION`` times the largest sculpted offset at its probe poses (its joint
  turned 15-90 degrees: ``_probe_poses``).

Centres. A joint's centres are its poses in the examples that move it (those where it moves
alone, when there are any), farthest from the bind pose and from each other first, each kept
only while the group's system stays within ``tol.JOINT_TERM_COND_TARGET``: a regression needs the term
smooth, not a centre per example, and nearly equal poses would otherwise force a narrow kernel.
sigma is ``tol.JOINT_SIGMA`` (``--sigma`` overrides): a group's centres and sigma depend on its
own joint's poses alone, whichever other sculpts share the fit.

What the additive part leaves at each example (``interactions``) goes into gated combination
terms, so that every example is reproduced.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from .. import tolerances as tol
from ..model.rbf import KERNELS, SCALE_FREE, distances
from . import rbf_fit as rbf
from .rbf_fit import CardinalRbf, RbfPlan

Joints = tuple[int, ...]


@dataclass(frozen=True)
class JointTerm:
    """One joint's term: its centres (example indices, the first with each pose) and its RBF."""

    joint: int
    solo: tuple[int, ...]  # examples that move this joint alone
    centres: tuple[int, ...]  # examples whose pose of this joint is a centre, in column order
    plan: RbfPlan  # centres with the bind pose first
    model: CardinalRbf  # one column per centre (the bind pose has none)
    basis: NDArray[np.float64]  # (K, L) the columns' weights at every example's pose
    penalty: NDArray[np.float64]  # (L, L) Q: the term's RKHS norm of values s is s^T Q s


def joint_sigma(kernel: str, sigma: float | None) -> float:
    """A joint group's sigma: ``--sigma``, else ``tol.JOINT_SIGMA`` (1 for scale-free kernels)."""
    if kernel in SCALE_FREE:
        return 1.0
    return float(sigma) if sigma is not None else tol.JOINT_SIGMA


def choose_centres(poses: NDArray[np.float64], kernel: str, sigma: float, degree: int, smoothing: float
                   ) -> list[int]:
    """Indices into poses (n, w) of the centres: farthest from the bind pose and the centres so
    far first; a pose is kept when it is not a duplicate (``tol.DUPLICATE_POSE_ATOL``) and the
    system over the bind pose and the centres stays within ``tol.JOINT_TERM_COND_TARGET``."""
    chosen: list[int] = []
    points = [np.zeros(poses.shape[1])]
    gap = np.linalg.norm(poses, axis=1)
    left = list(range(len(poses)))
    while left:
        i = max(left, key=lambda n: (gap[n], -n))
        left.remove(i)
        if gap[i] <= tol.DUPLICATE_POSE_ATOL:
            continue
        trial = np.array([*points, poses[i]])
        system = rbf.System(trial, kernel, degree, smoothing)
        if len(trial) > len(system.powers) and system.condition(sigma) <= tol.JOINT_TERM_COND_TARGET:
            chosen.append(i)
            points.append(poses[i])
            gap = np.minimum(gap, np.linalg.norm(poses - poses[i], axis=1))
    return chosen


def plan_term(joint: int, coords: NDArray[np.float64], active: Sequence[frozenset[int]], labels: Sequence[str],
              kernel: str, sigma: float | None, degree: int | None, smoothing: float, where_: str,
              clamp: bool = False, normalize: bool = False) -> JointTerm | None:
    """Joint ``joint``'s term over the examples' pose coordinates (K, J, w); None when no
    pose of it can be a centre. clamp, normalize: the stored options (``weights.apply_options``),
    applied to its weights at the examples as eval will apply them, so the fit is exact for them."""
    solo = tuple(k for k, a in enumerate(active) if a == {joint})
    moving = list(solo) if solo else [k for k, a in enumerate(active) if joint in a]
    deg = rbf.default_degree(kernel) if degree is None else int(degree)
    sig = joint_sigma(kernel, sigma)
    picks = choose_centres(coords[moving, joint], kernel, sig, deg, 0.0)  # the interpolant's conditioning
    if not picks:
        return None
    centres = tuple(moving[i] for i in picks)
    full = np.concatenate([np.zeros((1, coords.shape[2])), coords[list(centres), joint]])
    plan = rbf.plan_rbf(full, list(range(1, len(full))), ["bind", *(labels[k] for k in centres)], kernel=kernel,
                        sigma=sigma, degree=deg, smoothing=smoothing, where=where_, start=sig)
    model = plan.model(list(range(1, len(full))))
    exact = model
    if smoothing > 0:  # values fitted through the interpolant, weights written smoothed: the
        # product then approximates the examples by request (as a group of explicit drivers
        # whose shapes are its sculpts does) instead of undoing the smoothing
        exact = rbf.plan_rbf(full, list(range(1, len(full))), ["bind", *(labels[k] for k in centres)], kernel=kernel,
                             sigma=plan.sigma, degree=deg, smoothing=0.0, where=where_).model(list(range(1, len(full))))
    basis = exact.weights(coords[:, joint])
    if clamp:
        basis = np.clip(basis, 0.0, 1.0)
    if normalize:
        basis = basis / np.maximum(1.0, basis.sum(axis=1, keepdims=True))
    k = len(full)
    kernel_matrix = KERNELS[kernel](distances(plan.centers, plan.centers) / plan.sigma)
    c = exact.coefficients[:k]
    penalty = c.T @ kernel_matrix @ c
    return JointTerm(joint=joint, solo=solo, centres=centres, plan=plan, model=model, basis=basis,
                     penalty=(penalty + penalty.T) / 2)


def fit_signature(terms: Sequence[JointTerm], active: Sequence[frozenset[int]], data: NDArray[np.float64]
                  ) -> tuple[dict[int, NDArray[np.float64]], NDArray[np.float64]]:
    """(joint -> its values s_j (L_j, n, c), what the terms leave d_k - A(x_k) (K, n, c)) at the
    points of one signature, whose offsets are data (K, n, c) at every example; terms are the
    signature's joints' terms."""
    count, n, c = data.shape
    joints = {t.joint for t in terms}
    out: dict[int, NDArray[np.float64]] = {}
    rest = data.reshape(count, n * c).copy()
    for t in terms:  # joints sculpted alone: as sculpted
        if t.solo:
            rows = list(t.solo)
            s = _least_squares(t.basis[rows], rest[rows])
            out[t.joint] = s.reshape(-1, n, c)
    for t in terms:
        if t.joint in out:
            rest -= t.basis @ out[t.joint].reshape(-1, n * c)
    free = [t for t in terms if t.joint not in out]
    if free:
        rows = [k for k, a in enumerate(active) if a & joints]
        shared = np.array([len(active[k] & joints) > 1 for k in rows])
        root = scipy.linalg.block_diag(*[_root(t.penalty) for t in free])
        probes = [t.model.weights(_probe_poses(t)) for t in free]
        bound = tol.ADDITIVE_AMPLIFICATION * float(np.abs(data).max(initial=0.0))
        scale = 1.0
        while True:  # the ridge where several joints move, raised while a term swells off the examples
            ridge = np.where(shared, tol.ADDITIVE_RIDGE * scale, tol.ADDITIVE_RIDGE_EXACT)
            basis = np.concatenate([t.basis[rows] for t in free], axis=1) / np.sqrt(ridge)[:, None]
            lhs = np.concatenate([basis, root])
            rhs = np.concatenate([rest[rows] / np.sqrt(ridge)[:, None], np.zeros((len(root), n * c))])
            s = _least_squares(lhs, rhs)
            if not shared.any() or scale * tol.ADDITIVE_RIDGE >= tol.ADDITIVE_RIDGE_MAX or \
                    _largest_value(probes, free, s) <= bound:
                break
            scale *= 10.0
        rest -= np.concatenate([t.basis for t in free], axis=1) @ s
        start = 0
        for t in free:
            size = t.basis.shape[1]
            out[t.joint] = s[start:start + size].reshape(size, n, c)
            start += size
    return out, rest.reshape(count, n, c)


def _probe_poses(term: JointTerm) -> NDArray[np.float64]:
    """Poses of the term's joint off the examples, where a shot's motions take it: rotation
    vectors along each axis and each centre's direction, both ways, at ``tol.PROBE_ANGLES``
    (the rotation-vector pose space's coordinates; others are probed at the same points)."""
    centres = term.plan.centers[1:]  # the bind pose first
    dims = centres.shape[1]
    directions = [np.eye(dims)[i] for i in range(dims)]
    directions += [c / np.linalg.norm(c) for c in centres if np.linalg.norm(c) > 0]
    return np.array([sign * angle * d for d in directions for sign in (1.0, -1.0) for angle in tol.PROBE_ANGLES])


def _largest_value(probes: Sequence[NDArray[np.float64]], terms: Sequence[JointTerm], s: NDArray[np.float64]) -> float:
    """The largest value any of ``terms`` takes at its probe poses, with values ``s`` (stacked)."""
    largest, start = 0.0, 0
    for weights, t in zip(probes, terms, strict=True):
        size = t.basis.shape[1]
        largest = max(largest, float(np.abs(weights @ s[start:start + size]).max(initial=0.0)))
        start += size
    return largest


def _least_squares(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The minimum-norm least-squares solution of a x = b: a is small (examples + centres rows,
    centres columns), b has a column per point and coordinate, so the pseudo-inverse (SVD,
    LAPACK's default cutoff) is formed once and applied by one product."""
    return scipy.linalg.pinv(a) @ b


def _root(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """R with R^T R = Q for a symmetric positive semi-definite Q (negative round-off dropped)."""
    values, vectors = np.linalg.eigh(q)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))).T
