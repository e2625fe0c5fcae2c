"""Powell's direction-set method, run in lockstep over many independent 3-D problems.

Model. There are ``m`` independent problems (one per sculpted vertex)::

    minimise  f_k(x_k) = || r_k(x_k) ||^2     x_k in R^3,  k = 0..m-1

and one call of ``residual(X)`` with ``X`` of shape (m, 3) returns every ``r_k(X[k])``
at once: one whole-mesh black-box call serves all vertices. Each vertex keeps its own
direction set, line minimisations, Powell direction updates and convergence test
(exactly the per-problem state of ``scipy.optimize.minimize(method="Powell")``); the
vertices only share *when* the black box is called. A vertex that has finished keeps
its best point while the others go on.

Line minimisation is parabolic (Brent-style, derivative-free): from the current
point, evaluate at ``+a`` and ``-a`` along the direction, fit a parabola through the
three values, evaluate its vertex (clamped to ``LINE_SEARCH_GROW_LIMIT`` trial steps)
and keep the best of the four points. On an exactly quadratic objective this is an
exact line minimisation in three calls, and a conjugate direction set then finishes
in one cycle.

The trial step ``a`` comes from an optional linear model ``r(x) ~ r - J x`` (``J``:
per-vertex 3x3): ``a = (r . J u) / |J u|^2``, floored so the parabola stays well
posed. The model only picks where to sample; which point wins is decided by
function values alone, so the method stays derivative-free and a wrong model costs
evaluations, not correctness.

Statuses (``PowellResult.status``): ``CONVERGED`` residual norm <= ``atol``;
``STALLED`` Powell's relative-decrease test met above ``atol`` (a local minimum,
e.g. an unreachable target); ``MAX_CYCLES``; ``NONFINITE`` the residual was never
finite.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import tolerances as tol

Offsets = NDArray[np.float64]  # (m, 3)
Residuals = NDArray[np.float64]  # (m, 3)
ResidualFn = Callable[[Offsets], Residuals]

CONVERGED, STALLED, MAX_CYCLES, NONFINITE, RUNNING = 0, 1, 2, 3, -1
STATUS_NAMES = {CONVERGED: "converged", STALLED: "stalled", MAX_CYCLES: "max_cycles", NONFINITE: "nonfinite"}


@dataclass(frozen=True)
class PowellResult:
    """Per-problem minimisers with their residuals and a shared evaluation count."""

    x: Offsets  # (m, 3) best point per problem
    residual: Residuals  # (m, 3) residual vector at x
    status: NDArray[np.int8]  # (m,) CONVERGED / STALLED / MAX_CYCLES / NONFINITE
    nfev: int  # residual-function calls (each one black-box call for all problems)
    cycles: int  # Powell cycles run by the slowest problem

    @property
    def residual_norm(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.residual, axis=1)


def _objective(r: Residuals) -> NDArray[np.float64]:
    f = np.einsum("ij,ij->i", r, r)
    return np.where(np.isfinite(f), f, np.inf)


class _Lockstep:
    """Holds the shared state: best point, residual and objective per problem."""

    def __init__(self, residual: ResidualFn, x0: Offsets, r0: Residuals | None) -> None:
        self.residual = residual
        self.nfev = 0
        self.x = np.array(x0, dtype=np.float64, copy=True)
        self.r = self.call(self.x) if r0 is None else np.array(r0, dtype=np.float64)
        self.f = _objective(self.r)

    def call(self, x: Offsets) -> Residuals:
        self.nfev += 1
        r = np.asarray(self.residual(x), dtype=np.float64)
        if r.shape != x.shape:
            raise ValueError(f"residual function returned shape {r.shape}, expected {x.shape}")
        return r

    def trial(self, active: NDArray[np.bool_], steps: Offsets) -> tuple[Offsets, Residuals, NDArray[np.float64]]:
        """Evaluate x + steps on the active problems (others sit at their best point)."""
        xt = self.x.copy()
        xt[active] += steps[active]
        rt = self.call(xt)
        ft = np.full(len(xt), np.inf)
        ft[active] = _objective(rt[active])
        return xt, rt, ft

    def accept(self, mask: NDArray[np.bool_], x: Offsets, r: Residuals, f: NDArray[np.float64]) -> None:
        self.x[mask], self.r[mask], self.f[mask] = x[mask], r[mask], f[mask]

    def line_minimise(
        self, active: NDArray[np.bool_], u: Offsets, a: NDArray[np.float64]
    ) -> None:
        """Parabolic line minimisation along u (m, 3) with trial steps a (m,): 3 calls."""
        f0 = self.f.copy()
        xp, rp, fp = self.trial(active, a[:, None] * u)
        xm, rm, fm = self.trial(active, -a[:, None] * u)
        # f(alpha) ~ f0 + g alpha + c alpha^2 through alpha = -a, 0, +a
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            c = (fp + fm - 2.0 * f0) / (2.0 * a * a)
            g = (fp - fm) / (2.0 * a)
            alpha = -g / (2.0 * c)
        limit = tol.LINE_SEARCH_GROW_LIMIT * np.abs(a)
        # Not convex along the line (or non-finite): step towards the better side, doubled.
        fallback = np.where(fp <= fm, 2.0 * a, -2.0 * a)
        alpha = np.where(np.isfinite(alpha) & (c > 0), alpha, fallback)
        alpha = np.clip(alpha, -limit, limit)
        xs, rs, fs = self.trial(active, alpha[:, None] * u)
        for xc, rc, fc in ((xp, rp, fp), (xm, rm, fm), (xs, rs, fs)):
            better = active & (fc < self.f)
            self.accept(better, xc, rc, fc)


def _trial_steps(r: Residuals, ju: Offsets | None, u: Offsets, floor: NDArray[np.float64]) -> NDArray[np.float64]:
    """Step along u that the linear model predicts, floored to sample a real parabola."""
    if ju is not None:
        jj = np.einsum("ij,ij->i", ju, ju)
        with np.errstate(invalid="ignore", divide="ignore"):
            predicted = np.einsum("ij,ij->i", r, ju) / jj
            spread = 0.25 * np.linalg.norm(r, axis=1) / np.sqrt(jj)
        a = np.where(np.isfinite(predicted), np.abs(predicted), 0.0)
        a = np.maximum(a, np.where(np.isfinite(spread), spread, 0.0))
        sign = np.where(np.isfinite(predicted) & (predicted < 0), -1.0, 1.0)
    else:
        a = np.linalg.norm(r, axis=1) / np.maximum(np.linalg.norm(u, axis=1), 1e-300)
        sign = np.ones(len(r))
    a = np.where(np.isfinite(a), a, 0.0)
    return sign * np.maximum(a, floor)


def minimize_lockstep(
    residual: ResidualFn,
    x0: Offsets,
    *,
    directions: NDArray[np.float64] | None = None,
    jacobian: NDArray[np.float64] | None = None,
    r0: Residuals | None = None,
    atol: float | NDArray[np.float64] = 0.0,
    min_step: float = 1e-8,
    ftol: float = tol.POWELL_FTOL,
    max_cycles: int = tol.POWELL_MAX_CYCLES,
) -> PowellResult:
    """Run Powell's method on m independent 3-D least-squares problems at once.

    residual: maps X (m, 3) to R (m, 3); row k depends on X[k] only.
    x0: starting points (m, 3). r0: residual at x0 if already known (saves a call).
    directions: (m, 3, 3) initial direction set, ``directions[k, j]`` is direction j
        of problem k (default: the coordinate axes, as scipy).
    jacobian: (m, 3, 3) linear model of ``-dr/dx`` used only to choose trial steps.
    atol: residual norm at which a problem is done (scalar or per problem).
    min_step: smallest trial step (absolute), e.g. a few float32 ulps of the data.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    m = len(x0)
    state = _Lockstep(residual, x0, r0)
    direc = np.tile(np.eye(3), (m, 1, 1)) if directions is None else np.array(directions, dtype=np.float64)
    atol_v = np.broadcast_to(np.asarray(atol, dtype=np.float64), (m,))
    floor = np.full(m, float(min_step))
    status = np.full(m, RUNNING, dtype=np.int8)

    def settle() -> None:
        done = (status == RUNNING) & (state.f <= atol_v * atol_v)
        status[done] = CONVERGED

    settle()
    cycles = 0
    while (status == RUNNING).any() and cycles < max_cycles:
        cycles += 1
        f_start, x_start = state.f.copy(), state.x.copy()
        biggest_drop = np.zeros(m)
        biggest_index = np.zeros(m, dtype=np.intp)
        for j in range(3):
            active = status == RUNNING
            if not active.any():
                break
            u = direc[:, j, :]
            ju = None if jacobian is None else np.einsum("kab,kb->ka", jacobian, u)
            a = _trial_steps(state.r, ju, u, floor)
            f_before = state.f.copy()
            state.line_minimise(active, u, a)
            drop = np.where(active, f_before - state.f, 0.0)
            bigger = drop > biggest_drop
            biggest_drop[bigger], biggest_index[bigger] = drop[bigger], j
            settle()
        active = status == RUNNING
        if not active.any():
            break
        # Powell's termination test, as scipy: 2 (f_start - f) <= ftol (|f_start| + |f|)
        stalled = active & (2.0 * (f_start - state.f) <= ftol * (np.abs(f_start) + np.abs(state.f)) + 1e-300)
        status[stalled] = STALLED
        active = status == RUNNING
        if not active.any() or cycles >= max_cycles:
            break
        # Powell's direction update: extrapolate along the cycle's displacement and,
        # where the test says the new direction is worth it, line-minimise along it
        # and let it replace the direction of largest decrease.
        displacement = state.x - x_start
        fval = state.f.copy()
        _, _, fx2 = state.trial(active, displacement)
        with np.errstate(invalid="ignore", over="ignore"):
            t = 2.0 * (f_start + fx2 - 2.0 * fval) * (f_start - fval - biggest_drop) ** 2
            t -= biggest_drop * (f_start - fx2) ** 2
        replace = active & (f_start > fx2) & (t < 0.0) & np.isfinite(t)
        if replace.any():
            ju = None if jacobian is None else np.einsum("kab,kb->ka", jacobian, displacement)
            length = np.maximum(np.linalg.norm(displacement, axis=1), 1e-300)
            a = _trial_steps(state.r, ju, displacement, floor / length)
            state.line_minimise(replace, displacement, np.where(replace, a, 1.0))
            rows = np.nonzero(replace & np.any(displacement != 0.0, axis=1))[0]
            big = biggest_index[rows]
            direc[rows, big] = direc[rows, 2]
            direc[rows, 2] = displacement[rows]
            settle()

    status[status == RUNNING] = MAX_CYCLES
    nonfinite = ~np.isfinite(state.f)
    status[nonfinite] = NONFINITE
    return PowellResult(x=state.x, residual=state.r, status=status, nfev=state.nfev, cycles=cycles)
