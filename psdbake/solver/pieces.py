"""Disconnected pieces of a sculpted region, solved with their exact Jacobians.

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
Broyden secant for every piece, each piece's step accepted or cut on its own
(``solve_small_pieces``, the coupled inverse's first stage).

Its last stage (``solve_exactly``) does the same for pieces of up to ``EXACT_PIECE`` vertices
where the other stages leave vertices above the tolerance: on CesiumMan's large pieces the
sculpt needs ~2,500 directions the chain passes at 1e-3 of its gain, which no span of a few
dozen calls holds. There the Jacobian is coloured (Curtis, Powell and Reid's sparse
differences): one call measures how far a vertex's move reaches (``measure_reach``), and
vertices more than twice that apart move in one call (``colouring``); a piece's first Jacobian
is coloured by half that reach where it is near the answer and by two-fifths nearer still
(``TRUNCATED_REACH``, ``TRUNCATED_REACH_NEAR``: approximate columns, fewer calls, Broyden's
secant at each step), and what its steps leave above the tolerance is measured again exactly. Its columns are those
of the vertices still above the tolerance and their 1-ring (on CesiumMan 103 of the 731-vertex
piece's vertices miss when the stage starts), read on every sculpted vertex's output, and
widened where others go above it; the chord steps run on each piece's regularised misfit, and
a piece the chain cannot reproduce goes on with a stronger ridge and every vertex an unknown,
which bounds its offsets.

Only the chain is called. Whether the pieces really are independent shows in those calls: an
output outside the moved vertices' pieces that changes means they are not, and the stage gives
up (``solve_small_pieces`` returns None).
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass
from typing import TypeVar, cast

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.csgraph import connected_components, shortest_path

from ..arrays import Points
from .inverse import BlackBox

T = TypeVar("T")

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

#: Jacobian entries held at once (each piece's (3m)^2, and its Gram matrix and Cholesky factor as
#: many again: at most ~600 MB): pieces beyond it are solved in further batches, each its own
#: Jacobian calls (``batches``). CesiumMan's pieces hold 8.1M-9.7M entries, one batch.
EXACT_ENTRIES = 25_000_000
#: Pieces of at most this many vertices can have their exact Jacobians measured where the
#: other stages leave vertices above the tolerance (``solve_exactly``): the largest whose
#: Jacobian fits EXACT_ENTRIES, 3 calls a sculpted vertex at most (5,000, within
#: ``coupled.EXACT_CALLS``; coloured, far fewer: CesiumMan's 731-vertex piece 1,113). A rig
#: whose mesh is one piece of 1,312 vertices (the 1.3k bench rig) is one of them: with its
#: sculpts made on the plain-skinned mesh the stages before leave it short of an optimum, one
#: example's offsets at 10x the sculpt's move; solved here, each ends at its optimum with
#: offsets within 2.7x (docs/decisions/coupled-inverse-coarse-meshes.md).
EXACT_PIECE = int(np.sqrt(EXACT_ENTRIES)) // 3
#: Rings added to the chain's measured reach (``measure_reach``) before colouring a piece's
#: vertices for its Jacobian (``colouring``): a vertex whose reach is a little longer than the
#: probed one's still stays within its colour's rows; one much longer shows as a stray output
#: and the Jacobian is measured a vertex a call instead.
REACH_MARGIN = 1
#: ``solve_exactly`` colours a piece's first Jacobian by this share of that reach, each output
#: read as the column of the nearest vertex its call moved. Where two moved vertices' reaches
#: overlap, a column then holds a little of the other's (Delta Mush's response 5 rings out is a
#: few percent of a vertex's own). Chord steps need the right fixed point, not exact columns,
#: and where the residual vanishes any columns give it; what they leave above the tolerance is
#: measured again exactly, on those vertices and their neighbours. Measured on CesiumMan
#: through the chain (docs/decisions/coupled-inverse-cesiumman.md, "Truncated colouring").
TRUNCATED_REACH = 0.5
#: Only a piece whose RMS residual is within this many times the tolerance where the stage
#: starts is measured so: one further away is more often one the chain cannot reproduce, whose
#: optimum needs the exact Jacobian anyway, so a truncated one first is calls lost. Measured at
#: the stage's start: the sculpts made through the chain at 0.4-3.7 times (CesiumMan's pieces)
#: and 21.7 (the character fixture's 135 degree elbow); those made on the plain-skinned mesh at
#: 63.6 and 86.7 (the 1.3k rig's 20 and 40 degree elbows, where a truncated Jacobian first
#: cost 343 calls more, 39%) and up to 1e3-1e4 (CesiumMan's shipped sculpts).
TRUNCATE_WITHIN = 30.0
#: A piece nearer still, within TRUNCATE_NEAR_WITHIN times the tolerance, is coloured by this
#: smaller share: what a chord step on approximate columns leaves grows with the correction it
#: makes, so the smaller the correction, the rougher the columns may be. Each rough Jacobian
#: takes Broyden's secant at every chord step. Measured from where the stages before leave
#: them: CesiumMan's pieces (0.4-3.7 times) reach the tolerance with 4 of its 11 rings (90
#: and 89 colours for its 251-vertex piece, against 130 at half), and with 3 leave 61 vertices
#: at up to 2.1 times; the character fixture's 135 degree elbow (21.7 times) stalls at 40 times
#: with 4 (docs/decisions/coupled-inverse-cesiumman.md, "Two-fifths of the reach near the answer").
TRUNCATED_REACH_NEAR = 0.4
TRUNCATE_NEAR_WITHIN = 10.0
#: ``solve_exactly``'s unknowns: a piece's vertices within this many edges of those above the
#: tolerance where the stage starts (then within one more of those above it after the steps).
#: CesiumMan through the chain, calls an example (every vertex within the tolerance): 902 and
#: 939 with 1 ring; 1,147 and 942 with 2; every vertex of a piece an unknown, 1,271 and 1,299;
#: only the vertices above it, 775 and 1,526 with 4 and 7 vertices left (their neighbours'
#: offsets are needed too).
UNKNOWN_RINGS = 1
#: Chord steps (one call each, shared by all pieces) on the Jacobians measured at the start,
#: in each of ``solve_exactly``'s two phases. A piece settles (its optimum) when an accepted
#: step lowers its objective by less than CHORD_MIN_GAIN of it, or its step has been cut
#: below CHORD_MIN_SCALE.
CHORD_STEPS = 30
CHORD_MIN_GAIN = 1e-4
CHORD_MIN_SCALE = 1.0 / 64.0
#: Times a piece not at its optimum has its Jacobian measured again where the chord steps
#: left it (on CesiumMan's shipped sculpts, pieces of 3-11 vertices whose stale Jacobians'
#: steps were all cut). A piece still REACHABLE_SLACK times the tolerance away is not measured
#: again on the objective's own ridge: it goes on to the stronger one, where it is (CesiumMan's
#: shipped sculpts: 2,648 / 1,463 calls, not 5,245 / 4,587, the objective 0.07% higher and
#: 4.0% lower; the 1.3k rig's one piece sculpted on its plain skinning: 886-894 calls, not
#: 1,707-1,714, at five of its eight elbows).
REMEASURES = 3
#: A piece of more than SMALL_PIECE vertices is measured again only where it holds more than
#: this share of the batch's squared residual (its Jacobian costs 3 calls a vertex). On
#: CesiumMan's shipped sculpts the large pieces' chord steps end cut, short of their optimum,
#: holding most of the residual: measured again they settle (1,700 and 2,700 more calls, the
#: RMS within 0.3%), and the example is at its optimum rather than stopped short of it.
REMEASURE_SHARE = 0.01
#: A piece still above REACHABLE_SLACK times the tolerance after the chord steps on the
#: objective's ridge holds what the chain cannot produce (measured on CesiumMan: sculpts made
#: through the chain end within 1.8x the tolerance, its shipped sculpts at 1e3-1e4x).
REACHABLE_SLACK = 10.0
#: ``NormalEquations``' least ridge, a fraction of its Gram matrix's largest diagonal entry
#: (about 1e4 float64 ulps): where a ridge of 0 would leave the matrix singular.
FLOOR_RIDGE = 1e-12


@dataclass(frozen=True)
class Piece:
    """One small piece: ``positions`` of its sculpted vertices in the region's indices, and
    ``vertices``, all of its vertices (sculpted or not) in the mesh."""

    positions: NDArray[np.int64]
    vertices: NDArray[np.int64]


@dataclass(frozen=True)
class PiecesResult:
    """The small pieces' offsets: ``members`` (positions in the region's indices), their
    ``offsets`` (len(members), 3) and the chain's outputs at rest + offsets (all n points, from
    one call)."""

    members: NDArray[np.int64]
    offsets: NDArray[np.float64]
    outputs: Points


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


def outside(n: int, moving: list[Piece]) -> NDArray[np.bool_]:
    """Which of the mesh's ``n`` points lie outside the ``moving`` pieces."""
    others = np.ones(n, dtype=bool)
    for piece in moving:
        others[piece.vertices] = False
    return others


