"""The smoothest offsets a sculpted region can take: the coupled inverse's way into the right basin.

Where skinning folds the mesh, a chain that smooths (Delta Mush) leaves the inverse extremely
ill-conditioned: half the offset space barely moves the output (the 1.3k bench rig's tube is
bipartite, and half the singular values of the chain's Jacobian are below 1e-3 of the largest,
at any pose). A solve that follows large high-frequency offsets lands in a spurious minimum,
while the sculpt's own rest-space offset is smooth. Restricting the first steps to smooth
offsets lands next to it: ``coupled.smooth_start`` solves in the span of these bases
(``psdbake.smoothstart``), Newton-Krylov finishes.

The fields are the low end of the region's graph-Laplacian spectrum (the mesh's own "manifold
harmonics", Vallet and Levy, Computer Graphics Forum 2008), from the mesh's edges only: no
look inside the chain. ARPACK finds them in shift-invert mode (``scipy.sparse.linalg.eigsh``,
with SuperLU's minimum-degree ordering for the shifted Laplacian, and eigenvalues to
``EIGEN_TOL``); on the 100k bench rig's 34k-vertex regions its 57 fields take 145 shifted
solves, about 45% of a coupled example's time (profiled: 2.0 of 4.5 s). ``basis_sizes``
sizes the bases to the region, ``smooth_bases`` shares them among the region's connected
pieces. Should ARPACK fail, there is no smooth start (``coupled`` falls back as for a mesh
without edges).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import ArpackError, LinearOperator, eigsh, splu

from ..normals import Topology

#: Shift below the region's Laplacian spectrum for ARPACK's shift-invert mode, in units of its
#: mean vertex degree (the constant field has eigenvalue 0).
SHIFT = 1e-3
#: Regions up to this many vertices take a dense eigendecomposition (ARPACK needs b < k and
#: gains nothing on small matrices).
DENSE_BELOW = 800
#: Most fields in a fine basis, fewest in a coarse one (``basis_sizes``).
MAX_FIELDS = 256
MIN_FIELDS = 16
#: Fields b for a region of k vertices keep b^2 k under this (``basis_sizes``).
BASIS_WORK = 1.1e8
#: ARPACK's relative accuracy of the fields' eigenvalues. The smooth start needs the fields'
#: span, not eigenvalues to machine precision: on the 100k bench rig's 34k-vertex region
#: (57 fields) 1e-8 takes 145 solves against 174 at eigsh's default (machine precision), and
#: the span is the same to 1e-12 (cosine of the largest principal angle; 1e-3 as well).
EIGEN_TOL = 1e-8


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
    return _fields(inner, min(int(count), k - 1))


def smooth_bases(adjacency: sp.csr_matrix, region: NDArray[np.int64], coarse: int,
                 fine: int) -> tuple[NDArray[np.float64], int] | None:
    """The smooth start's bases, (columns (len(region), b), c): orthonormal fields, the first
    c of them the coarse basis, all b the fine one. Each connected piece of the region gets its
    share of ``coarse`` and ``fine`` by its vertex count (its constant field at least): a chain
    that smooths along edges moves no piece from another, and a real character's pieces (UV
    shells, parts) are many (CesiumMan's region: 136), so the region's smoothest fields would
    be little but one constant per piece. None when the region has no edge."""
    region = np.asarray(region, dtype=np.int64)
    k = len(region)
    inner = adjacency[region][:, region].tocsr()
    if inner.nnz == 0 or k < 2:
        return None
    pieces, label = connected_components(inner, directed=False)
    first: list[NDArray[np.float64]] = []
    rest: list[NDArray[np.float64]] = []
    for piece in range(pieces):
        members = np.nonzero(label == piece)[0]
        share = len(members) / k
        wanted = max(1, min(len(members), round(fine * share)))
        head = max(1, min(wanted, round(coarse * share)))
        fields = np.ones((1, 1)) if len(members) == 1 else _fields(inner[members][:, members].tocsr(), wanted)
        if fields is None:
            return None
        fields = fields / np.linalg.norm(fields, axis=0)
        for target, part in ((first, fields[:, :head]), (rest, fields[:, head:])):
            if part.shape[1]:
                column = np.zeros((k, part.shape[1]))
                column[members] = part
                target.append(column)
    coarse_part = np.concatenate(first, axis=1)
    columns = np.concatenate(first + rest, axis=1)
    return np.asarray(columns, dtype=np.float64), coarse_part.shape[1]


def _fields(inner: sp.csr_matrix, b: int) -> NDArray[np.float64] | None:
    """The b smoothest eigenvectors of the graph Laplacian of ``inner`` (a region's own edges),
    smoothest first: dense for small regions, else ARPACK in shift-invert mode; None if it fails."""
    k = inner.shape[0]
    degree = np.asarray(inner.sum(axis=1)).ravel()
    laplacian = (sp.diags(degree) - inner).tocsc()
    shift = SHIFT * max(float(degree.mean()), 1.0)
    if k <= DENSE_BELOW or b >= k - 1:
        values, vectors = np.linalg.eigh(laplacian.toarray())
        return np.asarray(vectors[:, :b], dtype=np.float64)
    # a fixed start vector (no random numbers: every run gives the same basis), not the
    # constant field, which is an exact eigenvector of the Laplacian
    start = 1.0 + 0.5 * np.sin(np.arange(1, k + 1, dtype=np.float64) * 0.6180339887498949)
    try:
        # shift-invert by our own LU: SuperLU's minimum-degree ordering on the symmetric pattern
        # fills a mesh Laplacian a third less than eigsh's default (COLAMD) and halves each of
        # ARPACK's ~3b solves (100k bench region, 34k vertices: 3.4 against 6.4 ms a solve)
        lu = splu((laplacian + shift * sp.identity(k, format="csc")).tocsc(), permc_spec="MMD_AT_PLUS_A")
        inverse = LinearOperator((k, k), matvec=lu.solve, dtype=np.float64)
        values, vectors = eigsh(laplacian, k=b, sigma=-shift, which="LM", v0=start, OPinv=inverse, tol=EIGEN_TOL)
    except (ArpackError, RuntimeError):  # ArpackNoConvergence is an ArpackError; SuperLU raises RuntimeError
        return None
    return np.asarray(vectors[:, np.argsort(values, kind="stable")], dtype=np.float64)


def basis_sizes(region: int) -> tuple[int, int]:
    """(coarse, fine) field counts for a region of ``region`` vertices: the fine basis is as
    large as ``BASIS_WORK`` allows (the span solve's Gram matrix costs ~18 b^2 k flops, kept
    under ~2e9), at most ``MAX_FIELDS`` and one fewer than the region's vertices; the coarse
    one is its smoothest quarter, at least ``MIN_FIELDS``."""
    fine = int(min(MAX_FIELDS, max(region - 1, 1), np.sqrt(BASIS_WORK / max(region, 1))))
    return max(min(MIN_FIELDS, fine), fine // 4), fine
