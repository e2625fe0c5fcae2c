"""Gauss-Newton on directions the chain's response was measured along, one call each.

The coupled inverse's finish where the smooth start leaves the sculpt nearly reproduced, and
its polish after the slower stages (``psdbake.solver.coupled``). What is left then is small
and sits where the smoothing model is wrong: at a fold, the last vertices' own offsets; over a
coarse mesh, directions the chain passes weakly. Each round measures new directions of the
offsets (forward differences, ``STEP_RTOL`` of the diagonal, about 100 float32 ulps of the
coordinates, so a column's noise is near 1%), every one a call:

* a **global** direction: the blocks' inverse on the residual the linear model of the
  directions so far leaves (weighted as below). Kept from round to round, these span a Krylov
  space that is never thrown away, where Newton-Krylov restarted its space at every step.
  While many vertices miss (more than ``OWN_MISSING``), more of them, until the linear model
  predicts a step worth its call (``FORCING``, at most ``KRYLOV_PER_ROUND``), as GMRES does;
* once few vertices miss, the **own** directions of the worst of them (``OWN_PER_ROUND`` a
  round): first a vertex's Newton direction (its block's inverse on its residual), then the
  two orthogonal to it; where every such vertex has all three, its edge neighbours' Newton
  directions. They are measured one at a time, and the round measures no more of them once
  the linear model of the directions so far predicts a step that brings every vertex within
  the tolerance (``clears``, no call), as GMRES stops at its target: at the 1.3k bench rig's
  100 degree fold that model's predictions came within 0.12 of the tolerance of the chain's
  outputs.

Then up to ``STEPS`` least-squares steps on every direction measured so far, 1 call each, with
Broyden's update of their responses from each call. The residual is weighted so that the few
vertices that miss are not outweighed by the many within the tolerance (``weights``), and
reweighted on the linear model, without calls, where the model predicts vertices above
``REWEIGHT_TARGET`` of the tolerance (a least-squares step otherwise trades a few vertices
just above it for many just above it). A step is kept where it leaves fewer vertices above
the tolerance, then a smaller worst residual. The solve ends when every vertex is within the
tolerance, ``STALL_CALLS`` calls after its last kept step, or at its budget of calls.

Measured on the bench rigs through LBS + Delta Mush (docs/decisions/coupled-inverse-coarse-meshes.md,
"Measured directions"): with the global directions alone the 1.3k rig's 80 degree elbow
stalls and goes on to the slower stages and the exact Jacobian (809 calls in all, against 60);
with own directions from the first round, where 133 of the character fixture's 168 vertices
miss at its 140 degree elbow, 903 calls (against 103), and the 3k rig's 100 degree elbow 97
(against 45).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from .. import tolerances as tol
from ..arrays import Points, is_singular
from .inverse import BlackBox

#: Calls the solve may take.
CALLS = 200
#: Entries the directions and their responses may hold (2 x 3k a direction, float64: 400 MB).
#: A region of 34k vertices (the 100k bench rig's) keeps every one of its 200; a
#: region of 400k vertices stops at 20 directions (a third of the 1M bench mesh: 25).
MAX_ENTRIES = 50_000_000
#: Own directions a round measures, of the worst vertices first, once at most ``OWN_MISSING``
#: vertices are above the tolerance (where more are, a call on one vertex moves too few of them).
OWN_PER_ROUND = 8
OWN_MISSING = 64
#: Least-squares steps after each round (each a call; a step not kept ends the round's steps).
STEPS = 2
#: Forward-difference step of a direction (scaled to a largest move of 1), a fraction of the diagonal.
STEP_RTOL = 1e-5
#: Singular values of the weighted responses below this fraction of the largest are dropped.
RCOND = 1e-6
#: Reweightings of a step on the linear model (no call), and the share of the tolerance it aims at.
REWEIGHTS = 20
REWEIGHT_TARGET = 0.8
#: While more than ``OWN_MISSING`` vertices miss, a round adds up to this many more global
#: directions, until the linear model predicts the largest residual within ``FORCING`` of
#: today's: the 13k bench rig 30.5 -> 20.0 calls an example, the 100k 20.1 -> 17.5 (with one
#: global direction a round); with few missing it cost the 1.3k rig's random poses 40.7 -> 55.1.
KRYLOV_PER_ROUND = 8
FORCING = 0.1
#: Calls since the last kept step before the solve stops (the bench rigs' folds have gone 30
#: calls without one, then finished).
STALL_CALLS = 80
#: ``weights``: the unit a vertex's residual is weighed in is at least this share of the tolerance.
WEIGHT_FLOOR = 0.5


@dataclass(frozen=True)
class SubspaceResult:
    """Where the solve ended: offsets (k, 3) and each vertex's residual there (k,), from the
    chain's own outputs."""

    offsets: Points
    residual: NDArray[np.float64]


