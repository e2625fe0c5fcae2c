"""Gauss-Newton on a structured model of a smoothing chain's Jacobian, fitted from a few calls.

A chain of skinning, then a deformer that smooths and adds back local detail (Delta Mush),
has the Jacobian ``J = A S^s M`` with respect to the rest offsets: ``M`` the skinning's own
3x3 block per vertex (skinning is per vertex and linear in the rest point), ``S^s`` the
mesh's umbrella smoothing (``s`` steps of weight 1/2, from its edges), and ``A`` a local
operator, each output reading its own and its edge neighbours' smoothed points (the frames in
which the detail is added back). The smoothed moves vary smoothly over a ring, so each output
reads its own point, the ring's gradient and two quadratic modes of it (``_rings``): 18 numbers
an axis whatever the valence, so a few dozen products of the whole chain determine all of it,
at any mesh size and however many pieces the mesh has, where measuring ``J`` itself costs a
call per vertex inside the chain's reach (docs/decisions/coupled-inverse-cesiumman.md, "A
structured Jacobian", "The skinning read from the chain's calls, and the ring read as a gradient
and two modes").

Only the chain and the skinning are called, both counted: ``M`` takes 4 calls of the skinning
(the stage that psdbake itself composes before the deformers; ``coupled`` measures it, and
reads them from the chain's own first calls where ``fit`` gives it the skinning as
``ChainSkinning``), ``A`` ``PRODUCTS`` calls of the chain. The model is a model: how well it
explains its own products (``misfit``) decides whether its steps are tried, and each step is
kept where the chain says it lowers the piece's residual. Measured on CesiumMan through LBS +
Delta Mush: the fit explains the products to 1.7e-2 at rest (each neighbour's own block, the
operator before, to 5.5e-3, float32's noise on a 1e-5 difference).

``solve_whole`` takes a region whose small pieces (UV shells a Delta Mush rotates) would cost
more calls measured exactly than the model does, small and large pieces together, from the
linearised start: damped steps with Broyden's update, and where they stall (the small pieces'
Jacobians have turned under its steps) each output's local operator turned with its smoothed
1-ring, for no call, since a deformer that adds detail back in frames carried by the surface
turns its Jacobian as the surface turns (CesiumMan: 41 and 42 calls an example as ``fit`` runs
it, from 97 and 124 through the exact small pieces, and 56 and 57 with the operator refitted
there from 15 products; docs/decisions/coupled-inverse-cesiumman.md, "The whole region", "The
model turned with the offsets").
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse.csgraph import connected_components

from ..arrays import Points
from .inverse import Counted

#: Products of the chain that fit ``A``: ``RING_FEATURES`` (18) unknowns an axis of an output
#: (each neighbour's own block before: 21 at valence 6, 27 at 8). With that operator, on
#: CesiumMan (offline, its small pieces held at their answers) 25
#: took every vertex within the tolerance in 30 and 31 calls from the smooth start, 30 in 34 and
#: 35 (the model 2.7e-3 and 3.5e-4 off the exact Jacobian on its 251-vertex piece at 25 and 30
#: products, 1.6e-2 at 21, 7.2e-2 at 15).
PRODUCTS = 25
#: The products' difference step, of the diagonal: float32 outputs make 1e-5 about 0.6% noisy;
#: at 1e-4 the chain's curvature left the fit 4.3e-2 off its products against 5.4e-3.
STEP_RTOL = 1e-5
#: The fit must explain its own products this well for its steps to be tried (CesiumMan through
#: Delta Mush, at rest: 1.7e-2 at its 10 smoothing steps; 4.4e-2 and 4.5e-2 at 12 and 8, a model
#: off by a fifth of the smoothing; 1.7e-2 to 2.0e-2 at the linearised starts of six frames).
MAX_MISFIT = 3e-2
#: Tikhonov filter of each piece's step, of its model's largest singular value. On CesiumMan's
#: first step from zero (its worst vertex 5,506 times the tolerance away): at 1e-4 the worst
#: vertex ended 2.5 times farther from the sculpt; at 3e-3 the RMS came to 19 times the
#: tolerance, at 1e-2 and 3e-2 to 35 and 212.
FILTER = 3e-3
#: Steps, one call each for every piece at once.
MAX_STEPS = 8
#: Largest piece (vertices of the region) whose model is formed: its dense model is (3p)^2.
MAX_PIECE = 1000
#: Most entries of the smoothed unit moves (points x region vertices, float64: 160 MB): a
#: larger mesh keeps the stages after this one (CesiumMan: 3,273 x 1,956).
MAX_ENTRIES = 20_000_000


@dataclass(frozen=True)
class StructuredResult:
    """The region's offsets (k, 3) after the stage, and the model's misfit on its products."""

    offsets: NDArray[np.float64]
    misfit: float


def umbrella(adjacency: sp.csr_matrix) -> sp.csr_matrix:
    """One umbrella step of weight 1/2 over the mesh's edges (identity rows for lone points)."""
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    lonely = degree == 0
    inverse = np.divide(0.5, degree, out=np.zeros_like(degree, dtype=np.float64), where=~lonely)
    return (sp.diags(np.where(lonely, 1.0, 0.5)) + sp.diags(inverse) @ adjacency).tocsr()