def moved_another(change: Points, others: NDArray[np.bool_]) -> bool:
    """Whether an output outside the moved pieces (``others``, from ``outside``) changed by more
    than ``COUPLING_RTOL`` of their largest change: then the pieces are not independent."""
    size = np.abs(change)
    return float(size[others].max(initial=0.0)) > COUPLING_RTOL * float(size[~others].max(initial=0.0))


#: A stage's calls as a generator: it yields the points it asks the chain's outputs at, is sent
#: those outputs, and returns its result. A stage written so can run on its own (``drive``) or
#: ride on another stage's calls, the pieces being independent.
Calls = Generator[Points, Points, T]


def drive(calls: Calls[T], call: BlackBox) -> T:
    """Run a stage's calls (``Calls``) through ``call`` to its result."""
    try:
        points = next(calls)
        while True:
            points = calls.send(call(points))
    except StopIteration as stop:
        return cast(T, stop.value)


@dataclass(frozen=True)
class Colouring:
    """Which of a piece's sculpted vertices move together in one Jacobian call: ``classes[k]``
    (positions among them), and for each class each vertex's column, ``owner[k][i]``: the
    moved vertex whose reach holds vertex i's output (-1: none does)."""

    classes: list[NDArray[np.int64]]
    owner: list[NDArray[np.int64]]

    @staticmethod
    def plain(m: int, rows: int | None = None) -> Colouring:
        """One vertex a call (of ``m`` moved; ``rows`` outputs read, ``m`` unless given)."""
        return Colouring([np.array([j]) for j in range(m)], [np.full(m if rows is None else rows, j) for j in range(m)])


