"""Whole-character fidelity: the humanoid fixture against its ground truth (``make fidelity``).

``fixtures/humanoid/`` (made by ``fixtures/humanoid.py``) is a 17-joint character whose true
shape at any pose is Pixar's ``UsdSkel.BakeSkinning`` of rest + known rest-space offsets:
seven regions (neck, shoulders, elbows, knees), each growing with sin of its joint's angle,
plus two combination terms (shoulder + elbow on each arm) that exist only when both joints
bend. Its EXAMPLES hold single-joint sculpts per region and one sculpt per combination; its
ANIM moves one region at a time and then all of them together.

Rows, each evaluated frame by frame over the shot and compared with the truth:

- plain skinning: ASSET + ANIM, no correctives;
- forward PSD: plain skinning + sum_c w_c(x) delta_c with the default fit's weights w_c, where
  delta_c = SKINNING_c(rest + shape_c) - SKINNING_c(rest) is corrective c carried into posed space
  at its own example's pose (for one group of cardinal correctives this is
  ``psdbake.report.comparison``'s sculpt_c - SKINNING_c(rest); for additive or combination
  correctives it is the same idea applied to each shape psdbake writes);
- inverse PSD, default fit: ``psdbake.api.fit(ASSET, [EXAMPLES], FitSettings())``;
- inverse PSD, hand-made groups: one ``FitSettings(group=region, drivers=(joint,))`` fit per
  region from that region's single-joint sculpts only (its own EXAMPLES file), all written
  into one CORRECTIVES with ``write_correctives(..., update=True)``.

Inverse rows are Pixar's ``BakeSkinning`` of the stack ASSET + CORRECTIVES + ANIM + WEIGHTS
(``api.evaluate`` + ``api.write_weights``). Errors: per vertex |p - truth|, mean and max over
the vertices of the frames in each part of the shot, relative to the rest mesh's bounding-box
diagonal and in millimetres. Also: the round trip at each combination example's pose
(evaluated with the examples' own poses as ANIM, compared with the sculpt).

Run: ``python -m benchmarks.humanoid`` (``--json`` prints the figures as JSON instead).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import traceback
from collections.abc import Callable

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURES = os.path.join(os.path.dirname(HERE), "fixtures")
sys.path.insert(0, FIXTURES)

import generate  # noqa: E402
import humanoid as hum  # noqa: E402

from psdbake import api  # noqa: E402
from psdbake.model.channels import column_weights  # noqa: E402
from psdbake.results import FitResult, WeightsResult  # noqa: E402
from psdbake.settings import FitSettings  # noqa: E402

ASSET = os.path.join(hum.HERE, hum.ASSET)
EXAMPLES = os.path.join(hum.HERE, hum.EXAMPLES)
ANIM = os.path.join(hum.HERE, hum.ANIM_FILE)

METHODS = ("plain skinning", "forward PSD", "inverse PSD, one global group", "inverse PSD, default fit",
           "inverse PSD, hand-made groups")
_KEEP: list = []


# --- Pixar's skinning of a stack ----------------------------------------------------------------

def bake(layers: list[str], times: list[float]) -> np.ndarray:
    """``UsdSkel.BakeSkinning`` of the stack ``layers`` (strongest first) at times: (f, n, 3)."""
    root = Sdf.Layer.CreateAnonymous(".usda")
    for path in layers:
        root.subLayerPaths.append(path)
    _KEEP.append(root)
    stage = Usd.Stage.Open(root)
    stage.SetEditTarget(Usd.EditTarget(root))
    if not UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(min(times), max(times))):
        raise RuntimeError(f"UsdSkel.BakeSkinning failed over {layers}")
    attr = UsdGeom.PointBased(stage.GetPrimAtPath(hum.MESH)).GetPointsAttr()
    return np.stack([np.array(attr.Get(Usd.TimeCode(t)), dtype=np.float64) for t in times])


def rest_points() -> np.ndarray:
    stage = Usd.Stage.Open(ASSET)
    return np.array(UsdGeom.PointBased(stage.GetPrimAtPath(hum.MESH)).GetPointsAttr().Get(), dtype=np.float64)


def truth(anim: str, poses: dict[float, hum.Pose]) -> np.ndarray:
    """The true shape at each pose: Pixar's skinning of rest + the known offsets."""
    field_points = hum.rest_points()
    baked = generate.bake_mesh_sculpts([anim, ASSET], sorted(poses),
                                       {hum.MESH: lambda t: hum.truth_offsets(poses[t], field_points)})[hum.MESH]
    return np.stack([baked[t] for t in sorted(poses)])


