"""What the report shows when the user does not say: which mesh, which vertices, which frames.

Each choice prefers where the comparison has something to show (the largest correction,
the largest disagreement between forward and inverse PSD) and is deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import InputError
from ..lookup import matches
from ..usd.meshview import MeshView
from .comparison import Comparison, MeshComparison, most_corrected_vertex
from .stats import VertexTurn, same_story, vertex_turn

#: A --views frame matches a compared frame within this many frames (frames are whole or
#: written as decimals on the command line; 1e-6 is far below any real frame spacing).
FRAME_ATOL = 1e-6


def choose_mesh(comparison: Comparison, mesh: str | None) -> MeshComparison:
    """--mesh, else the mesh whose inverse correction is largest relative to its size."""
    if mesh is not None:
        hits = matches(mesh, [m.mesh for m in comparison.meshes])
        for m in comparison.meshes:
            if hits and m.mesh == hits[0]:
                return m
        raise InputError(f"{comparison.fit.asset} <{mesh}>: --mesh was not fitted (fitted: "
                         + ", ".join(f"<{m.mesh}>" for m in comparison.meshes) + ")")

    def size(m: MeshComparison) -> float:
        return float(np.linalg.norm(m.inverse - m.ssd, axis=2).max() / (m.diagonal or 1.0))

    return max(comparison.meshes, key=size)


def most_disagreeing_vertex(m: MeshComparison) -> int:
    """The vertex where forward and inverse PSD end up furthest apart over the animation."""
    return int(np.argmax(np.linalg.norm(m.inverse - m.forward, axis=2).max(axis=0)))


def check_vertex(m: MeshComparison, vertex: int, label: str) -> None:
    """Refuse a --vertex out of range or without a corrective (its turn would say nothing)."""
    n = m.ssd.shape[1]
    if not 0 <= vertex < n:
        raise InputError(f"{label} <{m.mesh}>: --vertex {vertex} is out of range (0..{n - 1})")
    if vertex not in set(m.corrected.tolist()):
        raise InputError(f"{label} <{m.mesh}>: --vertex {vertex} has no corrective "
                         f"(the most corrected vertex is {most_corrected_vertex(m)})")


def choose_turns(m: MeshComparison, view: MeshView, vertex: int | None) -> tuple[VertexTurn, ...]:
    """--vertex, else the most corrected vertex and, when it tells another story, the one
    where forward and inverse disagree most."""
    if vertex is not None:
        return (vertex_turn(m, view, vertex, "--vertex"),)
    first = most_corrected_vertex(m)
    turns = [vertex_turn(m, view, first, "most corrected")]
    second = most_disagreeing_vertex(m)
    if second != first:
        other = vertex_turn(m, view, second, "forward and inverse disagree most")
        if not same_story(turns[0], other):
            turns.append(other)
    return tuple(turns)


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


def view_frames(m: MeshComparison, views: Sequence[float] | None) -> tuple[float, ...]:
    """--views matched to compared frames, else choose_views; sorted, each once."""
    frames = [float(m.times[frame_index(m, t)]) for t in views] if views else choose_views(m)
    return tuple(sorted(set(frames)))


def frame_index(m: MeshComparison, t: float) -> int:
    """Index of frame t among the compared frames, or InputError naming --views."""
    hits = np.nonzero(np.isclose(m.times, t, rtol=0.0, atol=FRAME_ATOL))[0]
    if not len(hits):
        raise InputError(
            f"--views {t:g}: not a compared frame (frames {m.times[0]:g}..{m.times[-1]:g}, {len(m.times)} in all)"
        )
    return int(hits[0])
