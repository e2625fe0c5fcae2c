"""``psdbake compare``'s report: SSD vs forward PSD vs inverse PSD, as files a person reads.

``write_report(comparison, out_dir)`` turns a ``Comparison`` into a folder:

- ``index.html``   self-contained page (inline CSS, no scripts, no network), figures by relative name
- ``correction_angle.png``  the paper's Figure 3 analysis: how far a vertex's correction vector
  has turned, forward vs inverse, against the turn of the bone that carries the vertex
- ``views_<frame>.png``     the mesh at chosen frames, SSD / forward / inverse side by side,
  coloured by the correction magnitude, plus where forward and inverse disagree
- ``stats.csv``, ``stats.json``  per-frame statistics (``stats.json`` also carries the
  series behind ``correction_angle.png`` under ``vertex_turn``)

Every file is written atomically (``atomic.replacing``); ``stats.json`` goes first and is the
marker that a folder was written by ``psdbake compare``: a non-empty folder without it is
refused, a folder with it is updated in place (files the previous report listed and this one
does not write are removed at the end).

All matplotlib code lives here and matplotlib is imported lazily (the ``report`` extra), with
the Agg canvas on standalone ``Figure`` objects: pyplot's global state is never touched.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import __version__, atomic
from .compare import Comparison, MeshComparison, correction_turn, most_corrected_vertex
from .errors import InputError, OutputError, PsdError

#: Files psdbake compare writes (and may therefore replace or remove in a report folder).
_OURS = re.compile(r"^(index\.html|stats\.csv|stats\.json|correction_angle\.png|views_[-+.0-9a-z]+\.png)$")
MARKER = "stats.json"
#: Frames whose correction is below this fraction of the vertex's largest are not drawn in
#: the angle figure: a vanishing vector has no meaningful direction (float32 noise).
FAINT = 0.02


class ReportError(PsdError):
    """The report cannot be drawn (matplotlib missing)."""

    exit_code = 1


# --- inputs ------------------------------------------------------------------------------

def parse_views(text: str | None) -> tuple[float, ...] | None:
    """'12,30,41' -> (12.0, 30.0, 41.0)."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(f"--views {text!r}: expected frames separated by commas (e.g. 12,30,41)")
    return values


