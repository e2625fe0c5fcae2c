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

Quasi-Newton refresh (``quasi_newton=True``, needs ``jacobian``). Before Powell's cycles,
each vertex takes quasi-Newton steps ``s = J^-1 r`` on its own 3x3 model, one lockstep
call per step. After every evaluated step the model takes the good-Broyden rank-one
update ``J += ((dr_obs - J s) s^T) / (s^T s)`` (``dr_obs`` the observed decrease of the
residual; the secant holds whether or not the step is accepted). A step is accepted only
where it lowers the vertex's objective; a rejected step shrinks that vertex's next step
to half its length (a trust radius), and a vertex rejected ``QN_MAX_REJECTS`` times in a
row, or whose model turns singular, leaves the quasi-Newton phase. Vertices not done
after it (or after ``QN_MAX_STEPS`` steps) go on to Powell's cycles with directions
refreshed from their updated model (the columns of ``J^-1``, conjugate for it) and that
model choosing the trial steps. Acceptance is still decided by function values alone.
On a smooth uncoupled chain Broyden's superlinear convergence finishes in a few calls
where Powell's cycles would cost 9-13 each.

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

from .. import tolerances as tol
from ..arrays import is_singular, row_norms

Offsets = NDArray[np.float64]  # (m, 3)
Residuals = NDArray[np.float64]  # (m, 3)
ResidualFn = Callable[[Offsets], Residuals]

CONVERGED, STALLED, MAX_CYCLES, NONFINITE, RUNNING = 0, 1, 2, 3, -1
STATUS_NAMES = {CONVERGED: "converged", STALLED: "stalled", MAX_CYCLES: "max_cycles", NONFINITE: "nonfinite"}

#: Most quasi-Newton steps (one lockstep call each) before Powell's cycles take over. Broyden
#: converges superlinearly from the linearised start: 3-5 steps on the bench's non-linear chain
#: (1e-2 down to 1e-6 of the diagonal); a vertex still running after 8 has a model too poor
#: for the secant updates to repair, and a Powell cycle (9-13 calls) is the better spend.
QN_MAX_STEPS = 8
#: A vertex whose quasi-Newton step fails to lower its objective this many times in a row
#: (each failure halves its next step) hands over to Powell's line searches.
QN_MAX_REJECTS = 3
#: A model with |det J| below this fraction of |J|_F^3 is singular for a quasi-Newton step
#: (as ``tolerances.JACOBIAN_RCOND`` for the initial one).
QN_RCOND = tol.JACOBIAN_RCOND


@dataclass(frozen=True)
class PowellResult:
    """Per-problem minimisers with their residuals and a shared evaluation count."""

    x: Offsets  # (m, 3) best point per problem
    residual: Residuals  # (m, 3) residual vector at x
    status: NDArray[np.int8]  # (m,) CONVERGED / STALLED / MAX_CYCLES / NONFINITE
    nfev: int  # residual-function calls (each one black-box call for all problems)
    cycles: int  # Powell cycles run by the slowest problem
    qn_steps: int = 0  # quasi-Newton steps (one call each) before Powell's cycles
    jacobian: NDArray[np.float64] | None = None  # (m, 3, 3) the Broyden-updated model, if any

    @property
    def residual_norm(self) -> NDArray[np.float64]:
        return row_norms(self.residual)  # np.linalg.norm(residual, axis=1), bit for bit


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