def region_pieces(adjacency: sp.csr_matrix, idx: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """The region's positions (in ``idx``) grouped by the mesh's connected pieces."""
    _, label = connected_components(adjacency, directed=False)
    of = label[idx]
    return [np.nonzero(of == p)[0] for p in np.unique(of)]


#: Smoothing steps the model tries; the one that explains the products best is kept (the
#: reference Delta Mush, 10 iterations of weight 1/2: 10).
SMOOTHING_STEPS = (4, 6, 8, 10, 12, 14, 16)


def solve(call: Counted, posed: NDArray[np.float64], rest: Points, sculpt: Points, idx: NDArray[np.int64],
          groups: list[NDArray[np.int64]], offsets: Points, outputs: Points, adjacency: sp.csr_matrix,
          diagonal: float, atol: float) -> StructuredResult | None:
    """From ``offsets`` ((k, 3), the chain's ``outputs`` there, (k, 3)): fit the model,
    then filtered Gauss-Newton (chord) steps on each piece of the region, one call for all of
    them, each kept where it lowers its piece's residual. None where a piece is larger than
    ``MAX_PIECE``, the mesh and region together larger than ``MAX_ENTRIES``, or the model does
    not explain its products (``MAX_MISFIT``; its calls are spent). ``posed``: the skinning's
    3x3 block per region vertex (k, 3, 3), from the skinning alone; ``groups``: the region's
    pieces (``region_pieces``)."""
    if not fits(groups, len(rest)):
        return None
    fitted = _model(call, posed, rest, idx, groups, offsets, outputs, adjacency, diagonal)
    if fitted is None:
        return None
    misfit = fitted.misfit
    factored = [_Filtered(model) for model in fitted.models]
    x = np.array(offsets, dtype=np.float64)
    r = sculpt[idx] - outputs
    for _ in range(MAX_STEPS):
        norms = np.linalg.norm(r, axis=1)
        live = [g for g, pos in enumerate(groups) if norms[pos].max() > atol]
        if not live:
            break
        trial = x.copy()
        tried = {g: factored[g].step(r[groups[g]].ravel()) for g in live}
        for g, step in tried.items():
            trial[groups[g]] += step.reshape(-1, 3)
        moved = rest.copy()
        moved[idx] += trial
        left = sculpt[idx] - call(moved)[idx]
        kept = False
        for g in tried:
            pos = groups[g]
            if float(np.sum(left[pos] ** 2)) < float(np.sum(r[pos] ** 2)):
                x[pos], r[pos], kept = trial[pos], left[pos], True
        if not kept:
            break
    return StructuredResult(x, misfit)


@dataclass(frozen=True)
class _Fitted:
    """The model fitted at some offsets: each piece's (3p, 3p) model, its misfit on its
    products, the smoothing steps it chose with their (n, k) unit moves, and each output's
    local operator (3, 3 neighbours)."""

    models: list[NDArray[np.float64]]
    misfit: float
    steps: int
    smoothed: NDArray[np.float64]
    local: list[NDArray[np.float64]]


def _model(call: Counted, posed: NDArray[np.float64], rest: Points, idx: NDArray[np.int64],
           groups: list[NDArray[np.int64]], offsets: Points, outputs: Points, adjacency: sp.csr_matrix,
           diagonal: float) -> _Fitted | None:
    """Each piece's model at ``offsets`` from ``PRODUCTS`` calls, with the smoothing that
    explains the products best (of ``SMOOTHING_STEPS``); None where the misfit exceeds
    ``MAX_MISFIT`` (its calls are spent)."""
    directions, images = _products(call, rest, idx, offsets, outputs, diagonal, PRODUCTS)
    ring = (adjacency + sp.identity(len(rest), format="csr")).tocsr()
    rings = _rings(rest, idx, ring)
    best: tuple[float, int, NDArray[np.float64]] | None = None
    for steps, moved in smoothings(adjacency, idx, SMOOTHING_STEPS):
        fitted = _fit(rest, idx, posed, moved, ring, groups, directions, images, build=False, rings=rings)[1]
        if best is None or fitted < best[0]:
            best = (fitted, steps, moved)
    assert best is not None
    _, steps, smoothed = best
    models, misfit, local = _fit(rest, idx, posed, smoothed, ring, groups, directions, images, build=True,
                                 rings=rings)
    if not misfit <= MAX_MISFIT:
        return None
    return _Fitted(models, misfit, steps, smoothed, local)


def fits(groups: list[NDArray[np.int64]], points: int) -> bool:
    """Whether the stage can run on a region of these pieces of a mesh of ``points`` points:
    several pieces, none over ``MAX_PIECE``, and within ``MAX_ENTRIES``."""
    k = sum(len(g) for g in groups)
    return len(groups) > 1 and max(len(g) for g in groups) <= MAX_PIECE and points * k <= MAX_ENTRIES


def smoothings(adjacency: sp.csr_matrix, idx: NDArray[np.int64], counts: tuple[int, ...]
               ) -> Iterator[tuple[int, NDArray[np.float64]]]:
    """(s, (n, k)) for each s of ``counts`` (ascending): each region vertex's unit move after
    s umbrella steps, each from the one before."""
    n, k = adjacency.shape[0], len(idx)
    moved = sp.csr_matrix((np.ones(k), (idx, np.arange(k))), shape=(n, k)).toarray()
    step, done = umbrella(adjacency), 0
    for steps in counts:
        for _ in range(steps - done):
            moved = np.asarray(step @ moved)
        done = steps
        yield steps, moved


def _products(call: Counted, rest: Points, idx: NDArray[np.int64], offsets: Points, outputs: Points,
              diagonal: float, count: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``count`` calls along fixed pseudo-random moves of every region vertex: the moves
    (k, 3, m) and the region's responses (k, 3, m), forward differences."""
    # fixed: the same inputs give the same model. The calls depend on the draw: on CesiumMan's six
    # measured frames 47.0 an example with this seed, 518 and 183 with two others (decision
    # record, "The 45 calls hold for one set of directions, not for others")
    generator = np.random.default_rng(20001)
    directions = generator.standard_normal((len(idx), 3, count))
    directions /= np.sqrt(np.mean(np.sum(directions**2, axis=1), axis=0))[None, None, :]
    at = rest.copy()
    at[idx] += offsets
    h = STEP_RTOL * diagonal
    images = np.empty((len(idx), 3, count))
    for j in range(count):
        moved = at.copy()
        moved[idx] += h * directions[:, :, j]
        images[:, :, j] = (call(moved)[idx] - outputs) / h
    return directions, images


#: The ring's variation the local operator reads beyond its gradient: this many quadratic modes
#: (those the ring's edges resolve best). Over CesiumMan's six measured frames, calls an example
#: with five direction sets (seeds 20001, 1, 2, 3, 4): 2 modes 40.8, 53.2, 103.3, 424.3, 58.7;
#: 1 mode 105.3 and 75.5, 3 modes 57.8 and 115.3 (at 20001 and 1); every neighbour's own
#: block (3 (valence + 1) unknowns an axis) 41.0, 415.2, 108.7, 884.7, 58.7.
RING_MODES = 2
#: An output's unknowns an axis: its own smoothed point (3), the ring's gradient (9) and its modes.
RING_FEATURES = 12 + 3 * RING_MODES


@dataclass(frozen=True)
class _Rings:
    """The outputs grouped by ring size: for each size, the outputs (positions in the region),
    their rings (B, size; the mesh's points, the output's own among them) and the linear maps
    (B, RING_FEATURES, 3 size) from a ring's moves to what the operator reads of them."""

    batches: list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]]


