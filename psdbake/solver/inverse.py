"""The black-box inverse of one example: which vertices, solve, how well.

For example i with black box ``SKINNING_i`` (rest points -> posed points), find for
every sculpted vertex v the rest-space offset d'_v minimising::

    || sculpt_v - SKINNING_i(rest + d')_v ||^2

The solver only *calls* ``SKINNING_i``; it never reads joint weights or matrices.
All sculpted vertices are solved together by ``powell.minimize_lockstep`` (one
black-box call evaluates every vertex's trial point), started from the one-shot
linearisation: three extra calls give a forward-difference Jacobian J per vertex,
whose inverse columns are conjugate directions for ``|J d - r|^2`` and whose
solution ``J^-1 r`` is the starting point. Where that start misses the tolerance (a
non-linear chain), each vertex's J takes a good-Broyden update from the step just
observed and quasi-Newton steps follow (one call each, accepted only where the
residual drops); Powell's own line minimisations and direction updates, along the
refreshed conjugate directions, finish whatever the model cannot. This assumes each output
vertex depends on its own input vertex only, as skinning does (the paper's
per-vertex formulation); a user deformer that couples vertices is solved
approximately.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..arrays import Points, row_norms
from ..errors import SculptOutOfRangeError
from . import powell

BlackBox = Callable[[Points], Points]
#: ``invert_example_with(stop_if_coupled=True)`` stopped after the linearised start: the chain couples vertices.
COUPLING_SEEN = "coupling seen"


@dataclass(frozen=True)
class LinearisedStart:
    """What the per-vertex solver measured before it saw the chain couple vertices, handed to
    the joint solve so that it pays for none of it again: the chain at rest, the per-vertex
    3x3 blocks (forward differences moving every sculpted vertex along x, then y, then z) and
    the linearised start's offsets with their outputs (one call each)."""

    posed_rest: Points  # (n, 3) the chain's output at rest
    blocks: NDArray[np.float64]  # (k, 3, 3) d posed / d rest at the sculpted vertices
    start: Points  # (k, 3) the offsets J^-1 r
    start_outputs: Points  # (k, 3) the chain's output at rest + start, on the sculpted vertices
    floor: float  # float32 floor of the data (``tolerances.float32_floor``)


@dataclass(frozen=True)
class InverseResult:
    """Rest-space offsets for the sculpted vertices of one example."""

    indices: NDArray[np.int64]  # (k,) sculpted vertex indices, ascending
    offsets: NDArray[np.float64]  # (k, 3) rest-space offsets d'
    residual: NDArray[np.float64]  # (k,) |sculpt - SKINNING(rest + d')| per vertex
    status: NDArray[np.int8]  # (k,) powell status codes
    evaluations: int  # black-box calls, all of them (detection, Jacobian, Powell)
    diagonal: float  # bounding-box diagonal of the skinned rest shape, the unit of tolerances
    atol: float  # absolute residual tolerance used
    seconds: float
    #: how the example was solved: "per-vertex" (each output vertex depends on its own input
    #: vertex only, as skinning: Powell in lockstep) or another regime the solver detected
    regime: str = "per-vertex"
    #: quasi-Newton (Broyden) steps and Powell cycles after the linearised start (one call per
    #: step; 3 per line minimisation in a cycle)
    qn_steps: int = 0
    cycles: int = 0
    #: RMS over the sculpted vertices of the sculpt's own displacement from the chain at rest:
    #: the unit of ``unreachable_fraction`` (0 when nothing was sculpted)
    sculpt_rms: float = 0.0
    #: the solve ended at a least-squares optimum (the last attempts could not lower the
    #: residual along any direction they tried), not on its call budget: vertices still above
    #: the tolerance there are what the chain cannot reproduce (coupled regimes only)
    at_optimum: bool = False
    #: set with regime ``COUPLING_SEEN``: the per-vertex solver's measurements, for the joint solve
    linearised: LinearisedStart | None = field(default=None, repr=False, compare=False)

    @property
    def missed(self) -> NDArray[np.int64]:
        """Indices of vertices that did not reach the tolerance."""
        return self.indices[self.status != powell.CONVERGED]

    @property
    def missed_statuses(self) -> dict[str, int]:
        """Why vertices missed: status name -> count (``stalled``, ``max_cycles``, ``nonfinite``).
        A chain that snaps or jumps shows as stalled vertices, a budget spent as max_cycles."""
        codes, counts = np.unique(self.status[self.status != powell.CONVERGED], return_counts=True)
        return {powell.STATUS_NAMES[int(c)]: int(n) for c, n in zip(codes, counts, strict=True)}

    @property
    def max_residual(self) -> float:
        return float(self.residual.max()) if len(self.residual) else 0.0

    @property
    def rms_residual(self) -> float:
        return float(np.sqrt(np.mean(self.residual**2))) if len(self.residual) else 0.0

    @property
    def unreachable_fraction(self) -> float:
        """The share of the sculpt (RMS over the sculpted vertices, relative to the sculpt's
        own displacement from the chain at rest) that the fitted offsets do not reproduce."""
        return self.rms_residual / self.sculpt_rms if self.sculpt_rms > 0 else 0.0


