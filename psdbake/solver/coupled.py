"""The black-box inverse when the chain couples vertices (Delta Mush, corrective smooth, wraps).

``invert`` is what ``fit`` runs per example. Whether the chain couples vertices shows in the
per-vertex solver's own Jacobian calls (they move only sculpted vertices: any other output that
changes was moved by a neighbour), so skinning stays at 5 calls per example. Where no unsculpted
vertex can show it (a sculpt that covers whole pieces of the mesh) a **probe** call with a few
well-separated sculpted vertices moved (farthest-point sample, deterministic) tells whether any
*other* sculpted vertex's output moved. Skinning and per-vertex deformers leave every other
output bit-identical; a coupling deformer moves the neighbours. Per-vertex chains keep
``inverse.invert_example``'s result (Powell in lockstep, regime "per-vertex").

Coupled chains are solved jointly::

    minimise || sculpt[S] - F(rest + D)[S] ||^2 + ridge || D ||^2     D: offsets on the sculpted vertices S

(vertices whose output the sculpt did not move keep a zero offset, so the fit never spreads
beyond them; ``ridge`` is ``smoothstart.ridge``, the documented regularisation that keeps the
offsets bounded where a sculpt asks for what the chain cannot produce). Everything the
per-vertex solver measured is reused: the chain at rest, the per-vertex 3x3 blocks (3 calls
moving *every* sculpted vertex along x, then y, then z: the row sums of the coupled chain's
Jacobian, for a smoothing deformer the skinning's own blocks) and its linearised start.

0s. **Many small pieces, on a structured Jacobian** (``_whole_structured``): where the region
   holds small pieces whose exact Jacobians would cost more calls than the structured model
   below (CesiumMan's 25-vertex shells: 76) and ``invert`` was given the chain's skinning, the
   whole region, small pieces and large, is solved on that model from the linearised start:
   damped Gauss-Newton with Broyden's update, the model turned with its smoothed 1-rings where
   it stalls (no call), a piece or two left finished on their exact Jacobians (CesiumMan: 41
   and 42 calls as ``fit`` runs it, against 97 and 124 through stage 0 and the smooth start).
   Where it misses more,
   its calls are spent and stage 0 starts afresh.
0. **Small pieces of the mesh** (``_small_pieces_first``, ``psdbake.solver.pieces``): where the
   region holds pieces of at most ``pieces.SMALL_PIECE`` vertices (a character's small UV
   shells, which Delta Mush rotates rather than smooths), their exact Jacobians (3 calls a
   vertex of the largest, shared by all pieces) and damped Gauss-Newton. Their calls after the
   first ride on the rest's solve (``_Riding``): each call of the stages below on the rest of
   the region also carries the small pieces' next one (CesiumMan: 284 / 313 -> 198 / 200
   calls). Where they reach the tolerance, the rest of the region is solved with them held;
   otherwise (the rest's solve is then given up) the stages below solve the whole region and
   each small piece keeps the better solution.
1. **The smooth start** (``smooth_start``, ``psdbake.solver.smoothstart``): Levenberg-Marquardt over
   the region's smoothest fields (``psdbake.solver.smoothbasis``, sized to the region), first the
   coarsest quarter of them, then all, on a model of the chain's Jacobian that knows how much
   the chain smooths (one probe call measures it), corrected by Broyden's update from every
   step's call. Where the smoothing reaches across a large part of a small mesh, the fields a
   sculpt needs come out of the chain at a fifth of their size or less; the blocks alone took
   them at full size, and the smooth start undershot by that much at every step.
   Where it misses, **the blocks are tried finely** (``_on_fine_blocks``): one call moves
   every sculpted vertex by ``FINE_BLOCKS_RTOL`` of the diagonal along x, y and z from the
   smooth start's offsets. Where the response is off the blocks' prediction by more than
   ``BLOCKS_DISAGREE``, their 1e-2 step crossed a fold's non-linearity: 2 calls more measure
   them there, the stages below use them, and a smooth start that left the sculpt far runs
   again on them from zero (the character fixture's 135 degree elbow: 131 -> 63 calls; its
   140, finished on measured directions on them: 103 -> 49).
   Where it misses on a region of several pieces of the mesh and ``invert`` was given the
   chain's skinning alone (``fit`` gives ``ChainSkinning``, which reads it from the chain's own
   calls): **a structured Jacobian** (``psdbake.solver.structured``): the model ``J = A S^s M``,
   the skinning's blocks ``M`` (4 calls of the skinning, or none where they are read from the
   chain's), the mesh's umbrella smoothing ``S^s`` and a 1-ring local operator ``A`` fitted
   from 25 products of the chain, and filtered Gauss-Newton steps on each piece
   (CesiumMan before stage 0s: the stage took 33 and 34 calls, 4 of the skinning's; 97 and
   124 calls an example in all, 36 and 61 of them the small pieces' own once the rest was
   done, against 187 and 189 on the pieces' Krylov spaces below). Where it leaves vertices above the tolerance, the
   stages below go on from it.
2. Where the smooth start leaves the sculpt nearly reproduced (the RMS residual within
   ``pieces.REACHABLE_SLACK`` times the tolerance): **Gauss-Newton on measured directions**
   (``psdbake.solver.subspace``), one call a direction: global ones (the blocks' inverse on
   what the directions so far leave, a Krylov space kept from step to step) and, once few
   vertices miss, the own directions of the worst of them, then their neighbours'. At a fold
   of a coarse mesh what is left sits on a few vertices' own offsets, which Krylov spaces hold
   little of: the 1.3k bench rig's 80 and 100 degree elbows took 60 and 76 calls in all,
   against 128 and 171 through the stages below.
   Otherwise **Newton-Krylov** from there: GMRES (right-preconditioned by the blocks, Arnoldi with
   modified Gram-Schmidt) on ``J delta = r``, each Jacobian-vector product one black-box call
   (forward difference, the largest vertex move a tenth of the largest residual, within
   ``JVP_MIN_STEP_RTOL`` and ``JVP_STEP_RTOL`` of the diagonal), stopping once the linear model
   predicts every vertex within a fraction of the tolerance; the step is the one in the
   Krylov space that minimises the regularised misfit's linear model; one call at
   ``rest + D`` checks it (halved up to ``BACKTRACKS`` times where it does not help). In this
   finish the vertices still above the tolerance weigh by how far above they are. Where it
   misses short of an optimum with at most ``POLISH_VERTICES`` left, measured directions
   finish it as above. With more left, all on pieces that stage 4 measures, and the RMS
   residual within ``pieces.TRUNCATE_WITHIN`` times the tolerance (a sculpt the chain can
   reproduce: the plain-skinned ones are 60 times away and more), measured directions **on
   trial** first, where they lie on one piece of the mesh (``MEASURED_TRIAL_PIECES``): one
   round (``MEASURED_TRIAL_ROUNDS``), going on only where it keeps a step.
   Stage 4 colours a piece by the chain's reach, and a piece that lies within reach of itself
   (the character fixture's 168-vertex arm) takes nearly a colour a vertex; the Krylov space
   learns it for less (that 135 degree elbow on the per-vertex solver's blocks: 131 calls,
   against 319). Where
   Newton-Krylov kept no step, the directions it measured at the start are the measured
   directions' first (``invert_coupled(measured=...)``): that elbow's 24 (171 calls without).
3. Where that misses: the **slower stages** (``_escalate``: the blocks' smooth start over the
   region's smoothest fields, the span's Jacobian measured, Newton-Krylov from zero; each while
   more vertices miss than ``POLISH_VERTICES``), then measured directions on the best.
   The fast path alone costs a few dozen calls; these cost hundreds where they run, and the
   best of every result is kept, so an example never ends worse than the fast path left it.
   Where more vertices miss than that and all of them are on pieces that stage 4
   measures, the slower stages are left out for it (``_exact_pieces_instead``).
4. Where vertices still miss on pieces of the mesh of at most ``pieces.EXACT_PIECE`` vertices
   and the RMS residual is within ``pieces.TRUNCATE_WITHIN`` times the tolerance: first
   **each piece on its own Krylov space** (``_krylov_pieces``, ``psdbake.solver.pieces_krylov``):
   Newton-GMRES whose every call carries one product of every piece, each piece's step the
   least-squares one on its own products. The chain's Jacobian is block-diagonal by piece, so
   after m calls each piece holds m directions where one space shared by all holds m in all
   (CesiumMan: 121 calls an example, against about 280 for the exact Jacobians below and 400
   or more for one shared space). Then, where vertices still miss,
   **those pieces' exact Jacobians** (``_exact_pieces``, ``pieces.solve_exactly``), measured
   where the stages above left them, on the vertices still above the tolerance and their
   1-ring (3 calls a colour of the largest piece, its vertices coloured by the chain's measured
   reach, shared by all pieces; first by part of it, two-fifths near the answer and half
   further, approximate columns, what they leave measured again exactly), and chord
   Gauss-Newton steps per piece. A piece still far
   above the tolerance at its optimum holds what the chain cannot produce, and is solved on the
   stronger ``UNREACHABLE_RIDGE``, every vertex an unknown, so that its offsets stay bounded.
   About 280 calls on CesiumMan where the Krylov spaces are left out (its large pieces need
   ~2,500 directions the chain passes at 1e-3 of its gain; 750 coloured by the whole reach),
   none where the stages above reach the tolerance.
5. Where the sculpt is still out of the chain's reach, no stage settled it at an optimum (a
   piece larger than stage 4 takes) and the offsets kept exceed what ``UNREACHABLE_RIDGE``
   lets through: **Newton-Krylov from zero on that ridge's objective** (``_regularised``),
   kept where it lowers it. It bounds the offsets; it is not called an optimum.

Of the stages' results the one kept leaves the fewest vertices above the tolerance where at most
``POLISH_VERTICES`` do, else the smallest sum of squared residuals (``_rank``).

The result is ``at_optimum`` when the last Krylov space could not lower the residual's linear
model by ``OPTIMUM_RTOL``, or when the pieces stage 4 could not settle at their optimum hold at
most ``OPTIMUM_SHARE`` of the residual left: what is left is orthogonal to everything the chain produced from
the directions tried, so vertices still above the tolerance there are what the chain smooths
away rather than what the solver failed to reach (``fit``'s report says which). Without edges
(no smooth start), Newton-Krylov from zero runs instead, then the per-vertex solve and a
restart from it, and the best is kept.

Powell's per-vertex line searches are not used here: they assume a vertex's residual depends
on its own offset only, which is exactly what a coupling deformer breaks.

Statuses are the per-vertex ``powell`` codes: CONVERGED within tolerance (checked by running
the full chain on rest + offsets), MAX_CYCLES the call budget ran out, STALLED Newton
stopped improving (or ended at an optimum), NONFINITE the chain returned non-finite values
there. The measurements behind these choices are in ``docs/decisions/coupled-inverse-coarse-meshes.md``.
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
from ..arrays import Points, is_singular
from . import pieces, pieces_krylov, powell, smoothstart, structured, subspace
from .inverse import COUPLING_SEEN, BlackBox, Counted, InverseResult, LinearisedStart, invert_example_with, sculpted_vertices
from .smoothbasis import basis_sizes, smooth_bases, smooth_basis

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
#: its start: enough for unfolded examples (docs/decisions/coupled-inverse.md); where skinning
#: folds the mesh the smooth start is what converges.
FROM_ZERO_EVALUATIONS = 64
#: Calls of the smooth start's two span solves (``smoothstart.span_solve``): over the coarse
#: basis, then the fine one. Each stops earlier at the tolerance or at its span's optimum.
COARSE_SPAN_CALLS = 20
FINE_SPAN_CALLS = 15
#: Newton-Krylov's calls after the smooth start, counted from its end.
FINISH_EVALUATIONS = 40
#: The polish: a result Newton-Krylov or the slower stages leave with at most this many vertices
#: above the tolerance is finished on measured directions (``_measured``); with more, the slower
#: stages run first. Results that leave at most this many rank before any other (``_rank``).
POLISH_VERTICES = 128
#: Rounds of measured directions on trial before stage 4 (above): where the first keeps no step,
#: the Krylov space's model does not hold there and stage 4 follows. The character fixture's 135
#: degree elbow keeps its first step at the round's 10th call (319 -> 171 calls in all, 131 with
#: Newton-Krylov's 24 directions handed on). CesiumMan's rounds keep none: the trial costs it 11
#: calls (430 / 468 -> 438 / 475 with the 3-4 calls ``inverse.Counted``'s memo saves); run to the
#: stall rule's 80 calls, 511 / 549.
MEASURED_TRIAL_ROUNDS = 1
#: The trial runs only where the vertices above the tolerance lie on at most this many pieces
#: of the mesh: measured directions span one space for all of them, which is what fails where
#: the pieces are independent (``pieces_krylov``). CesiumMan's misses lie on six large pieces:
#: without the trial 199 -> 188 calls an example, every vertex still within the tolerance; the
#: 135 degree elbow's lie on one arm and keep their trial (the character fixture 34.2 unchanged).
MEASURED_TRIAL_PIECES = 1
#: Where the smooth start misses, the blocks are tried at its offsets (``_on_fine_blocks``: 1
#: call, 3 where they are measured again) with a step this fraction of the diagonal, 100 times
#: smaller than the per-vertex solver's ``tol.JACOBIAN_STEP_RTOL``. That step suits skinning
#: (affine: exact at any step, and it keeps float32 noise out of the 5-call solve), but at a
#: deep fold it crosses Delta Mush's non-linearity. Float32 outputs put about 3e-4 of noise on
#: these; 1e-3 and 1e-5 gave the character fixture the same calls.
FINE_BLOCKS_RTOL = 1e-4
#: Where the response to that call is off the blocks' prediction (their row sums) by more than
#: this (relative, in the Frobenius norm over the region), the fine blocks are measured and the
#: stages after the smooth start use them; a smooth start that left the sculpt far (RMS residual
#: above ``pieces.REACHABLE_SLACK`` times the tolerance) runs again on them from zero, kept where
#: it ends nearer. Measured at the smooth start's offsets: the character fixture's 140 and 135
#: degree elbows 0.141 and 0.168 (a few crease vertices' blocks off by 80-100%); the 1.3k bench
#: rig's 80 degree elbow 0.112 (60 -> 62 calls), its other folds and the 3k rig's 0.069 at
#: most, the 13k's 0.025, CesiumMan's 0.002.
BLOCKS_DISAGREE = 0.1
#: What a result from the stages on the fine blocks says after "from the smooth start".
FINE_BLOCKS = " on fine blocks"
#: What a result finished on measured directions (``_measured``) says after its regime.
MEASURED = ", on measured directions"
#: And one whose pieces were solved on their exact Jacobians (``_exact_pieces``).
EXACT = "; pieces by their exact Jacobians"
#: And one whose pieces were solved on their own Krylov spaces (``_krylov_pieces``).
KRYLOV_PIECES = "; pieces on their own Krylov spaces"
#: The regime's note where the structured model of the chain's Jacobian finished the smooth start.
STRUCTURED = "; on a structured Jacobian"
#: That stage's calls at most: the coloured Jacobians it runs before cost more (CesiumMan's
#: 251-vertex piece, 270 calls), and it took 121 there.
KRYLOV_PIECES_CALLS = 200
#: A piece of the mesh that ``pieces.solve_exactly`` finds the chain cannot reproduce (still
#: ``pieces.REACHABLE_SLACK`` times the tolerance away at the objective's optimum) is solved on
#: ``|r|^2 + rho |D|^2`` with rho ``smoothstart.ridge(blocks, UNREACHABLE_RIDGE)``: along any
#: direction of the chain's Jacobian an offset removes at least a fifth of itself from the
#: residual (1 / (2 x 0.1) = 5). On CesiumMan's shipped @12, measured with one Jacobian per
#: piece, the objective's own ridge let offsets reach 3.7 of the diagonal for RMS 1.52e-3;
#: 1e-2, 0.44 for 1.77e-3; this, 0.06 for 2.13e-3 (0.087 as shipped, each piece at its optimum;
#: docs/decisions/coupled-inverse-cesiumman.md).
UNREACHABLE_RIDGE = 0.1
#: What a result kept by the out-of-reach stage (``_regularised``) says after its regime.
OUT_OF_REACH = "; out of reach: Newton-Krylov on the unreachable ridge"
#: Calls of that stage, from zero: on the 1.3k and 3k bench rigs' plain-skinned sculpts it
#: ended in 45-245 (its Krylov spaces could lower the objective no further).
OUT_OF_REACH_EVALUATIONS = 256
#: After the pieces' exact Jacobians, an example is at an optimum where the vertices above the
#: tolerance on pieces not settled at theirs hold at most this share of the squared residual
#: left (on CesiumMan's shipped sculpts: two pieces of 3 and 7 vertices, whose Delta Mush
#: output is a rigid turn of the piece and whose steps end cut, hold 1e-4 of it).
OPTIMUM_SHARE = 0.01
#: Calls the pieces' exact Jacobians may take an example (``_exact_pieces``), beyond the
#: stages before them; a batch is started only where its Jacobian a vertex a call would fit.
#: CesiumMan's examples take 1,271-1,299 calls in all through the chain, 3,938-4,510 on its
#: shipped sculpts (one batch, its re-measures included); a mesh of many large pieces stops
#: after the batches that fit, and those it leaves are not at an optimum.
EXACT_CALLS = 6000
#: Smooth fields of the measured smooth start (``measured_smooth_start``, 3 calls each, one
#: per axis), the last of the escalation's stages (``_escalate``).
MEASURED_FIELDS = 64
#: Gauss-Newton steps of the measured smooth start: the first on the measured Jacobian, then
#: Broyden's updates of it, 1 call each.
MEASURED_STEPS = 4
#: Singular values of the measured span's Jacobian below this fraction of the largest are
#: dropped (truncated least squares: the steps stay smooth and the columns' noise out).
MEASURED_RCOND = 1e-3
#: A Newton step whose Krylov space cannot lower the regularised misfit's linear model by this
#: fraction ends the solve at an optimum (``InverseResult.at_optimum``): the residual left is
#: orthogonal to everything the chain produced from the directions tried.
OPTIMUM_RTOL = 0.02
#: The finish after the smooth start regularises the offsets' departure from the smooth start,
#: ``|r|^2 + ridge |D - D_start|^2``, with the ridge's scale this fraction of the blocks' gain:
#: a direction the chain passes at less than that is not pushed further than what it removes.
#: Weaker, it chased detail no smoothing passes (a ripple around the 1.3k rig's tube: offsets
#: grew to 5.8x the sculpt's largest move at 1e-3); this leaves the smooth start's own offsets,
#: which the sculpt needs at full size, unpulled.
FINISH_RIDGE = 1e-2


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


def closed_region(adjacency: sp.csr_matrix, region: NDArray[np.int64]) -> bool:
    """Whether no edge leaves the region (it is a union of whole connected pieces)."""
    inside = np.zeros(adjacency.shape[0], dtype=bool)
    inside[region] = True
    rows = adjacency[region]
    return bool(np.all(inside[rows.indices]))


def is_coupled(call: BlackBox, rest: Points, base: Points, probed: NDArray[np.int64], step: float,
               others: NDArray[np.int64] | None = None) -> bool:
    """One call: does moving ``probed`` move any other vertex's output (any other of ``others``
    when given: a region closed under the mesh's edges has no outside vertex to show it)?"""
    if len(probed) == 0 or (others is None and len(probed) == len(rest)) or (others is not None and len(probed) == len(others)):
        return False
    moved = rest.copy()
    moved[probed] += step * np.array([0.8, 0.5, 0.3]) / np.sqrt(0.98)
    change = np.linalg.norm(call(moved) - base, axis=1)
    own = float(change[probed].max())
    change[probed] = 0.0
    moved_others = float(change.max() if others is None else change[others].max())
    return bool(moved_others > COUPLING_RTOL * max(own, step)) or not np.isfinite(moved_others)