def _rings(rest: Points, idx: NDArray[np.int64], ring: sp.csr_matrix) -> _Rings:
    """Each output's ring and what its operator reads of it: the output's own smoothed move, and
    the ring's moves relative to it as a gradient (least squares over the ring's rest edges) and
    ``RING_MODES`` quadratic modes. Ten umbrella steps leave the moves smooth over a ring, so
    these carry what the products see, in ``RING_FEATURES`` unknowns an axis whatever the
    valence, where each neighbour's own 3x3 block took 3 (valence + 1): 27 at valence 8, more
    than 25 products determine, and the minimum-norm fit's choice followed the draw
    (docs/decisions/coupled-inverse-cesiumman.md, "The skinning read from the chain's calls, and
    the ring read as a gradient and two modes")."""
    near = [ring.indices[ring.indptr[v]:ring.indptr[v + 1]] for v in idx]  # CSR rows, sorted
    sizes = np.array([len(a) for a in near])
    batches = []
    for size in np.unique(sizes):
        which = np.nonzero(sizes == size)[0]
        rings = np.stack([near[q] for q in which])  # (B, size)
        count = len(which)
        each = np.arange(count)
        rows = each[:, None]
        own = np.argmax(rings == idx[which][:, None], axis=1)  # the output's place in its ring
        others = np.nonzero(np.arange(size)[None, :] != own[:, None])[1].reshape(count, size - 1)  # ascending
        features = np.zeros((count, RING_FEATURES, 3 * size))
        for c in range(3):
            features[each, c, 3 * own + c] = 1.0
        if size > 1:
            edges = rest[rings[rows, others]] - rest[idx[which]][:, None]  # (B, size - 1, 3)
            gradient = np.linalg.pinv(edges)  # (B, 3, size - 1)
            maps = [gradient]
            if size - 1 > RING_MODES + 1:
                e = edges  # the quadratic moments of each edge
                quad = np.stack([e[..., 0] ** 2, e[..., 1] ** 2, e[..., 2] ** 2, e[..., 0] * e[..., 1],
                                 e[..., 0] * e[..., 2], e[..., 1] * e[..., 2]], axis=2)  # (B, size - 1, 6)
                beyond = quad - edges @ (gradient @ quad)  # what the gradient does not explain
                modes = np.linalg.svd(beyond, full_matrices=False)[2][:, :RING_MODES]  # (B, modes, 6)
                maps.append(np.linalg.pinv(quad @ np.swapaxes(modes, 1, 2)))  # (B, modes, size - 1)
            else:
                maps.append(np.zeros((count, RING_MODES, size - 1)))
            weights = np.concatenate(maps, axis=1)  # (B, 3 + modes, size - 1)
            for f in range(weights.shape[1]):
                for c in range(3):
                    features[rows, 3 + 3 * f + c, 3 * others + c] = weights[:, f, :]
                    features[each, 3 + 3 * f + c, 3 * own + c] = -weights[:, f, :].sum(axis=1)
        batches.append((which, rings, features))
    return _Rings(batches)


