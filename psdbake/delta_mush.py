"""A reference Delta Mush deformer: ``--deformer psdbake.delta_mush:delta_mush``.

Delta Mush (Mancewicz, Derksen, Rijpkema, Wilson: "Delta Mush: smoothing deformations while
preserving detail", DigiPro 2014), in its standard form:

* bind: smooth the REST mesh ``iterations`` times with uniform (umbrella) Laplacian steps
  ``p <- p + step * (mean of the edge neighbours - p)``, and store each vertex's delta
  ``rest_v - smooth(rest)_v`` in a tangent frame of the smoothed rest mesh (normal: the
  area-weighted normal of the adjacent faces; tangent: the edge to the vertex's first
  neighbour, lowest index, projected off the normal; bitangent: normal x tangent);
* deform: smooth the posed mesh the same way, rebuild the frames on it and add the stored
  deltas in those frames.

The rest mesh is the mesh's authored points (mesh local space, default time) and its faces'
edges; the deformer runs after skinning, in mesh local space (``psdbake.deformers``). An
identity pose (posed == rest) returns rest to float64 round-off. Every output vertex depends
on its ``iterations``-ring of input vertices: the deformer couples vertices, and ``fit``
detects that and uses its coupled inverse (``psdbake.solver.coupled``).

Parameters: ``delta_mush`` uses 10 iterations and step 0.5. For others, a file of your own::

    # my_mush.py, used as --deformer my_mush.py:mush
    from psdbake.delta_mush import make
    mush = make(iterations=20, step=0.3)

Vertices on no face are left where the skinning put them (no neighbours, zero delta); a
degenerate frame (no area or a zero-length tangent) falls back to the world axes.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from .arrays import Points
from .deformers import DeformerFactory, PointFn
from .normals import Topology, vertex_normals
from .solver.smoothbasis import edge_adjacency

DEFAULT_ITERATIONS = 10
DEFAULT_STEP = 0.5


class DeltaMush:
    """The deformer for one rest mesh: ``DeltaMush(rest, topology)(posed) -> deformed``."""

    def __init__(self, rest: Points, topology: Topology, iterations: int = DEFAULT_ITERATIONS,
                 step: float = DEFAULT_STEP) -> None:
        if iterations < 0 or not 0.0 < step <= 1.0:
            raise ValueError(f"delta mush: iterations {iterations} must be >= 0 and step {step} in (0, 1]")
        rest = np.asarray(rest, dtype=np.float64)
        if rest.shape != (topology.point_count, 3):
            raise ValueError(f"delta mush: {rest.shape[0]} points for a topology of {topology.point_count}")
        self.topology, self.iterations = topology, int(iterations)
        adj = edge_adjacency(topology)
        degree = np.asarray(adj.sum(axis=1)).ravel()
        lonely = degree == 0
        inv = np.divide(step, degree, out=np.zeros_like(degree), where=~lonely)
        keep = np.where(lonely, 1.0, 1.0 - step)
        #: one smoothing step as a sparse matrix: (1 - step) I + step D^-1 A (identity rows for lonely points)
        self.smoother = (sp.diags(keep) + sp.diags(inv) @ adj).tocsr()
        has = ~lonely
        first = np.zeros(len(degree), dtype=np.int64)
        first[has] = adj.indices[adj.indptr[:-1][has]]  # lowest-index neighbour
        self._first, self._has = first, has
        smooth = self.smooth(rest)
        t, b, nrm = self.frames(smooth)
        d = rest - smooth
        #: the rest deltas in the smoothed rest frames (n, 3): tangent, bitangent, normal components
        self.deltas = np.stack([_dot(d, t), _dot(d, b), _dot(d, nrm)], axis=1)

    def smooth(self, points: Points) -> Points:
        p = np.asarray(points, dtype=np.float64)
        for _ in range(self.iterations):
            p = self.smoother @ p
        return p

    def frames(self, smooth: Points) -> tuple[Points, Points, Points]:
        """Orthonormal (tangent, bitangent, normal) per vertex; world axes where degenerate."""
        nrm = vertex_normals(smooth, self.topology)
        edge = smooth[self._first] - smooth
        t = edge - _dot(edge, nrm)[:, None] * nrm
        length = np.sqrt(_dot(t, t))
        ok = self._has & (_dot(nrm, nrm) > 0.5) & (length > 0)
        if not np.all(np.isfinite(length)):
            ok &= np.isfinite(length)
        t = np.divide(t, length[:, None], out=np.zeros_like(t), where=ok[:, None])
        b = np.cross(nrm, t)
        if not ok.all():
            t[~ok], b[~ok], nrm[~ok] = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
        return t, b, nrm

    def __call__(self, posed: Points) -> Points:
        smooth = self.smooth(posed)
        t, b, nrm = self.frames(smooth)
        c = self.deltas
        return smooth + c[:, 0:1] * t + c[:, 1:2] * b + c[:, 2:3] * nrm


def _dot(a: Points, b: Points) -> NDArray[np.float64]:
    return np.einsum("ij,ij->i", a, b)


def make(iterations: int = DEFAULT_ITERATIONS, step: float = DEFAULT_STEP) -> DeformerFactory:
    """A ``--deformer`` factory for Delta Mush with these parameters."""
    if iterations < 0 or not 0.0 < step <= 1.0:
        raise ValueError(f"delta mush: iterations {iterations} must be >= 0 and step {step} in (0, 1]")

    def factory(stage: Any, mesh_path: str, time: float) -> PointFn:
        from .usd.meshrest import rest_mesh  # pxr lives under psdbake/usd only

        rest, topology = rest_mesh(stage, mesh_path)
        return DeltaMush(rest, topology, iterations, step)

    factory.__doc__ = f"Delta Mush, {iterations} iterations of step {step:g} (psdbake.delta_mush)."
    return factory


#: ``--deformer psdbake.delta_mush:delta_mush``: 10 iterations, step 0.5.
delta_mush = make()