def weights(norms: NDArray[np.float64], atol: float) -> NDArray[np.float64]:
    """Each vertex's weight in a least-squares step where few vertices miss, (k, 1): max(1,
    |r| / u), u the larger of the residuals' RMS and ``WEIGHT_FLOOR`` times the tolerance. The
    many vertices far within the tolerance then do not outweigh the few that miss it."""
    unit = max(WEIGHT_FLOOR * atol, float(np.sqrt(np.mean(norms**2))))
    return np.maximum(norms / unit, 1.0)[:, None]


def region_neighbours(adjacency: sp.csr_matrix, idx: NDArray[np.int64], positions: NDArray[np.int64]
                      ) -> NDArray[np.int64]:
    """The sculpted vertices (positions in ``idx``, sorted) one edge from those at ``positions``."""
    near = np.unique(adjacency[idx[positions]].indices)
    return np.intersect1d(idx, near, assume_unique=True, return_indices=True)[1]


def solve(call: BlackBox, rest: Points, target: Points, idx: NDArray[np.int64], offsets: Points, outputs: Points,
          blocks: NDArray[np.float64], atol: float, scale: float, adjacency: sp.csr_matrix | None,
          max_calls: int = CALLS, trial_rounds: int | None = None,
          seeded: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None) -> SubspaceResult:
    """Offsets on the sculpted vertices ``idx`` from ``offsets``, whose chain outputs there are
    ``outputs`` (module docstring). ``target`` is the sculpt at ``idx`` (k, 3), ``blocks`` the
    per-vertex 3x3 blocks, ``scale`` the diagonal. At most ``max_calls`` calls of ``call``, and
    no more than ``MAX_ENTRIES`` allow. With ``trial_rounds``, the solve stops where none of its
    first ``trial_rounds`` rounds kept a step: a caller with a surer, costlier stage to fall back
    on (``coupled``'s pieces by their exact Jacobians) spends a round to learn whether the
    measured directions' linear model holds here. ``seeded``: directions of the offsets already
    measured at ``offsets`` and the chain's responses to them, (m, 3k) each (Newton-Krylov's
    Krylov space where it kept no step), kept as the solve's first."""
    offsets = np.array(offsets, dtype=np.float64)
    out = np.asarray(outputs, dtype=np.float64)
    r = target - out
    norms = np.linalg.norm(r, axis=1)
    if not np.all(np.isfinite(norms)):
        return SubspaceResult(offsets, norms)
    k = len(idx)
    max_calls = min(max_calls, MAX_ENTRIES // max(6 * k, 1))
    h = STEP_RTOL * scale
    ok = ~is_singular(blocks, tol.JACOBIAN_RCOND)
    inverse = np.tile(np.eye(3), (k, 1, 1))
    if ok.any():
        inverse[ok] = np.linalg.inv(blocks[ok])
    moves = np.empty((0, 3 * k))  # one row per direction: the offsets' move, of size about 1
    responses = np.empty((0, 3 * k))  # and the chain's response to it
    if seeded is not None and len(seeded[0]):
        size = np.abs(seeded[0]).max(axis=1, keepdims=True)
        usable = (size[:, 0] > 0) & np.all(np.isfinite(seeded[1]), axis=1)
        moves, responses = seeded[0][usable] / size[usable], seeded[1][usable] / size[usable]
    own: dict[int, NDArray[np.float64]] = {}  # vertex -> its own directions so far, (m, 3)
    linear = r  # what the linear model of the directions so far leaves
    calls = last_kept = rounds = 0

    def evaluate(at: Points) -> Points:
        moved = rest.copy()
        moved[idx] += at
        return call(moved)[idx]

    def rank(n: NDArray[np.float64]) -> tuple[int, float]:
        return int(np.count_nonzero(n > atol)), float(n.max())

    while calls < max_calls and np.any(norms > atol) and calls - last_kept < STALL_CALLS and not (
            trial_rounds is not None and rounds >= trial_rounds and not last_kept):
        rounds += 1
        towards = _global(inverse, weights(norms, atol) * linear)
        fresh = [] if towards is None else [towards]
        few = np.count_nonzero(norms > atol) <= OWN_MISSING
        if few:
            fresh += _own(r, norms, atol, inverse, own, adjacency, idx)
        fresh = fresh[: max_calls - calls]
        if not fresh:
            break
        measured: list[NDArray[np.float64]] = []
        planned = None  # the round's first step, where its model cleared every vertex before the round's end
        for move in fresh:
            measured.append(((evaluate(offsets + h * move) - out) / h).ravel())
            calls += 1
            if few and len(measured) < len(fresh) and np.all(np.isfinite(measured[-1])):
                planned = clears(np.vstack([responses, measured]), r, norms, atol)
                if planned is not None:
                    _forget(own, fresh[len(measured):])
                    fresh = fresh[: len(measured)]
                    break
        if not np.all(np.isfinite(measured)):
            break  # the chain gave non-finite values: the directions so far
        moves = np.vstack([moves, np.array(fresh).reshape(len(fresh), -1)])
        responses = np.vstack([responses, measured])
        if np.count_nonzero(norms > atol) > OWN_MISSING:  # many miss: more of the Krylov space first
            moves, responses, made = _krylov(evaluate, inverse, moves, responses, offsets, out, r, norms, atol, h,
                                             min(KRYLOV_PER_ROUND, max_calls - calls - 1))
            calls += made
        for _ in range(STEPS):
            if calls >= max_calls or not np.any(norms > atol):
                break
            y, linear = planned if planned is not None else _step(responses, r, norms, atol)
            planned = None  # the responses change with this step's Broyden update
            yy = float(y @ y)
            if yy == 0.0:
                break
            trial = offsets + (y @ moves).reshape(r.shape)
            out_trial = evaluate(trial)
            calls += 1
            if not np.all(np.isfinite(out_trial)):
                break
            responses += np.outer(y, (out_trial - out).ravel() - y @ responses) / yy  # Broyden
            r_trial = target - out_trial
            n_trial = np.linalg.norm(r_trial, axis=1)
            if not rank(n_trial) < rank(norms):
                break
            offsets, out, r, norms, linear, last_kept = trial, out_trial, r_trial, n_trial, r_trial, calls
    return SubspaceResult(offsets, norms)


def _global(inverse: NDArray[np.float64], residual: Points) -> Points | None:
    """The blocks' inverse on a residual, its largest coordinate 1 (None where it is zero)."""
    d = np.einsum("kab,kb->ka", inverse, residual)
    size = float(np.abs(d).max(initial=0.0))
    return d / size if size > 0 and np.isfinite(size) else None


def _own(r: Points, norms: NDArray[np.float64], atol: float, inverse: NDArray[np.float64],
         own: dict[int, NDArray[np.float64]], adjacency: sp.csr_matrix | None, idx: NDArray[np.int64]
         ) -> list[Points]:
    """The next own directions of the worst vertices above the tolerance (module docstring),
    each a (k, 3) move of one vertex; ``own`` records them."""
    around = np.nonzero(norms > atol)[0]
    while True:
        picked: list[tuple[int, NDArray[np.float64]]] = []
        for v in map(int, around):
            if v not in own:
                d = inverse[v] @ r[v]
                size = float(np.linalg.norm(d))
                picked.append((v, d / size if size > 0 and np.isfinite(size) else np.eye(3)[0]))
            elif len(own[v]) < 3:  # the directions orthogonal to those it has
                q = np.linalg.qr(np.vstack([own[v], np.eye(3)]).T)[0]
                picked.extend((v, q[:, j]) for j in range(len(own[v]), 3))
        if picked or adjacency is None:
            break
        wider = np.union1d(around, region_neighbours(adjacency, idx, around))
        if len(wider) == len(around):
            break
        around = wider
    if len(picked) > OWN_PER_ROUND:  # the worst vertices' first, in vertex order
        worst = np.argsort(-norms[[v for v, _ in picked]], kind="stable")[:OWN_PER_ROUND]
        picked = [picked[i] for i in sorted(worst)]
    moves = []
    for v, d in picked:
        move = np.zeros_like(r)
        move[v] = d
        moves.append(move)
        own[v] = np.vstack([own[v], d]) if v in own else d[None, :]
    return moves


def _forget(own: dict[int, NDArray[np.float64]], moves: list[Points]) -> None:
    """Take back from ``own`` the directions ``_own`` recorded for ``moves`` that were not
    measured after all (each moves one vertex; the last recorded first)."""
    for move in reversed(moves):
        v = int(np.flatnonzero(np.abs(move).sum(axis=1))[0])
        if v in own:
            own[v] = own[v][:-1]
            if not len(own[v]):
                del own[v]


def clears(responses: NDArray[np.float64], r: Points, norms: NDArray[np.float64], atol: float
           ) -> tuple[NDArray[np.float64], Points] | None:
    """The least-squares step on these directions' responses (``_step``) where their linear
    model predicts it leaves every vertex within ``atol``; else None."""
    y, left = _step(responses, r, norms, atol)
    return (y, left) if bool(np.all(np.linalg.norm(left, axis=1) <= atol)) else None


def _krylov(evaluate: Callable[[Points], Points], inverse: NDArray[np.float64], moves: NDArray[np.float64],
            responses: NDArray[np.float64], offsets: Points, out: Points, r: Points, norms: NDArray[np.float64],
            atol: float, h: float, most: int) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """More global directions, 1 call each and at most ``most``, each from what the linear model
    of those so far leaves, until that model predicts the largest residual within ``FORCING``
    of today's (or within ``REWEIGHT_TARGET`` of the tolerance): as GMRES grows its Krylov
    space before a Newton step. Returns the directions and responses with them, and the calls
    made."""
    weight = np.repeat(weights(norms, atol)[:, 0], 3)
    calls = 0
    for _ in range(most):
        y = np.asarray(np.linalg.lstsq(responses.T * weight[:, None], r.ravel() * weight, rcond=RCOND)[0],
                       dtype=np.float64)
        left = (r.ravel() - y @ responses).reshape(r.shape)
        if np.linalg.norm(left, axis=1).max() <= max(FORCING * float(norms.max()), REWEIGHT_TARGET * atol):
            break
        towards = _global(inverse, weights(norms, atol) * left)
        if towards is None:
            break
        response = ((evaluate(offsets + h * towards) - out) / h).ravel()
        calls += 1
        if not np.all(np.isfinite(response)):
            break
        moves, responses = np.vstack([moves, towards.ravel()]), np.vstack([responses, response])
    return moves, responses, calls


def _step(responses: NDArray[np.float64], r: Points, norms: NDArray[np.float64], atol: float
          ) -> tuple[NDArray[np.float64], Points]:
    """The directions' coefficients of a least-squares step, and the residual their linear model
    predicts it leaves (k, 3): the residual weighted (``weights``), then reweighted where the
    linear model leaves vertices above ``REWEIGHT_TARGET`` of the tolerance, by how far above
    (``REWEIGHTS`` times at most)."""
    weight = np.repeat(weights(norms, atol)[:, 0], 3)
    b = r.ravel()
    y = np.asarray(np.linalg.lstsq(responses.T * weight[:, None], b * weight, rcond=RCOND)[0], dtype=np.float64)
    aim = REWEIGHT_TARGET * atol
    for _ in range(REWEIGHTS):
        predicted = np.linalg.norm((b - y @ responses).reshape(r.shape), axis=1)
        over = predicted > aim
        if not over.any():
            break
        grow = np.ones(len(predicted))
        grow[over] = predicted[over] / aim
        weight = weight * np.repeat(grow, 3)
        y = np.asarray(np.linalg.lstsq(responses.T * weight[:, None], b * weight, rcond=RCOND)[0], dtype=np.float64)
    return y, (b - y @ responses).reshape(r.shape)
