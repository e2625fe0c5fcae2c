"""The black-box inverse when the chain couples vertices (Delta Mush, corrective smooth, wraps).

``invert`` is what ``fit`` runs per example. Whether the chain couples vertices shows in the
per-vertex solver's own Jacobian calls (they move only sculpted vertices: any other output that
changes was moved by a neighbour), so skinning stays at 5 calls per example. Where no unsculpted
vertex can show it and the per-vertex solve misses, a **probe** call with a few well-separated
sculpted vertices moved (farthest-point sample, deterministic) tells whether any *other*
sculpted vertex's output moved. Skinning and per-vertex deformers leave every other output
bit-identical; a coupling deformer moves the neighbours. Per-vertex chains keep
``inverse.invert_example``'s result (Powell in lockstep, regime "per-vertex").

Coupled chains are solved jointly (the regimes named below), **matrix-free Newton-Krylov**::

    minimise || sculpt[S] - F(rest + D)[S] ||^2     D: offsets on the sculpted vertices S

* unknowns: the offsets of the sculpted vertices S only (a square system; vertices whose
  output the sculpt did not move keep a zero offset, so the fit never spreads beyond it);
* preconditioner: per-vertex 3x3 blocks from 3 calls moving *every* sculpted vertex along x,
  then y, then z (what the per-vertex solver measures as its Jacobian; in the coupled case
  the row sums of the Jacobian, which for a smoothing deformer is the skinning's own block);
* Newton step: GMRES (right-preconditioned, Arnoldi with modified Gram-Schmidt) on
  ``J delta = r``, each Jacobian-vector product one black-box call (forward difference, the
  largest vertex move a tenth of the largest residual, within ``JVP_MIN_STEP_RTOL`` and
  ``JVP_STEP_RTOL`` of the diagonal); it stops as soon as the linear model predicts every
  vertex within a fraction of the tolerance;
* then one call at ``rest + D`` checks the true residual; Newton repeats from there until
  every sculpted vertex is within tolerance, the call budget is spent or a step fails to
  improve (a step that does not is halved, up to ``BACKTRACKS`` times).

Where skinning folds the mesh, Newton from zero stalls: the chain's Jacobian has half its
singular values below 1e-3 of the largest (smoothing nearly annihilates high-frequency
offsets), and Newton follows large high-frequency offsets into a spurious minimum. The sculpt
is reachable all the same (the bench's ground-truth offsets give residuals 28-47x below the
tolerance at 13k). So where the mesh has edges Newton-Krylov starts from the **smooth start**
(``smooth_start``): Gauss-Newton restricted to the region's smoothest fields
(``psdbake.solver.smoothbasis``), with the per-vertex blocks as the span's Jacobian (a smooth field
moves each vertex as its neighbours, so a smoothing chain maps it much as skinning alone does)
and Broyden's updates of it from each step's call, which lands next to the smooth solution
(regime "coupled, from the smooth start"). On the bench's eight examples (elbow 20-160
degrees, 13k and 100k points) every sculpted vertex then reaches the tolerance in 52 and 19
calls per example. Where it misses, Newton-Krylov from zero (regime "coupled") and the smooth
start with the span's Jacobian measured, 3 calls a field (regime "coupled, from the measured
smooth start"), follow, and the best of them is kept.

Powell's per-vertex line searches are not used here: they assume a vertex's residual depends
on its own offset only, which is exactly what a coupling deformer breaks.

Statuses are the per-vertex ``powell`` codes: CONVERGED within tolerance (checked by running
the full chain on rest + offsets), MAX_CYCLES the call budget ran out, STALLED Newton
stopped improving, NONFINITE the chain returned non-finite values there.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from .. import tolerances as tol
from ..arrays import Points
from . import powell
from .inverse import COUPLING_SEEN, BlackBox, Counted, InverseResult, invert_example_with, sculpted_vertices
from .smoothbasis import smooth_basis

#: Vertices moved by the coupling probe (a farthest-point sample of the sculpted vertices).
PROBE_VERTICES = 16
#: An unprobed vertex whose output moves by more than this fraction of the probed vertices'
#: largest response means coupling. Per-vertex chains move it by exactly 0.
COUPLING_RTOL = 1e-6
#: Forward-difference step of a Jacobian-vector product: the largest vertex move is
#: ``JVP_RESIDUAL_STEP`` times the largest residual, clipped to [JVP_MIN_STEP_RTOL,
#: JVP_STEP_RTOL] of the diagonal. Where skinning folds the mesh Delta Mush is non-linear at
#: the scale of the correction still to make, and a secant much longer than it misleads the
#: model (13k bench, elbow at 60, 100 and 140 degrees: a fixed 1e-4 left 276 vertices above
#: the tolerance, a fixed 1e-5 5, a tenth of the residual none, there and on all eight). The
#: floor keeps UsdSkel's float32 rounding (~1e-7 relative, smoothed by the chain) well under
#: the difference.
JVP_STEP_RTOL = 1e-4
JVP_RESIDUAL_STEP = 0.1
JVP_MIN_STEP_RTOL = 1e-6
#: GMRES stops when the linear model predicts every vertex within this fraction of atol.
KRYLOV_TARGET = 0.25
#: Inexact Newton: a step's GMRES stops once the model predicts the largest vertex residual
#: reduced by this factor (or within KRYLOV_TARGET * atol). Solving the linear model further
#: than the model is right only fits what the chain's smoothing nearly annihilates, with
#: large high-frequency offsets.
FORCING = 0.1
#: Krylov vectors per Newton step (each one black-box call).
KRYLOV_MAX = 40
#: Trust region of a Newton step: its largest vertex move, in units of the largest residual.
STEP_CAP = 20.0
#: Halvings of a Newton step that does not reduce the residual before giving up.
BACKTRACKS = 4
#: Black-box calls of one joint solve from a start (the smooth start, or the per-vertex
#: solution), counted from that start.
MAX_EVALUATIONS = 160
#: The joint solve from zero, where the smooth start missed (or there is none), counted from
#: its start. Run first, as it was before the smooth start came first, it converged in 14-29
#: calls per example in all (unfolded bench and test examples, 1.3k to 100k points); where
#: skinning folds the mesh, never within 160 (12 bench examples, elbow at 60-160 degrees, 13k
#: and 100k).
FROM_ZERO_EVALUATIONS = 64
#: Smooth fields in ``smooth_start``'s span (3 calls each, one per axis, when its Jacobian is
#: measured). With the measured Jacobian, on the 13k bench's six folded examples 32 left 18
#: vertices above the tolerance, 64 none.
SMOOTH_FIELDS = 64
#: Gauss-Newton steps in that span: the first on the blocks' (or the measured) Jacobian, then
#: Broyden's updates of it, 1 call each. From the blocks, on the 13k bench's six folded
#: examples with Newton-Krylov from zero run first: 1 step left 4,284 vertices above the
#: tolerance, 2 left 115, 4, 8, 12 or 20 none; run first, as now, 3, 4, 6 and 8 none (measured
#: Jacobian: the residual went 2.0e-3, 5.0e-4, 4.7e-4, 4.1e-4 of the diagonal over four steps
#: on the 60-degree elbow).
SMOOTH_STEPS = 4
#: Singular values of the span's Jacobian below this fraction of the largest are dropped
#: (truncated least squares: the steps stay smooth and the noise of the measured columns out).
SMOOTH_RCOND = 1e-3


def probe_vertices(rest: Points, candidates: NDArray[np.int64], count: int = PROBE_VERTICES) -> NDArray[np.int64]:
    """Up to ``count`` well-separated candidates: farthest-point sampling from the first one."""
    if len(candidates) <= count:
        return np.asarray(candidates, dtype=np.int64)
    pts = rest[candidates]
    chosen = [0]
    dist = np.linalg.norm(pts - pts[0], axis=1)
    for _ in range(count - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
    return np.sort(candidates[np.array(chosen)])


def is_coupled(call: BlackBox, rest: Points, base: Points, probed: NDArray[np.int64], step: float) -> bool:
    """One call: does moving ``probed`` move any other vertex's output?"""
    if len(probed) == 0 or len(probed) == len(rest):
        return False
    moved = rest.copy()
    moved[probed] += step * np.array([0.8, 0.5, 0.3]) / np.sqrt(0.98)
    change = np.linalg.norm(call(moved) - base, axis=1)
    own = float(change[probed].max())
    change[probed] = 0.0
    others = float(change.max())
    return bool(others > COUPLING_RTOL * max(own, step)) or not np.isfinite(others)


