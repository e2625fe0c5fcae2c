"""The smooth fields the coupled inverse starts from (``psdbake.solver.smoothbasis``): the low end of a
sculpted region's graph-Laplacian spectrum, from the mesh's edges only."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import ROOT

from psdbake.normals import Topology
from psdbake.solver import smoothbasis
from psdbake.solver.smoothbasis import edge_adjacency, smooth_basis

sys.path.insert(0, ROOT)
from benchmarks import rigs


def _tube_adjacency(rings: int, segments: int) -> sp.csr_matrix:
    counts, indices = rigs.generate.tube_faces(rings, segments)
    return edge_adjacency(Topology(np.array(counts), np.array(indices), rings * segments))


def _dense_spectrum(adjacency: sp.csr_matrix, region: np.ndarray) -> np.ndarray:
    inner = adjacency[region][:, region].toarray()
    return np.linalg.eigvalsh(np.diag(inner.sum(axis=1)) - inner)


def test_edge_adjacency_of_a_quad_tube():
    adj = _tube_adjacency(5, 8)
    assert (adj != adj.T).nnz == 0 and adj.diagonal().sum() == 0
    degree = np.asarray(adj.sum(axis=1)).ravel()
    # a ring of 8 around the tube: 2 ring neighbours, plus 1 along the tube at the ends, 2 inside
    assert degree[:8].tolist() == [3] * 8 and degree[8:16].tolist() == [4] * 8


@pytest.mark.slow
@pytest.mark.parametrize("rings", [20, 70])  # 320 vertices: dense path; 1,120: ARPACK's
def test_the_basis_is_the_regions_smoothest_orthonormal_fields(rings):
    adj = _tube_adjacency(rings, 16)
    region = np.arange(16 * 2, 16 * (rings - 2))  # a band, free at its two borders
    assert (len(region) > smoothbasis.DENSE_BELOW) == (rings == 70)
    basis = smooth_basis(adj, region, 24)
    assert basis is not None and basis.shape == (len(region), 24)
    np.testing.assert_allclose(basis.T @ basis, np.eye(24), atol=1e-10)
    inner = adj[region][:, region]
    laplacian = sp.diags(np.asarray(inner.sum(axis=1)).ravel()) - inner
    rayleigh = np.einsum("ij,ij->j", basis, laplacian @ basis)
    # the Rayleigh quotients are the 24 lowest eigenvalues, in order (the span is the smoothest)
    np.testing.assert_allclose(rayleigh, _dense_spectrum(adj, region)[:24], atol=1e-9)
    # the first field is constant on a connected region (eigenvalue 0)
    np.testing.assert_allclose(np.abs(basis[:, 0]), 1 / np.sqrt(len(region)), rtol=1e-8)


def test_the_basis_is_deterministic():
    adj = _tube_adjacency(70, 16)
    region = np.arange(40, 1000)
    first, second = smooth_basis(adj, region, 32), smooth_basis(adj, region, 32)
    assert first is not None and second is not None and first.tobytes() == second.tobytes()


def test_a_region_without_edges_has_no_basis():
    adj = _tube_adjacency(10, 8)
    assert smooth_basis(adj, np.array([0, 2, 4, 6]), 8) is None  # every other vertex of one ring
    assert smooth_basis(adj, np.array([5]), 8) is None


def test_a_small_region_gets_at_most_one_field_fewer_than_its_vertices():
    adj = _tube_adjacency(10, 8)
    basis = smooth_basis(adj, np.arange(8), 64)
    assert basis is not None and basis.shape == (8, 7)


def test_when_arpack_fails_there_is_no_basis(monkeypatch):
    """ARPACK may not converge on some region: no smooth start then (the coupled inverse falls
    back as for a mesh without edges), not a failed fit."""
    from scipy.sparse.linalg import ArpackNoConvergence

    def fails(*args, **kwargs):
        raise ArpackNoConvergence("no convergence", np.zeros(0), np.zeros((0, 0)))

    monkeypatch.setattr(smoothbasis, "eigsh", fails)
    adj = _tube_adjacency(70, 16)
    assert smooth_basis(adj, np.arange(16 * 2, 16 * 68), 24) is None


def test_each_piece_of_a_region_gets_its_share_of_the_fields():
    """Two tubes in one mesh (a piece of 480 vertices and one of 160): each field lives on one
    piece, the pieces share the fields by size, each has its constant among the coarse ones."""
    big = _tube_adjacency(30, 16)
    small = _tube_adjacency(10, 16)
    adj = sp.block_diag([big, small], format="csr")
    region = np.arange(adj.shape[0])
    found = smoothbasis.smooth_bases(adj, region, 8, 32)
    assert found is not None
    basis, coarse = found
    np.testing.assert_allclose(basis.T @ basis, np.eye(basis.shape[1]), atol=1e-10)
    on_big = np.abs(basis[:480]).max(axis=0) > 0
    on_small = np.abs(basis[480:]).max(axis=0) > 0
    assert not np.any(on_big & on_small)  # no field straddles the pieces
    assert (on_big.sum(), on_small.sum()) == (24, 8) and (on_big[:coarse].sum(), on_small[:coarse].sum()) == (6, 2)
    for piece, columns in ((slice(0, 480), on_big[:coarse]), (slice(480, 640), on_small[:coarse])):
        constant = np.abs(basis[piece][:, :coarse][:, columns]).std(axis=0) < 1e-10
        assert constant.sum() == 1  # the piece's constant field is coarse


def test_basis_sizes_follow_the_region():
    """As many fields as keep the span's algebra cheap (b^2 k <= BASIS_WORK), at most
    MAX_FIELDS and one fewer than the region's vertices; the coarse basis a quarter."""
    assert smoothbasis.basis_sizes(100) == (24, 99)
    assert smoothbasis.basis_sizes(580) == (64, 256)  # the 1.3k bench rig's regions
    assert smoothbasis.basis_sizes(4600) == (38, 154)  # 13k
    assert smoothbasis.basis_sizes(34000) == (16, 56)  # 100k
    for k in (10, 300, 3000, 30000, 300000):
        coarse, fine = smoothbasis.basis_sizes(k)
        assert coarse <= fine <= min(k - 1, smoothbasis.MAX_FIELDS)
        assert fine**2 * k <= smoothbasis.BASIS_WORK