def invert(blackbox: BlackBox, rest: Points, sculpt: Points, *, rtol: float = tol.INVERSE_RTOL,
           neighbours: Callable[[], sp.csr_matrix | None] | None = None,
           skinning: BlackBox | None = None) -> InverseResult:
    """Solve the example per vertex, or jointly when the chain couples vertices, keeping the
    better solution (``InverseResult.regime`` says which ran and which was kept).

    The per-vertex solver's 3 Jacobian calls move only sculpted vertices, so they show for
    free whether any other vertex's output moved: skinning (5 calls) and per-vertex deformers
    pay nothing to find out. When they show coupling and the linearised start misses, the
    joint solve takes over from what the per-vertex solver measured (the chain at rest and the
    blocks cost no call again): the smooth start (``smooth_start``; ``neighbours()`` gives the
    mesh's edge adjacency), then measured directions or Newton-Krylov; where that misses short
    of an optimum, the slower stages (module docstring). Without edges, Newton-Krylov from zero, then
    the per-vertex solve and a restart from it; the kept result has the fewest vertices above
    the tolerance, then the smallest worst residual, both measured by running the chain.
    ``skinning``, where given, is the chain's skinning alone (``SkinningBlackBox.skin``): on a
    region of several pieces the smooth start is finished on a structured model of the chain's
    Jacobian (``psdbake.solver.structured``), its calls counted with the chain's. A
    sculpt that leaves no unsculpted neighbour is probed (1 call) once the linearised start
    misses; a chain that couples only vertices the per-vertex calls could not show otherwise
    is probed (2 calls) once the per-vertex solve misses."""
    started = time.perf_counter()
    rest = np.asarray(rest, dtype=np.float64)
    sculpt = np.asarray(sculpt, dtype=np.float64)
    adjacency: sp.csr_matrix | None = None
    read = False

    def closed_probe(call: BlackBox, base: Points, idx: NDArray[np.int64], step: float) -> bool:
        """A sculpt with no unsculpted edge neighbour (whole pieces of the mesh) cannot show
        coupling in the per-vertex solver's calls: probe it (1 call)."""
        nonlocal adjacency, read
        if not read:
            adjacency, read = (neighbours() if neighbours is not None else None), True
        if adjacency is None or len(idx) < 2 or not closed_region(adjacency, idx):
            return False
        return is_coupled(call, rest, base, probe_vertices(rest, idx), step, others=idx)

    first = invert_example_with(blackbox, rest, sculpt, rtol=rtol, stop_if_coupled=True, coupling_probe=closed_probe)
    if first.regime != COUPLING_SEEN and not len(first.missed):
        return first
    call = Counted(blackbox, first.evaluations)
    measured = first.linearised
    base = measured.posed_rest if measured is not None else call(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, sculpt)
    if measured is None:  # per-vertex ran to the end and missed: probe
        step = tol.JACOBIAN_STEP_RTOL * max(diagonal, floor)
        if not (len(idx) and is_coupled(call, rest, base, probe_vertices(rest, idx), step)):
            return dataclasses.replace(first, evaluations=call.calls, seconds=time.perf_counter() - started)
    # The joint stages' sums run on BLAS (GMRES, ARPACK, the Gram matrix), whose results depend
    # on its thread count: one thread, so a fit gives the same bytes on every machine (the 100k
    # bench: 8.76 s an example against 8.54 with two threads; the black box dominates)
    with threadpool_limits(limits=1, user_api="blas"):
        if not read:
            adjacency = neighbours() if neighbours is not None else None
        if adjacency is not None and skinning is not None and measured is not None:
            # 0s. many small pieces: the whole region on the structured model; where it misses,
            # its calls are spent and the stages below start afresh (on CesiumMan's shipped
            # sculpts, which no offset reproduces, its result ranked better but stopped short
            # of the optimum the exact pieces settle at)
            whole = _whole_structured(call, skinning, rest, sculpt, idx, diagonal, floor, adjacency, measured,
                                      rtol=rtol, started=started)
            if whole is not None and len(whole.missed) and len(whole.missed) <= POLISH_VERTICES:
                # a few vertices left: their pieces on their exact Jacobians, as stage 4 below
                whole = _exact_pieces(call, rest, sculpt, idx, whole, adjacency, measured.blocks)
            if whole is not None and not len(whole.missed):
                return dataclasses.replace(whole, evaluations=call.calls, seconds=time.perf_counter() - started,
                                           sculpt_rms=first.sculpt_rms)
        small: tuple[list[pieces.Piece], pieces.PiecesResult] | None = None
        if adjacency is not None:  # 0. the mesh's small pieces by their own Jacobians, the rest as below
            split, small = _small_pieces_first(call, blackbox, rest, sculpt, base, idx, diagonal, floor, adjacency,
                                               first, rtol=rtol, started=started, skinning=skinning)
            if split is not None:
                return split
        # the per-vertex 3x3 blocks, shared by every stage: the per-vertex solver's own, else 3 calls
        blocks = measured.blocks if measured is not None else chain_blocks(call, rest, base, idx, diagonal, floor)
        candidates: list[InverseResult] = []
        if adjacency is not None:  # 1. the smooth start, then Newton-Krylov
            start = smooth_start(call, rest, sculpt, base, idx, diagonal, blocks, adjacency,
                                 max(rtol * diagonal, floor))
            if start is not None:
                offsets, outputs = start
                begun = _at(sculpt, idx, offsets, outputs, diagonal, floor, rtol, call.calls, started)
                if len(begun.missed):  # the blocks tried finely where it misses (1 call; 3 where they are off)
                    begun, offsets, outputs, blocks = _on_fine_blocks(call, rest, sculpt, base, idx, diagonal, floor,
                                                                      blocks, adjacency, begun, offsets, outputs,
                                                                      rtol=rtol, started=started)
                reached = False
                groups = structured.region_pieces(adjacency, idx) if skinning is not None else []
                if len(begun.missed) and skinning is not None and structured.fits(groups, len(rest)):
                    # 1s. several pieces: the structured model of the chain's Jacobian, on the
                    # skinning's own blocks (``_skinning_blocks``, counted)
                    posed = _skinning_blocks(call, skinning, rest, idx, diagonal, floor)[1]
                    found = structured.solve(call, posed, rest, sculpt, idx, groups, offsets, outputs, adjacency,
                                             diagonal, begun.atol)
                    if found is not None:
                        there = _outputs(call, rest, idx, found.offsets)
                        tried = _at(sculpt, idx, found.offsets, there, diagonal, floor, rtol, call.calls, started)
                        if _rank(tried) < _rank(begun):
                            begun = dataclasses.replace(tried, regime=begun.regime + STRUCTURED)
                            offsets, outputs = found.offsets, there
                            reached = not len(begun.missed)
                if reached:
                    candidates.append(begun)
                elif len(begun.missed) and begun.rms_residual <= pieces.REACHABLE_SLACK * begun.atol:
                    # 1a. nearly reproduced: finished on measured directions
                    candidates.extend(_measured(call, rest, sculpt, idx, max(diagonal, floor), begun, blocks,
                                                adjacency, started=started, outputs=outputs))
                    if candidates and len(candidates[-1].missed) and not _exact_pieces_instead(candidates[-1],
                                                                                              adjacency, idx):
                        candidates.extend(_escalate(call, blackbox, rest, sculpt, base, idx, diagonal, floor, first,
                                                    blocks, adjacency, rtol=rtol, started=started))
                else:  # 1b. Newton-Krylov, then measured directions, then the slower stages
                    seeds: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
                    smooth = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                            max_evaluations=call.calls + FINISH_EVALUATIONS, start=offsets,
                                            start_outputs=outputs, blocks=blocks, weighted=True, measured=seeds)
                    handed = seeds[0] if seeds else None  # its directions, where it kept no step
                    candidates.append(dataclasses.replace(smooth, regime=begun.regime))
                    missing = bool(len(smooth.missed)) and not smooth.at_optimum
                    polish = missing and len(smooth.missed) <= POLISH_VERTICES
                    # else on trial before the exact pieces: kept where its first round keeps a step
                    trial = (missing and not polish and smooth.rms_residual <= pieces.TRUNCATE_WITHIN * smooth.atol
                             and _exact_pieces_instead(smooth, adjacency, idx)
                             and len(_missing_pieces(smooth, adjacency, idx)) <= MEASURED_TRIAL_PIECES)
                    if polish or trial:
                        candidates.extend(_measured(call, rest, sculpt, idx, max(diagonal, floor), candidates[-1],
                                                    blocks, adjacency, started=started, seeded=handed,
                                                    trial_rounds=MEASURED_TRIAL_ROUNDS if trial else None))
                    if len(candidates[-1].missed) and not candidates[-1].at_optimum and not _exact_pieces_instead(
                            candidates[-1], adjacency, idx):
                        candidates.extend(_escalate(call, blackbox, rest, sculpt, base, idx, diagonal, floor, first,
                                                    blocks, adjacency, rtol=rtol, started=started))
                best = min(candidates or [begun], key=_rank)
                if len(best.missed) and not best.at_optimum and not best.regime.endswith(MEASURED) and len(
                        best.missed) <= POLISH_VERTICES:  # the best of the slower stages, finished likewise
                    candidates.extend(_measured(call, rest, sculpt, idx, max(diagonal, floor), best, blocks, adjacency,
                                                started=started))
                if not candidates:
                    candidates.append(begun)
        if not candidates:  # 2. no smooth start (no edges, or ARPACK failed): from zero
            joint = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                   max_evaluations=call.calls + FROM_ZERO_EVALUATIONS, blocks=blocks)
            candidates.append(joint)
            if len(joint.missed):  # the per-vertex solution and a restart from it
                candidates.extend(_from_per_vertex(call, blackbox, rest, sculpt, base, idx, diagonal, floor, first,
                                                   blocks, rtol=rtol, started=started))
    best = min(candidates, key=_rank)
    if small is not None:
        best = _keep_better_pieces(call, rest, sculpt, idx, best, *small)
    if len(best.missed) and adjacency is not None:  # 4. the pieces still missing: near the answer on their
        with threadpool_limits(limits=1, user_api="blas"):  # own Krylov spaces, then by their exact Jacobians
            best = _krylov_pieces(call, rest, sculpt, idx, best, adjacency, blocks)
            if len(best.missed):
                best = _exact_pieces(call, rest, sculpt, idx, best, adjacency, blocks)
    if len(best.missed) and not best.at_optimum and _out_of_bounds(best, sculpt, base, blocks):  # 5. bounded
        with threadpool_limits(limits=1, user_api="blas"):
            best = _regularised(call, rest, sculpt, base, idx, diagonal, floor, best, blocks, rtol=rtol,
                                started=started)
    return dataclasses.replace(best, evaluations=call.calls, seconds=time.perf_counter() - started,
                               sculpt_rms=first.sculpt_rms)