def invert(blackbox: BlackBox, rest: Points, sculpt: Points, *, rtol: float = tol.INVERSE_RTOL,
           neighbours: Callable[[], sp.csr_matrix | None] | None = None) -> InverseResult:
    """Solve the example per vertex, or jointly when the chain couples vertices, keeping the
    better solution (``InverseResult.regime`` says which ran and which was kept).

    The per-vertex solver's 3 Jacobian calls move only sculpted vertices, so they show for
    free whether any other vertex's output moved: skinning (5 calls) and per-vertex deformers
    pay nothing to find out. When they show coupling and the linearised start misses, the
    joint solve takes over: Gauss-Newton in the span of the region's smoothest fields on the
    per-vertex blocks' model (``smooth_start``; ``neighbours()`` gives the mesh's edge
    adjacency), then Newton-Krylov. Where that leaves vertices above the tolerance, Newton-Krylov
    from zero, then the smooth start with the span's Jacobian measured and Newton-Krylov; without
    edges, Newton-Krylov from zero, then the per-vertex solve and a restart from it. The kept
    result has the fewest vertices above the tolerance, then the smallest worst residual, both
    measured by running the chain. A chain that couples only vertices with no unsculpted
    neighbour is probed (2 calls) once the per-vertex solve misses."""
    started = time.perf_counter()
    rest = np.asarray(rest, dtype=np.float64)
    sculpt = np.asarray(sculpt, dtype=np.float64)
    first = invert_example_with(blackbox, rest, sculpt, rtol=rtol, stop_if_coupled=True)
    if first.regime != COUPLING_SEEN and not len(first.missed):
        return first
    call = Counted(blackbox, first.evaluations)
    base = call(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, sculpt)
    if first.regime != COUPLING_SEEN:  # per-vertex ran to the end and missed: probe
        step = tol.JACOBIAN_STEP_RTOL * max(diagonal, floor)
        if not (len(idx) and is_coupled(call, rest, base, probe_vertices(rest, idx), step)):
            return dataclasses.replace(first, evaluations=call.calls, seconds=time.perf_counter() - started)
    # The joint stages' sums run on BLAS (GMRES, ARPACK, the Gram matrix), whose results depend
    # on its thread count: one thread, so a fit gives the same bytes on every machine (the 100k
    # bench: 8.76 s an example against 8.54 with two threads; the black box dominates)
    with threadpool_limits(limits=1, user_api="blas"):
        adjacency = neighbours() if neighbours is not None else None
        basis = smooth_basis(adjacency, idx, SMOOTH_FIELDS) if adjacency is not None else None
        blocks = chain_blocks(call, rest, base, idx, diagonal, floor)  # 3 calls, shared by every stage
        candidates: list[InverseResult] = []
        if basis is not None:  # 1. the model's smooth start, then Newton-Krylov
            start = smooth_start(call, rest, sculpt, base, idx, diagonal, floor, basis, model=blocks)
            smooth = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                    max_evaluations=call.calls + MAX_EVALUATIONS, start=start, blocks=blocks)
            candidates.append(dataclasses.replace(smooth, regime="coupled, from the smooth start"))
        if not candidates or len(candidates[0].missed):  # 2. Newton-Krylov from zero
            joint = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                   max_evaluations=call.calls + FROM_ZERO_EVALUATIONS, blocks=blocks)
            candidates.append(joint)
            if len(joint.missed) and basis is not None:  # 3. the span's Jacobian measured, then Newton-Krylov
                start = smooth_start(call, rest, sculpt, base, idx, diagonal, floor, basis)
                finished = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                          max_evaluations=call.calls + MAX_EVALUATIONS, start=start, blocks=blocks)
                candidates.append(dataclasses.replace(finished, regime="coupled, from the measured smooth start"))
            elif len(joint.missed):  # no edges: the per-vertex solution and a restart from it
                candidates.extend(_from_per_vertex(call, blackbox, rest, sculpt, base, idx, diagonal, floor, first,
                                                   blocks, rtol=rtol, started=started))
    best = min(candidates, key=lambda c: (len(c.missed), c.max_residual))
    return dataclasses.replace(best, evaluations=call.calls, seconds=time.perf_counter() - started)


