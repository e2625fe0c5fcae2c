"""A sculpted OBJ file -> its vertices (file order, float32) and faces, read by tinyobjloader.

Why tinyobjloader (pip ``tinyobjloader``, the official binding of syoyo's loader): it keeps
the ``v`` order (``attrib.vertices``) and, with ``triangulate = False``, every polygon as
written (``num_face_vertices``, ``vertex_indices``), resolves negative indices and accepts
vertex colours. meshio 5.3.5 refuses an OBJ whose ``vt`` count differs from its ``v`` count
(every mesh with a UV seam), and trimesh triangulates polygons, so neither can check a
sculpt's topology.

Two things of tinyobjloader 2.0.0rc13 this module works around, both measured: its numpy
accessors (``numpy_vertices``, ``numpy_num_face_vertices``) return zeros or wrong values,
so the list accessors are used; and it reads a coordinate it cannot parse (``nan``, ``inf``,
a typo) as 0 without a word, so every ``v`` line's three numbers are checked against what
it read: a sculpt is never silently flattened to 0.
"""

from __future__ import annotations

import math
import os
import re
import stat
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError

_LINES = re.compile(rb"\r\n|\r|\n")  # tinyobjloader's safeGetline: LF, CRLF or CR
#: Numbers from here on round to inf in float32: the largest float32 plus half its ulp (2^103).
_FLOAT32_LIMIT = float(np.finfo(np.float32).max) + 2.0**103


@dataclass(frozen=True)
class ObjMesh:
    """What a sculpt's OBJ holds, as psdbake compares it with the asset."""

    points: NDArray[np.float32]  # (n, 3), ``v`` lines in file order
    counts: NDArray[np.int64]  # corners per face, file order (every object of the file)
    indices: NDArray[np.int64]  # 0-based ``v`` index per corner


def read_obj(path: str, label: str) -> ObjMesh:
    """Read path (an OBJ) or raise InputError starting with label (the file, mesh and time)."""
    _require_file(path, label)
    import tinyobjloader  # loads only for psdbake sculpts

    reader, config = tinyobjloader.ObjReader(), tinyobjloader.ObjReaderConfig()
    config.triangulate = False  # faces as written: a re-triangulated sculpt must be seen
    if not reader.ParseFromFile(path, config):
        why = " ".join((reader.Error() or "unknown error").split())
        raise InputError(f"{label}: not a readable OBJ file (tinyobjloader: {why})")
    flat = np.array(reader.GetAttrib().vertices, dtype=np.float64)
    with np.errstate(over="ignore"):  # a coordinate past float32's range: the check below names it
        points = flat.astype(np.float32).reshape(-1, 3)
    _check_coordinates(path, label, points)
    counts: list[int] = []
    indices: list[int] = []
    for shape in reader.GetShapes():  # one per ``o``/``g``, in file order
        counts += list(shape.mesh.num_face_vertices)
        indices += list(shape.mesh.vertex_indices())
    return ObjMesh(points, np.array(counts, dtype=np.int64), np.array(indices, dtype=np.int64))


def _require_file(path: str, label: str) -> None:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{label}: missing (listed in manifest.json; was it renamed or not saved?)") from None
    except OSError as exc:
        raise InputError(f"{label}: cannot be read ({exc.strerror or exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{label}: is a folder, not an OBJ file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{label}: is not a regular file (a FIFO or device is never read)")
    if not os.access(path, os.R_OK):
        raise InputError(f"{label}: file is not readable (permission denied)")


def _check_coordinates(path: str, label: str, points: NDArray[np.float32]) -> None:
    """Each ``v`` line's first three numbers must read as the finite float32 values
    tinyobjloader returned (it turns what it cannot parse into 0)."""
    with open(path, "rb") as fh:
        data = fh.read()
    k = 0
    for number, raw in enumerate(_LINES.split(data), 1):
        line = raw.lstrip(b" \t")
        if not (line[:1] == b"v" and line[1:2] in (b" ", b"\t")):
            continue
        tokens = line[2:].split()
        if len(tokens) < 3:
            raise InputError(f"{label}: line {number}: a v line needs three coordinates, found {len(tokens)}")
        if k >= len(points):
            raise InputError(f"{label}: line {number}: more v lines than tinyobjloader read ({len(points)})")
        for axis, token in enumerate(tokens[:3]):
            text = token.decode("latin-1")
            try:
                value = float(text)
            except ValueError:
                raise InputError(f"{label}: line {number}: coordinate {text!r} is not a number") from None
            if not math.isfinite(value):
                raise InputError(f"{label}: line {number}: coordinate {text!r} is not finite")
            if abs(value) >= _FLOAT32_LIMIT:
                raise InputError(f"{label}: line {number}: coordinate {text!r} is beyond float32's range")
            if np.float32(value) != points[k, axis]:
                raise InputError(f"{label}: line {number}: coordinate {text!r} reads as {float(points[k, axis])!r} "
                                 "(tinyobjloader): write plain decimal numbers")
        k += 1
    if k != len(points):
        raise InputError(f"{label}: tinyobjloader read {len(points)} vertices from {k} v lines")