def _whole_structured(call: Counted, skinning: BlackBox, rest: Points, sculpt: Points, idx: NDArray[np.int64],
                      diagonal: float, floor: float, adjacency: sp.csr_matrix, measured: LinearisedStart, *,
                      rtol: float, started: float) -> InverseResult | None:
    """The whole region, small pieces included, on the structured model from the linearised
    start (``structured.solve_whole``), checked by one call: where the region holds small
    pieces whose exact Jacobians (``pieces.jacobian_calls``) cost more calls than the model's
    products and the skinning's blocks. On CesiumMan the exact Jacobians of its 25-vertex
    pieces cost 76 calls, and the small pieces' stage ended after the rest's at 97 and 124
    calls; from the linearised start the model took every vertex within the tolerance in 45
    and 46 (docs/decisions/coupled-inverse-cesiumman.md). None where it does not apply."""
    found = pieces.small_pieces(adjacency, idx)
    groups = structured.region_pieces(adjacency, idx)
    if not found or pieces.jacobian_calls(found) <= structured.PRODUCTS + 4 or not structured.fits(groups, len(rest)):
        return None
    skinned, posed = _skinning_blocks(call, skinning, rest, idx, diagonal, floor)
    atol = max(rtol * diagonal, floor)
    solved = structured.solve_whole(call, posed, rest, sculpt, idx, groups, measured.start, measured.start_outputs,
                                    adjacency, diagonal, atol, skinned)
    if solved is None:
        return None
    there = _outputs(call, rest, idx, solved.offsets)
    return dataclasses.replace(_at(sculpt, idx, solved.offsets, there, diagonal, floor, rtol, call.calls, started),
                               regime="coupled, from the linearised start" + STRUCTURED)