def _from_per_vertex(call: Counted, blackbox: BlackBox, rest: Points, sculpt: Points, base: Points,
                     idx: NDArray[np.int64], diagonal: float, floor: float, first: InverseResult,
                     blocks: NDArray[np.float64], *, rtol: float, started: float) -> list[InverseResult]:
    """Without mesh edges: the full per-vertex solve, and Newton-Krylov restarted from it."""
    per_vertex = first
    if first.regime == COUPLING_SEEN:
        per_vertex = invert_example_with(blackbox, rest, sculpt, rtol=rtol)
        call.calls += per_vertex.evaluations
    found = [dataclasses.replace(per_vertex, regime="coupled chain, per-vertex kept")]
    if len(per_vertex.missed) and np.array_equal(per_vertex.indices, idx):
        warm = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                              max_evaluations=call.calls + MAX_EVALUATIONS, start=per_vertex.offsets, blocks=blocks)
        found.append(dataclasses.replace(warm, regime="coupled, from the per-vertex solution"))
    return found


def _outputs(call: Counted, rest: Points, idx: NDArray[np.int64], offsets: Points) -> Points:
    """The chain's outputs at the sculpted vertices for rest + offsets there: one call."""
    moved = rest.copy()
    moved[idx] += offsets
    return call(moved)[idx]


