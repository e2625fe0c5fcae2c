"""Newton-GMRES on independent pieces at once (``psdbake.solver.pieces_krylov``).

A synthetic chain whose pieces are independent linear maps with different spectra: GMRES needs
as many products as a piece's matrix has distinct eigenvalues (in exact arithmetic), so each
piece on its own Krylov space needs a piece's worth of calls, where one Krylov space shared by
all of them needs the sum. That is what the stage buys on CesiumMan (121 calls an example
against about 400 for one shared space).
"""

from __future__ import annotations

import numpy as np

from psdbake.solver import pieces_krylov
from psdbake.solver.pieces import Piece

#: Pieces, and vertices each (3 unknowns a vertex).
PIECES, VERTICES = 4, 6
#: Each piece's eigenvalues are log-uniform over this range, distinct from piece to piece: a
#: spread spectrum, as the chain's (CesiumMan's directions pass at 1 to 1e-3 of its gain).
SPECTRUM = (1e-3, 1.0)


def _chain(leak: float = 0.0):
    """rest (n, 3), the pieces, the black box (rest + D -> rest + J D, J block-diagonal by piece;
    ``leak`` couples each piece to the mean move of the whole mesh), and J."""
    rng = np.random.default_rng(7)
    n = PIECES * VERTICES
    rest = rng.standard_normal((n, 3))
    size = 3 * VERTICES
    jacobian = np.zeros((3 * n, 3 * n))
    parts = []
    for p in range(PIECES):
        q, _ = np.linalg.qr(rng.standard_normal((size, size)))
        values = np.exp(rng.uniform(*np.log(SPECTRUM), size))
        block = slice(p * size, (p + 1) * size)
        jacobian[block, block] = q @ np.diag(values) @ q.T
        vertices = np.arange(p * VERTICES, (p + 1) * VERTICES)
        parts.append(Piece(vertices, vertices))

    def box(points: np.ndarray) -> np.ndarray:
        moved = points - rest
        out = rest + (jacobian @ moved.ravel()).reshape(n, 3)
        return out + leak * moved.mean(axis=0)

    return rest, parts, box, jacobian


class _Counted:
    def __init__(self, box) -> None:
        self.box, self.calls = box, 0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        self.calls += 1
        return self.box(points)


def _solve(parts, box, rest, truth, budget):
    n = len(rest)
    idx = np.arange(n)
    sculpt = box(rest + truth)
    call = _Counted(box)
    atol = 1e-9
    res = pieces_krylov.solve(call, rest, sculpt, idx, parts, np.zeros((n, 3)), box(rest),
                              np.tile(np.eye(3), (n, 1, 1)), 1.0, atol, budget)
    return res, call.calls, np.linalg.norm(box(rest + res.offsets) - sculpt, axis=1), atol


def test_each_piece_on_its_own_krylov_space_needs_a_pieces_worth_of_calls():
    """Every vertex within the tolerance, checked by running the chain, in at most one
    product a piece unknown plus the step's calls; one Krylov space shared by all four pieces
    misses in the same calls by more than 100 times the tolerance, and needs more than twice
    as many to reach it, as its polynomial must fit all four spectra at once."""
    rest, parts, box, _ = _chain()
    truth = np.random.default_rng(3).standard_normal(rest.shape) * 1e-3
    budget = 3 * VERTICES + 2
    _, own, residual, atol = _solve(parts, box, rest, truth, budget)
    assert residual.max() <= atol and own <= budget
    shared = [Piece(np.arange(len(rest)), np.arange(len(rest)))]
    _, _, residual, _ = _solve(shared, box, rest, truth, budget)
    assert residual.max() > 100 * atol
    _, calls, residual, _ = _solve(shared, box, rest, truth, 10 * budget)
    assert residual.max() <= atol and calls >= 2 * own  # measured 50 calls against 20


def test_pieces_that_move_each_other_end_the_stage():
    """A chain that couples the pieces (each output follows the whole mesh's mean move by
    1e-3) breaks what the stage rests on; the first product shows it, and the stage gives up
    rather than fit each piece to a product the others changed."""
    rest, parts, box, _ = _chain(leak=1e-3)
    truth = np.random.default_rng(3).standard_normal(rest.shape) * 1e-3
    n = len(rest)
    sculpt = box(rest + truth)
    half = parts[: PIECES // 2]  # the other pieces hold still, so their outputs show the leak
    call = _Counted(box)
    res = pieces_krylov.solve(call, rest, sculpt, np.arange(n), half, np.zeros((n, 3)), box(rest),
                              np.tile(np.eye(3), (n, 1, 1)), 1.0, 1e-9, 50)
    assert res is None and call.calls == 1