def _skinning_blocks(call: Counted, skinning: BlackBox, rest: Points, idx: NDArray[np.int64], diagonal: float,
                     floor: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The skinning alone at rest (n, 3) and its 3x3 blocks at the sculpted vertices (k, 3, 3),
    at the points of the per-vertex solver's first calls (rest, then every sculpted vertex moved
    by its step along x, y and z; skinning is linear in the rest point, so any step gives its
    blocks). Its calls are counted with the chain's: 4, or where the skinning says how many it
    ran afresh (``fresh``: ``SkinningBlackBox``'s ``ChainSkinning`` reads the skinning the chain's
    own calls at those points did on the way, on CesiumMan all 4), those."""
    before = getattr(skinning, "fresh", None)
    skinned = np.asarray(skinning(rest), dtype=np.float64)
    posed = blocks_at(skinning, rest, idx, np.zeros((len(idx), 3)), skinned[idx],
                      tol.JACOBIAN_STEP_RTOL * max(diagonal, floor))
    after = getattr(skinning, "fresh", None)
    call.calls += after - before if isinstance(before, int) and isinstance(after, int) else 4
    return skinned, posed


def _at(sculpt: Points, idx: NDArray[np.int64], offsets: Points, outputs: Points, diagonal: float, floor: float,
        rtol: float, calls: int, started: float) -> InverseResult:
    """The smooth start's result from its offsets and the chain's outputs there (no call)."""
    atol = max(rtol * diagonal, floor)
    norms = np.linalg.norm(sculpt[idx] - outputs, axis=1)
    status = _checked(np.full(len(idx), powell.STALLED, dtype=np.int8), norms, atol)
    status[~np.isfinite(norms)] = powell.NONFINITE
    return InverseResult(indices=idx, offsets=np.asarray(offsets, dtype=np.float64), residual=norms, status=status,
                         evaluations=calls, diagonal=diagonal, atol=atol, seconds=time.perf_counter() - started,
                         regime="coupled, from the smooth start")


def _on_fine_blocks(call: Counted, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
                    diagonal: float, floor: float, blocks: NDArray[np.float64], adjacency: sp.csr_matrix,
                    begun: InverseResult, offsets: Points, outputs: Points, *, rtol: float, started: float
                    ) -> tuple[InverseResult, Points, Points, NDArray[np.float64]]:
    """The smooth start's result, offsets, outputs and the blocks for the stages after it. One
    call moves every sculpted vertex by ``FINE_BLOCKS_RTOL`` of the diagonal along x, y and z
    at once from the smooth start's offsets; where the response differs from what ``blocks``
    predict by more than ``BLOCKS_DISAGREE``, the per-vertex solver's step measured them across
    a fold's non-linearity, and 2 calls more give the fine blocks (``blocks_at``; z's column is
    the first call's response less x's and y's). They are kept, and where the smooth start left
    the sculpt far, it runs again on them (the character fixture's 135 degree elbow: its model
    on the coarse blocks stalled at 350 times the tolerance; on the fine ones the coarse span
    alone came within 2.2 times it)."""
    step = FINE_BLOCKS_RTOL * max(diagonal, floor)
    moved = rest.copy()
    moved[idx] += offsets
    moved[idx] += step
    response = (call(moved)[idx] - outputs) / step
    size = float(np.linalg.norm(response))
    if not (np.isfinite(size) and float(np.linalg.norm(response - blocks.sum(axis=2))) > BLOCKS_DISAGREE * size):
        return begun, offsets, outputs, blocks
    fine = np.empty_like(blocks)
    fine[:, :, :2] = blocks_at(call, rest, idx, offsets, outputs, step, axes=2)
    fine[:, :, 2] = response - fine[:, :, 0] - fine[:, :, 1]
    if not np.all(np.isfinite(fine)):  # the chain gave non-finite values there: the blocks as they were
        return begun, offsets, outputs, blocks
    regime = begun.regime + FINE_BLOCKS
    if begun.rms_residual <= pieces.REACHABLE_SLACK * begun.atol:
        return dataclasses.replace(begun, regime=regime), offsets, outputs, fine
    again = smooth_start(call, rest, sculpt, base, idx, diagonal, fine, adjacency, max(rtol * diagonal, floor))
    if again is None:
        return begun, offsets, outputs, blocks
    redone = _at(sculpt, idx, again[0], again[1], diagonal, floor, rtol, call.calls, started)
    if not redone.rms_residual < begun.rms_residual:
        return begun, offsets, outputs, blocks
    return dataclasses.replace(redone, regime=regime), again[0], again[1], fine


#: The small pieces' calls ride on the rest's (``_Riding``): on CesiumMan their stage's 88 and
#: 115 calls, which came before the rest's, now go in the rest's own.
SMALL_PIECES_RIDE = True


class _SmallPiecesMissedError(Exception):
    """The small pieces' stage ended with a piece above the tolerance while the rest's solve,
    which assumed they would reach it, was running: that solve is given up."""


class _Riding:
    """The rest of the region's black box, carrying the small pieces' calls
    (``pieces.small_pieces_steps``) in its own: each call of the rest's solve also puts the
    small pieces where their stage asks next, and sends their outputs back to it. The pieces
    are independent (the first call, made ``alone``, shows it for every output outside them),
    so neither solve sees the other: the rest's solve is shown the small pieces at the chain's
    rest outputs (``base``), and the small pieces' stage every other output as ``base``. Where
    that stage ends with a piece short of the tolerance (``reached``) or with no result, the
    rest's solve, which assumed they would reach it, is given up (``_SmallPiecesMissedError``)."""

    def __init__(self, blackbox: BlackBox, steps: pieces.Calls[pieces.PiecesResult | None],
                 small: NDArray[np.bool_], base: Points, reached: Callable[[pieces.PiecesResult], bool]) -> None:
        self.blackbox, self.steps, self.small, self.base, self.reached = blackbox, steps, small, base, reached
        self.calls = 0
        self.done = False
        self.result: pieces.PiecesResult | None = None
        self.request: Points | None = next(steps)

    def _send(self, outputs: Points) -> None:
        try:
            self.request = self.steps.send(outputs)
        except StopIteration as stop:
            self.done, self.request, self.result = True, None, stop.value

    def alone(self, call: BlackBox) -> None:
        """The small pieces' next call on its own."""
        assert self.request is not None
        self._send(call(self.request))

    def __call__(self, points: Points) -> Points:
        merged = np.array(points, dtype=np.float64, copy=True)
        if self.request is not None:
            merged[self.small] = self.request[self.small]
        outputs = self.blackbox(merged)
        self.calls += 1
        if self.request is not None:
            seen = np.array(self.base, copy=True)
            seen[self.small] = outputs[self.small]
            self._send(seen)
            if self.done and (self.result is None or not self.reached(self.result)):
                raise _SmallPiecesMissedError
        shown = np.array(outputs, dtype=np.float64, copy=True)
        shown[self.small] = self.base[self.small]
        return shown