def _fit(rest: Points, idx: NDArray[np.int64], posed: NDArray[np.float64], smoothed: NDArray[np.float64],
         ring: sp.csr_matrix, groups: list[NDArray[np.int64]], directions: NDArray[np.float64],
         images: NDArray[np.float64], build: bool, rings: _Rings | None = None
         ) -> tuple[list[NDArray[np.float64]], float, list[NDArray[np.float64]]]:
    """Each piece's model (3p, 3p; with ``build``), the fit's relative misfit on the products, and
    its outputs' local operators (3, 3 neighbours), fitted by least squares to the products on
    what each reads of its ring (``_rings``; minimum-norm where the products leave it short)."""
    m = directions.shape[2]
    k = len(idx)
    seen = (smoothed @ np.einsum("kab,kbm->kam", posed, directions).reshape(k, 3 * m)).reshape(-1, 3, m)
    local: list[NDArray[np.float64]] = [np.empty(0)] * len(idx)
    wrong = 0.0
    for which, members, features in (rings or _rings(rest, idx, ring)).batches:  # one stack a ring size
        inputs = features @ seen[members].reshape(len(which), -1, m)  # (B, RING_FEATURES, m)
        measured = images[which]  # (B, 3, m)
        coef = np.linalg.pinv(np.swapaxes(inputs, 1, 2)) @ np.swapaxes(measured, 1, 2)  # (B, RING_FEATURES, 3)
        wrong += float(np.sum((np.swapaxes(coef, 1, 2) @ inputs - measured) ** 2))
        operators = np.swapaxes(coef, 1, 2) @ features  # (B, 3, 3 size)
        for b, q in enumerate(which):
            local[q] = operators[b]
    total = float(np.sum(images**2))
    models = _build(idx, posed, smoothed, ring, groups, local) if build else []
    return models, float(np.sqrt(wrong / total)) if total > 0 else float("inf"), local


