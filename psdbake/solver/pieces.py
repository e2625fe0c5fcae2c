"""Small disconnected pieces of a sculpted region, solved with their exact Jacobians.

A real character's mesh is split into pieces (connected components of its edges: UV shells,
parts). CesiumMan's sculpted region touches 136, 124 of them of 3-25 vertices. A chain that
couples vertices along edges moves no piece from another (measured: the full Jacobian, no output
outside a moved piece changed), but on a small piece it does not smooth: Delta Mush collapses
the piece and adds its deltas in frames rebuilt from it, so the piece's rotations pass at full
size where the smooth start's model (``smoothstart``) passes them at 1e-6. No cheap model fits
those pieces (docs/decisions/coupled-inverse-cesiumman.md); their exact Jacobians are cheap
instead: one call moves one vertex of *every* small piece along one axis, and each piece reads
its own column from its own outputs, so all pieces of at most m sculpted vertices cost 3m calls
together. Then damped Gauss-Newton on each piece, one call a step for all of them, each call a
Broyden secant for every piece, each piece's step accepted or cut on its own.

Only the chain is called. Whether the pieces really are independent shows in those calls: an
output outside the moved vertices' pieces that changes means they are not, and the stage gives
up (``solve_small_pieces`` returns None).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components

from ..arrays import Points
from .inverse import BlackBox

#: An output outside the moved pieces that changes by more than this fraction of the moved
#: pieces' largest change means the pieces are not independent (as ``coupled.COUPLING_RTOL``).
COUPLING_RTOL = 1e-6

#: A piece of the mesh with at most this many vertices is solved here (3 calls a vertex of the
#: largest one, shared by all): CesiumMan's 124 pieces of 3-25 vertices cost 75 calls. With 12,
#: its 19- and 25-vertex pieces stayed with the large ones and CesiumMan@12 ended with 997
#: vertices above the tolerance (844 without this stage, 425 with 25).
SMALL_PIECE = 25
#: Jacobian columns by forward differences of this step (a fraction of the diagonal, about 100
#: float32 ulps of the coordinates; the chain is linear over it on CesiumMan's pieces).
STEP_RTOL = 1e-5
#: Each piece's Gauss-Newton step is damped by (SMALL_RIDGE * its Jacobian's norm)^2: the
#: collapsed pieces' near-null directions would otherwise take huge offsets (measured on
#: CesiumMan's pieces, whose Jacobians' norms are 1.2-1.7: a damping of 1e-8 diverged, 1e-6
#: converged in 20-37 steps, 1e-5 left 10 vertices at @30).
SMALL_RIDGE = 1e-3
#: Steps (one call each) after the Jacobians; the stage stops earlier when every vertex is
#: within the tolerance or STALL_STEPS calls in a row improved no piece.
MAX_STEPS = 48
STALL_STEPS = 4


@dataclass(frozen=True)
class Piece:
    """One small piece: ``positions`` of its sculpted vertices in the region's indices, and
    ``vertices``, all of its vertices (sculpted or not) in the mesh."""

    positions: NDArray[np.int64]
    vertices: NDArray[np.int64]


@dataclass(frozen=True)
class PiecesResult:
    """The small pieces' offsets: ``members`` (positions in the region's indices), their
    ``offsets`` (len(members), 3), the chain's outputs at rest + offsets (all n points, from one
    call) and the calls made."""

    members: NDArray[np.int64]
    offsets: NDArray[np.float64]
    outputs: Points
    calls: int


def small_pieces(adjacency: sp.csr_matrix, idx: NDArray[np.int64], limit: int = SMALL_PIECE) -> list[Piece]:
    """The pieces of the mesh (connected components of all its edges) with at most ``limit``
    vertices that hold sculpted vertices, smallest label first."""
    _, label = connected_components(adjacency, directed=False)
    sizes = np.bincount(label)
    small = np.nonzero(sizes[label[idx]] <= limit)[0]
    pieces = []
    for piece in np.unique(label[idx[small]]):
        pieces.append(Piece(small[label[idx[small]] == piece], np.nonzero(label == piece)[0]))
    return pieces


def solve_small_pieces(call: BlackBox, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
                       pieces: list[Piece], diagonal: float, atol: float) -> PiecesResult | None:
    """Offsets for the small pieces (module docstring), from zero (``base``: the chain at rest).
    None where the calls show that the pieces are not independent, or the chain returns
    non-finite values."""
    vertex = [idx[p.positions] for p in pieces]
    h = STEP_RTOL * diagonal
    jac = [np.zeros((3 * len(v), 3 * len(v))) for v in vertex]
    calls = 0
    for j in range(max(len(v) for v in vertex)):  # 3 calls per j: column (j, axis) of every piece at once
        moving = [q for q, v in enumerate(vertex) if j < len(v)]
        others = np.ones(len(rest), dtype=bool)
        for q in moving:
            others[pieces[q].vertices] = False
        for axis in range(3):
            moved = rest.copy()
            for q in moving:
                moved[vertex[q][j], axis] += h
            out = call(moved)
            calls += 1
            if not np.all(np.isfinite(out)):
                return None
            change = np.abs(out - base)
            if float(change[others].max(initial=0.0)) > COUPLING_RTOL * float(change[~others].max(initial=0.0)):
                return None  # a piece moved another: not independent
            for q in moving:
                jac[q][:, 3 * j + axis] = ((out[vertex[q]] - base[vertex[q]]) / h).ravel()
    offsets = [np.zeros((len(v), 3)) for v in vertex]

    def accepted() -> Points:  # rest with every piece at its accepted offsets
        moved = rest.copy()
        for v, o in zip(vertex, offsets, strict=True):
            moved[v] += o
        return moved

    current = [base[v].copy() for v in vertex]
    scale = [1.0] * len(vertex)
    stalled = 0
    for _ in range(MAX_STEPS):
        residual = [sculpt[v] - c for v, c in zip(vertex, current, strict=True)]
        active = [q for q, r in enumerate(residual) if np.max(np.linalg.norm(r, axis=1)) > atol]
        if not active:
            break
        steps = {}
        moved = accepted()
        for q in active:
            a = jac[q]
            damping = (SMALL_RIDGE * np.linalg.norm(a, 2)) ** 2
            s = np.linalg.solve(a.T @ a + damping * np.eye(len(a)), a.T @ residual[q].ravel())
            steps[q] = scale[q] * s
            moved[vertex[q]] += steps[q].reshape(-1, 3)
        out = call(moved)
        calls += 1
        if not np.all(np.isfinite(out)):
            return None
        improved = False
        for q, s in steps.items():
            trial = out[vertex[q]]
            change = (trial - current[q]).ravel()
            if float(s @ s) > 0:  # Broyden: the secant, whether the step is taken or not
                jac[q] += np.outer(change - jac[q] @ s, s) / float(s @ s)
            if np.sum((sculpt[vertex[q]] - trial) ** 2) < np.sum(residual[q] ** 2):
                offsets[q] += s.reshape(-1, 3)
                current[q] = trial
                scale[q] = min(1.0, 2.0 * scale[q])
                improved = True
            else:
                scale[q] *= 0.25
        stalled = 0 if improved else stalled + 1
        if stalled >= STALL_STEPS:
            break
    outputs = call(accepted())  # every piece at its accepted offsets, in one call
    calls += 1
    if not np.all(np.isfinite(outputs)):
        return None
    members = np.concatenate([p.positions for p in pieces])
    return PiecesResult(members, np.concatenate(offsets), outputs, calls)