def _small_pieces_first(call: Counted, blackbox: BlackBox, rest: Points, sculpt: Points, base: Points,
                        idx: NDArray[np.int64], diagonal: float, floor: float, adjacency: sp.csr_matrix,
                        first: InverseResult, *, rtol: float, started: float, skinning: BlackBox | None = None
                        ) -> tuple[InverseResult | None, tuple[list[pieces.Piece], pieces.PiecesResult] | None]:
    """The sculpted region's small pieces of the mesh (``pieces.SMALL_PIECE`` vertices or fewer)
    solved with their exact Jacobians (``pieces.solve_small_pieces``). On CesiumMan the smooth
    start's model is off by up to 1e6 there, and with them in the region the later stages
    leave more of the large pieces above the tolerance too (docs/decisions/coupled-inverse-cesiumman.md).

    The rest of the region is solved by ``invert`` through the chain while the small pieces'
    calls after the first ride on its own (``_Riding``, ``SMALL_PIECES_RIDE``; the small pieces
    shown to it at their rest outputs, so not sculpted). Where every small piece reaches the
    tolerance (the sculpt is the chain's own output there), one call checks every vertex at
    the combined offsets: (result, None). Where they do not (a sculpt
    the chain cannot reproduce), the whole region is solved as before and each small piece
    keeps the better of the two solutions (``_keep_better_pieces``): (None, (pieces, their
    solution)), the rest's solve given up as soon as their stage ends; on CesiumMan's shipped
    sculpts solving the rest alone left a larger RMS on the large pieces than the whole solve.
    (None, None) where the region holds no small piece, or the pieces turn out not to be
    independent."""
    found = pieces.small_pieces(adjacency, idx)
    if not found:
        return None, None
    atol = max(rtol * diagonal, floor)
    small = ~pieces.outside(len(rest), found)
    others = np.setdiff1d(np.arange(len(idx)), np.concatenate([p.positions for p in found]))

    def reached(solved: pieces.PiecesResult) -> bool:
        return bool(np.all(np.linalg.norm(sculpt[idx[solved.members]] - solved.outputs[idx[solved.members]],
                                          axis=1) <= atol))

    riding = _Riding(blackbox, pieces.small_pieces_steps(rest, sculpt, base, idx, found, diagonal, atol), small,
                     base, reached)
    riding.alone(call)  # alone: it shows whether the small pieces move any output outside them
    inner: InverseResult | None = None
    if len(others) and SMALL_PIECES_RIDE and not riding.done:
        held = sculpt.copy()
        held[small] = base[small]  # as the rider shows them: not sculpted
        skinned = Counted(skinning) if skinning is not None else None  # its calls count with the rider's
        try:
            inner = invert(riding, rest, held, rtol=rtol, neighbours=lambda: adjacency, skinning=skinned)
        except _SmallPiecesMissedError:
            inner = None
        call.calls += riding.calls + (skinned.calls if skinned is not None else 0)
    while not riding.done:  # what the rest's calls did not carry
        riding.alone(call)
    solved = riding.result
    if solved is None:
        return None, None
    if not reached(solved):
        return None, (found, solved)
    offsets = np.zeros((len(idx), 3))
    offsets[solved.members] = solved.offsets
    status = np.full(len(idx), powell.STALLED, dtype=np.int8)
    if len(others) and inner is None:
        shift = np.zeros_like(rest)
        shift[idx[solved.members]] = solved.offsets
        held = sculpt.copy()
        for piece in found:
            held[piece.vertices] = solved.outputs[piece.vertices]
        inner = invert(lambda points: blackbox(points + shift), rest, held, rtol=rtol, neighbours=lambda: adjacency,
                       skinning=None if skinning is None else lambda points: skinning(points + shift))
        call.calls += inner.evaluations
    if inner is not None:
        where = np.searchsorted(idx, inner.indices)
        if len(where) and (where.max() >= len(idx) or not np.array_equal(idx[where], inner.indices)):
            return None, (found, solved)
        offsets[where] = inner.offsets
        status[where] = inner.status
    residual = np.linalg.norm(sculpt[idx] - _outputs(call, rest, idx, offsets), axis=1)
    status = _checked(status, residual, atol)
    regime = "coupled, small pieces by their Jacobians" + (f"; the rest {inner.regime}" if inner is not None else "")
    return InverseResult(idx, offsets, residual, status, call.calls, diagonal, atol, time.perf_counter() - started,
                         regime=regime,
                         qn_steps=inner.qn_steps if inner is not None else 0, sculpt_rms=first.sculpt_rms,
                         at_optimum=bool(inner is not None and inner.at_optimum)), None


def _keep_better_pieces(call: Counted, rest: Points, sculpt: Points, idx: NDArray[np.int64], best: InverseResult,
                        found: list[pieces.Piece], solved: pieces.PiecesResult) -> InverseResult:
    """``best`` with each small piece's offsets replaced by its own solution where that leaves
    the piece a smaller residual (pieces do not move each other), checked by one call."""
    if not np.array_equal(best.indices, idx):
        return best
    row = np.full(len(idx), -1)
    row[solved.members] = np.arange(len(solved.members))
    mine = np.linalg.norm(sculpt[idx] - solved.outputs[idx], axis=1)
    offsets = best.offsets.copy()
    changed = False
    for piece in found:
        if float(np.sum(mine[piece.positions] ** 2)) < float(np.sum(best.residual[piece.positions] ** 2)):
            offsets[piece.positions] = solved.offsets[row[piece.positions]]
            changed = True
    if not changed:
        return best
    residual = np.linalg.norm(sculpt[idx] - _outputs(call, rest, idx, offsets), axis=1)
    status = _checked(best.status, residual, best.atol)
    return dataclasses.replace(best, offsets=offsets, residual=residual, status=status,
                               regime=best.regime + "; small pieces by their Jacobians")


def _krylov_pieces(call: Counted, rest: Points, sculpt: Points, idx: NDArray[np.int64], best: InverseResult,
                   adjacency: sp.csr_matrix, blocks: NDArray[np.float64]) -> InverseResult:
    """``best`` with the pieces of the mesh where it leaves vertices above the tolerance solved
    by Newton-GMRES, each piece on its own Krylov space and all of them in the same calls
    (``pieces_krylov.solve``), where ``best`` is near the answer (RMS within
    ``pieces.TRUNCATE_WITHIN`` times the tolerance, as the rough colourings' gate: a sculpt
    the chain cannot reproduce goes to the exact Jacobians, which bound its offsets). Kept
    where it ranks better (``_rank``). On CesiumMan the fast path leaves six large pieces up
    to 15 times the tolerance away: this reaches every vertex in 121 calls an example, where
    their coloured Jacobians took about 280 (docs/decisions/coupled-inverse-cesiumman.md)."""
    if (KRYLOV_PIECES_CALLS <= 0 or not np.array_equal(best.indices, idx) or not np.all(np.isfinite(best.offsets))
            or not best.rms_residual <= pieces.TRUNCATE_WITHIN * best.atol):
        return best
    chosen = _missing_pieces(best, adjacency, idx)
    if not chosen:
        return best
    moved = rest.copy()
    moved[idx] += best.offsets
    outputs = call(moved)
    if not np.all(np.isfinite(outputs)):
        return best
    solved = pieces_krylov.solve(call, rest, sculpt, idx, chosen, best.offsets, outputs, blocks, best.diagonal,
                                 best.atol, KRYLOV_PIECES_CALLS)
    if solved is None:
        return best
    offsets = best.offsets.copy()
    offsets[solved.members] = solved.offsets
    residual = np.linalg.norm(sculpt[idx] - solved.outputs[idx], axis=1)
    found = dataclasses.replace(best, offsets=offsets, residual=residual,
                                status=_checked(best.status, residual, best.atol), regime=best.regime + KRYLOV_PIECES)
    return found if _rank(found) < _rank(best) else best