class Counted:
    """The black box, counting its calls (``InverseResult.evaluations``), from ``calls``.

    The last call's points and outputs are kept: a stage that starts where the one before it
    ended (measured directions after Newton-Krylov's last accepted step) asks for the same points
    again, and a deterministic chain gives the same outputs, so that costs no call."""

    def __init__(self, blackbox: BlackBox, calls: int = 0) -> None:
        self.blackbox, self.calls = blackbox, calls
        self._last: tuple[Points, Points] | None = None

    def __call__(self, points: Points) -> Points:
        if self._last is not None and np.array_equal(self._last[0], points):
            return self._last[1].copy()
        self.calls += 1
        out = self.blackbox(points)
        self._last = (np.array(points, copy=True), np.array(out, copy=True))
        return out


def _jacobians(
    blackbox: BlackBox, rest: Points, idx: NDArray[np.int64], posed_rest: Points, step: float,
    moved: Points | None = None,
) -> tuple[NDArray[np.float64], bool]:
    """Forward-difference d posed / d rest at every sculpted vertex: 3 black-box calls. Also
    whether the chain couples vertices, for free: only sculpted vertices move in these calls,
    so any other vertex whose output changes was moved by a neighbour (Delta Mush, smoothing).
    moved: a copy of rest to move the vertices in (left equal to rest), else one is made."""
    jac = np.empty((len(idx), 3, 3))
    coupled = False
    base = np.take(posed_rest, idx, axis=0)  # take: rows[idx] 4x faster than fancy indexing, the same copy
    moved = rest.copy() if moved is None else moved
    for axis in range(3):
        moved[idx, axis] += step
        out = blackbox(moved)
        moved[idx, axis] = rest[idx, axis]  # back to rest for the next axis
        column = np.take(out, idx, axis=0)
        column -= base
        column /= step
        jac[:, :, axis] = column
        # Did any row outside idx change? More changed entries in all rows than in idx's rows
        # (idx is unique) says so, without writing False over idx's rows of the (n, 3) mask.
        changed = out != posed_rest
        coupled |= bool(np.count_nonzero(changed) > np.count_nonzero(np.take(changed, idx, axis=0)))
        del out, column, changed  # freed before the next call makes its own (one output alive, not two)
    return jac, coupled


def _conjugate_start(
    jac: NDArray[np.float64], r0: Points
) -> tuple[NDArray[np.float64], Points, NDArray[np.bool_]]:
    """Directions J^-1 e_j and start J^-1 r per vertex; identity/zero where J is singular."""
    # Conditioning test without an SVD (a third of an LBS example's time at 100k vertices).
    ok, inv = powell.conditioned_inverses(jac, tol.JACOBIAN_RCOND)  # adjugate / det, where well-conditioned
    if ok.all():  # the usual case: every J invertible, so no identity rows to fill in and mask over
        return np.transpose(inv, (0, 2, 1)).copy(), np.einsum("kab,kb->ka", inv, np.ascontiguousarray(r0)), ok
    directions = np.tile(np.eye(3), (len(jac), 1, 1))
    start = np.zeros_like(r0)
    if ok.any():
        directions[ok] = np.transpose(inv, (0, 2, 1))  # row j = column j of J^-1
        start[ok] = np.einsum("kab,kb->ka", inv, r0[ok])
    return directions, start, ok


def sculpted_vertices(rest: Points, posed_rest: Points, sculpt: Points) -> tuple[float, float, NDArray[np.int64]]:
    """(bounding-box diagonal of the posed rest shape, float32 floor of the data, the vertices
    the sculpt moved); refuses a vertex absurdly far from its skinned position."""
    diagonal = tol.bbox_diagonal(posed_rest)
    moved_by = row_norms(sculpt, posed_rest)
    worst = int(np.argmax(moved_by)) if len(moved_by) else 0
    if len(moved_by) and moved_by[worst] > tol.ABSURD_SCULPT_DIAGONALS * diagonal:
        raise SculptOutOfRangeError(worst, float(moved_by[worst]), diagonal)
    floor = max(tol.float32_floor(posed_rest), tol.float32_floor(rest))  # the floor of both, no joined copy
    unmoved = max(tol.UNMOVED_RTOL * diagonal, floor)
    return diagonal, floor, np.nonzero(moved_by > unmoved)[0].astype(np.int64)


def invert_example(
    blackbox: BlackBox,
    rest: Points,
    sculpt: Points,
    *,
    rtol: float = tol.INVERSE_RTOL,
    max_cycles: int = tol.POWELL_MAX_CYCLES,
) -> InverseResult:
    """Solve the rest-space offsets that make ``blackbox`` reproduce ``sculpt``.

    rest, sculpt: (n, 3) float64. rtol: residual tolerance as a fraction of the
    bounding-box diagonal of the skinned rest shape (never below the float32 floor of
    the data). Raises SculptOutOfRangeError for a vertex absurdly far from its skinned position.
    """
    return invert_example_with(blackbox, rest, sculpt, rtol=rtol, max_cycles=max_cycles)


