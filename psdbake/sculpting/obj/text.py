"""One posed mesh as OBJ text: ``v`` lines that read back bit-exactly, the asset's faces.

Why '%.9g': nine significant digits identify every float32 (USD stores points as float32),
and the decimal they give lies within 5e-9 (relative) of the value while the next float32
is at least 3e-8 away, so any reader that parses to double, or a little worse, and rounds to
float32 gets the very bits back (tests/test_obj.py checks 10^5 random values across every
binade). A sculpt application that keeps the vertex order writes the same ``v`` lines back,
moved where the artist moved them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .faces import MeshFaces


def _numbers(rows: NDArray[np.float32], tag: str) -> list[str]:
    fmt = f"{tag}" + " %.9g" * rows.shape[1]
    return [fmt % tuple(row) for row in np.asarray(rows, dtype=np.float32).astype(np.float64).tolist()]


def obj_text(points: NDArray[np.float32], faces: MeshFaces, name: str, comments: Sequence[str] = ()) -> str:
    """The OBJ file of one posed mesh: comments, ``o name``, ``v`` per point (the mesh's own
    order), ``vt`` when the mesh has UVs, then ``f`` per face with 1-based indices."""
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    lines = [f"# {c}" for c in comments]
    lines.append(f"o {name}")
    lines += _numbers(points, "v")
    uv = faces.uv_indices if faces.uvs is not None else None
    if faces.uvs is not None:
        lines += _numbers(faces.uvs, "vt")
    starts = np.concatenate([[0], np.cumsum(faces.counts)]).tolist()
    corners = (faces.indices + 1).tolist()
    uv_corners = (uv + 1).tolist() if uv is not None else None
    for f in range(faces.face_count):
        lo, hi = starts[f], starts[f + 1]
        if uv_corners is None:
            lines.append("f " + " ".join(str(v) for v in corners[lo:hi]))
        else:
            lines.append("f " + " ".join(f"{v}/{t}" for v, t in zip(corners[lo:hi], uv_corners[lo:hi], strict=True)))
    return "\n".join(lines) + "\n"
