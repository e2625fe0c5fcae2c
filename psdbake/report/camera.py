"""One orthographic camera for every view of the report: pure numpy, no matplotlib.

Points are row vectors in matplotlib's z-up plot frame (``plot_space``). The camera looks
from a little above, around the up axis, from the direction that sees most corrected
surface: faces facing the camera and not hidden behind others (a coarse screen-grid depth
test, ``visible``), weighted by their area and their correction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Vector = NDArray[np.float64]  # (3,)

_TO_Z_UP = {"Z": np.eye(3), "Y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])}  # row vectors: (x,y,z)->(x,-z,y)


def plot_space(points: NDArray[np.float64], to_world: NDArray[np.float64], up: str) -> NDArray[np.float64]:
    """Mesh-local points -> world -> matplotlib's z-up frame (row vectors)."""
    return (points @ to_world[:3, :3] + to_world[3, :3]) @ _TO_Z_UP[up]


@dataclass(frozen=True)
class Camera:
    """Where the views look from (degrees, matplotlib's elev/azim) and what they frame."""

    elev: float
    azim: float
    centre: NDArray[np.float64]  # what the view is centred on (plot space)
    half_width: float  # half the visible extent along the screen's right and up directions
    half_height: float

    def axes(self) -> tuple[Vector, Vector, Vector]:
        """(toward the camera, screen right, screen up), matplotlib's convention (roll 0)."""
        e, a = math.radians(self.elev), math.radians(self.azim)
        toward = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        right = np.array([-math.sin(a), math.cos(a), 0.0])
        up = np.array([-math.sin(e) * math.cos(a), -math.sin(e) * math.sin(a), math.cos(e)])
        return toward, right, up


def face_normals(poly: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normals (right-handed winding) and areas of triangles (F, 3, 3)."""
    cross = np.cross(poly[:, 1] - poly[:, 0], poly[:, 2] - poly[:, 0])
    area = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(area, 1e-30)[:, None], area / 2


def visible(centroids: NDArray[np.float64], toward: Vector, right: Vector, up: Vector, cell: float) -> NDArray[np.bool_]:
    """Faces not hidden behind others from this direction, on a coarse screen grid (cell:
    about two faces wide): a face is visible when its centroid is among the nearest to the
    camera in its grid cell."""
    a, b, depth = centroids @ right, centroids @ up, centroids @ toward
    ia = np.floor((a - a.min()) / cell).astype(np.int64)
    key = ia * (int(np.floor(np.ptp(b) / cell)) + 2) + np.floor((b - b.min()) / cell).astype(np.int64)
    order = np.argsort(key, kind="stable")
    _, start = np.unique(key[order], return_index=True)
    nearest = np.maximum.reduceat(depth[order], start)
    front = np.empty_like(depth)
    front[order] = np.repeat(nearest, np.diff(np.append(start, len(order))))
    return depth >= front - cell


def choose_camera(clouds: Sequence[NDArray[np.float64]], corrections: Sequence[NDArray[np.float64]],
                  tris: NDArray[np.int64], handed: float) -> Camera:
    """One camera for every panel and view: among views from a little above, around the
    up axis, the one that sees most corrected surface (unoccluded area facing the camera,
    weighted by the correction) while the mesh shows its broad side; then framed to the
    posed meshes' extent on screen."""
    pts = np.concatenate(clouds)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    faces = [(*face_normals(cloud[tris]), cloud[tris].mean(axis=1), mag[tris].mean(axis=1))
             for cloud, mag in zip(clouds, corrections, strict=True)] if len(tris) else []
    best: tuple[float, Camera] | None = None
    for elev in (12.0, 28.0):
        for azim in range(-180, 180, 10):
            cam = Camera(elev, float(azim), centre, 1.0, 1.0)
            score = _score(cam, pts, faces, handed)
            if best is None or score > best[0] * (1 + 1e-9):
                best = (score, cam)
    assert best is not None
    cam = best[1]
    _, right, up = cam.axes()
    a, b = (pts - centre) @ right, (pts - centre) @ up
    shift = right * (a.max() + a.min()) / 2 + up * (b.max() + b.min()) / 2
    return Camera(cam.elev, cam.azim, centre + shift, float(np.ptp(a)) / 2 or 1.0, float(np.ptp(b)) / 2 or 1.0)


def _score(cam: Camera, pts: NDArray[np.float64], faces: Sequence[tuple[NDArray[np.float64], ...]], handed: float
           ) -> float:
    """Corrected surface seen from cam (or 1 when none is), times the root of the mesh's
    on-screen breadth, so a side view of a thin limb loses to its broad side."""
    toward, right, up = cam.axes()
    rel = pts - cam.centre
    breadth = float(np.ptp(rel @ right) * np.ptp(rel @ up))
    seen = 0.0
    for normals, area, centroids, mag in faces:
        facing = np.clip(handed * normals @ toward, 0.0, None)
        cell = 2.0 * math.sqrt(2.0 * float(np.median(area)))
        seen += float(np.sum((area * mag * facing)[visible(centroids, toward, right, up, cell)]))
    return (seen if seen > 0 else 1.0) * math.sqrt(breadth)