def invert_example_with(
    blackbox: BlackBox,
    rest: Points,
    sculpt: Points,
    *,
    rtol: float = tol.INVERSE_RTOL,
    max_cycles: int = tol.POWELL_MAX_CYCLES,
    quasi_newton: bool = True,
    stop_if_coupled: bool = False,
    coupling_probe: Callable[[BlackBox, Points, NDArray[np.int64], float], bool] | None = None,
) -> InverseResult:
    """``invert_example`` with the solver's switches. ``quasi_newton=False`` skips the
    Broyden refresh and runs Powell alone after the linearised start (the benchmarks'
    reference method, side by side). ``stop_if_coupled``: when
    the Jacobian calls show the chain couples vertices and the linearised start misses the
    tolerance, return there (regime ``COUPLING_SEEN``, 5 calls) for a joint solve to take over.
    ``coupling_probe(call, posed_rest, idx, step)`` is asked, when the Jacobian calls showed no
    coupling and the start misses, whether the chain couples vertices all the same (a sculpt
    that covers whole pieces of the mesh leaves no unsculpted neighbour to show it)."""
    started = time.perf_counter()
    rest = np.asarray(rest, dtype=np.float64)
    sculpt = np.asarray(sculpt, dtype=np.float64)
    call = Counted(blackbox)

    posed_rest = call(rest)
    diagonal, floor, idx = sculpted_vertices(rest, posed_rest, sculpt)
    atol = max(rtol * diagonal, floor)
    if len(idx) == 0:
        return InverseResult(
            indices=idx, offsets=np.zeros((0, 3)), residual=np.zeros(0), status=np.zeros(0, np.int8),
            evaluations=call.calls, diagonal=diagonal, atol=atol, seconds=time.perf_counter() - started,
        )
    target = np.take(sculpt, idx, axis=0)  # take: rows[idx] 4x faster than fancy indexing, the same copy
    r0 = target - np.take(posed_rest, idx, axis=0)
    step = tol.JACOBIAN_STEP_RTOL * max(diagonal, floor)
    # Every call's input, put back to rest after it (not a new copy of the mesh per call); idx's
    # rows written through the flat cells they occupy, 3x faster than assigning rows[idx].
    moved, at_rest = rest.copy(), np.take(rest, idx, axis=0)
    cells, flat = (idx[:, None] * 3 + np.arange(3)).reshape(-1), moved.reshape(-1)
    jac, coupled = _jacobians(call, rest, idx, posed_rest, step, moved)
    directions, start, _ = _conjugate_start(jac, r0)

    def residual(offsets: NDArray[np.float64]) -> NDArray[np.float64]:
        flat[cells] = np.ravel(at_rest + offsets)
        try:
            return target - np.take(call(moved), idx, axis=0)
        finally:
            flat[cells] = at_rest.reshape(-1)

    # Keep the linearised start only where it improves on zero offset.
    r_start = residual(start)
    f_start = np.einsum("ij,ij->i", r_start, r_start)
    worse = f_start > np.einsum("ij,ij->i", r0, r0)
    worse |= ~np.all(np.isfinite(r_start), axis=1)
    if stop_if_coupled and not coupled and coupling_probe is not None and not np.all(f_start <= atol * atol):
        coupled = coupling_probe(call, posed_rest, idx, step)
    if stop_if_coupled and coupled:
        norms = np.linalg.norm(r_start, axis=1)
        if not np.all(norms <= atol):
            return InverseResult(
                indices=idx, offsets=start, residual=np.where(np.isfinite(norms), norms, np.inf),
                status=np.where(norms <= atol, powell.CONVERGED, powell.MAX_CYCLES).astype(np.int8),
                evaluations=call.calls, diagonal=diagonal, atol=atol, seconds=time.perf_counter() - started,
                regime=COUPLING_SEEN, sculpt_rms=_rms(r0),
                linearised=LinearisedStart(posed_rest=posed_rest, blocks=jac, start=start.copy(),
                                           start_outputs=target - r_start, floor=floor),
            )
    if quasi_newton:
        # The start was a full step from zero offset: its secant refines J where the start
        # missed the tolerance (finite rows only; on affine skinning that is no vertex).
        missed = ~(f_start <= atol * atol)
        powell.broyden_update(jac, missed, start, r0 - r_start, np.full(len(idx), floor))
    start[worse], r_start[worse] = 0.0, r0[worse]

    result = powell.minimize_lockstep(
        residual, start, directions=directions, jacobian=jac, r0=r_start,
        atol=atol, min_step=floor, max_cycles=max_cycles, quasi_newton=quasi_newton,
    )
    return InverseResult(
        indices=idx,
        offsets=result.x,
        residual=result.residual_norm,
        status=result.status,
        evaluations=call.calls,
        diagonal=diagonal,
        atol=atol,
        seconds=time.perf_counter() - started,
        qn_steps=result.qn_steps,
        cycles=result.cycles,
        sculpt_rms=_rms(r0),
    )


def _rms(rows: Points) -> float:
    """RMS of the rows' lengths (0 for none)."""
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", rows, rows)))) if len(rows) else 0.0
