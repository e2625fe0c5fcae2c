"""Is a sculpt's OBJ the posed mesh, sculpted? Topology, placement and what moved.

Topology: the sculpt must have the asset's vertex count and its very faces (same corner
counts, same vertex indices, in OBJ winding). When the face sizes agree but the indices do
not, a consistent renumbering is told apart ("vertices re-ordered": the application did not
keep the vertex order) from other changes; a face count or size that differs means the
faces were re-triangulated or changed.

Placement: a corrective sculpt moves a region; the measured fixtures' sculpts leave the
median vertex where skinning put it (at most 0.0022 of the bounding-box diagonal: the
arm, the character, the humanoid, CesiumMan). A median distance above ``FAR_RTOL`` (0.05 of
the diagonal, 20x that) means most of the mesh moved, which a sculpt does not do: it is
another mesh or pose, or the file was converted on export. Common conversions are tried
and named: other units (the ratios in ``UNITS``) and a 90-degree turn about X (Y-up vs
Z-up), each alone or together.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ... import tolerances as tol
from ...errors import InputError
from .faces import MeshFaces
from .read import ObjMesh

#: Median vertex distance (fraction of the posed mesh's bounding-box diagonal) above which a
#: sculpt is not near its posed mesh (see the module docstring for why 0.05).
FAR_RTOL = 0.05

#: Sculpt size / posed size ratios that are unit mix-ups, and their names (sculpt vs asset).
UNITS: tuple[tuple[float, str], ...] = (
    (100.0, "centimetres vs metres"), (0.01, "metres vs centimetres"),
    (1000.0, "millimetres vs metres"), (0.001, "metres vs millimetres"),
    (10.0, "millimetres vs centimetres"), (0.1, "centimetres vs millimetres"),
    (2.54, "centimetres vs inches"), (1 / 2.54, "inches vs centimetres"),
    (1 / 0.0254, "inches vs metres"), (0.0254, "metres vs inches"),
)

#: A +90 degree turn about X: Y-up -> Z-up ((x, y, z) -> (x, -z, y)), row-vector convention.
_RX90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def up_rotation(source: str, target: str) -> NDArray[np.float64]:
    """Row-vector matrix taking source-up coordinates to target-up ones (Y or Z)."""
    if source == target:
        return np.eye(3)
    return _RX90 if (source, target) == ("Y", "Z") else _RX90.T


def check_topology(obj: ObjMesh, faces: MeshFaces, label: str) -> None:
    """Refuse a sculpt whose vertices or faces are not the asset mesh's."""
    n = faces.point_count
    if len(obj.points) != n:
        raise InputError(f"{label}: {len(obj.points)} vertices, the asset's mesh has {n} (vertex count changed: "
                         "export the whole mesh, nothing added, deleted or merged)")
    if not np.array_equal(obj.counts, faces.counts):
        if obj.counts.size and np.all(obj.counts == 3) and not np.all(faces.counts == 3):
            raise InputError(f"{label}: faces re-triangulated: {_sizes(obj.counts)}, the asset's mesh has "
                             f"{_sizes(faces.counts)}; export the polygons as they are (no triangulation)")
        raise InputError(f"{label}: faces changed: {_sizes(obj.counts)}, the asset's mesh has {_sizes(faces.counts)}"
                         + _first_face_difference(obj.counts, faces.counts))
    if np.array_equal(obj.indices, faces.indices):
        return
    first = int(np.argmax(obj.indices != faces.indices))
    pairs = np.unique(np.stack([faces.indices, obj.indices], axis=1), axis=0)
    if len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1])):
        a, b = int(faces.indices[first]), int(obj.indices[first])
        raise InputError(f"{label}: vertices re-ordered: the faces are the asset's with the vertices renumbered (asset "
                         f"vertex {a + 1} is OBJ vertex {b + 1}); export keeping the vertex order")
    face = int(np.searchsorted(np.cumsum(faces.counts), first, side="right"))
    raise InputError(f"{label}: faces changed: face {face + 1} has other vertices than the asset's (first at corner "
                     f"{first + 1}: vertex {int(obj.indices[first]) + 1}, the asset's {int(faces.indices[first]) + 1})")


def _first_face_difference(obj: NDArray[np.int64], asset: NDArray[np.int64]) -> str:
    common = min(len(obj), len(asset))
    differ = np.nonzero(obj[:common] != asset[:common])[0]
    if not differ.size:
        return ""
    f = int(differ[0])
    return f" (face {f + 1} has {int(obj[f])} corners, the asset's {int(asset[f])})"