def _build(idx: NDArray[np.int64], posed: NDArray[np.float64], smoothed: NDArray[np.float64], ring: sp.csr_matrix,
           groups: list[NDArray[np.int64]], local: list[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    """Each piece's model (3p, 3p) from its outputs' local operators: ``A S^s M``, the smoothed
    responses formed only at the points the piece's outputs read."""
    near = [ring.indices[ring.indptr[v]:ring.indptr[v + 1]] for v in idx]
    models = []
    for pos in groups:
        rows = np.unique(np.concatenate([near[q] for q in pos]))
        responses = np.einsum("nk,kab->nakb", smoothed[np.ix_(rows, pos)], posed[pos], order="C")
        responses = responses.reshape(len(rows), 3, 3 * len(pos))
        model = np.empty((3 * len(pos), 3 * len(pos)))
        for t, q in enumerate(pos):
            model[3 * t:3 * t + 3] = local[q] @ responses[np.searchsorted(rows, near[q])].reshape(-1, 3 * len(pos))
        models.append(model)
    return models


def _turned(local: list[NDArray[np.float64]], idx: NDArray[np.int64], ring: sp.csr_matrix,
            fitted_at: NDArray[np.float64], now: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Each output's local operator turned with its 1-ring: ``R A_j R^T`` for every neighbour's
    block, ``R`` the rotation that best takes the ring's smoothed points (relative to the
    output's own, (n, 3) ``fitted_at`` where the operator was fitted) onto the same ring ``now``
    (Kabsch, by SVD). A deformer that adds detail back in frames carried by the smoothed surface
    is rotation-equivariant: where a small shell turns under the offsets, its Jacobian turns
    with it, and this follows that for no call."""
    near = [ring.indices[ring.indptr[v]:ring.indptr[v + 1]] for v in idx]
    turned: list[NDArray[np.float64]] = [np.empty(0)] * len(idx)
    sizes = np.array([len(a) for a in near])
    for size in np.unique(sizes):  # the outputs with as many neighbours, as one stack
        which = np.nonzero(sizes == size)[0]
        rings = np.stack([near[q] for q in which])  # (B, size)
        before = fitted_at[rings] - fitted_at[idx[which]][:, None]  # (B, size, 3)
        after = now[rings] - now[idx[which]][:, None]
        u, sigma, vt = np.linalg.svd(np.swapaxes(before, 1, 2) @ after)  # H = before^T after
        flip = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
        vt[:, 2, :] *= flip[:, None]  # a rotation, not a reflection
        rotation = np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)  # (B, 3, 3)
        # a ring on one line fixes no turn about that line: the least rotation that takes the
        # line where it went (Rodrigues), where Kabsch would spin it about the line at random
        line = ~(sigma[:, 1] > 1e-9 * sigma[:, 0])
        if np.any(line):
            rotation[line] = _least_rotations(u[line, :, 0], vt[line, 0, :])
        for b, q in enumerate(which):
            blocks = local[q].reshape(3, size, 3)
            turned[q] = np.einsum("ab,btc,dc->atd", rotation[b], blocks, rotation[b]).reshape(3, -1)
    return turned


def _largest(gram: NDArray[np.float64]) -> float:
    """The Gram matrix's largest eigenvalue, by 30 power iterations from a fixed start
    (deterministic; its scale is all the damping needs)."""
    v = np.ones(len(gram)) / np.sqrt(len(gram))
    largest = 0.0
    for _ in range(30):
        w = gram @ v
        largest = float(np.linalg.norm(w))
        if not largest > 0:
            break
        v = w / largest
    return largest


class _Filtered:
    """One piece's model, factored once, for Tikhonov-filtered least-squares steps
    ``(J^T J + (FILTER sigma_1)^2)^-1 J^T r`` (Cholesky of the regularised Gram matrix, whose
    condition number the filter bounds by 1/FILTER^2; an SVD of CesiumMan's 731-vertex piece
    took several times as long). Chord steps: with Broyden's update on CesiumMan the calls were
    the same (93 and 120) and each update needs the factor again."""

    def __init__(self, model: NDArray[np.float64]) -> None:
        self.model = model
        gram = model.T @ model
        largest = _largest(gram)
        gram[np.diag_indices_from(gram)] += (FILTER**2) * largest
        self.factor = cho_factor(gram) if largest > 0 else None

    def step(self, r: NDArray[np.float64]) -> NDArray[np.float64]:
        if self.factor is None:
            return np.zeros(self.model.shape[1])
        return np.asarray(cho_solve(self.factor, self.model.T @ r), dtype=np.float64)


#: ``solve_whole``'s damping, of each piece's largest squared singular value: where it starts
#: (``FILTER``), its least, and its factors on a rejected and on a kept step (Levenberg-
#: Marquardt). On CesiumMan through Delta Mush, from the linearised start: a least of 1e-4 took
#: the large pieces within the tolerance in 4 and 6 steps, against 10 and 7 at 3e-3 (the chord
#: steps of ``solve``); 4 and 2 left fewer small pieces behind than 10 and 3.
LEAST_DAMPING = 1e-4
DAMPING_UP = 4.0
DAMPING_DOWN = 2.0
#: Steps on the first model, and on it turned with the offsets where it leaves vertices above
#: the tolerance (``_turned``). On CesiumMan the small pieces' Jacobians change by 20-90% between
#: the linearised start and the answer, so the first model's steps stall 2-5 times the tolerance
#: away; turned there, its steps finish them. Calls an example over CesiumMan's two examples and
#: four more frames (6, 18, 24, 40), every vertex within the tolerance: 47.0 (43-51) at 5 and 14
#: steps, the same at 5 and 20; 53.3 at 5 and 8 (three examples finished by later stages), 49.5
#: at 6 and 20, 54.7 at 4 and 20. Refitted there for the change instead (15 products, the
#: previous method): 56.5 (56-57). Turned before every step (the Broyden updates lost each
#: time): 127 and 114 at the two examples.
WHOLE_STEPS = 5
TURNED_STEPS = 14


@dataclass(frozen=True)
class WholeResult:
    """``solve_whole``'s offsets (k, 3), the chain's outputs there (k, 3, piece by piece from
    the calls that kept them), and the first model's misfit on its products."""

    offsets: NDArray[np.float64]
    outputs: NDArray[np.float64]
    misfit: float


class _Damped:
    """One piece's model for Levenberg-Marquardt steps, updated by Broyden's rank-one secant
    after each step (its Gram matrix with it, so that a damping change costs one Cholesky of
    (3p)^2, not a product)."""

    def __init__(self, model: NDArray[np.float64], damping: float) -> None:
        self.model = model
        self.gram = model.T @ model
        self.largest = _largest(self.gram)
        self.damping = damping

    def step(self, r: NDArray[np.float64]) -> NDArray[np.float64]:
        if not self.largest > 0:
            return np.zeros(self.model.shape[1])
        gram = self.gram.copy()
        gram[np.diag_indices_from(gram)] += (self.damping**2) * self.largest
        return np.asarray(cho_solve(cho_factor(gram), self.model.T @ r), dtype=np.float64)

    def update(self, s: NDArray[np.float64], y: NDArray[np.float64], kept: bool) -> None:
        """The secant (step ``s``, its change of the outputs ``y``), and the damping by whether
        the step was kept."""
        size = float(s @ s)
        if size > 0 and np.all(np.isfinite(y)):
            u = (y - self.model @ s) / size
            ju = self.model.T @ u
            self.gram += np.outer(s, ju) + np.outer(ju, s) + float(u @ u) * np.outer(s, s)
            self.model += np.outer(u, s)
        self.damping = max(self.damping / DAMPING_DOWN, LEAST_DAMPING) if kept else self.damping * DAMPING_UP


def solve_whole(call: Counted, posed: NDArray[np.float64], rest: Points, sculpt: Points, idx: NDArray[np.int64],
                groups: list[NDArray[np.int64]], offsets: Points, outputs: Points, adjacency: sp.csr_matrix,
                diagonal: float, atol: float, skinned: Points) -> WholeResult | None:
    """The whole region, its small pieces with the rest, on the structured model from
    ``offsets`` (the linearised start; the chain's ``outputs`` there): damped Gauss-Newton
    steps on every piece at once (``_Damped``, one call a step), each piece's kept where it
    lowers that piece's residual; where vertices are still above the tolerance, each output's
    local operator turned with its smoothed 1-ring from where the model was fitted to there
    (``_turned``, no call) and ``TURNED_STEPS`` steps on the turned model. ``skinned``: the
    skinning alone at rest, (n, 3), whose smoothing with the offsets' smoothed moves gives the
    rings. None as ``solve``. The pieces must be independent (connected components of a
    smoothing chain): the caller checks the result with one call of the whole region."""
    if not fits(groups, len(rest)):
        return None
    fitted = _model(call, posed, rest, idx, groups, offsets, outputs, adjacency, diagonal)
    if fitted is None:
        return None
    x = np.array(offsets, dtype=np.float64)
    out = np.array(outputs, dtype=np.float64)
    damped = dict(enumerate(_Damped(model, FILTER) for model in fitted.models))
    for phase in range(2):
        for _ in range(WHOLE_STEPS if phase == 0 else TURNED_STEPS):
            r = sculpt[idx] - out
            norms = np.linalg.norm(r, axis=1)
            live = [g for g, pos in enumerate(groups) if norms[pos].max() > atol and g in damped]
            if not live:
                break
            trial = x.copy()
            tried = {g: damped[g].step(r[groups[g]].ravel()) for g in live}
            for g, step in tried.items():
                trial[groups[g]] += step.reshape(-1, 3)
            moved = rest.copy()
            moved[idx] += trial
            seen = call(moved)[idx]
            for g, step in tried.items():
                pos = groups[g]
                kept = bool(np.all(np.isfinite(seen[pos]))) and float(np.sum((sculpt[idx[pos]] - seen[pos]) ** 2)
                                                                      ) < float(np.sum(r[pos] ** 2))
                damped[g].update(step, (seen[pos] - out[pos]).ravel(), kept)
                if kept:
                    x[pos], out[pos] = trial[pos], seen[pos]
        if phase == 0:
            if np.all(np.linalg.norm(sculpt[idx] - out, axis=1) <= atol):
                break
            norms = np.linalg.norm(sculpt[idx] - out, axis=1)
            live = [g for g, pos in enumerate(groups) if norms[pos].max() > atol]
            ring = (adjacency + sp.identity(len(rest), format="csr")).tocsr()
            smoothed_rest = np.asarray(skinned, dtype=np.float64)
            step = umbrella(adjacency)
            for _ in range(fitted.steps):
                smoothed_rest = np.asarray(step @ smoothed_rest)
            turned = _turned(fitted.local, idx, ring, _smoothed_points(smoothed_rest, fitted.smoothed, posed, offsets),
                             _smoothed_points(smoothed_rest, fitted.smoothed, posed, x))
            models = _build(idx, posed, fitted.smoothed, ring, [groups[g] for g in live], turned)
            damped = {g: _Damped(model, LEAST_DAMPING) for g, model in zip(live, models, strict=True)}
    return WholeResult(x, out, fitted.misfit)


def _least_rotations(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(B, 3, 3): the least rotation taking each unit ``a`` (B, 3) onto ``b`` (Rodrigues); the
    identity where the two are opposite or not defined (a lone point)."""
    axis = np.cross(a, b)
    cosine = np.einsum("ij,ij->i", a, b)
    cross = np.zeros((len(a), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    cross -= np.swapaxes(cross, 1, 2)
    scale = np.divide(1.0, 1.0 + cosine, out=np.zeros_like(cosine), where=1.0 + cosine > 1e-12)
    rotations = np.eye(3)[None] + cross + (cross @ cross) * scale[:, None, None]
    rotations[~(1.0 + cosine > 1e-12)] = np.eye(3)
    return rotations


def _smoothed_points(smoothed_rest: NDArray[np.float64], smoothed: NDArray[np.float64], posed: NDArray[np.float64],
                     offsets: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mesh's smoothed skinned points (n, 3) at ``offsets`` (k, 3): skinning is linear in the
    rest point (``posed``, its blocks), and so is the umbrella smoothing (``smoothed``, the
    region's unit moves; ``smoothed_rest``, the skinning at rest smoothed)."""
    return smoothed_rest + smoothed @ np.einsum("kab,kb->ka", posed, offsets)