def chain_blocks(call: BlackBox, rest: Points, base: Points, idx: NDArray[np.int64], diagonal: float,
                 floor: float) -> NDArray[np.float64]:
    """Per-vertex 3x3 blocks (len(idx), 3, 3) from 3 calls moving every sculpted vertex along
    x, then y, then z (forward differences, ``JACOBIAN_STEP_RTOL`` of the diagonal): the
    per-vertex solver's Jacobian; for a coupled chain the row sums of its Jacobian, which for a
    smoothing deformer (weights summing to 1) are the skinning's own blocks."""
    jstep = tol.JACOBIAN_STEP_RTOL * max(diagonal, floor)
    blocks = np.empty((len(idx), 3, 3))
    for axis in range(3):
        moved = rest.copy()
        moved[idx, axis] += jstep
        blocks[:, :, axis] = (call(moved)[idx] - base[idx]) / jstep
    return blocks


def smooth_start(call: Counted, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
                 diagonal: float, floor: float, basis: NDArray[np.float64],
                 model: NDArray[np.float64] | None = None) -> Points:
    """Offsets (len(idx), 3) from Gauss-Newton restricted to smooth fields: ``basis`` (k, b)
    per axis. The span's Jacobian is the per-vertex blocks' (``model``, from ``chain_blocks``:
    no call; a smooth field moves each vertex as its neighbours, so a smoothing chain maps it
    as skinning alone does, and the steps' Broyden updates learn the rest) or, without a
    model, measured: 3b calls (forward differences, the largest vertex move
    ``JACOBIAN_STEP_RTOL`` of the diagonal). The step is the truncated least-squares solve
    (singular values below ``SMOOTH_RCOND`` of the largest dropped), and ``SMOOTH_STEPS - 1``
    more steps refresh that Jacobian by Broyden updates, 1 call each. A step is kept only if
    it lowers the residual (``smoothbasis`` says why this helps)."""
    k, b = basis.shape
    target = sculpt[idx]
    out = base[idx]
    cols = np.empty((3 * b, 3 * k))  # the span's Jacobian, stored by column (one row each)
    if model is not None:
        for c in range(b):
            for axis in range(3):
                cols[3 * c + axis] = (model[:, :, axis] * basis[:, c, None]).ravel()
    else:
        step = tol.JACOBIAN_STEP_RTOL * max(diagonal, floor)
        for c in range(b):
            h = step / max(float(np.abs(basis[:, c]).max()), 1e-300)
            for axis in range(3):
                moved = rest.copy()
                moved[idx, axis] += h * basis[:, c]
                cols[3 * c + axis] = ((call(moved)[idx] - out) / h).ravel()
    offsets = np.zeros((k, 3))
    if not np.all(np.isfinite(cols)):  # the chain gave non-finite values: no smooth start
        return offsets
    r = target - out
    # Truncated least squares through the span's Gram matrix (3b x 3b): the same solution as
    # an SVD of the (3k, 3b) Jacobian, which at 100k points took 1.2 s a step
    gram = cols @ cols.T
    for _ in range(SMOOTH_STEPS):
        values, vectors = np.linalg.eigh(gram)
        keep = values > SMOOTH_RCOND**2 * values[-1] if values[-1] > 0 else np.zeros(len(values), dtype=bool)
        if not keep.any():
            break
        y = vectors[:, keep] @ ((vectors[:, keep].T @ (cols @ r.ravel())) / values[keep])
        trial = offsets + basis @ y.reshape(b, 3)
        out_trial = _outputs(call, rest, idx, trial)
        if not np.all(np.isfinite(out_trial)):
            break
        # Broyden's update J += u y^T / (y.y), column by column (no (3k, 3b) temporary), and
        # the Gram matrix's with it
        u = (out_trial - out).ravel() - y @ cols
        yy = float(y @ y)
        if yy == 0.0:
            break
        ju = cols @ u
        for j in range(len(y)):
            cols[j] += (y[j] / yy) * u
        gram += (np.outer(ju, y) + np.outer(y, ju)) / yy + np.outer(y, y) * (float(u @ u) / yy**2)
        r_trial = target - out_trial
        if np.linalg.norm(r_trial) < np.linalg.norm(r):
            offsets, out, r = trial, out_trial, r_trial
    return offsets


