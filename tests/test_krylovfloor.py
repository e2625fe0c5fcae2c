"""The floor benchmark's arithmetic (``benchmarks.krylovfloor``): the GMRES count it reports for
the real characters is only a floor if it is GMRES's true count, so it is checked on Jacobians
whose count is known."""

from __future__ import annotations

import sys

import numpy as np
from conftest import ROOT

sys.path.insert(0, ROOT)
from benchmarks import krylovfloor


def _blocks_times(blocks: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """The Jacobian ``inner`` with each vertex's 3x3 block applied after it, (3k, 3k)."""
    k = len(blocks)
    full = np.zeros((3 * k, 3 * k))
    for i in range(k):
        full[3 * i:3 * i + 3, 3 * i:3 * i + 3] = blocks[i]
    return full @ inner


def test_a_jacobian_with_m_distinct_preconditioned_eigenvalues_takes_m_products():
    """GMRES ends in as many products as the preconditioned Jacobian has distinct eigenvalues
    that the right-hand side touches, and not before: 4 here, with random 3x3 blocks in front."""
    rng = np.random.default_rng(5)
    k = 40
    blocks = np.eye(3) + 0.3 * rng.standard_normal((k, 3, 3))
    q = np.linalg.qr(rng.standard_normal((3 * k, 3 * k)))[0]
    eigen = np.repeat([1.0, 0.5, 0.1, 0.01], 3 * k // 4)
    inner = q @ np.diag(eigen) @ q.T  # J = B S, S symmetric with 4 distinct eigenvalues
    jac = _blocks_times(blocks, inner)
    b = jac @ rng.standard_normal(3 * k)
    atol = 1e-9 * float(np.linalg.norm(b))
    assert krylovfloor.gmres_products(jac, np.linalg.inv(blocks), b, atol) == 4


def test_the_blocks_are_therow_sums_the_solver_measures():
    """The blocks the floor preconditions with are the chain's response to moving every vertex
    along one axis: the row sums of the Jacobian's 3x3 tiles, as the solver's 3 calls give."""
    rng = np.random.default_rng(6)
    k = 7
    jac = rng.standard_normal((3 * k, 3 * k))
    blocks = krylovfloor.row_sums(jac, k)
    for axis in range(3):
        move = np.zeros((k, 3))
        move[:, axis] = 1.0
        np.testing.assert_allclose(blocks[:, :, axis], (jac @ move.ravel()).reshape(k, 3), rtol=1e-12, atol=1e-12)
