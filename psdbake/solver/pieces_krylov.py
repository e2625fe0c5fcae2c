"""Newton-GMRES on a region's independent pieces at once, each piece on its own Krylov space.

A chain that couples vertices only along edges (Delta Mush) moves no piece of the mesh from
another, so its Jacobian over the region is block-diagonal by piece, and so is the per-vertex
preconditioner. One call can then carry one Jacobian-vector product of *every* piece: each
piece's part of the moved offsets is the next vector of its own Arnoldi process, and each piece
reads its product from its own outputs. Each piece's step then minimises its own residual over
its own Krylov space. A joint GMRES over the region (``coupled.invert_coupled``) builds the same
spaces, but fits one coefficient per product for all pieces together, so after m calls it holds
m directions where this holds m for every piece. On CesiumMan one space shared by its six
large pieces took 400 calls at its first example and missed at its second after 400.

Measured on CesiumMan (docs/decisions/coupled-inverse-cesiumman.md, "Each piece on its own
Krylov space"): with the exact Jacobian at the answer, GMRES from zero needs 363 products on the
whole region, and at most 75 on any one piece. From where the fast path leaves its large
pieces (up to 10 times the tolerance), one Newton step of this stage brings every vertex within
the tolerance in 121 calls, where their coloured Jacobians (``pieces.solve_exactly``) took 276.

Only the chain is called; whether the pieces really are independent shows in every call (an
output outside the moved pieces that changes ends the stage: ``pieces.moved_another``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..arrays import Points
from .inverse import BlackBox
from .pieces import Piece, moved_another, outside

#: Each product's secant is the largest residual left on the pieces (``SECANT_RESIDUAL`` times
#: it), within these fractions of the diagonal. Float32 outputs (~6e-8 of the diagonal) make a
#: secant of 1e-6 of it 4.8% wrong on CesiumMan, 1e-5 0.5% and 1e-4 0.3% (the chain's
#: curvature), against its Jacobian at the answer. On CesiumMan's two examples this stage took
#: 120 and 121 calls with the secant at the residual, 160 and 165 at half of it, 124 and 161 at
#: twice it; at a tenth (Newton-Krylov's rule, 20 products a Newton step) it left 8 vertices
#: above the tolerance after 300 calls.
SECANT_MIN_RTOL = 1e-5
SECANT_MAX_RTOL = 1e-4
SECANT_RESIDUAL = 1.0
#: A piece's Arnoldi process stops once its linear model predicts every vertex of the piece
#: within this fraction of the tolerance. On CesiumMan 0.5 took 120 and 121 calls, 0.25 147 and
#: more than 200 (the last products refine what the chain's noise blurs), 0.7 129 and 160 (a
#: second Newton step for the few vertices the first left just above the tolerance).
KRYLOV_TARGET = 0.5
#: A piece's step that does not lower its residual is halved at most this many times.
BACKTRACKS = 4


@dataclass(frozen=True)
class KrylovResult:
    """Offsets for the pieces (``members``, positions in the region's indices, and their
    ``offsets``) and the chain's outputs with every piece there (all n points; each piece's
    from the call that kept its step, which the pieces' independence makes the same)."""

    members: NDArray[np.int64]
    offsets: NDArray[np.float64]
    outputs: Points


MovedCall = Callable[[NDArray[np.float64], list[Piece]], Points | None]


@dataclass
class _Arnoldi:
    """One piece's GMRES on ``J s = b`` (its residual), right-preconditioned by its blocks."""

    piece: Piece
    b: NDArray[np.float64]
    beta: float
    basis: list[NDArray[np.float64]]
    directions: list[NDArray[np.float64]] = field(default_factory=list)  # M^-1 v_j
    images: list[NDArray[np.float64]] = field(default_factory=list)  # J M^-1 v_j
    hessenberg: list[NDArray[np.float64]] = field(default_factory=list)  # its columns
    done: bool = False

    @staticmethod
    def on(piece: Piece, b: NDArray[np.float64]) -> _Arnoldi:
        """The process for ``piece`` whose residual is ``b``, its first basis vector ``b``'s direction."""
        beta = float(np.linalg.norm(b))
        return _Arnoldi(piece, b, beta, [b / beta])

    def take(self, image: NDArray[np.float64], atol: float) -> None:
        """The chain's image of the latest direction: orthogonalised (modified Gram-Schmidt)
        into the next basis vector, unless the linear model now holds every vertex of the
        piece within ``KRYLOV_TARGET`` of the tolerance, or the space is exhausted."""
        self.images.append(image.copy())
        w = image
        column = np.zeros(len(self.basis) + 1)
        for i, v in enumerate(self.basis):
            column[i] = v @ w
            w = w - column[i] * v
        column[-1] = float(np.linalg.norm(w))
        self.hessenberg.append(column)
        m = len(self.hessenberg)
        hess = np.zeros((m + 1, m))
        for j, col in enumerate(self.hessenberg):
            hess[: len(col), j] = col
        rhs = np.zeros(m + 1)
        rhs[0] = self.beta
        y = np.linalg.lstsq(hess, rhs, rcond=None)[0]
        predicted = (self.b - y @ np.array(self.images)).reshape(-1, 3)
        if np.linalg.norm(predicted, axis=1).max() <= KRYLOV_TARGET * atol or column[-1] <= 1e-14 * self.beta:
            self.done = True
        else:
            self.basis.append(w / column[-1])

    def step(self) -> NDArray[np.float64]:
        """The least-squares step on the measured products, (len(piece.positions), 3)."""
        y = np.linalg.lstsq(np.array(self.images).T, self.b, rcond=None)[0]
        return (np.array(self.directions).T @ y).reshape(-1, 3)