def _cofactors(m: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """The nine cofactors C_ij of each 3x3 block (row-major), each (k,), and the determinant
    by the first row's expansion, m00 C00 + m01 C01 + m02 C02."""
    a, b, c = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    d, e, f = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    g, h, i = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    with np.errstate(invalid="ignore", over="ignore"):
        c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
        det = a * c00 + b * c01 + c * c02
        return (c00, c01, c02, c * h - b * i, a * i - c * g, b * g - a * h, b * f - c * e, c * d - a * f,
                a * e - b * d, det)


def det3(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Determinants of 3x3 blocks (k, 3, 3) by cofactors: ~5x faster than ``np.linalg.det``'s
    batched LU on a million blocks, and the very value ``conditioned_inverses`` divides by."""
    return _cofactors(m)[-1]


def _adjugate_over(cofactors: list[NDArray[np.float64]], det: NDArray[np.float64]) -> NDArray[np.float64]:
    """The cofactors transposed (the adjugate), divided by det: (k, 3, 3) inverses."""
    c00, c01, c02, c10, c11, c12, c20, c21, c22 = cofactors
    adjugate = np.stack([c00, c10, c20, c01, c11, c21, c02, c12, c22], axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        adjugate /= det[:, None]  # in place: the stack is this function's own
    return adjugate.reshape(-1, 3, 3)


def _invertible(jac: NDArray[np.float64], det: NDArray[np.float64], rcond: float) -> NDArray[np.bool_]:
    """|det J| against |J|_F^3 (``arrays.is_singular``)."""
    return ~is_singular(jac, rcond, det)


def well_conditioned(jac: NDArray[np.float64], rcond: float = QN_RCOND) -> NDArray[np.bool_]:
    """Per problem: is the 3x3 model invertible? (``_invertible``)"""
    return _invertible(jac, det3(jac), rcond)


def conditioned_inverses(jac: NDArray[np.float64], rcond: float = QN_RCOND
                         ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """``well_conditioned(jac, rcond)`` and the inverses of the blocks that pass, from one set of
    cofactors: the adjugate over the determinant (Cramer's rule), in float64, ~3x faster than
    ``np.linalg.inv`` on a million blocks (per-vertex Jacobians). The two differ by rounding,
    relative ~eps |J|_F^3 / |det J| (the cofactors' cancellation), which on the blocks that pass
    is below eps / rcond (~2e-10 at JACOBIAN_RCOND; tests/test_powell.py): far below the
    forward-difference Jacobian's own error."""
    *cofactors, det = _cofactors(jac)
    ok = _invertible(jac, det, rcond)
    if ok.all():  # the usual case: no masked copies of the cofactors
        return ok, _adjugate_over(cofactors, det)
    return ok, _adjugate_over([c[ok] for c in cofactors], det[ok])


def broyden_update(
    jac: NDArray[np.float64], mask: NDArray[np.bool_], step: Offsets, decrease: Residuals, min_step: NDArray[np.float64]
) -> None:
    """Good-Broyden rank-one update of the model ``r(x + s) ~ r(x) - J s``, in place, where
    ``mask``: ``J += ((dr - J s) s^T) / (s^T s)`` with ``dr = r(x) - r(x + s)`` observed.

    Skipped where the step is not longer than ``min_step`` (the float32 noise of the black
    box would then dominate the secant) or the observation is not finite.
    """
    rows = np.nonzero(mask)[0]
    s, dr = step[rows], decrease[rows]
    ss = np.einsum("ij,ij->i", s, s)
    use = (ss > min_step[rows] ** 2) & np.all(np.isfinite(dr), axis=1) & np.all(np.isfinite(s), axis=1)
    if not use.any():
        return
    rows, s, dr, ss = rows[use], s[use], dr[use], ss[use]
    j = jac[rows]
    miss = dr - np.einsum("kab,kb->ka", j, s)
    jac[rows] = j + miss[:, :, None] * s[:, None, :] / ss[:, None, None]


def _quasi_newton(
    state: _Lockstep,
    jac: NDArray[np.float64],
    status: NDArray[np.int8],
    settle: Callable[[], None],
    floor: NDArray[np.float64],
    ftol: float,
    max_steps: int,
) -> int:
    """Broyden-updated quasi-Newton steps in lockstep (see the module docstring); returns the
    number of steps (= calls). Leaves ``status`` RUNNING on the vertices Powell must finish."""
    m = len(jac)
    radius = np.full(m, np.inf)
    rejects = np.zeros(m, dtype=np.intp)
    steps = 0
    while steps < max_steps:
        qn = (status == RUNNING) & (rejects < QN_MAX_REJECTS)
        if not qn.any():
            break
        qn[qn] = well_conditioned(jac[qn])
        if not qn.any():
            break
        step = np.zeros_like(state.x)
        step[qn] = np.linalg.solve(jac[qn], state.r[qn][:, :, None])[:, :, 0]
        length = np.linalg.norm(step, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            shrink = np.where(length > radius, radius / length, 1.0)
        step *= np.where(np.isfinite(shrink), shrink, 0.0)[:, None]
        qn &= np.all(np.isfinite(step), axis=1)
        if not qn.any():
            break
        steps += 1
        xt, rt, ft = state.trial(qn, step)
        broyden_update(jac, qn, step, state.r - rt, floor)
        f0 = state.f.copy()
        better = qn & (ft < f0)
        # A decrease below Powell's relative test is no progress either (float32 noise level).
        with np.errstate(invalid="ignore"):
            progress = better & (2.0 * (f0 - ft) > ftol * (np.abs(f0) + np.abs(ft)) + 1e-300)
        state.accept(better, xt, rt, ft)
        rejects[progress] = 0
        radius[progress] = np.inf
        failed = qn & ~progress
        rejects[failed] += 1
        radius[failed] = 0.5 * np.linalg.norm(step[failed], axis=1)
        settle()
    return steps


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
    quasi_newton: bool = False,
    max_qn_steps: int = QN_MAX_STEPS,
) -> PowellResult:
    """Run Powell's method on m independent 3-D least-squares problems at once.

    residual: maps X (m, 3) to R (m, 3); row k depends on X[k] only.
    x0: starting points (m, 3). r0: residual at x0 if already known (saves a call).
    directions: (m, 3, 3) initial direction set, ``directions[k, j]`` is direction j
        of problem k (default: the coordinate axes, as scipy).
    jacobian: (m, 3, 3) linear model of ``-dr/dx``: chooses trial steps (and, with
        ``quasi_newton``, the quasi-Newton steps); never decides which point wins.
    atol: residual norm at which a problem is done (scalar or per problem).
    min_step: smallest trial step (absolute), e.g. a few float32 ulps of the data.
    quasi_newton: with ``jacobian``, first take Broyden-updated quasi-Newton steps (one call
        each, at most ``max_qn_steps``) and start Powell's cycles from the updated model and
        its conjugate directions; False runs Powell alone (the benchmarks' "old" path).
    """
    x0 = np.asarray(x0, dtype=np.float64)
    m = len(x0)
    state = _Lockstep(residual, x0, r0)
    atol_v = np.broadcast_to(np.asarray(atol, dtype=np.float64), (m,))
    floor = np.full(m, float(min_step))
    status = np.full(m, RUNNING, dtype=np.int8)

    def settle() -> None:
        done = (status == RUNNING) & (state.f <= atol_v * atol_v)
        status[done] = CONVERGED

    settle()
    if not (status == RUNNING).any():  # done at x0 (a linearised start that hit): no direction set to copy
        model = np.array(jacobian, dtype=np.float64) if quasi_newton and jacobian is not None else None
        return _finished(state, status, cycles=0, qn_steps=0, jacobian=model)
    direc = np.tile(np.eye(3), (m, 1, 1)) if directions is None else np.array(directions, dtype=np.float64)
    qn_steps = 0
    if quasi_newton and jacobian is not None:
        jacobian = np.array(jacobian, dtype=np.float64)  # a copy: updated in place
        qn_steps = _quasi_newton(state, jacobian, status, settle, floor, ftol, max_qn_steps)
        refresh = status == RUNNING
        refresh[refresh], inverses = conditioned_inverses(jacobian[refresh])
        if refresh.any():
            direc[refresh] = np.transpose(inverses, (0, 2, 1))  # row j = J^-1 e_j
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

    return _finished(state, status, cycles=cycles, qn_steps=qn_steps, jacobian=jacobian if quasi_newton else None)


def _finished(state: _Lockstep, status: NDArray[np.int8], *, cycles: int, qn_steps: int,
              jacobian: NDArray[np.float64] | None) -> PowellResult:
    """The result once the lockstep stops: problems still running ran out of cycles, and a
    never-finite residual says so whatever else happened."""
    status[status == RUNNING] = MAX_CYCLES
    nonfinite = ~np.isfinite(state.f)
    status[nonfinite] = NONFINITE
    return PowellResult(
        x=state.x, residual=state.r, status=status, nfev=state.nfev, cycles=cycles, qn_steps=qn_steps,
        jacobian=jacobian,
    )