def _exact_pieces(call: Counted, rest: Points, sculpt: Points, idx: NDArray[np.int64], best: InverseResult,
                  adjacency: sp.csr_matrix, blocks: NDArray[np.float64]) -> InverseResult:
    """``best`` with the pieces of the mesh (at most ``pieces.EXACT_PIECE`` vertices) where it
    leaves vertices above the tolerance solved on their exact Jacobians, measured at its
    offsets (``pieces.solve_exactly``). On CesiumMan's large pieces the stages above stop at
    1e-5 of the diagonal: reaching the tolerance there takes ~2,500 directions the chain passes
    at 1e-3 of its gain, which only the Jacobian holds (docs/decisions/coupled-inverse-cesiumman.md).
    A piece the chain cannot reproduce is solved on ``UNREACHABLE_RIDGE``, so its offsets stay
    bounded; where the vertices still above the tolerance are on pieces settled at their
    objective's optimum (up to ``OPTIMUM_SHARE`` of the residual), the result is ``at_optimum``."""
    if not np.array_equal(best.indices, idx) or not np.all(np.isfinite(best.offsets)):
        return best
    chosen = _missing_pieces(best, adjacency, idx)
    if not chosen:
        return best
    offsets = best.offsets.copy()
    moved = rest.copy()
    moved[idx] += offsets
    outputs = call(moved)
    if not np.all(np.isfinite(outputs)):
        return best
    explained = np.zeros(len(idx), dtype=bool)  # on a piece whose objective is at its optimum
    inside = np.zeros(len(idx), dtype=bool)
    budget = call.calls + EXACT_CALLS
    for batch in pieces.batches(chosen):  # the pieces are independent: each batch from where the last left them
        if call.calls + pieces.jacobian_calls(batch) > budget:
            break
        solved = pieces.solve_exactly(call, rest, sculpt, idx, batch, offsets, outputs, best.diagonal, best.atol,
                                      smoothstart.ridge(blocks), smoothstart.ridge(blocks, UNREACHABLE_RIDGE),
                                      budget - call.calls, adjacency)
        if solved is None:
            break
        offsets[solved.members] = solved.offsets
        outputs = solved.outputs
        explained[solved.members] = solved.settled
        inside[solved.members] = True
    if not inside.any():
        return best
    residual = np.linalg.norm(sculpt[idx] - outputs[idx], axis=1)
    status = _checked(best.status, residual, best.atol)
    above = status != powell.CONVERGED
    status[above & explained] = powell.STALLED  # at its optimum, not out of budget
    left = float(np.sum(residual[above] ** 2))
    unsettled = float(np.sum(residual[above & inside & ~explained] ** 2))
    at_optimum = unsettled <= OPTIMUM_SHARE * left and (best.at_optimum or not np.any(above & ~inside))
    return dataclasses.replace(best, offsets=offsets, residual=residual, status=status, at_optimum=at_optimum,
                               regime=best.regime + EXACT)


def _out_of_bounds(result: InverseResult, sculpt: Points, base: Points, blocks: NDArray[np.float64]) -> bool:
    """Whether ``result`` leaves most of the sculpt out of the chain's reach (its RMS residual
    above ``pieces.REACHABLE_SLACK`` times the tolerance, as ``pieces.solve_exactly`` tells a
    piece the chain cannot reproduce: sculpts made through the chain end within 2x of it where
    they miss at all, made on the plain-skinned mesh at 4-800x) with offsets larger than the
    unreachable ridge lets through: 1 / (2 ``UNREACHABLE_RIDGE``) = 5 times the sculpt's largest
    move over the chain's gain (the largest a direction's offset can be, per unit of its
    residual, at that ridge's optimum)."""
    if not result.rms_residual > pieces.REACHABLE_SLACK * result.atol:
        return False
    move = float(np.max(np.linalg.norm(sculpt[result.indices] - base[result.indices], axis=1), initial=0.0))
    limit = move / (2.0 * np.sqrt(smoothstart.ridge(blocks, UNREACHABLE_RIDGE)))
    return bool(np.max(np.linalg.norm(result.offsets, axis=1), initial=0.0) > limit)


def _regularised(call: Counted, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64], diagonal: float,
                 floor: float, best: InverseResult, blocks: NDArray[np.float64], *, rtol: float,
                 started: float) -> InverseResult:
    """5. A sculpt out of the chain's reach whose offsets no stage settled within the ridge's
    bound (``_out_of_bounds``; a piece too large for stage 4): Newton-Krylov from zero on
    ``|r|^2 + rho |D|^2`` with the unreachable ridge (``UNREACHABLE_RIDGE``, as stage 4 solves
    such pieces), up to ``OUT_OF_REACH_EVALUATIONS`` calls, kept where it lowers that objective
    below ``best``'s. The stages before chase the residual without a ridge: on the 3k and 13k
    bench rigs' plain-skinned sculpts they kept offsets of up to 7 and 17 times the sculpt's
    largest move. It is not called an optimum: on the 1.3k rig, where stage 4 finds the true
    one, it ends 1-28% above its objective (Krylov spaces hold few of the directions the ridge
    shrinks; docs/decisions/coupled-inverse-coarse-meshes.md)."""
    rho = smoothstart.ridge(blocks, UNREACHABLE_RIDGE)
    found = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                           max_evaluations=call.calls + OUT_OF_REACH_EVALUATIONS, blocks=blocks, ridge=rho)

    def objective(result: InverseResult) -> float:
        return float(np.sum(result.residual**2)) + rho * float(np.sum(result.offsets**2))

    if not np.array_equal(found.indices, best.indices) or not objective(found) < objective(best):
        return best
    return dataclasses.replace(found, regime=best.regime + OUT_OF_REACH, at_optimum=False)


def _exact_pieces_instead(result: InverseResult, adjacency: sp.csr_matrix, idx: NDArray[np.int64]) -> bool:
    """Whether the slower stages (``_escalate``) are left out for the pieces' exact Jacobians
    (``_exact_pieces``): where more vertices miss than ``POLISH_VERTICES`` and every one of them
    is on a piece the exact stage measures. There the slower stages cost hundreds of calls and
    leave most of them (CesiumMan from known offsets: 425 and 662 vertices after ~400 calls),
    and the exact stage reaches the tolerance from the fast path's result as well: CesiumMan
    2,749 / 2,853 -> 2,350 / 2,378 calls (a vertex a call), the character fixture's 135 degree
    elbow 757 -> 560, every vertex within the tolerance."""
    missing = result.status != powell.CONVERGED
    if np.count_nonzero(missing) <= POLISH_VERTICES:
        return False
    covered = np.zeros(len(idx), dtype=bool)
    for p in _missing_pieces(result, adjacency, idx):
        covered[p.positions] = True
    return bool(np.all(covered[missing]))


def _missing_pieces(result: InverseResult, adjacency: sp.csr_matrix, idx: NDArray[np.int64]) -> list[pieces.Piece]:
    """The pieces of the mesh that stage 4 measures (at most ``pieces.EXACT_PIECE`` vertices)
    holding a vertex ``result`` leaves above the tolerance."""
    missing = result.status != powell.CONVERGED
    return [p for p in pieces.small_pieces(adjacency, idx, pieces.EXACT_PIECE) if missing[p.positions].any()]


def _rank(result: InverseResult) -> tuple[int, int, float]:
    """The better of two results ranks lower. One that leaves few enough vertices above the
    tolerance for the polish on measured directions (``POLISH_VERTICES``) ranks before any
    other, by fewer of them, then the smaller worst residual: the goal is every vertex within it. Among results that
    leave more, the smaller sum of squared residuals ranks first: where most of the sculpt is
    out of the chain's reach, the count says nothing, and the least-squares misfit is what the
    inverse minimises. On the 3k bench rig's sculpts made on the plain-skinned mesh (one
    piece of 3,120 vertices, LBS + Delta Mush) the count kept Newton-Krylov from zero, which is
    unregularised: at 80 and 120 degrees 2,855 and 3,022 vertices above the tolerance, RMS
    5.7e-4 and 1.9e-3 of the diagonal, offsets 27x the sculpt's move; by the misfit, results
    with 2,868 and all 3,120 above it, RMS 2.6e-4 and 6.0e-4, offsets 5.5x and 1.2x (the
    out-of-reach stage then bounds the first; docs/decisions/coupled-inverse-coarse-meshes.md)."""
    missed = len(result.missed)
    if missed <= POLISH_VERTICES:
        return 0, missed, result.max_residual
    return 1, 0, float(np.sum(result.residual**2))