def _sizes(counts: NDArray[np.int64]) -> str:
    kinds = ", ".join(f"{int(c)} {'triangles' if k == 3 else 'quads' if k == 4 else f'{k}-gons'}"
                      for k, c in zip(*np.unique(counts, return_counts=True), strict=True))
    return f"{len(counts)} faces ({kinds or 'none'})"


def _median_distance(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    return float(np.median(np.linalg.norm(a - b, axis=1))) if len(a) else 0.0


def check_placement(sculpt: NDArray[np.float64], raw: NDArray[np.float64], posed: NDArray[np.float64], asset_up: str,
                    label: str, flags_given: bool = False, file_name: str = "") -> None:
    """Refuse a sculpt (after --scale/--up-axis) that is not near its posed mesh, naming the
    unit or up-axis conversion the raw OBJ points show when one explains them (and how to give
    it for this file alone, when ``file_name`` says which)."""
    diag = tol.bbox_diagonal(posed)
    far = _median_distance(sculpt, posed)
    if far <= FAR_RTOL * diag:
        return
    rel = f"{far / diag:.2g} of its diagonal" if diag else "the posed mesh is a point"
    where = f"{label}: not near the posed mesh (median vertex distance {far:.3g}, {rel})"
    found = explain(raw, posed, asset_up)
    if found == (1.0, "") and flags_given:
        raise InputError(f"{where}: the OBJ as written is near it: drop --scale and --up-axis")
    if found is not None and found != (1.0, ""):
        raise InputError(f"{where}: {_conversion(*found, asset_up, file_name)}")
    raise InputError(f"{where}; a sculpt moves a region, not the whole mesh: is it the right mesh and time code, or "
                     "was it moved, turned or scaled as a whole on export?")


def explain(raw: NDArray[np.float64], posed: NDArray[np.float64], asset_up: str) -> tuple[float, str] | None:
    """(factor, turn) such that the raw OBJ points are near factor x the posed points turned by
    ``turn`` ("": none, "Y"/"Z": exported with that up axis, "other": 90 degrees about X the
    other way), the closest such conversion; None when none brings it near."""
    other = "Z" if asset_up == "Y" else "Y"
    turns = {"": np.eye(3), other: up_rotation(asset_up, other), "other": up_rotation(other, asset_up)}
    diag = tol.bbox_diagonal(posed)
    best, found = FAR_RTOL * diag, None
    for name, turn in turns.items():
        for factor in (1.0, *(k for k, _ in UNITS)):
            d = _median_distance(raw, factor * (posed @ turn)) / factor  # in the posed mesh's units
            if d < best or (found is None and d == best):
                best, found = d, (factor, name)
    return found


def _conversion(factor: float, turn: str, asset_up: str, file_name: str = "") -> str:
    """What the raw OBJ looks like and the flags that undo it."""
    text = _conversion_flags(factor, turn, asset_up)
    if file_name and "use --" in text:
        alone = " ".join(f"{flag} {file_name}={value}" for flag, value in
                         zip(text.split("use ", 1)[1].split()[::2], text.split("use ", 1)[1].split()[1::2], strict=False))
        text += f" (for this file alone: {alone})"
    return text


def _conversion_flags(factor: float, turn: str, asset_up: str) -> str:
    units = next((name for k, name in UNITS if k == factor), "")
    scale = f"--scale {1 / factor:.4g}"
    if turn == "other":
        other = "Z" if asset_up == "Y" else "Y"
        return (f"it is turned 90 degrees about X, but the other way than a {asset_up}-up to {other}-up export (no "
                f"--up-axis undoes that): re-export it unturned" + (f", and use {scale}" if factor != 1.0 else ""))
    if turn and factor != 1.0:
        return f"exported {turn}-up and looks like {units} (scale {factor:.4g}x); use --up-axis {turn} {scale}"
    if turn:
        return f"exported {turn}-up; use --up-axis {turn}"
    return f"looks like {units}: scale {factor:.4g}x; use {scale}"


def displacement(sculpt: NDArray[np.float64], posed: NDArray[np.float64]) -> tuple[int, float, float, float]:
    """(vertices moved, largest distance, mean distance of the moved ones, diagonal): moved is
    farther than fit's unmoved tolerance (``UNMOVED_RTOL`` of the diagonal, at least 16 float32
    ulps), so the count is the vertices fit will give a corrective."""
    diag = tol.bbox_diagonal(posed)
    d = np.linalg.norm(sculpt - posed, axis=1)
    moved = d > max(tol.UNMOVED_RTOL * diag, tol.float32_floor(np.concatenate([posed, sculpt])))
    return int(moved.sum()), float(d.max(initial=0.0)), float(d[moved].mean()) if moved.any() else 0.0, diag