def _rings(adjacency: sp.csr_matrix, piece: Piece, sources: NDArray[np.int64]) -> NDArray[np.float64]:
    """Edges between ``sources`` (positions in ``piece.vertices``) and every vertex of the piece,
    through the piece: (len(sources), len(piece.vertices))."""
    graph = adjacency[piece.vertices][:, piece.vertices]
    return np.asarray(shortest_path(graph, unweighted=True, directed=False, indices=sources), dtype=np.float64)


def dsatur(conflict: NDArray[np.bool_]) -> NDArray[np.int64]:
    """A colour for each vertex of the graph ``conflict`` (symmetric (n, n) adjacency), no two
    neighbours alike: Brélaz's DSATUR, which colours next the uncoloured vertex whose
    neighbours already hold the most distinct colours (ties: the most neighbours, then the
    lowest index), each with the lowest colour they leave free. A colour is 3 calls of the
    chain: on CesiumMan's 251-vertex piece, with two moved vertices more than 8 edges apart,
    89 colours against 103 colouring in index order and 92 largest neighbourhood first; at 10
    apart, 130 against 143 (the 130 vertices within 5 edges of one vertex need a colour each,
    so 130 is the fewest). Written here rather than taken from networkx: 15 lines of numpy on
    the dense conflict matrix the colouring has anyway."""
    n = len(conflict)
    conflict = conflict & ~np.eye(n, dtype=bool)
    colour = np.full(n, -1, dtype=np.int64)
    seen = np.zeros((n, n + 1), dtype=bool)  # seen[v, c]: a neighbour of v has colour c
    saturation = np.zeros(n, dtype=np.int64)
    degree = conflict.sum(axis=1)
    for _ in range(n):
        v = int(np.argmax(np.where(colour < 0, saturation * (n + 1) + degree, -1)))  # argmax: the lowest index of ties
        c = int(np.argmin(seen[v]))
        colour[v] = c
        fresh = conflict[v] & ~seen[:, c]
        seen[fresh, c] = True
        saturation[fresh] += 1
    return colour


def colouring(adjacency: sp.csr_matrix, piece: Piece, idx: NDArray[np.int64], reach: int,
              unknown: NDArray[np.int64] | None = None, nearest: bool = False) -> Colouring:
    """A colouring (``dsatur``) of ``piece``'s sculpted vertices (of those at ``unknown``,
    positions among them, where given) so that two of one colour are more than ``2 * reach``
    edges apart (through the whole piece): moved together, no output within ``reach`` edges of
    one is within ``reach`` of another, so each output (every sculpted vertex's) changes for
    one of them only and is that one's column (Curtis-Powell-Reid's idea for sparse Jacobians).
    ``nearest``: each output is the column of the nearest moved vertex, however far (with a
    ``reach`` shorter than the chain's: approximate columns in fewer calls)."""
    inside = np.searchsorted(piece.vertices, idx[piece.positions])  # the sculpted vertices, in the piece
    moving = np.arange(len(inside)) if unknown is None else unknown
    rings = _rings(adjacency, piece, inside[moving])[:, inside]  # (s, m): from each moved vertex to each output
    colour = dsatur(rings[:, moving] <= 2 * reach)
    classes = [np.nonzero(colour == c)[0] for c in range(int(colour.max()) + 1)]
    owner = []
    for members in classes:
        if nearest:
            owner.append(members[np.argmin(rings[members], axis=0)].astype(np.int64))
            continue
        close = rings[members].T <= reach  # (m, len(members))
        found = np.where(close.any(axis=1), members[np.argmax(close, axis=1)], -1)
        owner.append(found.astype(np.int64))
    return Colouring(classes, owner)