def _measured(call: Counted, rest: Points, sculpt: Points, idx: NDArray[np.int64], scale: float,
              result: InverseResult, blocks: NDArray[np.float64], adjacency: sp.csr_matrix | None, *,
              started: float, outputs: Points | None = None, trial_rounds: int | None = None,
              seeded: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None) -> list[InverseResult]:
    """``result`` finished on measured directions (``psdbake.solver.subspace``): its offsets, the
    chain's outputs there (``outputs``, else one call), up to ``subspace.CALLS`` calls more, or
    only ``trial_rounds`` rounds where none of them keeps a step; ``seeded``: directions already
    measured at ``result``'s offsets (``invert_coupled(measured=...)``). Empty where the chain
    gives non-finite values there."""
    offsets = np.asarray(result.offsets, dtype=np.float64)
    out = _outputs(call, rest, idx, offsets) if outputs is None else np.asarray(outputs, dtype=np.float64)
    if not np.all(np.isfinite(out)):
        return []
    found = subspace.solve(call, rest, sculpt[idx], idx, offsets, out, blocks, result.atol, scale, adjacency,
                           trial_rounds=trial_rounds, seeded=seeded)
    return [InverseResult(indices=idx, offsets=found.offsets, residual=found.residual,
                          status=_checked(result.status, found.residual, result.atol), evaluations=call.calls,
                          diagonal=result.diagonal, atol=result.atol, seconds=time.perf_counter() - started,
                          regime=result.regime + MEASURED)]


def _escalate(call: Counted, blackbox: BlackBox, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
              diagonal: float, floor: float, first: InverseResult, blocks: NDArray[np.float64],
              adjacency: sp.csr_matrix, *, rtol: float, started: float) -> list[InverseResult]:
    """Where the smooth start's finish (and the polish on measured directions after it) misses
    short of an optimum: the slower stages, unregularised, each while the best so far leaves
    more vertices above the tolerance than ``POLISH_VERTICES`` (``invert`` polishes the best on
    measured directions). The smooth start over the region's ``MEASURED_FIELDS`` smoothest fields
    with the blocks as the span's model (``measured_smooth_start``) and Newton-Krylov from it
    (up to ``MAX_EVALUATIONS``), the same with the span's Jacobian measured (3 calls a field),
    then Newton-Krylov from zero (``FROM_ZERO_EVALUATIONS``); where ARPACK finds no basis,
    Newton-Krylov from zero, the per-vertex solution and Newton-Krylov restarted from it. On the
    folds where the stages ran before measured directions (the 3k rig's 100 degree elbow; with
    the per-vertex polish of the time held back, the
    1.3k rig's 80 and 100, the 3k rig's 80 and the character fixture's 140) the blocks' model
    left 150-562 vertices above the tolerance, the measured span 6-580 and Newton-Krylov from
    zero 168-1,230; the 13k rig's 60 degree elbow, which the polish leaves to them, finishes
    with the first (118 calls; 340 with the measured span first). So the cheaper model goes
    first, and the stages stop once the polish can take what is left (the 3k rig's 100 degree
    elbow: 458 calls, 521 when every stage ran). Every call counts; ``invert`` keeps the best."""
    found: list[InverseResult] = []

    def keep(result: InverseResult) -> bool:
        """Keeps ``result``; whether the best kept leaves at most ``POLISH_VERTICES`` vertices."""
        found.append(result)
        return len(min(found, key=_rank).missed) <= POLISH_VERTICES

    basis = smooth_basis(adjacency, idx, MEASURED_FIELDS)
    if basis is not None:
        for model, regime in ((blocks, "coupled, from the smooth start"),
                              (None, "coupled, from the measured smooth start")):
            start = measured_smooth_start(call, rest, sculpt, base, idx, diagonal, floor, basis, model=model)
            spanned = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                                     max_evaluations=call.calls + MAX_EVALUATIONS, start=start, blocks=blocks,
                                     ridge=0.0)
            if keep(dataclasses.replace(spanned, regime=regime)):
                return found
    joint = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                           max_evaluations=call.calls + FROM_ZERO_EVALUATIONS, blocks=blocks, ridge=0.0)
    if keep(joint) or basis is not None:
        return found
    # ARPACK failed (a region of many pieces): the per-vertex solution and a restart from it
    found.extend(_from_per_vertex(call, blackbox, rest, sculpt, base, idx, diagonal, floor, first, blocks,
                                  rtol=rtol, started=started, ridge=0.0))
    return found


def measured_smooth_start(call: Counted, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64],
                          diagonal: float, floor: float, basis: NDArray[np.float64],
                          model: NDArray[np.float64] | None = None) -> Points:
    """Offsets (len(idx), 3) from Gauss-Newton restricted to smooth fields, ``basis`` (k, b)
    per axis, with the span's Jacobian measured: 3b calls (forward differences, the largest
    vertex move ``JACOBIAN_STEP_RTOL`` of the diagonal). The step is the truncated
    least-squares solve (singular values below ``MEASURED_RCOND`` of the largest dropped), and
    ``MEASURED_STEPS - 1`` more steps refresh that Jacobian by Broyden updates, 1 call each. A
    step is kept only if it lowers the residual."""
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
    # truncated least squares through the span's Gram matrix (3b x 3b): the same solution as an
    # SVD of the (3k, 3b) Jacobian, at a fraction of its cost on large regions
    gram = cols @ cols.T
    for _ in range(MEASURED_STEPS):
        values, vectors = np.linalg.eigh(gram)
        keep = values > MEASURED_RCOND**2 * values[-1] if values[-1] > 0 else np.zeros(len(values), dtype=bool)
        if not keep.any():
            break
        y = vectors[:, keep] @ ((vectors[:, keep].T @ (cols @ r.ravel())) / values[keep])
        trial = offsets + basis @ y.reshape(b, 3)
        out_trial = _outputs(call, rest, idx, trial)
        if not np.all(np.isfinite(out_trial)):
            break
        yy = float(y @ y)
        if yy == 0.0:
            break
        smoothstart.broyden(cols, gram, y, (out_trial - out).ravel())
        r_trial = target - out_trial
        if np.linalg.norm(r_trial) < np.linalg.norm(r):
            offsets, out, r = trial, out_trial, r_trial
    return offsets


def _from_per_vertex(call: Counted, blackbox: BlackBox, rest: Points, sculpt: Points, base: Points,
                     idx: NDArray[np.int64], diagonal: float, floor: float, first: InverseResult,
                     blocks: NDArray[np.float64], *, rtol: float, started: float,
                     ridge: float | None = None) -> list[InverseResult]:
    """Without mesh edges (or a smooth basis): the full per-vertex solve, and Newton-Krylov
    restarted from it (``ridge``: as ``invert_coupled``)."""
    per_vertex = first
    if first.regime == COUPLING_SEEN:
        per_vertex = invert_example_with(blackbox, rest, sculpt, rtol=rtol)
        call.calls += per_vertex.evaluations
    found = [dataclasses.replace(per_vertex, regime="coupled chain, per-vertex kept")]
    if len(per_vertex.missed) and np.array_equal(per_vertex.indices, idx):
        warm = invert_coupled(call, rest, sculpt, base, idx, diagonal, floor, rtol=rtol, started=started,
                              max_evaluations=call.calls + MAX_EVALUATIONS, start=per_vertex.offsets, blocks=blocks,
                              ridge=ridge)
        found.append(dataclasses.replace(warm, regime="coupled, from the per-vertex solution"))
    return found


def _checked(status: NDArray[np.int8], residual: NDArray[np.float64], atol: float) -> NDArray[np.int8]:
    """Statuses after the chain was run on the final offsets: CONVERGED where the residual is
    within atol, STALLED where a vertex that had converged no longer is, the others kept."""
    out = status.copy()
    out[residual <= atol] = powell.CONVERGED
    out[(residual > atol) & (out == powell.CONVERGED)] = powell.STALLED
    return out


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
    return blocks_at(call, rest, idx, np.zeros((len(idx), 3)), base[idx],
                     tol.JACOBIAN_STEP_RTOL * max(diagonal, floor))


def blocks_at(call: BlackBox, rest: Points, idx: NDArray[np.int64], offsets: Points, outputs: Points,
              step: float, axes: int = 3) -> NDArray[np.float64]:
    """The per-vertex 3x3 blocks (len(idx), 3, axes) at ``rest + offsets`` on ``idx``, whose
    outputs there are ``outputs``: a call a column, moving every sculpted vertex by ``step``
    along x, then y, then z (forward differences; the first ``axes`` of them)."""
    at = rest.copy()
    at[idx] += offsets
    blocks = np.empty((len(idx), 3, axes))
    for axis in range(axes):
        moved = at.copy()
        moved[idx, axis] += step
        blocks[:, :, axis] = (call(moved)[idx] - outputs) / step
    return blocks


