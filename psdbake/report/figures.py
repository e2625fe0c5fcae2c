"""The report's figures, drawn with matplotlib into a given path.

- ``correction_angle.png``: the paper's Figure 3 analysis, one row per chosen vertex: how
  far its correction turns, forward vs inverse, against the turn of the bone carrying it;
- ``views_<frame>.png``: the mesh at one frame, SSD / forward / inverse side by side,
  coloured by the correction magnitude, plus where forward and inverse disagree.

All matplotlib code of psdbake lives here and matplotlib is imported lazily (the
``report`` extra), with the Agg canvas on standalone ``Figure`` objects: pyplot's global
state is never touched. PNG metadata holds psdbake's version only, so figures are
byte-for-byte reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import __version__
from ..errors import ReportError
from ..usd.meshview import MeshView
from .camera import Camera, choose_camera, face_normals, plot_space
from .comparison import MeshComparison
from .stats import VertexTurn

#: Frames whose correction is below this fraction of the vertex's largest are not drawn in
#: the angle figure: a vanishing vector has no meaningful direction (float32 noise).
FAINT = 0.02
DEG = 180.0 / math.pi


def require_matplotlib() -> tuple[Any, Any, Any]:
    """(matplotlib, Figure, FigureCanvasAgg), or ReportError saying how to install it."""
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise ReportError("psdbake compare draws its figures with matplotlib: pip install 'psdbake[report]'") from None
    return matplotlib, Figure, FigureCanvasAgg


def _save(fig: Any, path: str) -> None:
    fig.savefig(path, format="png", metadata={"Software": f"psdbake {__version__}"})


def leaf(joint: str | None) -> str:
    """Last name of a joint path ('?' for none)."""
    return joint.split("/")[-1] if joint else "?"


def draw_correction_angle(turns: Sequence[VertexTurn], path: str) -> None:
    """One row per vertex: turn against frame (left), turn against the predicted turn (right)."""
    _, figure_cls, canvas_cls = require_matplotlib()
    rows = len(turns)
    fig = figure_cls(figsize=(12.5, 4.4 * rows), dpi=100, layout="constrained")
    canvas_cls(fig)
    for r, turn in enumerate(turns):
        _angle_row(fig, rows, r, turn)
    _save(fig, path)


def _angle_row(fig: Any, rows: int, r: int, turn: VertexTurn) -> None:
    t = np.array(turn.times, dtype=float)
    carried = np.array(turn.carried_turn, dtype=float) * DEG
    joint = np.array(turn.joint_turn, dtype=float) * DEG
    series = {}
    for key in ("forward", "inverse"):
        a = np.array(getattr(turn, key), dtype=float) * DEG
        mag = np.array(getattr(turn, f"{key}_magnitude"), dtype=float)
        a[mag < FAINT * max(mag.max(), 1e-300)] = np.nan
        series[key] = a
    name, ref = leaf(turn.joint), f"{turn.reference_time:g}"
    ax = fig.add_subplot(rows, 2, 2 * r + 1)
    ax.plot(t, joint, color="0.6", ls=":", lw=1.4, label=f"bone {name}: rotation angle")
    ax.plot(t, carried, color="0.3", ls="--", lw=1.6, label=f"frame-{ref} correction carried by bone {name}")
    ax.plot(t, series["forward"], color="tab:blue", marker="o", ms=3, lw=1.6, label="forward PSD (posed-space)")
    ax.plot(t, series["inverse"], color="tab:red", marker="s", ms=3, lw=1.6, label="inverse PSD (rest-space)")
    ax.axvline(turn.reference_time, color="0.75", lw=0.8)
    ax.set_xlabel("frame")
    ax.set_ylabel(f"turn since frame {ref} (degrees)")
    ax.set_title(f"vertex {turn.vertex} ({turn.why}): direction of its correction", fontsize=11)
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
    ax2.set_title(f"vertex {turn.vertex}: actual against carried turn, one point per frame", fontsize=11)
    ax2.set_xlim(0, top * 1.05)
    ax2.set_ylim(0, top * 1.05)
    ax2.set_aspect("equal", adjustable="box")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8.5, loc="upper left", framealpha=0.85)


@dataclass(frozen=True)
class ViewStyle:
    """What every view shares, so views compare: one camera and one pair of colour scales."""

    camera: Camera
    scale: tuple[float, float]  # largest |result - SSD| and largest |inverse - forward| over the views


def view_style(m: MeshComparison, view: MeshView, idx: Sequence[int]) -> ViewStyle:
    """The camera and colour scales for the views at frame indices idx."""
    clouds = [plot_space(m.ssd[i], view.to_world[i], view.up) for i in idx]
    cam = choose_camera(clouds, [np.linalg.norm(m.inverse[i] - m.ssd[i], axis=1) for i in idx], view.triangles,
                        view.handed)
    corr = np.linalg.norm(np.concatenate([m.forward[idx], m.inverse[idx]]) - np.concatenate([m.ssd[idx]] * 2), axis=2)
    diff = np.linalg.norm(m.inverse[idx] - m.forward[idx], axis=2)
    return ViewStyle(cam, (max(float(corr.max()), 1e-12), max(float(diff.max()), 1e-12)))


def _frame(ax: Any, cam: Camera, fill: float = 0.94) -> None:
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


def _draw_mesh(ax: Any, pts: NDArray[np.float64], values: NDArray[np.float64], tris: NDArray[np.int64], cam: Camera,
               handed: float, cmap: Any, norm: Any) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    _frame(ax, cam)
    if len(tris):
        poly = pts[tris]
        normals, _ = face_normals(poly)
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


def draw_views(m: MeshComparison, view: MeshView, i: int, style: ViewStyle, title: str, path: str) -> None:
    """Four panels at frame i: SSD, forward, inverse (colour: |result - SSD|, one colour bar)
    and |inverse - forward| (its own colour bar). Colours are % of the bounding-box diagonal."""
    matplotlib, figure_cls, canvas_cls = require_matplotlib()
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    cam, diag = style.camera, m.diagonal or 1.0
    cmap, cmap_diff = matplotlib.colormaps["YlOrRd"], matplotlib.colormaps["PuBu"]
    norm, norm_diff = Normalize(0.0, style.scale[0] / diag * 100), Normalize(0.0, style.scale[1] / diag * 100)
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
        _draw_mesh(ax, plot_space(pts, view.to_world[i], view.up), values / diag * 100, view.triangles, cam,
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
    _save(fig, path)