# --- correctives ----------------------------------------------------------------------------------

def stacked(correctives: str, anim: str, times: list[float], folder: str, tag: str
            ) -> tuple[np.ndarray, WeightsResult]:
    """ASSET + CORRECTIVES + ANIM + WEIGHTS baked at times, and the weights."""
    weights = api.evaluate(ASSET, correctives, anim)
    path = api.write_weights(weights, os.path.join(folder, f"weights_{tag}.usda"))
    return bake([path, anim, correctives, ASSET], times), weights


def channel_weights(weights: WeightsResult, times: list[float]) -> dict[str, np.ndarray]:
    """channel -> weight per time (psdbake's channels of the one animation)."""
    (anim,) = weights.animations
    rows = [int(np.argmin(np.abs(anim.times - t))) for t in times]
    return {ch: anim.weights[rows, k] for k, ch in enumerate(anim.channels) if ch.startswith("psd_")}


def corrective_shapes(correctives: str) -> dict[str, np.ndarray]:
    """channel -> dense rest-space offsets (n, 3) of the BlendShape it targets, as written."""
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths[:] = [correctives, ASSET]
    _KEEP.append(root)
    stage = Usd.Stage.Open(root)
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath(hum.MESH))
    n = len(UsdGeom.PointBased(stage.GetPrimAtPath(hum.MESH)).GetPointsAttr().Get())
    out = {}
    for ch, target in zip(binding.GetBlendShapesAttr().Get(), binding.GetBlendShapeTargetsRel().GetTargets(),
                          strict=True):
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        dense = np.zeros((n, 3))
        offsets = np.array(shape.GetOffsetsAttr().Get(), dtype=np.float64)
        indices = shape.GetPointIndicesAttr().Get()
        dense[np.array(indices, dtype=np.int64) if indices else slice(None)] = offsets
        out[str(ch)] = dense
    return out


def forward_deltas(result: FitResult, correctives: str, poses_layer: str, plain_at: dict[float, np.ndarray]
                   ) -> dict[str, np.ndarray]:
    """channel -> posed-space delta at its own example's pose (forward PSD's data; a channel
    carries its column's corrective times a scale, and skinning is linear in rest offsets)."""
    example_time = {}
    for m in result.meshes:
        column_time = {col: ex.time for col, ex in zip(m.channels, m.examples, strict=True) if col}
        for ch, col in zip(m.driver_data.channels, m.driver_data.channel_columns, strict=True):
            example_time[ch] = column_time[m.driver_data.shapes[int(col)]]
    out = {}
    for ch, shape in corrective_shapes(correctives).items():
        if ch not in example_time:
            continue
        t = example_time[ch]
        posed = generate.bake_mesh_sculpts([poses_layer, ASSET], [t], {hum.MESH: lambda _t, s=shape: s})[hum.MESH][t]
        out[ch] = posed - plain_at[t]
    return out


def forward(plain: np.ndarray, weights: dict[str, np.ndarray], deltas: dict[str, np.ndarray]) -> np.ndarray:
    out = plain.copy()
    for ch, delta in deltas.items():
        out += weights[ch][:, None, None] * delta[None]
    return out


def hand_grouped(folder: str) -> tuple[str, list[str]]:
    """One group per region from that region's single-joint sculpts, in one CORRECTIVES."""
    path = os.path.join(folder, "correctives_hand.usda")
    notes = []
    for region, spec in hum.REGIONS.items():
        poses = {t: hum.EXAMPLE_POSES[t] for t in hum.SINGLE_EXAMPLES if region in hum.EXAMPLE_ANGLES[t][1]}
        examples = hum.write_examples(os.path.join(folder, f"examples_{region}.usda"), ASSET, poses)
        result = api.fit(ASSET, [examples], FitSettings(group=region, drivers=(spec.joint,)))
        notes += list(result.warnings)
        api.write_correctives(result, path, update=True)
    return path, notes


