"""Gauss-Newton on measured directions (``psdbake.solver.subspace``), on synthetic chains whose
Jacobian is known: a linear smoothing chain it must invert to the tolerance within its budget,
the order in which it measures a vertex's own directions, and its budget kept."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import smoothing_chain, tube_with_edges

from psdbake.solver import coupled, subspace
from psdbake.solver.inverse import Counted


def _tube(rings: int = 24, segments: int = 12) -> tuple[np.ndarray, sp.csr_matrix]:
    return tube_with_edges(rings, segments)


def _smoothing(rest: np.ndarray, adjacency: sp.csr_matrix, steps: int = 6):
    return smoothing_chain(rest, adjacency, steps, twist=0.8)


def _problem(seed: int = 3):
    """The tube's middle third sculpted by the chain from a smooth offset (an exact answer
    exists), the start a little off it: what the smooth start leaves at a fold."""
    rest, adjacency = _tube()
    chain = _smoothing(rest, adjacency)
    region = np.arange(12 * 8, 12 * 16)
    truth = np.zeros_like(rest)
    x = rest[region, 0]
    truth[region, 1] = 0.05 * np.sin(np.pi * (x - x.min()) / (x.max() - x.min())) ** 2
    sculpt = chain(rest + truth)
    rng = np.random.default_rng(seed)
    start = truth[region] + 2e-4 * rng.standard_normal((len(region), 3))
    return rest, adjacency, chain, region, sculpt, start


def test_a_linear_coupling_chain_is_inverted_to_the_tolerance_within_the_budget():
    rest, adjacency, chain, region, sculpt, start = _problem()
    box = Counted(chain)
    base = box(rest)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(box, rest, base, region, diagonal, 0.0)
    moved = rest.copy()
    moved[region] += start
    outputs = box(moved)[region]
    atol = 1e-6 * diagonal
    before = box.calls
    found = subspace.solve(box, rest, sculpt[region], region, start, outputs, blocks, atol, diagonal, adjacency)
    assert box.calls - before <= subspace.CALLS
    moved = rest.copy()
    moved[region] += found.offsets
    residual = np.linalg.norm(sculpt[region] - chain(moved)[region], axis=1)
    assert np.array_equal(residual, found.residual)  # the residual it reports is the chain's own
    start_residual = np.linalg.norm(sculpt[region] - outputs, axis=1)
    assert start_residual.max() > 10 * atol and residual.max() <= atol, (start_residual.max(), residual.max(), atol)


def test_a_round_measures_no_more_directions_once_its_model_clears_every_vertex():
    """A chain that does not couple (the twist alone): the blocks' inverse on the residual is
    the exact step, so the round's first direction already clears the few vertices that miss.
    The solve then takes that step instead of measuring their own directions: 1 direction and
    1 step (with the round's own directions of the 5 vertices first, 7 calls)."""
    rest, adjacency = _tube()
    chain = smoothing_chain(rest, adjacency, 0, twist=0.8)
    region = np.arange(12 * 8, 12 * 16)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    atol = 1e-6 * diagonal
    truth = np.zeros((len(region), 3))
    sculpt = chain(rest)
    start = truth.copy()
    start[[3, 17, 40, 61, 80]] = 50 * atol * np.array([0.6, 0.0, 0.8])  # 5 vertices, 50 tolerances off
    moved = rest.copy()
    moved[region] += start
    outputs = chain(moved)[region]
    blocks = coupled.chain_blocks(chain, rest, sculpt, region, diagonal, 0.0)
    box = Counted(chain)
    found = subspace.solve(box, rest, sculpt[region], region, start, outputs, blocks, atol, diagonal, adjacency)
    assert found.residual.max() <= atol and box.calls == 2, (found.residual.max() / atol, box.calls)


def test_the_budget_holds_where_the_tolerance_cannot_be_met():
    """A chain that annihilates what is left (a constant output): every call the solve makes
    counts against its budget, and it ends with the start's residual, not a worse one."""
    rest, adjacency, _chain, region, sculpt, start = _problem()
    box = Counted(lambda points: np.zeros_like(points))
    blocks = np.tile(np.eye(3), (len(region), 1, 1))
    found = subspace.solve(box, rest, sculpt[region], region, start, np.zeros((len(region), 3)), blocks, 1e-9, 1.0,
                           adjacency, max_calls=17)
    assert box.calls <= 17
    np.testing.assert_array_equal(found.offsets, start)  # no step kept
    np.testing.assert_allclose(found.residual, np.linalg.norm(sculpt[region], axis=1), rtol=0, atol=0)


def test_a_vertex_gets_its_newton_direction_then_the_two_orthogonal_to_it_then_its_neighbours():
    _rest, adjacency = _tube()
    region = np.arange(12 * 8, 12 * 16)
    k = len(region)
    r = np.zeros((k, 3))
    r[5] = (0.0, 3e-5, 4e-5)
    norms = np.linalg.norm(r, axis=1)
    inverse = np.tile(np.diag([1.0, 2.0, 1.0]), (k, 1, 1))
    own: dict[int, np.ndarray] = {}
    first = subspace._own(r, norms, 1e-6, inverse, own, adjacency, region)
    assert len(first) == 1 and np.count_nonzero(np.linalg.norm(first[0], axis=1)) == 1
    newton = inverse[5] @ r[5]
    np.testing.assert_allclose(first[0][5], newton / np.linalg.norm(newton), rtol=0, atol=1e-15)
    second = subspace._own(r, norms, 1e-6, inverse, own, adjacency, region)
    assert len(second) == 2
    together = np.array([first[0][5], second[0][5], second[1][5]])
    np.testing.assert_allclose(together @ together.T, np.eye(3), rtol=0, atol=1e-12)  # an orthonormal frame
    third = subspace._own(r, norms, 1e-6, inverse, own, adjacency, region)
    moved = sorted(int(np.nonzero(np.linalg.norm(m, axis=1))[0][0]) for m in third)
    neighbours = sorted(int(v) for v in subspace.region_neighbours(adjacency, region, np.array([5])))
    assert 0 < len(third) <= subspace.OWN_PER_ROUND and set(moved) <= set(neighbours) and 5 not in moved


@pytest.mark.parametrize("count", [3, 40])
def test_a_round_measures_at_most_its_share_of_own_directions_worst_first(count):
    _rest, adjacency = _tube()
    region = np.arange(12 * 8, 12 * 16)
    k = len(region)
    r = np.zeros((k, 3))
    picked = np.linspace(0, k - 1, count).astype(int)
    r[picked, 2] = np.arange(1, count + 1) * 1e-5  # the later, the worse
    norms = np.linalg.norm(r, axis=1)
    moves = subspace._own(r, norms, 1e-6, np.tile(np.eye(3), (k, 1, 1)), {}, adjacency, region)
    moved = [int(np.nonzero(np.linalg.norm(m, axis=1))[0][0]) for m in moves]
    assert moved == sorted(picked[-subspace.OWN_PER_ROUND:].tolist())


def test_the_directions_kept_fit_their_memory_bound(monkeypatch):
    """On a region too large for ``CALLS`` directions in ``MAX_ENTRIES``, the solve takes no more
    calls than that many directions allow."""
    rest, adjacency, chain, region, sculpt, start = _problem()
    monkeypatch.setattr(subspace, "MAX_ENTRIES", 6 * len(region) * 5)
    box = Counted(chain)
    moved = rest.copy()
    moved[region] += start
    outputs = chain(moved)[region]
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(chain, rest, chain(rest), region, diagonal, 0.0)
    subspace.solve(box, rest, sculpt[region], region, start, outputs, blocks, 1e-6 * diagonal, diagonal, adjacency)
    assert 0 < box.calls <= 5


def test_a_chain_that_turns_non_finite_ends_the_solve_within_its_budget():
    """A chain that returns NaN from its 4th call on (many vertices miss, so the Krylov
    directions are what meets it): the solve stops, its offsets finite and its budget kept."""
    rest, adjacency, chain, region, sculpt, _start = _problem()
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(chain, rest, chain(rest), region, diagonal, 0.0)
    made = [0]

    def failing(points: np.ndarray) -> np.ndarray:
        made[0] += 1
        return chain(points) if made[0] < 4 else np.full_like(points, np.nan)

    box = Counted(failing)
    start = np.zeros((len(region), 3))
    found = subspace.solve(box, rest, sculpt[region], region, start, chain(rest)[region], blocks, 1e-6 * diagonal,
                           diagonal, adjacency, max_calls=12)
    assert box.calls <= 12 and np.all(np.isfinite(found.offsets)) and np.all(np.isfinite(found.residual))


def test_on_trial_a_round_that_keeps_no_step_ends_the_solve():
    """Where the measured directions' linear model does not hold (here a chain linear over a
    forward difference but strongly curved over a step, so that every step is refused), a solve
    on trial (``trial_rounds=1``, as ``coupled`` runs it before the pieces' exact Jacobians)
    gives up after its first round and hands back the start; without it the solve goes on to
    the stall rule. Calls the trial may take: its global direction, its Krylov directions and
    one refused step."""
    rest, adjacency, chain, region, sculpt, start = _problem()

    def curved(points: np.ndarray) -> np.ndarray:
        moved = np.linalg.norm(points - rest, axis=1, keepdims=True) ** 2
        return chain(points) + 1e4 * moved

    blocks = np.tile(np.eye(3), (len(region), 1, 1))
    start = np.zeros_like(start)
    outputs = curved(rest)[region]
    spent = {}
    for trial in (1, None):
        box = Counted(curved)
        found = subspace.solve(box, rest, sculpt[region], region, start, outputs, blocks, 1e-6, 1.0, adjacency,
                               trial_rounds=trial)
        np.testing.assert_array_equal(found.offsets, start)  # no step kept
        spent[trial] = box.calls
    assert spent[1] <= 1 + subspace.KRYLOV_PER_ROUND + 1, spent
    assert spent[None] >= subspace.STALL_CALLS, spent


def test_directions_measured_before_are_used_as_the_solves_own():
    """Directions of the offsets measured at the start by a stage before (Newton-Krylov's Krylov
    space where it kept no step) and handed on (``seeded``) save their calls: the seeded solve
    reaches the tolerance in fewer calls than the one that measures them again."""
    rest, adjacency, chain, region, sculpt, start = _problem()
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(Counted(chain), rest, np.asarray(chain(rest)), region, diagonal, 0.0)
    atol = 1e-6 * diagonal
    moved = rest.copy()
    moved[region] += start
    outputs = chain(moved)[region]
    inverse = np.linalg.inv(blocks)
    h = subspace.STEP_RTOL * diagonal
    moves, responses = [], []
    towards = np.einsum("kab,kb->ka", inverse, sculpt[region] - outputs)
    for _ in range(12):  # the blocks-preconditioned Krylov space, as Newton-Krylov measures it
        towards = towards / np.abs(towards).max()
        moved_h = moved.copy()
        moved_h[region] += h * towards
        response = (chain(moved_h)[region] - outputs) / h
        moves.append(towards.ravel())
        responses.append(response.ravel())
        towards = np.einsum("kab,kb->ka", inverse, response)
    spent = {}
    for seeded in (None, (3.0 * np.array(moves), 3.0 * np.array(responses))):  # any scale: it is normalised
        box = Counted(chain)
        found = subspace.solve(box, rest, sculpt[region], region, start, outputs, blocks, atol, diagonal, adjacency,
                               seeded=seeded)
        moved_found = rest.copy()
        moved_found[region] += found.offsets
        assert np.linalg.norm(sculpt[region] - chain(moved_found)[region], axis=1).max() <= atol
        spent[seeded is not None] = box.calls
    assert spent[True] < spent[False], spent
