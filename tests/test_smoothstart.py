"""The smooth start's model of a coupled chain (``psdbake.solver.smoothstart``): the chain's smoothing
measured by one probe, the model's columns and Gram matrix, and Levenberg-Marquardt over the
span, on synthetic chains whose Jacobian is known."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import smoothing_chain, tube_with_edges

from psdbake.solver import coupled, smoothstart
from psdbake.solver.inverse import Counted
from psdbake.solver.smoothbasis import smooth_bases


def _tube(rings: int = 40, segments: int = 16) -> tuple[np.ndarray, sp.csr_matrix]:
    return tube_with_edges(rings, segments)


def _smoothing_chain(rest: np.ndarray, adjacency: sp.csr_matrix, steps: int):
    return smoothing_chain(rest, adjacency, steps, twist=0.6)


@pytest.mark.parametrize("steps", [0, 4, 10])
def test_one_probe_measures_how_far_the_chain_smooths(steps):
    rest, adjacency = _tube()
    chain = Counted(_smoothing_chain(rest, adjacency, steps))
    region = np.arange(16 * 8, 16 * 32)
    base = chain(rest)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(chain, rest, base, region, diagonal, 0.0)
    basis, coarse = smooth_bases(adjacency, region, 32, 128)
    freqs = smoothstart.frequencies(adjacency, region, basis)
    before = chain.calls
    reach = smoothstart.measure_reach(chain, rest, base, region, blocks, basis[:, :coarse], freqs[:coarse], diagonal)
    assert chain.calls == before + 1  # one call
    assert abs(reach.steps - steps) <= 1.0 and reach.misfit < 0.2, reach  # measured: 0, 4, 10 exactly (misfit 0-0.04)


def _columns(blocks, basis, gain):
    """The model's Jacobian on the span written out: row 3j + a is the blocks' response to
    field j along axis a, times its gain."""
    k, b = basis.shape
    cols = np.empty((3 * b, 3 * k))
    for j in range(b):
        for axis in range(3):
            field = np.zeros((k, 3))
            field[:, axis] = basis[:, j]
            cols[3 * j + axis] = gain[j] * np.einsum("kab,kb->ka", blocks, field).ravel()
    return cols


def test_the_span_model_is_its_columns_and_keeps_its_gram_through_broyden_updates():
    """The model is applied, never formed: its products, its Gram matrix, its Broyden updates
    and the coarse span's updates carried into the fine one are those of the written-out
    columns (float64 round-off)."""
    rng = np.random.default_rng(3)
    k, b, coarse = 60, 9, 3
    blocks = rng.normal(size=(k, 3, 3))
    basis = np.linalg.qr(rng.normal(size=(k, b)))[0]
    gain = rng.uniform(0.1, 1.0, size=b)
    cols = _columns(blocks, basis, gain)
    model = smoothstart.SpanModel(blocks, basis, gain)
    gram = smoothstart.model_gram(blocks, basis, gain)
    np.testing.assert_allclose(gram, cols @ cols.T, atol=1e-12)
    r, y = rng.normal(size=3 * k), rng.normal(size=3 * b)
    np.testing.assert_allclose(model.apply(r), cols @ r, atol=1e-12)
    np.testing.assert_allclose(model.respond(y), y @ cols, atol=1e-12)
    # two Broyden updates on the coarse span, then carried into the whole span
    first, first_gram = model.leading(coarse), gram[: 3 * coarse, : 3 * coarse].copy()
    dense = cols[: 3 * coarse].copy()
    for _ in range(2):
        step, observed = rng.normal(size=3 * coarse), rng.normal(size=3 * k)
        first.update(first_gram, step, observed)
        dense += np.outer(step, observed - step @ dense) / float(step @ step)
        np.testing.assert_allclose(step @ dense, observed, atol=1e-12)  # the secant equation
    np.testing.assert_allclose(first.respond(y[: 3 * coarse]), y[: 3 * coarse] @ dense, atol=1e-12)
    np.testing.assert_allclose(first_gram, dense @ dense.T, atol=1e-11)
    model.carry(first, gram, first_gram)
    cols[: 3 * coarse] = dense
    np.testing.assert_allclose(model.apply(r), cols @ r, atol=1e-12)
    np.testing.assert_allclose(model.respond(y), y @ cols, atol=1e-12)
    np.testing.assert_allclose(gram, cols @ cols.T, atol=1e-11)


def test_the_span_solve_reaches_a_sculpt_in_its_span_on_a_smoothing_chain():
    """A sculpt made from smooth offsets in the span, through a chain that smooths 10 steps: the
    model with the chain's reach is its Jacobian on the span up to the region's border, so each
    call gains far more than with the blocks alone (reach 0), which take every field at full
    size."""
    rest, adjacency = _tube()
    steps = 10
    chain = _smoothing_chain(rest, adjacency, steps)
    region = np.arange(16 * 8, 16 * 32)
    basis, _ = smooth_bases(adjacency, region, 16, 64)
    offsets = basis[:, :12] @ np.random.default_rng(5).normal(scale=0.02, size=(12, 3))
    moved = rest.copy()
    moved[region] += offsets
    sculpt = chain(moved)
    base = chain(rest)
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    blocks = coupled.chain_blocks(chain, rest, base, region, diagonal, 0.0)
    freqs = smoothstart.frequencies(adjacency, region, basis)
    worst = {}
    for reach in (0.0, float(steps)):
        call = Counted(chain)
        gain = smoothstart.gains(freqs, reach)
        found = smoothstart.span_solve(call, rest, sculpt, region, basis, smoothstart.SpanModel(blocks, basis, gain),
                                       1e-9 * diagonal, smoothstart.ridge(blocks), 3, start_outputs=base[region],
                                       gram=smoothstart.model_gram(blocks, basis, gain))
        worst[reach] = float(np.linalg.norm(sculpt[region] - found.outputs, axis=1).max()) / diagonal
        assert found.calls == call.calls == 3
    # measured after 3 calls: 1.3e-7 against 5.7e-6 of the diagonal (after 6: 4.9e-9 against 4.3e-7)
    assert worst[float(steps)] < 1e-6 < worst[0.0] and worst[float(steps)] < 0.1 * worst[0.0], worst