def smooth_start(call: Counted, rest: Points, sculpt: Points, base: Points, idx: NDArray[np.int64], diagonal: float,
                 blocks: NDArray[np.float64], adjacency: sp.csr_matrix, atol: float
                 ) -> tuple[Points, Points] | None:
    """Offsets (k, 3) and the chain's outputs there (k, 3), from Levenberg-Marquardt over the
    region's smoothest fields (``psdbake.solver.smoothstart``): one probe call measures how much the
    chain smooths; the solve runs over the coarse basis (a quarter of the fields, the
    smoothest of each piece of the region: ``smoothbasis.smooth_bases``), then over the fine
    one from there, the coarse solve's Broyden-corrected model carried over. None where the
    region has no edges (or ARPACK failed)."""
    bases = smooth_bases(adjacency, idx, *basis_sizes(len(idx)))
    if bases is None:
        return None
    basis, coarse = bases
    freqs = smoothstart.frequencies(adjacency, idx, basis)
    reach = smoothstart.measure_reach(call, rest, base, idx, blocks, basis[:, :coarse], freqs[:coarse], diagonal)
    steps = reach.steps if reach.misfit <= smoothstart.REACH_MAX_MISFIT else 0.0
    believe = reach.misfit <= smoothstart.BELIEVE_MISFIT
    gain = smoothstart.gains(freqs, steps)
    model = smoothstart.SpanModel(blocks, basis, gain)
    gram = smoothstart.model_gram(blocks, basis, gain)
    first, first_gram = model.leading(coarse), gram[: 3 * coarse, : 3 * coarse].copy()
    ridge = smoothstart.ridge(blocks)
    span = smoothstart.span_solve(call, rest, sculpt, idx, basis[:, :coarse], first, atol, ridge, COARSE_SPAN_CALLS,
                                  start_outputs=base[idx], gram=first_gram, believe=believe)
    x = np.zeros((basis.shape[1], 3))
    x[:coarse] = span.coefficients
    outputs = span.outputs
    done = bool(np.all(np.linalg.norm(sculpt[idx] - outputs, axis=1) <= atol))
    if not done and basis.shape[1] > coarse:
        model.carry(first, gram, first_gram)  # the coarse solve's Broyden corrections carried over
        span = smoothstart.span_solve(call, rest, sculpt, idx, basis, model, atol, ridge, FINE_SPAN_CALLS, start=x,
                                      start_outputs=outputs, gram=gram, believe=believe)
        x, outputs = span.coefficients, span.outputs
    return basis @ x, outputs


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
    start_outputs: Points | None = None,
    blocks: NDArray[np.float64] | None = None,
    weighted: bool = False,
    ridge: float | None = None,
    measured: list[tuple[NDArray[np.float64], NDArray[np.float64]]] | None = None,
) -> InverseResult:
    """Newton-Krylov on the sculpted vertices' offsets (module docstring). ``base`` is
    ``call(rest)``; ``call.calls`` counts the example's calls so far (the budget's measure);
    ``start_outputs`` the chain's outputs at ``start`` when known (else one call);
    ``blocks`` are ``chain_blocks`` (measured here when not given). Steps lower the
    regularised misfit ``|r|^2 + ridge |D - anchor|^2`` (``smoothstart.ridge`` and zero from
    zero; after the smooth start ``FINISH_RIDGE`` and the start, with ``weighted``); the result is
    ``at_optimum`` where no direction of a step's Krylov space could lower its linear model
    by ``OPTIMUM_RTOL``. ``weighted``: each vertex's residual weighs by how far above the
    residuals' RMS it is (``subspace.weights``), for a finish where few vertices are left above
    the tolerance. ``ridge``, where given, replaces that rule: this ridge, towards zero (0: none,
    the escalation's stages, ``_escalate``; the out-of-reach stage's, ``_regularised``). Where no step
    was kept, ``measured`` gets the directions measured at the start and the chain's responses
    to them, (m, 3k) each, as its one item: a stage that starts there again (``_measured``) need
    not measure them."""
    atol = max(rtol * diagonal, floor)
    target = sculpt[idx]
    k = len(idx)

    def evaluate(offsets: Points) -> Points:
        return _outputs(call, rest, idx, offsets)

    # Per-vertex 3x3 blocks (row sums in the coupled case): the preconditioner.
    if blocks is None:
        blocks = chain_blocks(call, rest, base, idx, diagonal, floor)
    ok = ~is_singular(blocks, tol.JACOBIAN_RCOND)  # singular, or non-finite points there: no block to invert
    inverse_blocks = np.tile(np.eye(3), (k, 1, 1))
    if ok.any():
        inverse_blocks[ok] = np.linalg.inv(blocks[ok])

    def precondition(v: Points) -> Points:
        return np.einsum("kab,kb->ka", inverse_blocks, v)

    offsets = np.zeros((k, 3)) if start is None else np.array(start, dtype=np.float64)
    if start is None:
        out = base[idx]
    else:
        out = evaluate(offsets) if start_outputs is None else np.asarray(start_outputs, dtype=np.float64)
    r = target - out
    norms = np.linalg.norm(r, axis=1)
    stalled = optimum = False
    steps = 0
    at_start: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    # the regularisation: offsets pulled towards zero weakly (``smoothstart.ridge``); after the
    # smooth start, its departures from the smooth start more strongly (``FINISH_RIDGE``)
    anchor = np.zeros((k, 3)) if start is None or not weighted else np.array(start, dtype=np.float64)
    if ridge is None:
        ridge = smoothstart.ridge(blocks) * ((FINISH_RIDGE / smoothstart.SPAN_RIDGE) ** 2 if weighted else 1.0)
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
        # vertices above the tolerance weigh by how far above they are: the least-squares
        # model then works on the vertices that miss, not on the many already far within it
        weight = subspace.weights(norms, atol) if weighted else np.ones((k, 1))
        target_lin = max(KRYLOV_TARGET * atol, FORCING * float(norms.max())) * float(weight.max())

        def weighted_jvp(z: Points, jvp: Callable[[Points], Points] = jvp, weight: NDArray[np.float64] = weight
                         ) -> Points:
            return weight * jvp(z)

        directions, images = _gmres(weighted_jvp, precondition, weight * r, target_lin, budget)
        if not steps:  # measured at the start (unweighted)
            at_start = (directions, (images.reshape(-1, k, 3) / weight).reshape(images.shape))
        scaled = weight * r
        merit = float(np.sum(scaled**2)) + ridge * float(np.sum((offsets - anchor) ** 2))
        delta, left = _ridge_step(scaled, offsets - anchor, directions, images, ridge)
        if float(np.sum(scaled**2)) - float(np.sum(left**2)) <= OPTIMUM_RTOL * float(np.sum(scaled**2)):
            stalled = optimum = True  # no direction tried lowers the residual: an optimum
            break
        # Trust region: no vertex moves further than STEP_CAP times the largest residual.
        lengths = np.linalg.norm(delta, axis=1)
        cap = STEP_CAP * float(norms.max())
        delta = delta * np.minimum(1.0, cap / np.maximum(lengths, 1e-300))[:, None]
        for _ in range(BACKTRACKS + 1):  # the full step, then halvings
            trial = offsets + delta
            out_trial = evaluate(trial)
            r_trial = target - out_trial
            better = bool(np.all(np.isfinite(r_trial))
                          and float(np.sum((weight * r_trial) ** 2)) + ridge * float(np.sum((trial - anchor) ** 2)) < merit)
            if better or call.calls >= max_evaluations - 1:
                break
            delta = 0.5 * delta
        if not better:
            stalled = True
            break
        offsets, out, r = trial, out_trial, r_trial
        norms = np.linalg.norm(r, axis=1)
        steps += 1
    if measured is not None and not steps and at_start is not None:
        measured.append(at_start)

    status = np.full(k, powell.STALLED if stalled or optimum else powell.MAX_CYCLES, dtype=np.int8)
    status[norms <= atol] = powell.CONVERGED
    status[~np.isfinite(norms)] = powell.NONFINITE
    return InverseResult(
        indices=idx, offsets=offsets, residual=norms, status=status, evaluations=call.calls, diagonal=diagonal,
        atol=atol, seconds=time.perf_counter() - started, regime="coupled", at_optimum=optimum,
    )


def _gmres(jvp: Callable[[Points], Points], precondition: Callable[[Points], Points], r: Points,
           target: float, max_iter: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Right-preconditioned GMRES for ``J delta = r`` ((k, 3) vectors), at most ``max_iter``
    products; stops once the linear model predicts every vertex's residual <= ``target``.
    Returns the Krylov directions ``M^-1 v_j`` and their images ``J M^-1 v_j`` (m, 3k), from
    which the caller takes its step (``_ridge_step``)."""
    shape = r.shape
    b = r.ravel()
    beta = float(np.linalg.norm(b))
    if max_iter <= 0 or beta == 0.0:
        return np.zeros((0, b.size)), np.zeros((0, b.size))
    basis = np.zeros((max_iter + 1, b.size))
    images = np.zeros((max_iter, b.size))  # J M^-1 v_j
    directions = np.zeros((max_iter, b.size))  # M^-1 v_j
    hess = np.zeros((max_iter + 1, max_iter))
    basis[0] = b / beta
    used = 0
    for j in range(max_iter):
        directions[j] = precondition(basis[j].reshape(shape)).ravel()
        w = jvp(directions[j].reshape(shape)).ravel()
        if not np.all(np.isfinite(w)):  # the chain gave non-finite points: the model so far
            break
        images[j] = w
        used = j + 1
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
    return directions[:used], images[:used]


def _ridge_step(r: Points, offsets: Points, directions: NDArray[np.float64], images: NDArray[np.float64],
                ridge: float) -> tuple[Points, Points]:
    """The step in the Krylov space minimising the linear model of the regularised misfit
    ``|r - J delta|^2 + ridge |offsets + delta|^2``, and the residual ``r - J delta`` that
    model predicts."""
    if not len(directions):
        return np.zeros_like(r), r.copy()
    scale = np.sqrt(ridge)
    system = np.concatenate([images.T, scale * directions.T])
    rhs = np.concatenate([r.ravel(), -scale * offsets.ravel()])
    y = np.asarray(np.linalg.lstsq(system, rhs, rcond=None)[0], dtype=np.float64)
    return (y @ directions).reshape(r.shape), (r.ravel() - y @ images).reshape(r.shape)