def invert_coupled(
    call: Counted,
    rest: Points,
    sculpt: Points,
    base: Points,
    idx: NDArray[np.int64],
    diagonal: float,
    floor: float,
    *,
    rtol: float = tol.INVERSE_RTOL,
    started: float,
    max_evaluations: int = MAX_EVALUATIONS,
    start: Points | None = None,
    blocks: NDArray[np.float64] | None = None,
) -> InverseResult:
    """Newton-Krylov on the sculpted vertices' offsets (module docstring). ``base`` is
    ``call(rest)``; ``call.calls`` counts the example's calls so far (the budget's measure);
    ``blocks`` are ``chain_blocks`` (measured here when not given)."""
    atol = max(rtol * diagonal, floor)
    target = sculpt[idx]
    k = len(idx)

    def evaluate(offsets: Points) -> Points:
        return _outputs(call, rest, idx, offsets)

    # Per-vertex 3x3 blocks (row sums in the coupled case): the preconditioner.
    if blocks is None:
        blocks = chain_blocks(call, rest, base, idx, diagonal, floor)
    scale = np.einsum("kab,kab->k", blocks, blocks) ** 1.5
    ok = np.isfinite(scale)  # a chain that gives non-finite points there: no block to invert
    ok[ok] = np.abs(np.linalg.det(blocks[ok])) > tol.JACOBIAN_RCOND * np.maximum(scale[ok], 1e-300)
    inverse_blocks = np.tile(np.eye(3), (k, 1, 1))
    if ok.any():
        inverse_blocks[ok] = np.linalg.inv(blocks[ok])

    def precondition(v: Points) -> Points:
        return np.einsum("kab,kb->ka", inverse_blocks, v)

    offsets = np.zeros((k, 3)) if start is None else np.array(start, dtype=np.float64)
    out = base[idx] if start is None else evaluate(offsets)
    r = target - out
    norms = np.linalg.norm(r, axis=1)
    stalled = False
    scale = max(diagonal, floor)
    while np.isfinite(norms).all() and norms.max() > atol and call.calls < max_evaluations - 2:
        at, out_at = offsets, out
        # the secant shrinks with the residual: where skinning folds the mesh the chain is
        # strongly non-linear, and a step far larger than the correction misleads the model
        h_move = min(JVP_STEP_RTOL * scale, max(JVP_RESIDUAL_STEP * float(norms.max()), JVP_MIN_STEP_RTOL * scale))

        def jvp(z: Points, at: Points = at, out_at: Points = out_at, h_move: float = h_move) -> Points:
            h = h_move / max(float(np.sqrt(np.mean(np.einsum("ij,ij->i", z, z)))), 1e-300)
            return (evaluate(at + h * z) - out_at) / h

        budget = min(KRYLOV_MAX, max_evaluations - 2 - call.calls)
        target_lin = max(KRYLOV_TARGET * atol, FORCING * float(norms.max()))
        delta = _gmres(jvp, precondition, r, target_lin, budget)
        size = np.linalg.norm(r)
        # Trust region: no vertex moves further than STEP_CAP times the largest residual.
        lengths = np.linalg.norm(delta, axis=1)
        cap = STEP_CAP * float(norms.max())
        delta = delta * np.minimum(1.0, cap / np.maximum(lengths, 1e-300))[:, None]
        for _ in range(BACKTRACKS + 1):  # the full step, then halvings
            trial = offsets + delta
            out_trial = evaluate(trial)
            r_trial = target - out_trial
            better = bool(np.all(np.isfinite(r_trial)) and np.linalg.norm(r_trial) < size)
            if better or call.calls >= max_evaluations - 1:
                break
            delta = 0.5 * delta
        if not better:
            stalled = True
            break
        offsets, out, r = trial, out_trial, r_trial
        norms = np.linalg.norm(r, axis=1)

    status = np.full(k, powell.STALLED if stalled else powell.MAX_CYCLES, dtype=np.int8)
    status[norms <= atol] = powell.CONVERGED
    status[~np.isfinite(norms)] = powell.NONFINITE
    return InverseResult(
        indices=idx, offsets=offsets, residual=norms, status=status, evaluations=call.calls, diagonal=diagonal,
        atol=atol, seconds=time.perf_counter() - started, regime="coupled",
    )