def _previous_files(path: str) -> list[str] | None:
    """Files listed by a previous report in path (None when path holds no psdbake report)."""
    try:
        with open(os.path.join(path, MARKER), encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("command") != "compare" or "psdbake" not in data:
        return None
    return [f for f in data.get("files", []) if isinstance(f, str) and _OURS.match(f)]


def check_report_dir(path: str, inputs: Iterable[str] = ()) -> None:
    """Refuse a REPORT_DIR that cannot be written, is a file, or holds someone else's files."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputError(f"{path}: exists and is not a folder (REPORT_DIR is a folder psdbake compare fills)")
    if os.path.isdir(path):
        if os.listdir(path) and _previous_files(path) is None:
            raise OutputError(f"{path}: folder is not empty and was not written by psdbake compare; give a new or empty folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputError(f"{path}: folder is not writable")
        real = os.path.realpath(path)
        for src in inputs:
            if src and os.path.dirname(os.path.realpath(src)) == real and _OURS.match(os.path.basename(src)):
                raise OutputError(f"{path}: would overwrite the input {src}")
        return
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: cannot create the folder ({parent} is not a writable folder)")


# --- numbers -----------------------------------------------------------------------------

MINUS = "\u2212"  # typographic minus, for figures and the page
METRICS = (
    ("forward_ssd", "|forward \u2212 SSD|"),
    ("inverse_ssd", "|inverse \u2212 SSD|"),
    ("inverse_forward", "|inverse \u2212 forward|"),
)


def frame_stats(m: MeshComparison) -> dict[str, NDArray[np.float64]]:
    """Per frame: max and mean distance between the three results. Means are over the
    vertices that have a corrective (every vertex when none has); ``*_rel`` divide by the
    bounding-box diagonal."""
    cols = m.corrected if len(m.corrected) else np.arange(m.ssd.shape[1])
    pairs = {"forward_ssd": (m.forward, m.ssd), "inverse_ssd": (m.inverse, m.ssd), "inverse_forward": (m.inverse, m.forward)}
    diag = m.diagonal if m.diagonal > 0 else 1.0
    out: dict[str, NDArray[np.float64]] = {}
    for key, (a, b) in pairs.items():
        d = np.linalg.norm(a - b, axis=2)
        out[f"{key}_max"] = d.max(axis=1)
        out[f"{key}_mean"] = d[:, cols].mean(axis=1)
    for key in list(out):
        out[f"{key}_rel"] = out[key] / diag
    return out


def most_disagreeing_vertex(m: MeshComparison) -> int:
    """The vertex where forward and inverse PSD end up furthest apart over the animation."""
    return int(np.argmax(np.linalg.norm(m.inverse - m.forward, axis=2).max(axis=0)))


def choose_views(m: MeshComparison, count: int = 3) -> list[float]:
    """Default frames to draw, in this order of preference and at least an eighth of the
    animation apart: where forward and inverse disagree most, where the correction is
    largest (usually at an example, where the two agree), where a driver is bent furthest,
    then frames spread over the animation."""
    n = len(m.times)
    picks = [
        int(np.argmax(np.linalg.norm(m.inverse - m.forward, axis=2).max(axis=1))),
        int(np.argmax(np.linalg.norm(m.inverse - m.ssd, axis=2).max(axis=1))),
        int(np.argmax(m.driver_angles.max(axis=1))) if m.driver_angles.size else 0,
    ]
    picks += [round(q * (n - 1)) for q in (0.5, 0.25, 0.75, 0.1, 0.9, 0.0, 1.0)]
    chosen: list[int] = []
    for gap in (max(1, n // 8), 1):
        for p in picks:
            if len(chosen) < min(count, n) and all(abs(p - c) >= gap for c in chosen):
                chosen.append(p)
    return [float(m.times[i]) for i in sorted(chosen)]


def _frame_index(m: MeshComparison, t: float) -> int:
    hits = np.nonzero(np.isclose(m.times, t, rtol=0.0, atol=1e-6))[0]
    if not len(hits):
        raise InputError(
            f"--views {t:g}: not a compared frame (frames {m.times[0]:g}..{m.times[-1]:g}, {len(m.times)} in all)"
        )
    return int(hits[0])


def frame_token(t: float) -> str:
    """Frame number for file names: 12 -> '12', 12.5 -> '12.5', -3 -> '-3'."""
    return f"{int(t)}" if float(t).is_integer() else f"{t:g}".replace("+", "")


# --- what the rig says about the mesh (a small USD read) ----------------------------------

@dataclass(frozen=True)
class MeshView:
    """What the report needs from USD beyond the comparison: faces, transforms, bones."""

    triangles: NDArray[np.int64]  # (F, 3) fan-triangulated faces; (0, 3) when the prim has none
    to_world: NDArray[np.float64]  # (f, 4, 4) row-vector local-to-world per compared frame
    up: str  # stage up axis, "Y" or "Z"
    joints: tuple[str, ...]  # skeleton joint order
    dominant: NDArray[np.int64]  # (n,) skeleton joint with the largest skinning weight per point
    joint_rotations: NDArray[np.float64]  # (f, joints, 4) skeleton-space rotations (scipy quats)
    mesh_to_skel: NDArray[np.float64]  # (f, 3, 3) row-vector linear map, mesh-local -> skeleton space
    handed: float  # +1 when right-handed face winding gives outward normals in the plot frame, else -1


def read_mesh_view(comparison: Comparison, m: MeshComparison) -> MeshView:
    from pxr import Usd, UsdGeom

    from . import posespace
    from .usd.read import Scene

    scene = Scene([comparison.anim, comparison.fit.asset], label=comparison.anim)
    prim = scene.prim(m.mesh)
    n = m.ssd.shape[1]
    tris = np.zeros((0, 3), dtype=np.int64)
    if prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        indices = np.array(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        if counts.sum() == len(indices) and (len(indices) == 0 or (indices.min() >= 0 and indices.max() < n)):
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            rows = [np.stack([indices[s] * np.ones(c - 2, dtype=np.int64), indices[s + 1:s + c - 1], indices[s + 2:s + c]], 1)
                    for s, c in zip(starts, counts, strict=True) if c >= 3]
            if rows:
                tris = np.concatenate(rows)
    skin, skel = scene.query(m.mesh)
    xform, skel_xform = UsdGeom.Xformable(prim), UsdGeom.Xformable(skel.GetSkeleton().GetPrim())
    to_world = np.array([np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode(float(t)))) for t in m.times])
    skel_world = np.array([np.array(skel_xform.ComputeLocalToWorldTransform(Usd.TimeCode(float(t)))) for t in m.times])
    mesh_to_skel = (to_world @ np.linalg.inv(skel_world))[:, :3, :3]
    joints = tuple(str(j) for j in skel.GetJointOrder())
    order = skin.GetJointOrder()
    remap = np.array([joints.index(str(j)) if str(j) in joints else -1 for j in order]) if order else np.arange(len(joints))
    dominant = np.full(n, -1, dtype=np.int64)
    influences = skin.ComputeJointInfluences()
    if influences:
        k = max(skin.GetNumInfluencesPerComponent(), 1)
        idx = np.array(influences[0], dtype=np.int64).reshape(-1, k)
        w = np.array(influences[1], dtype=np.float64).reshape(-1, k)
        best = idx[np.arange(len(idx)), np.argmax(w, axis=1)]
        best = np.where((best >= 0) & (best < len(remap)), remap[np.clip(best, 0, len(remap) - 1)], -1)
        dominant[:] = best[0] if len(best) == 1 else best[:n]
    quats = np.empty((len(m.times), len(joints), 4))
    for i, t in enumerate(m.times):
        mats = np.array([np.array(x) for x in skel.ComputeJointSkelTransforms(Usd.TimeCode(float(t)))])
        quats[i] = posespace.rotations(mats).as_quat()
    up = str(UsdGeom.GetStageUpAxis(scene.stage))
    handed = -1.0 if mesh_orientation(prim) == "leftHanded" else 1.0
    if len(to_world) and np.linalg.det(to_world[0][:3, :3]) < 0:
        handed = -handed
    return MeshView(tris, to_world, "Z" if up == "Z" else "Y", joints, dominant, quats, mesh_to_skel, handed)


def mesh_orientation(prim) -> str:
    from pxr import UsdGeom

    return str(UsdGeom.Mesh(prim).GetOrientationAttr().Get()) if prim.IsA(UsdGeom.Mesh) else "rightHanded"


def vertex_turn(m: MeshComparison, view: MeshView, vertex: int, why: str) -> dict:
    """The series behind one row of correction_angle.png (radians, NaN where undefined).

    forward, inverse: compare.correction_turn from the frame where the inverse correction
    is largest. carried_turn: how far that reference correction would have turned had the
    vertex's bone (its largest skinning weight) carried it rigidly, which is what rest-space
    interpolation predicts for one example and one bone. joint_turn: that bone's rotation
    angle since the reference frame (skeleton space), an upper bound of carried_turn: a
    vector turns by the full angle only when it is perpendicular to the rotation axis."""
    from scipy.spatial.transform import Rotation

    fwd_vec = m.forward[:, vertex] - m.ssd[:, vertex]
    inv_vec = m.inverse[:, vertex] - m.ssd[:, vertex]
    inv_mag = np.linalg.norm(inv_vec, axis=1)
    ref = int(np.argmax(inv_mag))  # compare.correction_turn's default reference
    forward, inverse = correction_turn(m, vertex, reference=ref)
    joint = int(view.dominant[vertex]) if len(view.dominant) else -1
    joint_turn = np.full(len(m.times), np.nan)
    carried_turn = np.full(len(m.times), np.nan)
    if joint >= 0 and inv_mag[ref] > 0:
        rot = Rotation.from_quat(view.joint_rotations[:, joint])
        rel = rot * rot[ref].inv()
        joint_turn = rel.magnitude()
        in_skel = inv_vec[ref] @ view.mesh_to_skel[ref]
        carried = np.einsum("fi,fij->fj", rel.apply(in_skel), np.linalg.inv(view.mesh_to_skel))
        cos = carried @ inv_vec[ref] / (np.linalg.norm(carried, axis=1) * inv_mag[ref])
        carried_turn = np.arccos(np.clip(cos, -1.0, 1.0))
    return {
        "vertex": int(vertex),
        "why": why,
        "reference_time": float(m.times[ref]),
        "joint": view.joints[joint] if joint >= 0 else None,
        "times": m.times.tolist(),
        "carried_turn": carried_turn.tolist(),
        "joint_turn": joint_turn.tolist(),
        "forward": forward.tolist(),
        "inverse": inverse.tolist(),
        "forward_magnitude": np.linalg.norm(fwd_vec, axis=1).tolist(),
        "inverse_magnitude": inv_mag.tolist(),
    }


def _same_story(a: dict, b: dict, atol: float = math.radians(2.0)) -> bool:
    """Two vertex_turn series that would draw the same picture (neighbouring vertices)."""
    if a["joint"] != b["joint"]:
        return False
    with np.errstate(invalid="ignore"):
        gaps = [np.nanmax(np.abs(np.array(a[k], dtype=float) - np.array(b[k], dtype=float)), initial=0.0)
                for k in ("forward", "inverse")]
    return max(gaps) < atol


def choose_mesh(comparison: Comparison, mesh: str | None) -> MeshComparison:
    """--mesh, else the mesh whose inverse correction is largest relative to its size."""
    if mesh is not None:
        for m in comparison.meshes:
            if m.mesh == mesh:
                return m
        raise InputError(f"{comparison.fit.asset} <{mesh}>: --mesh was not fitted (fitted: "
                         + ", ".join(f"<{m.mesh}>" for m in comparison.meshes) + ")")

    def size(m: MeshComparison) -> float:
        return float(np.linalg.norm(m.inverse - m.ssd, axis=2).max() / (m.diagonal or 1.0))

    return max(comparison.meshes, key=size)


# --- figures -----------------------------------------------------------------------------

def _mpl():
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise ReportError("psdbake compare draws its figures with matplotlib: pip install 'psdbake[report]'") from None
    return matplotlib, Figure, FigureCanvasAgg


def _save(fig, path: str, inputs: Sequence[str]) -> str:
    with atomic.replacing(path, inputs) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": f"psdbake {__version__}"})
    return path


def _leaf(joint: str | None) -> str:
    return joint.split("/")[-1] if joint else "?"


def draw_correction_angle(turns: Sequence[dict], path: str, inputs: Sequence[str] = ()) -> str:
    """One row per vertex: turn against frame (left), turn against the predicted turn (right)."""
    _, figure_cls, canvas_cls = _mpl()
    rows = len(turns)
    fig = figure_cls(figsize=(12.5, 4.4 * rows), dpi=100, layout="constrained")
    canvas_cls(fig)
    deg = 180.0 / math.pi
    for r, turn in enumerate(turns):
        t = np.array(turn["times"], dtype=float)
        carried = np.array(turn["carried_turn"], dtype=float) * deg
        joint = np.array(turn["joint_turn"], dtype=float) * deg
        series = {}
        for key in ("forward", "inverse"):
            a = np.array(turn[key], dtype=float) * deg
            mag = np.array(turn[f"{key}_magnitude"], dtype=float)
            a[mag < FAINT * max(mag.max(), 1e-300)] = np.nan
            series[key] = a
        name, ref = _leaf(turn["joint"]), f"{turn['reference_time']:g}"
        ax = fig.add_subplot(rows, 2, 2 * r + 1)
        ax.plot(t, joint, color="0.6", ls=":", lw=1.4, label=f"bone {name}: rotation angle")
        ax.plot(t, carried, color="0.3", ls="--", lw=1.6, label=f"frame-{ref} correction carried by bone {name}")
        ax.plot(t, series["forward"], color="tab:blue", marker="o", ms=3, lw=1.6, label="forward PSD (posed-space)")
        ax.plot(t, series["inverse"], color="tab:red", marker="s", ms=3, lw=1.6, label="inverse PSD (rest-space)")
        ax.axvline(turn["reference_time"], color="0.75", lw=0.8)
        ax.set_xlabel("frame")
        ax.set_ylabel(f"turn since frame {ref} (degrees)")
        ax.set_title(f"vertex {turn['vertex']} ({turn['why']}): direction of its correction", fontsize=11)
        ax.grid(alpha=0.3)
        high = float(np.nanmax(np.concatenate([joint, carried, series["forward"], series["inverse"], [1e-3]])))
        ax.set_ylim(0, high * 1.4)  # room for the legend above the curves
        ax.legend(fontsize=8.5, loc="upper center", ncol=2, framealpha=0.9)
        ax2 = fig.add_subplot(rows, 2, 2 * r + 2)
        top = float(np.nanmax(np.concatenate([carried, series["forward"], series["inverse"], [1e-3]])))
        ax2.plot([0, top * 1.05], [0, top * 1.05], color="0.3", ls="--", lw=1.2, label="turns with the bone")
        ax2.scatter(carried, series["forward"], s=14, color="tab:blue", label="forward PSD")
        ax2.scatter(carried, series["inverse"], s=14, color="tab:red", marker="s", label="inverse PSD")
        ax2.set_xlabel(f"turn of the frame-{ref} correction carried by bone {name} (degrees)")
        ax2.set_ylabel("turn of the correction (degrees)")
        ax2.set_title(f"vertex {turn['vertex']}: actual against carried turn, one point per frame", fontsize=11)
        ax2.set_xlim(0, top * 1.05)
        ax2.set_ylim(0, top * 1.05)
        ax2.set_aspect("equal", adjustable="box")
        ax2.grid(alpha=0.3)
        ax2.legend(fontsize=8.5, loc="upper left", framealpha=0.85)
    return _save(fig, path, inputs)


_TO_Z_UP = {"Z": np.eye(3), "Y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])}  # row vectors: (x,y,z)->(x,-z,y)


def _plot_space(points: NDArray[np.float64], to_world: NDArray[np.float64], up: str) -> NDArray[np.float64]:
    """Mesh-local points -> world -> matplotlib's z-up frame (row vectors)."""
    return (points @ to_world[:3, :3] + to_world[3, :3]) @ _TO_Z_UP[up]


@dataclass(frozen=True)
class _Camera:
    elev: float
    azim: float
    centre: NDArray[np.float64]  # what the view is centred on (plot space)
    half_width: float  # half the visible extent along the screen's right and up directions
    half_height: float

    def axes(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(toward the camera, screen right, screen up), matplotlib's convention (roll 0)."""
        e, a = math.radians(self.elev), math.radians(self.azim)
        toward = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        right = np.array([-math.sin(a), math.cos(a), 0.0])
        up = np.array([-math.sin(e) * math.cos(a), -math.sin(e) * math.sin(a), math.cos(e)])
        return toward, right, up


def _face_normals(poly: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit normals (right-handed winding) and areas of triangles (F, 3, 3)."""
    cross = np.cross(poly[:, 1] - poly[:, 0], poly[:, 2] - poly[:, 0])
    area = np.linalg.norm(cross, axis=1)
    return cross / np.maximum(area, 1e-30)[:, None], area / 2


def _visible(centroids: NDArray[np.float64], toward, right, up, cell: float) -> NDArray[np.bool_]:
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


def _camera(clouds: Sequence[NDArray[np.float64]], corrections: Sequence[NDArray[np.float64]],
            tris: NDArray[np.int64], handed: float) -> _Camera:
    """One camera for every panel and view: among views from a little above, around the
    up axis, the one that sees most corrected surface (unoccluded area facing the camera,
    weighted by the correction) while the mesh shows its broad side; then framed to the
    posed meshes' extent on screen."""
    pts = np.concatenate(clouds)
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    faces = [(*_face_normals(cloud[tris]), cloud[tris].mean(axis=1), mag[tris].mean(axis=1))
             for cloud, mag in zip(clouds, corrections, strict=True)] if len(tris) else []
    best = None
    for elev in (12.0, 28.0):
        for azim in range(-180, 180, 10):
            cam = _Camera(elev, float(azim), centre, 1.0, 1.0)
            toward, right, up = cam.axes()
            rel = pts - centre
            breadth = float(np.ptp(rel @ right) * np.ptp(rel @ up))
            seen = 0.0
            for normals, area, centroids, mag in faces:
                facing = np.clip(handed * normals @ toward, 0.0, None)
                cell = 2.0 * math.sqrt(2.0 * float(np.median(area)))
                seen += float(np.sum((area * mag * facing)[_visible(centroids, toward, right, up, cell)]))
            score = (seen if seen > 0 else 1.0) * math.sqrt(breadth)
            if best is None or score > best[0] * (1 + 1e-9):
                best = (score, cam)
    cam = best[1]
    _, right, up = cam.axes()
    a, b = (pts - centre) @ right, (pts - centre) @ up
    shift = right * (a.max() + a.min()) / 2 + up * (b.max() + b.min()) / 2
    return _Camera(cam.elev, cam.azim, centre + shift, float(np.ptp(a)) / 2 or 1.0, float(np.ptp(b)) / 2 or 1.0)


def _frame(ax, cam: _Camera, fill: float = 0.94) -> None:
    """Limits, view and zoom so the camera's extent fills the axes (equal aspect)."""
    from mpl_toolkits.mplot3d import proj3d

    h = max(cam.half_width, cam.half_height)
    c = cam.centre
    ax.set_xlim(c[0] - h, c[0] + h)
    ax.set_ylim(c[1] - h, c[1] + h)
    ax.set_zlim(c[2] - h, c[2] + h)
    ax.set_box_aspect((1, 1, 1), zoom=1.0)
    ax.view_init(elev=cam.elev, azim=cam.azim)
    ax.apply_aspect()
    _, right, _ = cam.axes()
    probe = np.stack([c, c + right * h])
    x, y, _ = proj3d.proj_transform(probe[:, 0], probe[:, 1], probe[:, 2], ax.get_proj())
    px = ax.transData.transform(np.c_[x, y])
    per_unit = float(np.linalg.norm(px[1] - px[0])) / h  # pixels per scene unit at zoom 1
    bbox = ax.bbox
    zoom = fill * min(bbox.width / (2 * cam.half_width * per_unit), bbox.height / (2 * cam.half_height * per_unit))
    ax.set_box_aspect((1, 1, 1), zoom=zoom)


def _draw_mesh(ax, pts: NDArray[np.float64], values: NDArray[np.float64], tris: NDArray[np.int64], cam: _Camera,
               handed: float, cmap, norm) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    _frame(ax, cam)
    if len(tris):
        poly = pts[tris]
        normals, _ = _face_normals(poly)
        toward, right, up = cam.axes()
        light = toward + 0.35 * up - 0.2 * right
        light /= np.linalg.norm(light)
        facing = handed * normals @ light
        # light enough that colours still read against the colour bar; back faces a little darker
        shade = 0.55 + 0.45 * np.where(facing > 0, facing, 0.5 * np.abs(facing))
        colours = cmap(norm(values[tris].mean(axis=1)))
        colours[:, :3] *= shade[:, None]
        ax.add_collection3d(Poly3DCollection(poly, facecolors=colours, edgecolors=colours, linewidths=0.3))
    else:
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=cmap(norm(values)), s=4, depthshade=False)
    ax.set_axis_off()


def draw_views(m: MeshComparison, view: MeshView, i: int, cam: _Camera, scale: tuple[float, float],
               title: str, path: str, inputs: Sequence[str] = ()) -> str:
    """Four panels at frame i: SSD, forward, inverse (colour: |result - SSD|, one colour bar)
    and |inverse - forward| (its own colour bar). Colours are % of the bounding-box diagonal."""
    matplotlib, figure_cls, canvas_cls = _mpl()
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    diag = m.diagonal or 1.0
    cmap = matplotlib.colormaps["YlOrRd"]
    cmap_diff = matplotlib.colormaps["PuBu"]
    norm = Normalize(0.0, scale[0] / diag * 100)
    norm_diff = Normalize(0.0, scale[1] / diag * 100)
    # inches: four panels shaped like the meshes on screen, titles above, colour bars below. A 3D
    # axes is always square, so each is a square as large as its panel's longer side, centred
    # on the panel, with a transparent background (the mesh itself stays inside its panel).
    width, panel_w, top, bottom = 16.0, 3.76, 1.0, 1.0
    panel_h = min(max(panel_w * cam.half_height / cam.half_width, 2.4), 7.0)
    side = max(panel_w, panel_h)
    height = panel_h + top + bottom
    fig = figure_cls(figsize=(width, height), dpi=100)
    canvas_cls(fig)
    ssd = m.ssd[i]
    panels = [
        ("SSD: plain skinning", ssd, np.zeros(len(ssd)), cmap, norm),
        ("forward PSD: posed-space deltas", m.forward[i], np.linalg.norm(m.forward[i] - ssd, axis=1), cmap, norm),
        ("inverse PSD: rest-space (psdbake)", m.inverse[i], np.linalg.norm(m.inverse[i] - ssd, axis=1), cmap, norm),
        ("where they differ: |inverse \u2212 forward|", m.inverse[i], np.linalg.norm(m.inverse[i] - m.forward[i], axis=1),
         cmap_diff, norm_diff),
    ]
    for k, (name, pts, values, cm, nm) in enumerate(panels):
        cx, cy = (0.08 + 0.2375 * k * width + panel_w / 2), bottom + panel_h / 2
        rect = ((cx - side / 2) / width, (cy - side / 2) / height, side / width, side / height)
        ax = fig.add_axes(rect, projection="3d", proj_type="ortho")
        ax.patch.set_visible(False)
        _draw_mesh(ax, _plot_space(pts, view.to_world[i], view.up), values / diag * 100, view.triangles, cam,
                   view.handed, cm, nm)
        peak = values.max() / diag * 100
        fig.text(cx / width, (bottom + panel_h + 0.08) / height,
                 f"{name}\n" + ("(no correction: the reference)" if k == 0 else f"largest {peak:.3g}% of diagonal"),
                 ha="center", va="bottom", fontsize=10)
    bar = fig.add_axes((0.06, 0.5 / height, 0.58, 0.16 / height))
    fig.colorbar(ScalarMappable(norm, cmap), cax=bar, orientation="horizontal",
                 label="correction |result \u2212 SSD|, % of the bounding-box diagonal (same scale in every view)")
    bar2 = fig.add_axes((0.735, 0.5 / height, 0.22, 0.16 / height))
    fig.colorbar(ScalarMappable(norm_diff, cmap_diff), cax=bar2, orientation="horizontal",
                 label="|inverse \u2212 forward|, % of diagonal")
    fig.suptitle(title, fontsize=12, y=1 - 0.12 / height, va="top")
    return _save(fig, path, inputs)


# --- tables ------------------------------------------------------------------------------

def _labels(comparison: Comparison, m: MeshComparison) -> tuple[list[str], list[str]]:
    """Driver joint paths and the example label of each weight column."""
    fit = next(f for f in comparison.fit.meshes if f.mesh == m.mesh)
    examples = [ex.label for ex, ch in zip(fit.examples, fit.channels, strict=True) if ch]
    return list(fit.drivers), examples


def _finite(values) -> list:
    return [None if (isinstance(v, float) and not math.isfinite(v)) else v for v in values]


def stats_rows(comparison: Comparison, m: MeshComparison) -> tuple[list[str], list[list]]:
    """stats.csv: header and one row per frame."""
    drivers, examples = _labels(comparison, m)
    stats = frame_stats(m)
    keys = [f"{k}_{s}" for k, _ in METRICS for s in ("max", "mean")]
    header = (["time"] + [f"angle_rad:{d}" for d in drivers] + [f"weight:{e}" for e in examples]
              + keys + [f"{k}_rel" for k in keys])
    rows = []
    for i, t in enumerate(m.times):
        rows.append([float(t), *m.driver_angles[i].tolist(), *m.weights[i].tolist(),
                     *(float(stats[k][i]) for k in keys), *(float(stats[f"{k}_rel"][i]) for k in keys)])
    return header, rows


def _csv_text(header: list[str], rows: list[list]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow([v if isinstance(v, str) else repr(float(v)) for v in row])
    return buf.getvalue()


# --- HTML --------------------------------------------------------------------------------

_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1250px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em} h2{font-size:1.25em;margin-top:1.8em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.9em;margin:.6em 0} td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3} td.l,th.l{text-align:left} code{background:#f5f5f5;padding:0 .2em}
figure{margin:1.2em 0} figure img{max-width:100%;border:1px solid #ddd} figcaption{font-size:.92em;color:#333;max-width:1100px}
.note{color:#555;font-size:.9em} details{margin:.8em 0} summary{cursor:pointer;font-weight:600}
"""


def _e(text) -> str:
    return html.escape(str(text), quote=True)


def _pct(x: float) -> str:
    return f"{x * 100:.3g}%"


def _html(comparison, m, label, stats, header, rows, turns, view_files, files_angle) -> str:
    fit = comparison.fit
    mfit = next(f for f in fit.meshes if f.mesh == m.mesh)
    examples = [ex.label for ex, ch in zip(mfit.examples, mfit.channels, strict=True) if ch]
    s = fit.settings
    d = mfit.driver_data
    deg = 180.0 / math.pi
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           '<meta name="generator" content="psdbake compare">',
           f"<title>psdbake compare: {_e(os.path.basename(label))}</title>", f"<style>{_CSS}</style></head><body>",
           f"<h1>Forward vs inverse PSD: {_e(os.path.basename(label))}</h1>",
           '<p class="note">Written by psdbake ' + _e(__version__) + " <code>compare</code>. At every frame the "
           "three results use the <em>same</em> RBF weights, so the only difference between forward and inverse PSD is "
           "the space in which the sculpted examples are interpolated: after skinning (posed space, forward) or before "
           "it (rest space, inverse, what psdbake writes as blend shapes).</p>",
           "<h2>Inputs</h2><table>"]
    inputs = [
        ("asset", label), ("examples", ", ".join(fit.example_files)), ("animation", comparison.anim),
        ("mesh", f"{m.mesh} ({m.ssd.shape[1]} points, {len(m.corrected)} with a corrective, "
                 f"bounding-box diagonal {m.diagonal:.4g})"),
        ("frames", f"{m.times[0]:g}..{m.times[-1]:g} ({len(m.times)} frames)"),
        ("drivers", ", ".join(_leaf(j) for j in mfit.drivers)),
        ("examples fitted", ", ".join(ex.label for ex in mfit.examples)),
        ("RBF", f"kernel {d.kernel}, sigma {d.sigma:.4g} rad, degree {d.degree}, smoothing {d.smoothing:g}"
                + ("" if s.rest_example else ", no rest example")),
        ("deformers", ", ".join(s.deformers) or "none"),
    ]
    if len(comparison.meshes) > 1:
        others = [o.mesh for o in comparison.meshes if o.mesh != m.mesh]
        inputs.append(("other meshes", ", ".join(others) + " (choose with --mesh)"))
    out += [f'<tr><th class="l">{_e(k)}</th><td class="l">{_e(v)}</td></tr>' for k, v in inputs]
    out.append("</table>")

    out.append("<h2>Summary over the animation</h2>")
    out.append('<table><tr><th class="l">distance per vertex</th><th>largest</th><th>% of diagonal</th><th>at frame</th>'
               "<th>mean over frames of the mean over corrected vertices, % of diagonal</th></tr>")
    for key, name in METRICS:
        mx = stats[f"{key}_max"]
        i = int(np.argmax(mx))
        out.append(f'<tr><td class="l">{_e(name)}</td><td>{mx[i]:.4g}</td><td>{_pct(stats[f"{key}_max_rel"][i])}</td>'
                   f"<td>{m.times[i]:g}</td><td>{_pct(float(stats[f'{key}_mean_rel'].mean()))}</td></tr>")
    out.append("</table>")
    for turn in turns:
        top = {k: float(np.nanmax(np.append(np.array(turn[k], dtype=float), 0.0))) * deg
               for k in ("inverse", "forward", "carried_turn", "joint_turn")}
        out.append(
            f'<p>Vertex {turn["vertex"]} ({_e(turn["why"])}): from frame {turn["reference_time"]:g} its correction turns '
            f"by up to <b>{top['inverse']:.1f}°</b> with inverse PSD and <b>{top['forward']:.1f}°</b> with forward PSD. "
            f"Carried rigidly by the bone that moves the vertex most ({_e(_leaf(turn['joint']))}, which rotates by up to "
            f"{top['joint_turn']:.1f}°), the frame-{turn['reference_time']:g} correction would turn by up to "
            f"{top['carried_turn']:.1f}°.</p>"
        )

    out.append("<h2>Does the correction turn with the joint?</h2>")
    out.append(f'<figure><img src="{_e(files_angle)}" alt="correction turn against the bone turn">')
    out.append(
        "<figcaption>The paper's Figure 3 analysis. The correction of a vertex is the vector <em>result \u2212 SSD</em>. "
        "<b>Left</b>: the angle between that vector at each frame and the same vector at the reference frame (thin "
        "vertical line: where the vertex's inverse-PSD correction is largest). The dashed line is the prediction for a "
        "correction that turns with the limb: the reference correction, carried rigidly by the bone with the "
        "vertex's largest skinning weight. The dotted line is that bone's own rotation angle since the reference "
        "frame; a vector turns by that full angle only when it is perpendicular to the rotation axis, so the dashed "
        "line never rises above it (a correction along the axis does not turn at all). <b>Right</b>: the same "
        "numbers, one point per frame, against the prediction; the diagonal is 'turns with the bone'. "
        "<b>Inverse PSD (red)</b> interpolates the examples in the rest pose and lets skinning pose the result, so "
        "its correction turns with the bone and its points lie near the diagonal (exactly on it for a vertex bound "
        "to one bone and driven by one example; blended skinning weights and examples whose rest-space "
        "corrections point different ways move it off). <b>Forward PSD (blue)</b> interpolates the sculpted "
        "deltas in posed space, so between and beyond the examples its correction keeps the direction it was "
        "sculpted in: it turns only as the weights blend examples sculpted in different directions, and it "
        "stays put where one example dominates while the limb moves on. Where blue sits below red, forward PSD "
        "pushes the surface in a direction the limb has already turned away from. Frames where a correction is "
        f"under {FAINT:.0%} of its largest are not drawn (a vanishing vector has no direction); the numbers are "
        "in stats.json under <code>vertex_turn</code>.</figcaption></figure>"
    )

    out.append("<h2>The mesh at chosen frames</h2>")
    out.append(
        "<p>Each figure shows one frame in four panels, through one orthographic camera shared by every panel and "
        "every view (chosen to see as much of the corrected surface as possible). The first three panels are "
        "coloured by the correction |result \u2212 SSD| on one colour scale, the same in every view: SSD has no "
        "correction by definition (it is the reference); forward and inverse PSD correct by nearly the same amount "
        "(same weights, same examples) but not in the same direction, which the last panel shows as the distance "
        "between the two results, |inverse \u2212 forward|, on its own scale: zero at the example poses, where both "
        "reproduce the sculpts, and growing as the limb turns away from them. The shapes differ by a few percent "
        "of the mesh's size at most, so the colours, not the silhouettes, carry the comparison.</p>"
    )
    for t, name in view_files:
        i = int(np.argmin(np.abs(m.times - t)))
        weights = ", ".join(f"{_e(e)} {w:.2f}" for e, w in zip(examples, m.weights[i], strict=True))
        out.append(f'<figure><img src="{_e(name)}" alt="SSD, forward and inverse PSD at frame {t:g}">'
                   f"<figcaption>Frame {t:g}: example weights {weights}; |inverse \u2212 forward| up to "
                   f"{_pct(stats['inverse_forward_max_rel'][i])} of the diagonal "
                   f"(largest over the animation: {_pct(stats['inverse_forward_max_rel'].max())}).</figcaption></figure>")

    out.append("<h2>Per-frame statistics</h2>")
    out.append('<p class="note">Also in <a href="stats.csv">stats.csv</a> and <a href="stats.json">stats.json</a> '
               "(which holds the series drawn in correction_angle.png under <code>vertex_turn</code>). "
               "Distances in scene units; <code>_rel</code> columns are fractions of the bounding-box diagonal; "
               "means are over the vertices with a corrective; angles are each driver's rotation away from the "
               "bind pose, in radians.</p>")
    out.append("<details><summary>Table, one row per frame</summary><table><tr>"
               + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{v:.4g}</td>" for v in row) + "</tr>")
    out.append("</table></details>")
    if "cesiumman" in label.lower():
        out.append('<p class="note">CesiumMan model: CC-BY 4.0, Cesium.</p>')
    out.append("</body></html>\n")
    return "\n".join(out)


# --- the report --------------------------------------------------------------------------

@dataclass(frozen=True)
class Prepared:
    """Everything a report shows, computed and checked before anything is written."""

    comparison: Comparison
    mesh: MeshComparison
    label: str
    inputs: tuple[str, ...]
    view: MeshView
    turns: tuple[dict, ...]
    view_frames: tuple[float, ...]
    header: list[str]
    rows: list[list]
    payload: dict  # stats.json

    @property
    def files(self) -> list[str]:
        return list(self.payload["files"])


def prepare(
    comparison: Comparison,
    *,
    asset_label: str | None = None,
    mesh: str | None = None,
    vertex: int | None = None,
    views: Sequence[float] | None = None,
    inputs: Sequence[str] = (),
) -> Prepared:
    """Choose the mesh, vertices and frames and compute every number of the report."""
    label = asset_label or comparison.fit.asset
    all_inputs = (comparison.fit.asset, *comparison.fit.example_files, comparison.anim, *inputs)
    m = choose_mesh(comparison, mesh)
    n = m.ssd.shape[1]
    if vertex is not None and not 0 <= vertex < n:
        raise InputError(f"{label} <{m.mesh}>: --vertex {vertex} is out of range (0..{n - 1})")
    if vertex is not None and vertex not in set(m.corrected.tolist()):
        raise InputError(f"{label} <{m.mesh}>: --vertex {vertex} has no corrective "
                         f"(the most corrected vertex is {most_corrected_vertex(m)})")
    view_frames = [float(m.times[_frame_index(m, t)]) for t in views] if views else choose_views(m)
    view_frames = sorted(set(view_frames))
    view = read_mesh_view(comparison, m)
    if vertex is not None:
        turns = [vertex_turn(m, view, vertex, "--vertex")]
    else:
        first = most_corrected_vertex(m)
        turns = [vertex_turn(m, view, first, "most corrected")]
        second = most_disagreeing_vertex(m)
        if second != first:
            other = vertex_turn(m, view, second, "forward and inverse disagree most")
            if not _same_story(turns[0], other):
                turns.append(other)
    header, rows = stats_rows(comparison, m)
    drivers, examples = _labels(comparison, m)
    files = [MARKER, "correction_angle.png", *(f"views_{frame_token(t)}.png" for t in view_frames), "stats.csv", "index.html"]
    payload = {
        "psdbake": __version__, "command": "compare", "asset": label, "examples": list(comparison.fit.example_files),
        "anim": comparison.anim, "mesh": m.mesh, "points": n, "corrected_vertices": len(m.corrected),
        "diagonal": m.diagonal, "drivers": drivers, "weight_columns": examples,
        "columns": header, "frames": [dict(zip(header, _finite(r), strict=True)) for r in rows],
        "vertex_turn": [{k: _finite(v) if isinstance(v, list) else v for k, v in t.items()} for t in turns],
        "views": view_frames, "files": files,
    }
    return Prepared(comparison, m, label, all_inputs, view, tuple(turns), tuple(view_frames), header, rows, payload)


def write_prepared(rep: Prepared, out_dir: str) -> list[str]:
    """Write a prepared report into out_dir (created if missing); returns the file names
    written (relative to out_dir), stats.json first and index.html last."""
    _mpl()  # fail before writing anything when matplotlib is missing
    check_report_dir(out_dir, rep.inputs)
    previous = (_previous_files(out_dir) or []) if os.path.isdir(out_dir) else []
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the folder ({exc.strerror or exc})") from None
    m, view, inputs = rep.mesh, rep.view, rep.inputs
    files = rep.files

    def p(name: str) -> str:
        return os.path.join(out_dir, name)

    atomic.write_text(p(MARKER), json.dumps(rep.payload, indent=1, sort_keys=True, allow_nan=False) + "\n", inputs)
    draw_correction_angle(rep.turns, p("correction_angle.png"), inputs)
    idx = [_frame_index(m, t) for t in rep.view_frames]
    clouds = [_plot_space(m.ssd[i], view.to_world[i], view.up) for i in idx]
    cam = _camera(clouds, [np.linalg.norm(m.inverse[i] - m.ssd[i], axis=1) for i in idx], view.triangles, view.handed)
    corr = np.linalg.norm(np.concatenate([m.forward[idx], m.inverse[idx]]) - np.concatenate([m.ssd[idx]] * 2), axis=2)
    diff = np.linalg.norm(m.inverse[idx] - m.forward[idx], axis=2)
    scale = (max(float(corr.max()), 1e-12), max(float(diff.max()), 1e-12))
    examples = rep.payload["weight_columns"]
    for t, i in zip(rep.view_frames, idx, strict=True):
        weights = ", ".join(f"{e.split('@')[-1]}: {w:.2f}" for e, w in zip(examples, m.weights[i], strict=True))
        title = (f"{os.path.basename(rep.label)}  <{m.mesh.split('/')[-1]}>  frame {t:g}    "
                 f"example weights (by example frame): {weights}")
        draw_views(m, view, i, cam, scale, title, p(f"views_{frame_token(t)}.png"), inputs)
    atomic.write_text(p("stats.csv"), _csv_text(rep.header, rep.rows), inputs)
    stats = frame_stats(m)
    view_files = [(t, f"views_{frame_token(t)}.png") for t in rep.view_frames]
    page = _html(rep.comparison, m, rep.label, stats, rep.header, rep.rows, rep.turns, view_files, "correction_angle.png")
    atomic.write_text(p("index.html"), page, inputs)
    for stale in sorted(set(previous) - set(files)):
        try:
            os.remove(p(stale))
        except FileNotFoundError:
            pass
    return files


def summary(rep: Prepared, out_dir: str) -> dict:
    """The --json summary of psdbake compare."""
    out = {"output": out_dir, "files": rep.files, "mesh": rep.mesh.mesh, "frames": len(rep.mesh.times),
           "views": list(rep.view_frames), "largest": {}, "vertex_turn": []}
    for key, _ in METRICS:
        i = int(np.argmax([f[f"{key}_max"] for f in rep.payload["frames"]]))
        f = rep.payload["frames"][i]
        out["largest"][key] = {"max": f[f"{key}_max"], "max_rel": f[f"{key}_max_rel"], "time": f["time"]}
    for t in rep.turns:
        top = {k: float(np.nanmax(np.append(np.array(t[k], dtype=float), 0.0)))
               for k in ("inverse", "forward", "carried_turn", "joint_turn")}
        out["vertex_turn"].append({"vertex": t["vertex"], "why": t["why"], "joint": t["joint"],
                                   "reference_time": t["reference_time"], **{f"max_{k}": v for k, v in top.items()}})
    return out


def summary_lines(rep: Prepared, out_dir: str) -> list[str]:
    """The terminal summary of psdbake compare."""
    s = summary(rep, out_dir)
    lines = [f"psdbake compare: <{s['mesh']}> over {s['frames']} frame(s), "
             f"views at {', '.join(f'{t:g}' for t in s['views'])}"]
    for key, name in METRICS:
        big = s["largest"][key]
        lines.append(f"  largest {name.replace(MINUS, '-')}: {big['max']:.4g} ({big['max_rel'] * 100:.3g}% of diagonal) "
                     f"at frame {big['time']:g}")
    deg = 180.0 / math.pi
    for t in s["vertex_turn"]:
        lines.append(f"  vertex {t['vertex']} ({t['why']}): its correction turns up to {t['max_inverse'] * deg:.1f} deg "
                     f"with inverse PSD, {t['max_forward'] * deg:.1f} deg with forward PSD; "
                     f"carried by its bone {_leaf(t['joint'])} it would turn {t['max_carried_turn'] * deg:.1f} deg")
    lines.append(f"wrote {os.path.join(out_dir, 'index.html')} and {len(s['files']) - 1} other file(s)")
    return lines


def write_report(
    comparison: Comparison,
    out_dir: str,
    *,
    asset_label: str | None = None,
    mesh: str | None = None,
    vertex: int | None = None,
    views: Sequence[float] | None = None,
    inputs: Sequence[str] = (),
) -> list[str]:
    """Compute and write the report (see the module docstring); returns the file names
    written, relative to out_dir."""
    rep = prepare(comparison, asset_label=asset_label, mesh=mesh, vertex=vertex, views=views, inputs=inputs)
    return write_prepared(rep, out_dir)