def measure_reach(call: BlackBox, at: Points, out: Points, adjacency: sp.csr_matrix, pieces: list[Piece],
                  vertex: list[NDArray[np.int64]], h: float) -> int | None:
    """How many edges an input vertex's move reaches through the chain: one call moving the
    first sculpted vertex of every piece along a diagonal, the farthest changed output (more
    than ``COUPLING_RTOL`` of the piece's largest change) counted in edges through its piece.
    None where nothing changed or the chain returned non-finite values."""
    moved = at.copy()
    for v in vertex:
        moved[v[0]] += h * np.array([0.8, 0.5, 0.3]) / np.sqrt(0.98)
    change = call(moved)
    if not np.all(np.isfinite(change)):
        return None
    size = np.linalg.norm(change - out, axis=1)
    farthest = -1
    for piece, v in zip(pieces, vertex, strict=True):
        local = size[piece.vertices]
        changed = np.nonzero(local > COUPLING_RTOL * float(local.max(initial=0.0)))[0]
        if not len(changed):
            continue
        start = np.searchsorted(piece.vertices, v[:1])
        farthest = max(farthest, int(np.max(_rings(adjacency, piece, start)[0, changed])))
    return farthest if farthest >= 0 else None


def jacobians(call: BlackBox, at: Points, out: Points, pieces: list[Piece], vertex: list[NDArray[np.int64]],
              h: float, colours: list[Colouring] | None = None,
              unknowns: list[NDArray[np.int64]] | None = None) -> tuple[list[NDArray[np.float64]], int] | None:
    """``jacobian_steps`` through ``call``."""
    return drive(jacobian_steps(at, out, pieces, vertex, h, colours, unknowns), call)


def jacobian_steps(at: Points, out: Points, pieces: list[Piece], vertex: list[NDArray[np.int64]], h: float,
                   colours: list[Colouring] | None = None, unknowns: list[NDArray[np.int64]] | None = None
                   ) -> Calls[tuple[list[NDArray[np.float64]], int] | None]:
    """Each piece's exact Jacobian at the points ``at`` (whose outputs are ``out``): forward
    differences of step ``h``, one call moving one vertex of every piece along one axis
    (``vertex[q]``: piece q's sculpted vertices in the mesh, its outputs; ``unknowns[q]``, the
    ones moved, all of them unless given), so 3 calls a vertex of the largest piece; with
    ``colours`` (``colouring``), one call moves a whole colour of every piece, so 3 calls a
    colour. With the calls made; None where an output outside the moved pieces changed (the
    pieces are not independent), an output farther from the moved vertices than the
    colouring's reach did (it does not hold), or the chain returned non-finite values. A
    generator of the points to call the chain at (``Calls``), so that these calls can ride on
    another stage's (``coupled._small_pieces_first``)."""
    moves = vertex if unknowns is None else unknowns
    jac = [np.zeros((3 * len(v), 3 * len(u))) for v, u in zip(vertex, moves, strict=True)]
    plan = colours or [Colouring.plain(len(u), len(v)) for v, u in zip(vertex, moves, strict=True)]
    calls = 0
    for k in range(max(len(c.classes) for c in plan)):  # 3 calls per colour: its columns of every piece at once
        moving = [q for q, c in enumerate(plan) if k < len(c.classes)]
        others = outside(len(at), [pieces[q] for q in moving])
        for axis in range(3):
            moved = at.copy()
            for q in moving:
                moved[moves[q][plan[q].classes[k]], axis] += h
            change = yield moved
            calls += 1
            if not np.all(np.isfinite(change)):
                return None
            change -= out
            if moved_another(change, others):
                return None  # a piece moved another: not independent
            for q in moving:
                rows = change[vertex[q]] / h  # (m, 3)
                owner = plan[q].owner[k]  # each row's moved vertex (column), -1: none within reach
                if np.any(owner < 0):
                    stray = float(np.abs(rows[owner < 0]).max())
                    if stray > COUPLING_RTOL * float(np.abs(rows).max(initial=0.0)):
                        return None  # an output beyond the reach moved: the colouring does not hold
                mine = np.nonzero(owner >= 0)[0]
                for a in range(3):
                    jac[q][3 * mine + a, 3 * owner[mine] + axis] = rows[mine, a]
    return jac, calls


