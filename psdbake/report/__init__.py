"""``psdbake compare``: SSD vs forward PSD vs inverse PSD, as a folder of files a person reads.

``compare`` computes the three results at every frame (``comparison``); ``prepare`` chooses
what to show and computes every number (``prepare``, ``choose``, ``stats``, with the mesh's
faces and bones read by ``psdbake.usd.meshview``); ``write_prepared`` draws the figures
(``figures``, ``camera``) and the page (``page``) and writes them all in one commit
(``folder``). The folder:

- ``index.html``   self-contained page (inline CSS, no scripts, no network), figures by relative name
- ``correction_angle.png``  the paper's Figure 3 analysis: how far a vertex's correction vector
  has turned, forward vs inverse, against the turn of the bone that carries the vertex
- ``views_<frame>.png``     the mesh at chosen frames, SSD / forward / inverse side by side,
  coloured by the correction magnitude, plus where forward and inverse disagree
- ``stats.csv``, ``stats.json``  per-frame statistics (``stats.json`` also carries the
  series behind ``correction_angle.png`` under ``vertex_turn``)
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import InputError, ReportError
from . import figures, page
from .choose import frame_index
from .comparison import Comparison, MeshComparison, compare, correction_turn, most_corrected_vertex
from .folder import MARKER, Writer, check_report_dir, text_writer, write_folder
from .prepare import ANGLE_FIGURE, PAGE, STATS_CSV, Prepared, frame_token, prepare, view_file
from .stats import METRICS, VertexTurn, labels

__all__ = [
    "Comparison", "MeshComparison", "Prepared", "ReportError", "VertexTurn", "check_report_dir", "compare",
    "correction_turn", "frame_token", "most_corrected_vertex", "parse_views", "prepare", "summary", "summary_lines",
    "write_prepared", "write_report",
]

MINUS = "\u2212"  # typographic minus, as the figures and the page write it


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


def _writers(rep: Prepared) -> list[tuple[str, Writer]]:
    """Every file of the report with the function that writes it, in rep.files order."""
    m, view = rep.mesh, rep.view
    idx = [frame_index(m, t) for t in rep.view_frames]
    style = figures.view_style(m, view, idx)
    _, examples = labels(rep.comparison, m)

    def views(t: float, i: int) -> Writer:
        weights = ", ".join(f"{e.split('@')[-1]}: {w:.2f}" for e, w in zip(examples, m.weights[i], strict=True))
        title = (f"{os.path.basename(rep.label)}  <{m.mesh.split('/')[-1]}>  frame {t:g}    "
                 f"example weights (by example frame): {weights}")
        return lambda path: figures.draw_views(m, view, i, style, title, path)

    out: list[tuple[str, Writer]] = [
        (MARKER, text_writer(json.dumps(rep.payload(), indent=1, sort_keys=True, allow_nan=False) + "\n")),
        (ANGLE_FIGURE, lambda path: figures.draw_correction_angle(rep.turns, path)),
        *((view_file(t), views(t, i)) for t, i in zip(rep.view_frames, idx, strict=True)),
        (STATS_CSV, text_writer(rep.table.csv_text())),
        (PAGE, text_writer(page.render(rep))),
    ]
    assert [name for name, _ in out] == rep.files
    return out


def write_prepared(rep: Prepared, out_dir: str) -> list[str]:
    """Write a prepared report into out_dir (created if missing), all files in one commit;
    returns the file names written (relative to out_dir), stats.json first and index.html last."""
    figures.require_matplotlib()  # fail before writing anything when matplotlib is missing
    check_report_dir(out_dir, rep.inputs)  # before drawing anything
    return write_folder(out_dir, _writers(rep), rep.inputs)


def summary(rep: Prepared, out_dir: str) -> dict[str, Any]:
    """The --json summary of psdbake compare."""
    largest: dict[str, Any] = {}
    frames = rep.table.records()
    for key, _ in METRICS:
        i = int(np.argmax([f[f"{key}_max"] for f in frames]))
        f = frames[i]
        largest[key] = {"max": f[f"{key}_max"], "max_rel": f[f"{key}_max_rel"], "time": f["time"]}
    turns = [{"vertex": t.vertex, "why": t.why, "joint": t.joint, "reference_time": t.reference_time,
              **{f"max_{k}": t.peak(k) for k in ("inverse", "forward", "carried_turn", "joint_turn")}}
             for t in rep.turns]
    return {"output": out_dir, "files": rep.files, "mesh": rep.mesh.mesh, "frames": len(rep.mesh.times),
            "views": list(rep.view_frames), "largest": largest, "vertex_turn": turns}


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
                     f"carried by its bone {figures.leaf(t['joint'])} it would turn {t['max_carried_turn'] * deg:.1f} deg")
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
