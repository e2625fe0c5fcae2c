"""The report's numbers as data: per-frame distances, the per-frame table, and the turn of
one vertex's correction (the series behind ``correction_angle.png``).

Distances are between the three results of ``comparison.compare`` (SSD, forward PSD,
inverse PSD), per vertex, in scene units; ``*_rel`` divide by the bounding-box diagonal.
Angles are radians; NaN where a direction is undefined (a vanishing correction).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..usd.meshview import MeshView
from .comparison import Comparison, MeshComparison, correction_turn

Series = NDArray[np.float64]  # (f,) one value per compared frame

#: The three distances, by key, with the name the page and the terminal show.
METRICS = (
    ("forward_ssd", "|forward \u2212 SSD|"),
    ("inverse_ssd", "|inverse \u2212 SSD|"),
    ("inverse_forward", "|inverse \u2212 forward|"),
)


@dataclass(frozen=True)
class Distance:
    """One distance between two results, per frame: largest and mean over the vertices."""

    max: Series
    mean: Series  # over the vertices with a corrective (every vertex when none has)
    max_rel: Series
    mean_rel: Series


@dataclass(frozen=True)
class FrameStats:
    """Per frame, how far apart the three results are."""

    forward_ssd: Distance
    inverse_ssd: Distance
    inverse_forward: Distance

    def metric(self, key: str) -> Distance:
        """The Distance of a METRICS key."""
        value: Distance = getattr(self, key)
        return value


def frame_stats(m: MeshComparison) -> FrameStats:
    """Per frame: max and mean distance between the three results. Means are over the
    vertices that have a corrective (every vertex when none has)."""
    cols = m.corrected if len(m.corrected) else np.arange(m.ssd.shape[1])
    diag = m.diagonal if m.diagonal > 0 else 1.0

    def distance(a: NDArray[np.float64], b: NDArray[np.float64]) -> Distance:
        d = np.linalg.norm(a - b, axis=2)
        mx, mean = d.max(axis=1), d[:, cols].mean(axis=1)
        return Distance(mx, mean, mx / diag, mean / diag)

    return FrameStats(distance(m.forward, m.ssd), distance(m.inverse, m.ssd), distance(m.inverse, m.forward))


def finite(values: Sequence[Any]) -> list[Any]:
    """JSON has no NaN or inf: None in their place."""
    return [None if (isinstance(v, float) and not math.isfinite(v)) else v for v in values]


@dataclass(frozen=True)
class StatsTable:
    """stats.csv: one row per frame (time, driver angles, example weights, distances)."""

    header: tuple[str, ...]
    rows: tuple[tuple[float, ...], ...]

    def records(self) -> list[dict[str, Any]]:
        """One dict per frame, non-finite values as None (stats.json's ``frames``)."""
        return [dict(zip(self.header, finite(r), strict=True)) for r in self.rows]

    def csv_text(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header)
        for row in self.rows:
            w.writerow([repr(float(v)) for v in row])
        return buf.getvalue()


def labels(comparison: Comparison, m: MeshComparison) -> tuple[list[str], list[str]]:
    """Driver joint paths and the example label of each weight column."""
    fit = next(f for f in comparison.fit.meshes if f.mesh == m.mesh)
    examples = [ex.label for ex, ch in zip(fit.examples, fit.channels, strict=True) if ch]
    return list(fit.drivers), examples


def stats_table(comparison: Comparison, m: MeshComparison, stats: FrameStats) -> StatsTable:
    """stats.csv: header and one row per frame."""
    drivers, examples = labels(comparison, m)
    columns = [(f"{k}_{s}", getattr(stats.metric(k), s)) for k, _ in METRICS for s in ("max", "mean")]
    relative = [(f"{k}_{s}_rel", getattr(stats.metric(k), f"{s}_rel")) for k, _ in METRICS for s in ("max", "mean")]
    header = (["time"] + [f"angle_rad:{d}" for d in drivers] + [f"weight:{e}" for e in examples]
              + [name for name, _ in columns + relative])
    rows = []
    for i, t in enumerate(m.times):
        rows.append((float(t), *m.driver_angles[i].tolist(), *m.weights[i].tolist(),
                     *(float(values[i]) for _, values in columns + relative)))
    return StatsTable(tuple(header), tuple(rows))


@dataclass(frozen=True)
class VertexTurn:
    """How far one vertex's correction turns, forward vs inverse, against its bone.

    forward, inverse: ``comparison.correction_turn`` from the reference frame (where the
    inverse correction is largest). carried_turn: how far that reference correction would
    have turned had the vertex's bone (its largest skinning weight) carried it rigidly,
    which is what rest-space interpolation predicts for one example and one bone.
    joint_turn: that bone's rotation angle since the reference frame (skeleton space), an
    upper bound of carried_turn: a vector turns by the full angle only when it is
    perpendicular to the rotation axis."""

    vertex: int
    why: str  # why this vertex was chosen, as the page says it
    reference_time: float
    joint: str | None  # the vertex's bone; None when no joint carries it
    times: Series
    carried_turn: Series
    joint_turn: Series
    forward: Series
    inverse: Series
    forward_magnitude: Series
    inverse_magnitude: Series

    def peak(self, key: str) -> float:
        """Largest value of a series (0 when it is all NaN or negative)."""
        return float(np.nanmax(np.append(np.array(getattr(self, key), dtype=float), 0.0)))

    def as_json(self) -> dict[str, Any]:
        """stats.json's ``vertex_turn`` entry."""
        out: dict[str, Any] = {"vertex": self.vertex, "why": self.why, "reference_time": self.reference_time,
                               "joint": self.joint}
        for key in ("times", "carried_turn", "joint_turn", "forward", "inverse", "forward_magnitude", "inverse_magnitude"):
            out[key] = finite(getattr(self, key).tolist())
        return out


def vertex_turn(m: MeshComparison, view: MeshView, vertex: int, why: str) -> VertexTurn:
    """The series behind one row of correction_angle.png (radians, NaN where undefined)."""
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
    return VertexTurn(int(vertex), why, float(m.times[ref]), view.joints[joint] if joint >= 0 else None,
                      m.times, carried_turn, joint_turn, forward, inverse,
                      np.linalg.norm(fwd_vec, axis=1), inv_mag)


def same_story(a: VertexTurn, b: VertexTurn, atol: float = math.radians(2.0)) -> bool:
    """Two turns that would draw the same picture (neighbouring vertices)."""
    if a.joint != b.joint:
        return False
    with np.errstate(invalid="ignore"):
        gaps = [np.nanmax(np.abs(getattr(a, k) - getattr(b, k)), initial=0.0) for k in ("forward", "inverse")]
    return bool(max(gaps) < atol)