def solve_small_pieces(call: BlackBox, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
                       pieces: list[Piece], diagonal: float, atol: float) -> PiecesResult | None:
    """Offsets for the small pieces (module docstring), from zero (``base``: the chain at rest).
    None where the calls show that the pieces are not independent, or the chain returns
    non-finite values."""
    return drive(small_pieces_steps(rest, sculpt, base, idx, pieces, diagonal, atol), call)


def small_pieces_steps(rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64], pieces: list[Piece],
                       diagonal: float, atol: float) -> Calls[PiecesResult | None]:
    """``solve_small_pieces`` as a generator of the points to call the chain at (``Calls``): the
    chain's outputs there are sent back, and the result is the generator's return value."""
    vertex = [idx[p.positions] for p in pieces]
    measured = yield from jacobian_steps(rest, base, pieces, vertex, STEP_RTOL * diagonal)
    if measured is None:
        return None
    jac = measured[0]
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
        out = yield moved
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
    outputs = yield accepted()  # every piece at its accepted offsets, in one call
    if not np.all(np.isfinite(outputs)):
        return None
    members = np.concatenate([p.positions for p in pieces])
    return PiecesResult(members, np.concatenate(offsets), outputs)


def batches(pieces: list[Piece]) -> list[list[Piece]]:
    """``pieces`` in batches whose Jacobians hold at most ``EXACT_ENTRIES`` entries together
    (a piece larger than that alone), largest first: a batch costs 3 calls a sculpted vertex of
    its largest piece."""
    found: list[list[Piece]] = []
    held = EXACT_ENTRIES + 1
    for piece in sorted(pieces, key=lambda p: -len(p.positions)):  # alike sizes together: fewer calls
        entries = (3 * len(piece.positions)) ** 2
        if held + entries > EXACT_ENTRIES:
            found.append([])
            held = 0
        found[-1].append(piece)
        held += entries
    return found


def jacobian_calls(pieces: list[Piece]) -> int:
    """Calls ``solve_exactly`` spends on measuring these pieces' Jacobians once."""
    return 3 * max((len(p.positions) for p in pieces), default=0) + 1


@dataclass(frozen=True)
class ExactResult:
    """Offsets for some pieces from their exact Jacobians (``solve_exactly``): ``members``
    (positions in the region's indices), their ``offsets``, the chain's outputs with every
    piece at its offsets (all n points), and which members belong to a piece whose solve ended
    at its optimum (``settled``: its model saw nothing left to gain, or a step
    gained next to nothing), not on its step budget or on steps cut until they vanished (a
    chain whose small moves say nothing of its large ones, as one that snaps to a grid)."""

    members: NDArray[np.int64]
    offsets: NDArray[np.float64]
    outputs: Points
    settled: NDArray[np.bool_]


class NormalEquations:
    """A piece's measured Jacobian J and the Cholesky factors of ``J^T J + rho I``, one per
    ridge rho: a chord step needs only those (``step``). An SVD of J gave the same steps: on
    the 1.3k bench rig's one piece (3,936 columns, one BLAS thread) it took 29 s, the Gram
    matrix and its factor 2.3 s. The Gram matrix squares J's condition number, which the ridge
    bounds: at the objective's ridge (``smoothstart.SPAN_RIDGE``) rho is 1e-6 of the blocks'
    median gain squared, so ``J^T J + rho I``'s is about 1e6 times (J's largest singular value
    / that gain)^2: 2.7e8 on a tube's Delta Mush Jacobian, where the steps match a
    least-squares solve that never forms it to 1.2e-8."""

    def __init__(self, jacobian: NDArray[np.float64]) -> None:
        self.jacobian = jacobian
        self.gram = jacobian.T @ jacobian
        self._factors: dict[float, tuple[NDArray[np.float64], bool]] = {}

    def step(self, residual: NDArray[np.float64], offsets: NDArray[np.float64], rho: float) -> NDArray[np.float64]:
        """The minimiser's change of ``offsets`` for ``|residual - J s|^2 + rho |offsets + s|^2``:
        ``(J^T J + rho I)^-1 (J^T residual - rho offsets)``. A ridge of 0 (no gain measured)
        is raised to ``FLOOR_RIDGE`` of the Gram matrix's largest diagonal entry, so that the
        factor exists."""
        if rho not in self._factors:
            floor = FLOOR_RIDGE * float(np.max(np.diag(self.gram), initial=0.0))
            self._factors[rho] = cho_factor(self.gram + max(rho, floor) * np.eye(len(self.gram)))
        return np.asarray(cho_solve(self._factors[rho], self.jacobian.T @ residual - rho * offsets))