# --- the run --------------------------------------------------------------------------------------

def errors(points: np.ndarray, true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points - true, axis=2)


def run(folder: str) -> dict:
    started = time.perf_counter()
    frames = sorted(hum.shot_poses())
    one = [t for t in frames if hum.ONE_JOINT_RANGE[0] <= t <= hum.ONE_JOINT_RANGE[1]]
    together = [t for t in frames if hum.ALL_TOGETHER_FRAMES[0] <= t <= hum.ALL_TOGETHER_FRAMES[1]]
    parts = {"one joint": [frames.index(t) for t in one], "all together": [frames.index(t) for t in together]}
    rest = rest_points()
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    mm = 1000.0 * UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(ASSET))

    # the examples' own poses as an ANIM (no sculpted points: they would be skinned again)
    poses_layer = hum.write_animation(os.path.join(folder, "example_poses.usda"), hum.EXAMPLE_POSES)
    combos = list(hum.COMBINATION_EXAMPLES)
    ex_times = sorted(hum.EXAMPLE_POSES)
    sculpts = {t: np.array(Sdf.Layer.FindOrOpen(EXAMPLES).QueryTimeSample(
        Sdf.Path(hum.MESH).AppendProperty("points"), t), dtype=np.float64) for t in ex_times}

    true = truth(ANIM, hum.shot_poses())
    shot: dict[str, np.ndarray | None] = dict.fromkeys(METHODS)
    at_combos: dict[str, np.ndarray | None] = dict.fromkeys(METHODS)
    shot["plain skinning"] = bake([ANIM, ASSET], frames)
    plain_ex = bake([poses_layer, ASSET], ex_times)
    at_combos["plain skinning"] = plain_ex[[ex_times.index(t) for t in combos]]
    failures: dict[str, str] = {}
    notes: dict[str, list[str]] = {}
    combo_weight = None

    def attempt(method: str, fn: Callable[[], None]) -> None:
        try:
            fn()
        except Exception as exc:  # reported verbatim; the other rows still run
            failures[method] = f"{type(exc).__name__}: {exc}"
            traceback.print_exc(file=sys.stderr)

    def default() -> None:
        nonlocal combo_weight
        result = api.fit(ASSET, [EXAMPLES], FitSettings())
        notes["default fit"] = [*result.warnings, *result.layout, *(f"skipped {s}" for s in result.skipped)]
        path = os.path.join(folder, "correctives_default.usda")
        api.write_correctives(result, path)
        shot["inverse PSD, default fit"], w_shot = stacked(path, ANIM, frames, folder, "default")
        ex_pts, w_ex = stacked(path, poses_layer, ex_times, folder, "default_examples")
        at_combos["inverse PSD, default fit"] = ex_pts[[ex_times.index(t) for t in combos]]
        # combination correctives (driven by several joints): their weights where one region moves alone
        ws = channel_weights(w_shot, frames)
        combo_columns = [column_weights(m.driver_data, np.stack([ws[c] for c in m.driver_data.channels], axis=1))
                         for m in result.meshes if len(m.drivers) > 1]
        combo_weight = max((float(np.abs(b[parts["one joint"]]).max()) for b in combo_columns), default=None)

        def forward_rows() -> None:
            deltas = forward_deltas(result, path, poses_layer, dict(zip(ex_times, plain_ex, strict=True)))
            shot["forward PSD"] = forward(shot["plain skinning"], ws, deltas)
            fwd_ex = forward(plain_ex, channel_weights(w_ex, ex_times), deltas)
            at_combos["forward PSD"] = fwd_ex[[ex_times.index(t) for t in combos]]

        attempt("forward PSD", forward_rows)

    attempt("inverse PSD, default fit", default)

    def global_group() -> None:
        """psdbake 0.1's default: one RBF over every driver (``--group main``)."""
        result = api.fit(ASSET, [EXAMPLES], FitSettings(group="main"))
        path = os.path.join(folder, "correctives_global.usda")
        api.write_correctives(result, path)
        shot["inverse PSD, one global group"], _ = stacked(path, ANIM, frames, folder, "global")
        ex_pts, _ = stacked(path, poses_layer, ex_times, folder, "global_examples")
        at_combos["inverse PSD, one global group"] = ex_pts[[ex_times.index(t) for t in combos]]

    attempt("inverse PSD, one global group", global_group)
    if "inverse PSD, default fit" in failures:
        failures.setdefault("forward PSD", "needs the default fit's weights: " + failures["inverse PSD, default fit"])

    def hand() -> None:
        path, hand_notes = hand_grouped(folder)
        notes["hand-made groups"] = hand_notes
        shot["inverse PSD, hand-made groups"], _ = stacked(path, ANIM, frames, folder, "hand")
        ex_pts, _ = stacked(path, poses_layer, ex_times, folder, "hand_examples")
        at_combos["inverse PSD, hand-made groups"] = ex_pts[[ex_times.index(t) for t in combos]]

    attempt("inverse PSD, hand-made groups", hand)

    rows = []
    for method in METHODS:
        pts = shot[method]
        row: dict = {"method": method, "error": failures.get(method)}
        if pts is not None:
            err = errors(pts, true)
            for part, idx in parts.items():
                e = err[idx]
                row[part] = {"mean": float(e.mean()) / diagonal, "max": float(e.max()) / diagonal,
                             "mean_mm": float(e.mean()) * mm, "max_mm": float(e.max()) * mm}
        rows.append(row)
    combo_rows = []
    for k, t in enumerate(combos):
        entry: dict = {"time": t, "angles": hum.EXAMPLE_ANGLES[t][1]}
        for method in METHODS:
            pts = at_combos[method]
            entry[method] = None if pts is None else float(errors(pts[k][None], sculpts[t][None]).max()) / diagonal
        combo_rows.append(entry)
    return {
        "fixture": {"asset": os.path.relpath(ASSET), "examples": os.path.relpath(EXAMPLES),
                    "anim": os.path.relpath(ANIM), "points": len(rest), "diagonal": diagonal,
                    "diagonal_mm": diagonal * mm, "one_joint_frames": [one[0], one[-1]],
                    "all_together_frames": [together[0], together[-1]]},
        "rows": rows, "combinations": combo_rows, "failures": failures, "notes": notes,
        "max_combination_weight_one_joint_frames": combo_weight,
        "criteria": criteria(rows), "seconds": time.perf_counter() - started,
    }