def solve(call: BlackBox, rest: Points, sculpt: Points, idx: NDArray[np.int64], pieces: list[Piece],
          start: NDArray[np.float64], start_outputs: Points, blocks: NDArray[np.float64], diagonal: float,
          atol: float, max_calls: int) -> KrylovResult | None:
    """Newton steps on ``pieces`` from the region's offsets ``start`` ((len(idx), 3), which the
    other pieces keep; ``start_outputs`` the chain there, all n points): each step's Krylov
    spaces are built one product of every piece a call (preconditioned by the inverses of the
    per-vertex ``blocks``), each piece's step is the least-squares one on its own products, and
    is accepted where it lowers that piece's residual, else halved on its own. At most
    ``max_calls`` calls; None where the pieces turn out not to be independent or the chain
    gives non-finite values."""
    offsets = np.array(start, dtype=np.float64)
    outputs = np.array(start_outputs, dtype=np.float64)
    target = sculpt[idx]
    r = target - outputs[idx]
    inverse = np.linalg.inv(blocks)
    calls = 0

    def moved_call(trial: NDArray[np.float64], moving: list[Piece]) -> Points | None:
        """The chain at ``rest + trial``, where only ``moving`` pieces left ``offsets``."""
        nonlocal calls
        points = rest.copy()
        points[idx] += trial
        change = call(points)
        calls += 1
        if not np.all(np.isfinite(change)) or moved_another(change - outputs, outside(len(points), moving)):
            return None  # non-finite, or a piece moved another: not independent
        return change

    while calls < max_calls:
        norms = np.linalg.norm(r, axis=1)
        active = [p for p in pieces if norms[p.positions].max() > atol]
        if not active:
            break
        secant = float(np.clip(SECANT_RESIDUAL * norms.max(), SECANT_MIN_RTOL * diagonal, SECANT_MAX_RTOL * diagonal))
        processes = [_Arnoldi.on(p, r[p.positions].ravel()) for p in active]
        while calls < max_calls - 1 and not all(a.done for a in processes):  # one product of every piece a call
            live = [a for a in processes if not a.done]
            moves = [np.einsum("kab,kb->ka", inverse[a.piece.positions], a.basis[-1].reshape(-1, 3)) for a in live]
            together = np.concatenate(moves)
            h = secant / max(float(np.sqrt(np.mean(np.einsum("ij,ij->i", together, together)))), 1e-300)
            trial = offsets.copy()
            for a, d in zip(live, moves, strict=True):
                a.directions.append(d.ravel())
                trial[a.piece.positions] += h * d
            moved = moved_call(trial, [a.piece for a in live])
            if moved is None:
                return None
            for a in live:
                a.take(((moved[idx[a.piece.positions]] - outputs[idx[a.piece.positions]]) / h).ravel(), atol)
        steps = [(a.piece, a.step()) for a in processes if a.images]
        kept = _accept(moved_call, offsets, outputs, r, target, idx, steps, lambda: max_calls - calls) if steps else False
        if kept is None:
            return None
        if not kept:
            break
    members = np.concatenate([p.positions for p in pieces]) if pieces else np.zeros(0, dtype=np.int64)
    return KrylovResult(members, offsets[members], outputs)


def _accept(moved_call: MovedCall, offsets: NDArray[np.float64], outputs: Points, r: Points, target: Points,
            idx: NDArray[np.int64], steps: list[tuple[Piece, NDArray[np.float64]]], left: Callable[[], int]
            ) -> bool | None:
    """Each piece's step tried in one call for all of them, kept where it lowers that piece's
    residual, else halved and tried again (``BACKTRACKS``). ``offsets``, ``outputs`` and ``r``
    are updated in place on the pieces that kept theirs; whether any did (None: the call
    failed, as ``moved_call`` says)."""
    pending = steps
    kept = False
    for _ in range(BACKTRACKS + 1):
        if not pending or left() <= 0:
            break
        trial = offsets.copy()
        for p, step in pending:
            trial[p.positions] += step
        moved = moved_call(trial, [p for p, _ in pending])
        if moved is None:
            return None
        left_over = target - moved[idx]
        again = []
        for p, step in pending:
            pos = p.positions
            if float(np.sum(left_over[pos] ** 2)) < float(np.sum(r[pos] ** 2)):
                offsets[pos] = trial[pos]
                outputs[p.vertices] = moved[p.vertices]
                r[pos] = left_over[pos]
                kept = True
            else:
                again.append((p, 0.5 * step))
        pending = again
    return kept
