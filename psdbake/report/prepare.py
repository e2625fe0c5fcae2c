"""Everything a report shows, computed and checked before anything is written.

``prepare`` chooses the mesh, vertices and frames, reads what it needs from USD (via
``psdbake.usd.meshview``) and computes every number; a bad ``--vertex`` or ``--views``
fails here, before the folder is touched.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .. import __version__
from ..usd.meshview import MeshView, layer_attribution, read_mesh_view
from .choose import check_vertex, choose_mesh, choose_turns, view_frames
from .comparison import Comparison, MeshComparison
from .folder import MARKER
from .stats import FrameStats, StatsTable, VertexTurn, frame_stats, labels, stats_table

ANGLE_FIGURE = "correction_angle.png"
STATS_CSV = "stats.csv"
PAGE = "index.html"


def frame_token(t: float) -> str:
    """Frame number for file names: 12 -> '12', 12.5 -> '12.5', -3 -> '-3'."""
    return f"{int(t)}" if float(t).is_integer() else f"{t:g}".replace("+", "")


def view_file(t: float) -> str:
    """File name of the views figure at frame t."""
    return f"views_{frame_token(t)}.png"


@dataclass(frozen=True)
class Prepared:
    """A report ready to write: the comparison, the choices made and every number."""

    comparison: Comparison
    mesh: MeshComparison
    label: str  # the asset as the user named it
    inputs: tuple[str, ...]  # every file read: never overwritten by the report
    view: MeshView
    turns: tuple[VertexTurn, ...]
    view_frames: tuple[float, ...]
    stats: FrameStats
    table: StatsTable
    credits: tuple[str, ...]  # attributions the input layers carry, shown on the page

    @property
    def files(self) -> list[str]:
        """The report's files, in the order they are written (stats.json first)."""
        return [MARKER, ANGLE_FIGURE, *(view_file(t) for t in self.view_frames), STATS_CSV, PAGE]

    def payload(self) -> dict[str, Any]:
        """stats.json: what was compared, the per-frame table, the turn series, the files."""
        comparison, m = self.comparison, self.mesh
        drivers, examples = labels(comparison, m)
        return {
            "psdbake": __version__, "command": "compare", "asset": self.label,
            "examples": list(comparison.fit.example_files), "anim": comparison.anim, "mesh": m.mesh,
            "points": m.ssd.shape[1], "corrected_vertices": len(m.corrected), "diagonal": m.diagonal,
            "drivers": drivers, "weight_columns": examples, "columns": list(self.table.header),
            "frames": self.table.records(), "vertex_turn": [t.as_json() for t in self.turns],
            "views": list(self.view_frames), "files": self.files,
        }


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
    fit = comparison.fit
    all_inputs = (fit.asset, *fit.example_files, comparison.anim, *inputs)
    m = choose_mesh(comparison, mesh)
    if vertex is not None:
        check_vertex(m, vertex, label)
    frames = view_frames(m, views)
    view = read_mesh_view([comparison.anim, fit.asset], comparison.anim, m.mesh, m.times, m.ssd.shape[1])
    turns = choose_turns(m, view, vertex)
    stats = frame_stats(m)
    credits = layer_attribution([fit.asset, *fit.example_files, comparison.anim])
    return Prepared(comparison, m, label, all_inputs, view, turns, frames, stats, stats_table(comparison, m, stats),
                    credits)