def criteria(rows: list[dict]) -> dict[str, bool | None]:
    """Issue 12's targets for the default fit over the all-together frames."""
    by = {r["method"]: r.get("all together") for r in rows}
    plain, default, hand = by["plain skinning"], by["inverse PSD, default fit"], by["inverse PSD, hand-made groups"]
    if not (plain and default):
        return {}
    return {
        "mean <= 10% of plain": default["mean"] <= 0.10 * plain["mean"],
        "mean <= hand-made groups": None if not hand else default["mean"] <= hand["mean"],
        "max <= 15% of plain": default["max"] <= 0.15 * plain["max"],
    }


def _cell(row: dict, part: str, key: str) -> str:
    stats = row.get(part)
    if stats is None:
        return "failed"
    return f"{stats[key]:.2e}" if not key.endswith("mm") else f"{stats[key]:.4f}"


def render(report: dict) -> str:
    fx = report["fixture"]
    lines = [
        f"Humanoid ({fx['asset']}): {fx['points']} points, diagonal {fx['diagonal_mm']:.0f} mm; "
        f"one joint at a time = frames {fx['one_joint_frames'][0]:g}-{fx['one_joint_frames'][1]:g}, "
        f"all together = frames {fx['all_together_frames'][0]:g}-{fx['all_together_frames'][1]:g}. "
        "Vertex error vs the ground truth (relative to the diagonal, and in mm).",
        "",
        "| method | one joint: mean | max | mean mm | max mm | all together: mean | max | mean mm | max mm |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in report["rows"]:
        cells = [_cell(row, part, key) for part in ("one joint", "all together")
                 for key in ("mean", "max", "mean_mm", "max_mm")]
        lines.append(f"| {row['method']} | " + " | ".join(cells) + " |")
    lines += ["", "Round trip at each combination example's pose (max vertex error / diagonal vs the sculpt):", "",
              "| example | pose (deg) | " + " | ".join(METHODS) + " |", "|---|---|" + "---|" * len(METHODS)]
    for c in report["combinations"]:
        pose = ", ".join(f"{r} {a:g}" for r, a in c["angles"].items())
        cells = ["failed" if c[m] is None else f"{c[m]:.2e}" for m in METHODS]
        lines.append(f"| t={c['time']:g} | {pose} | " + " | ".join(cells) + " |")
    if report["max_combination_weight_one_joint_frames"] is not None:
        lines += ["", "Default fit: largest combination-corrective weight over the one-joint frames: "
                  f"{report['max_combination_weight_one_joint_frames']:.2e}"]
    if report["criteria"]:
        lines += ["", "Issue 12 targets (default fit, all-together frames): " + "; ".join(
            f"{k}: {'n/a' if v is None else ('yes' if v else 'NO')}" for k, v in report["criteria"].items())]
    for method, why in report["failures"].items():
        lines += ["", f"{method} FAILED: {why}"]
    for who, msgs in report["notes"].items():
        for msg in msgs:
            lines.append(f"note ({who}): {msg}")
    lines += ["", f"({report['seconds']:.1f} s)"]
    return "\n".join(lines)


ABOUT = (
    "A 17-joint humanoid (`fixtures/humanoid/`, made by `fixtures/humanoid.py`) with seven regions (neck, "
    "shoulders, elbows, knees) whose true rest-space correctives follow sin of their joint's bend, plus a "
    "combination term for each shoulder+elbow pair (sin·sin, zero when either is at bind). 13 sculpts in one "
    "EXAMPLES file: 11 bend one joint, 2 bend a shoulder and its elbow. The shot moves one region at a time, "
    "past the sculpted angles, then all seven together. Errors relative to the bounding-box diagonal."
)


def tables(report: dict) -> list[dict]:
    """The humanoid's tables for the results record."""
    from . import results

    fx = report["fixture"]
    rows = [[row["method"], *(_cell(row, part, key) for part in ("one joint", "all together") for key in ("mean", "max"))]
            for row in report["rows"]]
    notes = (f"{fx['points']} points, diagonal {fx['diagonal_mm']:.0f} mm; one joint at a time = frames "
             f"{fx['one_joint_frames'][0]:g}-{fx['one_joint_frames'][1]:g}, all together = frames "
             f"{fx['all_together_frames'][0]:g}-{fx['all_together_frames'][1]:g}.")
    if report["max_combination_weight_one_joint_frames"] is not None:
        notes += (" Default fit: the largest combination weight while one joint moves alone is "
                  f"{report['max_combination_weight_one_joint_frames']:.1e}.")
    out = [results.table("A whole character: vertex error against the ground truth",
                         ["method", "one joint: mean", "max", "all together: mean", "max"], rows, notes)]
    combos = [[f"t={c['time']:g}", ", ".join(f"{r} {a:g}" for r, a in c["angles"].items()),
               *("failed" if c[m] is None else f"{c[m]:.2e}" for m in METHODS)] for c in report["combinations"]]
    out.append(results.table("Round trip at each combination sculpt's pose (max vertex error / diagonal)",
                             ["example", "pose (deg)", *METHODS], combos))
    return out


def main(argv: list[str] | None = None) -> None:
    from . import results

    parser = argparse.ArgumentParser(description="Whole-character fidelity table on fixtures/humanoid/.")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--record", default=results.path_of("humanoid"), help="where to write the results record")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        report = run(folder)
    print(json.dumps(report, indent=2, sort_keys=True) if args.json else render(report))
    results.write("humanoid", argv, ABOUT, tables(report), raw=report, path=args.record)


if __name__ == "__main__":
    main()