def _gmres(jvp: Callable[[Points], Points], precondition: Callable[[Points], Points], r: Points,
           target: float, max_iter: int) -> Points:
    """Right-preconditioned GMRES for ``J delta = r`` ((k, 3) vectors), at most ``max_iter``
    products; stops once the linear model predicts every vertex's residual <= ``target``."""
    shape = r.shape
    b = r.ravel()
    beta = float(np.linalg.norm(b))
    if max_iter <= 0 or beta == 0.0:
        return np.zeros(shape)
    basis = np.zeros((max_iter + 1, b.size))
    images = np.zeros((max_iter, b.size))  # J M^-1 v_j
    directions = np.zeros((max_iter, b.size))  # M^-1 v_j
    hess = np.zeros((max_iter + 1, max_iter))
    basis[0] = b / beta
    y = np.zeros(0)
    for j in range(max_iter):
        directions[j] = precondition(basis[j].reshape(shape)).ravel()
        w = jvp(directions[j].reshape(shape)).ravel()
        if not np.all(np.isfinite(w)):  # the chain gave non-finite points: the model so far
            break
        images[j] = w
        for i in range(j + 1):  # modified Gram-Schmidt
            hess[i, j] = basis[i] @ w
            w = w - hess[i, j] * basis[i]
        hess[j + 1, j] = np.linalg.norm(w)
        rhs = np.zeros(j + 2)
        rhs[0] = beta
        y = np.asarray(np.linalg.lstsq(hess[: j + 2, : j + 1], rhs, rcond=None)[0], dtype=np.float64)
        predicted = (b - y @ images[: j + 1]).reshape(shape)
        if np.linalg.norm(predicted, axis=1).max() <= target or hess[j + 1, j] <= 1e-14 * beta:
            break
        basis[j + 1] = w / hess[j + 1, j]
    return (y @ directions[: len(y)]).reshape(shape)
