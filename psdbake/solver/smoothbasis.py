"""The smoothest offsets a sculpted region can take: the coupled inverse's way into the right basin.

Where skinning folds the mesh, a chain that smooths (Delta Mush) leaves the inverse extremely
ill-conditioned: half the offset space barely moves the output (measured on the 1.3k bench rig at
a 100-degree elbow: 879 of 1,761 singular values of the chain's Jacobian below 1e-3 of the
largest). Newton from zero then follows large high-frequency offsets into a spurious minimum
(14-100x above the tolerance, even with the exact Jacobian), while the sculpt's own rest-space
offset is smooth. Restricting the first Gauss-Newton steps to smooth offsets lands next to it:
``coupled.smooth_start`` solves in the span of this basis, Newton-Krylov finishes.

The basis is the low end of the region's graph-Laplacian spectrum (the mesh's own "manifold
harmonics", Vallet and Levy, Computer Graphics Forum 2008), from the mesh's edges only: no
look inside the chain. ARPACK finds it in shift-invert mode (``scipy.sparse.linalg.eigsh``):
64 fields in 0.13 s on a 4.6k-vertex region, 1.7 s on a grid of 35k (the 100k bench rig's
sculpted regions are 34k: about half of a coupled example's 3.1 s there, and more than its
19 calls of the Delta Mush chain), 6.6 s on 100k, 32 s on 340k. Should ARPACK fail, there is
no smooth start (``coupled`` falls back as for a mesh without edges).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import ArpackError, eigsh

from ..normals import Topology

#: Shift below the region's Laplacian spectrum for ARPACK's shift-invert mode, in units of its
#: mean vertex degree (the constant field has eigenvalue 0).
SHIFT = 1e-3
#: Regions up to this many vertices take a dense eigendecomposition (ARPACK needs b < k and
#: gains nothing on small matrices).
DENSE_BELOW = 800


def edge_adjacency(topology: Topology) -> sp.csr_matrix:
    """Symmetric 0/1 adjacency (n, n) of the polygons' edges (consecutive corners)."""
    counts, corners = topology.face_vertex_counts, topology.face_vertex_indices
    starts = np.cumsum(counts) - counts
    position = np.arange(corners.size) - np.repeat(starts, counts)
    following = np.where(position + 1 < np.repeat(counts, counts), np.arange(corners.size) + 1,
                         np.repeat(starts, counts))
    a, b = corners, corners[following]
    n = topology.point_count
    adj = sp.coo_matrix((np.ones(2 * a.size), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(n, n)).tocsr()
    adj.setdiag(0)
    adj.eliminate_zeros()
    adj.data[:] = 1.0
    adj.sort_indices()
    return adj


def smooth_basis(adjacency: sp.csr_matrix, region: NDArray[np.int64], count: int) -> NDArray[np.float64] | None:
    """Orthonormal columns (len(region), b <= count): the ``count`` smoothest fields on the
    region's own edges (eigenvectors of its graph Laplacian, free at its border), smoothest
    first; None when the region has no edge (nothing to be smooth along)."""
    region = np.asarray(region, dtype=np.int64)
    k = len(region)
    inner = adjacency[region][:, region].tocsr()
    if inner.nnz == 0 or k < 2:
        return None
    degree = np.asarray(inner.sum(axis=1)).ravel()
    laplacian = (sp.diags(degree) - inner).tocsc()
    shift = SHIFT * max(float(degree.mean()), 1.0)
    b = min(int(count), k - 1)
    if k <= DENSE_BELOW:
        values, vectors = np.linalg.eigh(laplacian.toarray())
        return np.asarray(vectors[:, :b], dtype=np.float64)
    # a fixed start vector (no random numbers: every run gives the same basis), not the
    # constant field, which is an exact eigenvector of the Laplacian
    start = 1.0 + 0.5 * np.sin(np.arange(1, k + 1, dtype=np.float64) * 0.6180339887498949)
    try:
        values, vectors = eigsh(laplacian, k=b, sigma=-shift, which="LM", v0=start)
    except (ArpackError, RuntimeError):  # ArpackNoConvergence is an ArpackError; SuperLU raises RuntimeError
        return None
    return np.asarray(vectors[:, np.argsort(values, kind="stable")], dtype=np.float64)