def solve_exactly(call: BlackBox, rest: Points, sculpt: Points, idx: NDArray[np.int64], pieces: list[Piece],
                  start: NDArray[np.float64], start_outputs: Points, diagonal: float, atol: float, ridge: float,
                  unreachable_ridge: float, max_calls: int, adjacency: sp.csr_matrix) -> ExactResult | None:
    """Pieces whose vertices other stages left above the tolerance, on their exact Jacobians
    measured at ``start`` (the region's offsets, (len(idx), 3), which the other pieces keep;
    ``start_outputs`` the chain there, all n points), their columns those of the vertices within
    ``UNKNOWN_RINGS`` of the ones above the tolerance (the others held): chord Gauss-Newton
    steps (each Jacobian's normal equations factored once, ``NormalEquations``) on each
    piece's ``|r|^2 + rho |D|^2``, one call a step for all pieces, each piece's step accepted
    or cut on its own. A piece that took steps
    and is not at its optimum, or whose steps left vertices beyond its unknowns above the
    tolerance, has its Jacobian measured again where they left it, those vertices and their
    neighbours unknowns too (a large piece only where it holds ``REMEASURE_SHARE`` of the
    residual), up to ``REMEASURES`` times while ``max_calls`` allows (one whose every step was
    cut is not: its Jacobian says nothing of the chain at the scale of a step). A piece whose
    first Jacobian was coloured short of the reach is measured again exactly on what its steps
    left above the tolerance and their 1-ring, widened by a ring each time it still misses:
    an optimum over those few vertices is not the piece's, and is not called one. ``rho`` is
    ``ridge`` (the objective's), and where a piece still misses the tolerance by more than
    ``REACHABLE_SLACK`` times after that, the sculpt asks what the chain cannot produce there:
    that piece goes on with ``unreachable_ridge`` and every vertex an unknown, which bounds its
    offsets (``coupled.UNREACHABLE_RIDGE``), where ``max_calls`` allows measuring it whole
    (else it is left as it is, not at its optimum). None where the pieces turn out not to be
    independent or the chain returns non-finite values."""
    count = len(pieces)
    vertex = [idx[p.positions] for p in pieces]
    offsets = [start[p.positions].ravel().copy() for p in pieces]
    current = [start_outputs[v].ravel().copy() for v in vertex]
    targets = [sculpt[v].ravel() for v in vertex]
    rho, settled = [ridge] * count, [False] * count
    optimal = [False] * count  # settled by a step that gained next to nothing, not by cut steps
    gained = [False] * count
    factors: list[NormalEquations | None] = [None] * count
    rough = [False] * count  # its Jacobian's colouring was truncated (``TRUNCATED_REACH[_NEAR]``): columns approximate
    narrowed = [False] * count  # its unknowns cut to those a rough Jacobian's steps left above the tolerance
    inside = [np.searchsorted(p.vertices, v) for p, v in zip(pieces, vertex, strict=True)]

    def around(q: int, seeds: NDArray[np.int64], rings: int) -> NDArray[np.int64]:
        """Piece q's sculpted vertices within ``rings`` edges of ``seeds`` (positions among them)."""
        if not len(seeds):
            return seeds
        near = _rings(adjacency, pieces[q], inside[q][seeds])[:, inside[q]] <= rings
        return np.nonzero(near.any(axis=0))[0]

    def residuals(q: int) -> NDArray[np.float64]:
        """Piece q's residual per sculpted vertex where its offsets are now."""
        return np.asarray(np.linalg.norm((targets[q] - current[q]).reshape(-1, 3), axis=1))

    def above(q: int) -> NDArray[np.int64]:
        """Piece q's sculpted vertices above the tolerance now (positions among them)."""
        return np.nonzero(residuals(q) > atol)[0]

    # each piece's unknowns (positions among its sculpted vertices): those near the ones above
    # the tolerance where the stages left them, and near those that go above it later; every
    # one where the chain cannot reproduce the piece
    unknown = [around(q, above(q), UNKNOWN_RINGS) for q in range(count)]
    calls = 0

    held = rest.copy()  # every other sculpted vertex where ``start`` has it
    held[idx] += start

    def moved_by(changes: dict[int, NDArray[np.float64]] | None = None) -> Points:
        moved = held.copy()
        for q, v in enumerate(vertex):
            moved[v] = rest[v] + (offsets[q] if changes is None or q not in changes else changes[q]).reshape(-1, 3)
        return moved

    def rms(q: int) -> float:
        return float(np.sqrt(np.mean(residuals(q) ** 2)))

    def worst(q: int) -> float:
        return float(np.max(residuals(q)))

    def objective(q: int, out: NDArray[np.float64], off: NDArray[np.float64]) -> float:
        return float(np.sum((targets[q] - out) ** 2)) + rho[q] * float(off @ off)

    def coordinates(q: int) -> NDArray[np.int64]:
        return (3 * unknown[q][:, None] + np.arange(3)).ravel()

    def newcomers(q: int) -> NDArray[np.int64]:
        """Piece q's vertices near those above the tolerance now that are not yet unknowns."""
        return np.setdiff1d(around(q, above(q), UNKNOWN_RINGS + 1), unknown[q])

    def widen(q: int, more: NDArray[np.int64]) -> None:
        """Piece q's unknowns with ``more`` (only right before its Jacobian is measured again)."""
        unknown[q] = np.union1d(unknown[q], more)
        plans.pop(q, None)
        narrowed[q] = narrowed[q] and len(unknown[q]) < len(pieces[q].positions)  # every vertex: its optimum is the piece's

    reach: list[int | None] = []  # measured once, by the first measure
    plans: dict[int, Colouring] = {}  # each piece's colouring, for its measures again

    def measure(which: list[int], truncated: dict[int, float] | None = None) -> bool:
        """The Jacobians of pieces ``which`` where they are now (coloured by the chain's
        measured reach, those in ``truncated`` by the share of it it gives, else a vertex a
        call), and their normal equations."""
        nonlocal calls
        at = moved_by()
        base = call(at)
        calls += 1
        chosen, where = [pieces[q] for q in which], [vertex[q] for q in which]
        moving = [vertex[q][unknown[q]] for q in which]
        if not reach:
            reach.append(measure_reach(call, at, base, adjacency, chosen, where, STEP_RTOL * diagonal))
            calls += 1
        found, short = None, [False] * len(which)
        if reach[0] is not None:
            full = reach[0] + REACH_MARGIN
            spans = {q: max(int(share * full), 1) for q, share in (truncated or {}).items()}
            short = [spans.get(q, full) < full for q in which]
            plan = []
            for q, cut in zip(which, short, strict=True):
                if cut:
                    plan.append(colouring(adjacency, pieces[q], idx, spans[q], unknown[q], nearest=True))
                    continue
                if q not in plans:
                    plans[q] = colouring(adjacency, pieces[q], idx, full, unknown[q])
                plan.append(plans[q])
            if max(len(c.classes) for c in plan) < max(len(u) for u in moving):
                found = jacobians(call, at, base, chosen, where, STEP_RTOL * diagonal, plan, moving)
                if found is None:  # an output beyond the reach moved: a vertex a call (its calls, at most)
                    calls += 3 * max(len(c.classes) for c in plan)
        if found is None:
            short = [False] * len(which)
            found = jacobians(call, at, base, chosen, where, STEP_RTOL * diagonal, unknowns=moving)
        if found is None:
            return False
        calls += found[1]
        for q, a, cut in zip(which, found[0], short, strict=True):
            factors[q] = NormalEquations(a)
            rough[q] = cut
        return True

    def measure_calls(sizes: list[int]) -> int:
        """At most what ``measure`` spends on pieces of ``sizes`` unknowns: a vertex a call."""
        return 3 * max(sizes) + 1

    def chord(which: list[int]) -> bool:
        """Up to CHORD_STEPS steps on pieces ``which`` until each is within the tolerance or
        settled; ``gained`` says which of them took a step."""
        nonlocal calls
        scale = dict.fromkeys(which, 1.0)
        for q in which:
            gained[q] = False
        for _ in range(CHORD_STEPS):
            which = [q for q in which if worst(q) > atol and not settled[q]]
            if not which:
                break
            trial = {}
            for q in which:
                factor = factors[q]
                assert factor is not None  # measured before any chord on it
                where = coordinates(q)
                step = np.zeros_like(offsets[q])
                step[where] = factor.step(targets[q] - current[q], offsets[q][where], rho[q])
                now = objective(q, current[q], offsets[q])
                predicted = objective(q, current[q] + factor.jacobian @ step[where], offsets[q] + step)
                if now - predicted <= CHORD_MIN_GAIN * now and not narrowed[q]:  # the model sees nothing left to gain here
                    settled[q] = optimal[q] = True
                    continue
                trial[q] = offsets[q] + scale[q] * step
            if not trial:
                break
            out = call(moved_by(trial))
            calls += 1
            if not np.all(np.isfinite(out)):
                return False
            for q, off in trial.items():
                if rough[q]:  # Broyden: an approximate Jacobian takes the secant, whether the step is taken or not
                    where = coordinates(q)
                    factor = factors[q]
                    assert factor is not None
                    secant = (off - offsets[q])[where]
                    change = out[vertex[q]].ravel() - current[q]
                    jac = factor.jacobian + np.outer(change - factor.jacobian @ secant, secant) / float(secant @ secant)
                    factors[q] = NormalEquations(jac)
                before, after = objective(q, current[q], offsets[q]), objective(q, out[vertex[q]].ravel(), off)
                if after < before:
                    offsets[q], current[q], gained[q] = off, out[vertex[q]].ravel(), True
                    scale[q] = min(1.0, 2.0 * scale[q])
                    settled[q] = optimal[q] = before - after <= CHORD_MIN_GAIN * before
                else:
                    scale[q] *= 0.25
                    settled[q] = scale[q] < CHORD_MIN_SCALE
        return True

    for phase in range(2):
        if phase == 0:
            todo = [q for q in range(count) if worst(q) > atol]
        else:  # the pieces the chain cannot reproduce, on the stronger ridge, every vertex an unknown
            todo = [q for q in range(count) if worst(q) > REACHABLE_SLACK * atol]
            whole = [q for q in todo if len(unknown[q]) < len(pieces[q].positions)]
            if whole and calls + measure_calls([len(pieces[q].positions) for q in whole]) > max_calls:
                todo = [q for q in todo if q not in whole]
                for q in whole:  # no calls left to measure them whole: left as they are, not at an optimum
                    optimal[q] = False
            for q in todo:
                rho[q], settled[q], optimal[q] = unreachable_ridge, False, False
        if not todo:
            continue
        stale = [q for q in todo if factors[q] is None or rough[q] or len(unknown[q]) < len(pieces[q].positions)]
        if phase == 1:
            for q in stale:
                widen(q, np.arange(len(pieces[q].positions)))
        near_enough = {q: TRUNCATED_REACH_NEAR if rms(q) <= TRUNCATE_NEAR_WITHIN * atol else TRUNCATED_REACH
                       for q in stale if phase == 0 and rms(q) <= TRUNCATE_WITHIN * atol}
        if stale and not measure(stale, near_enough):
            return None
        for _ in range(1 + REMEASURES):
            if not chord(todo):
                return None
            # a truncated Jacobian's optimum is not the objective's: a piece it leaves above the
            # tolerance is measured again exactly, on the vertices above it and their neighbours
            # where it came near (else on the same unknowns), before anything is concluded of it
            near = [q for q in todo if rough[q] and worst(q) > atol]
            for q in todo:
                optimal[q] = optimal[q] and not rough[q]
            for q in near:
                if worst(q) <= REACHABLE_SLACK * atol:
                    unknown[q] = around(q, above(q), UNKNOWN_RINGS)
                    plans.pop(q, None)
                    narrowed[q] = True
                settled[q] = False
            todo = [q for q in todo if not rough[q]]
            left = sum(float(np.sum((targets[p] - current[p]) ** 2)) for p in range(count))
            # a piece still on its way, or one whose unknowns were cut to a rough Jacobian's
            # leftovers (an optimum over those few is not the piece's: it widens by a ring)
            more = {q: newcomers(q) for q in todo if worst(q) > atol and (gained[q] or narrowed[q])
                    and (phase == 1 or worst(q) <= REACHABLE_SLACK * atol)}  # (far off: on to the stronger ridge)
            todo = [q for q in more if (len(more[q]) or not optimal[q])  # with new unknowns or short of its optimum,
                    and (len(pieces[q].positions) <= SMALL_PIECE or narrowed[q]  # and cheap to measure again
                         or float(np.sum((targets[q] - current[q]) ** 2)) > REMEASURE_SHARE * left)]  # or worth it
            sizes = [len(unknown[q]) + len(more[q]) for q in todo] + [len(unknown[q]) for q in near]
            if not sizes or calls + measure_calls(sizes) > max_calls:
                break
            for q in todo:  # measured again where they are, and on
                widen(q, more[q])
                settled[q] = False
            todo = sorted(todo + near)
            if not measure(todo):
                return None
    for q in range(count):  # an optimum over a rough Jacobian's leftovers alone is none of the piece's
        optimal[q] = optimal[q] and not (narrowed[q] and worst(q) > atol)
    outputs = call(moved_by())
    calls += 1
    if not np.all(np.isfinite(outputs)):
        return None
    members = np.concatenate([p.positions for p in pieces])
    sizes = [len(p.positions) for p in pieces]
    return ExactResult(members, np.concatenate(offsets).reshape(-1, 3), outputs,
                       np.repeat(optimal, sizes).astype(bool))
