"""Sculpts from any frame: correctives fitted from frames of a shot, measured on motions nobody sculpted.

The humanoid of ``fixtures/humanoid/`` (17 joints, seven regions) in a shot where every region
moves at once, each on its own rate and phase (``humanoid.sculpted_shot_angles``); ten of its
frames are sculpted (``humanoid.SHOT_SCULPTS``), with two known truths (``humanoid.TRUTHS``):

- ``additive``: every region's bulge (sin of its joint's bend), no combination term;
- ``dual quaternion``: the same character skinned with dual quaternions, the look a TD sculpts
  onto its linear-blend rig (not additive across joints).

Rows per truth and motion, each Pixar's ``BakeSkinning`` of the stack against the truth:

- plain skinning (no correctives);
- default fit (``psdbake fit`` with no options) of the ten shot sculpts;
- one global group (``--group main``) of the same sculpts: what the default fit made of them
  before per-joint terms (every example in one RBF over every joint that moved);
- for reference, the default fit of eleven single-joint sculpts of the same truth
  (``humanoid.SINGLE_EXAMPLES``' poses).

Motions: the sculpted shot's 60 frames, ANIM's one-joint part (``humanoid.ONE_JOINT_FRAMES``:
one region at a time, past the sculpted angles) and a second shot with other rates and phases
(``humanoid.second_shot_angles``). Errors per vertex |p - truth|, mean and max over every vertex
of every frame, relative to the rest mesh's bounding-box diagonal and in millimetres. Also the
round trip of each fit at its own examples (``FitResult.checks``: the largest vertex error over
the sculpt's diagonal).

Run: ``python -m benchmarks.shots`` (``--json`` prints the figures as JSON instead).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np
from pxr import Usd, UsdGeom

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "fixtures"))

import generate  # noqa: E402
import humanoid as hum  # noqa: E402

from psdbake import api  # noqa: E402
from psdbake.settings import FitSettings  # noqa: E402

from . import humanoid as whole  # noqa: E402

ASSET = whole.ASSET
MOTIONS = ("sculpted shot", "one joint", "second shot")
METHODS = ("plain skinning", "default fit", "one global group", "single-joint sculpts, default fit")
#: what each fitted row fits: (examples key of ``humanoid.write_shot_files``, settings)
FITS = {"default fit": ("", FitSettings()), "one global group": ("", FitSettings(group="main")),
        "single-joint sculpts, default fit": ("single ", FitSettings())}


def _motions(folder: str, files: dict[str, str]) -> dict[str, tuple[str, dict[float, hum.Pose]]]:
    """motion -> (ANIM layer, frame -> pose)."""
    one = {t: p for t, p in hum.shot_poses().items() if hum.ONE_JOINT_RANGE[0] <= t <= hum.ONE_JOINT_RANGE[1]}
    return {"sculpted shot": (files["shot"], {t: hum.pose_of(a) for t, a in hum.sculpted_shot_angles().items()}),
            "one joint": (hum.write_animation(os.path.join(folder, "one_joint.usda"), one), one),
            "second shot": (files["second"], {t: hum.pose_of(a) for t, a in hum.second_shot_angles().items()})}


def _truth(truth: str, files: dict[str, str], anim: str, poses: dict[float, hum.Pose]) -> np.ndarray:
    """The true shape at each frame: (f, n, 3)."""
    times = sorted(poses)
    rest = hum.rest_points()
    if truth == "additive":
        baked = generate.bake_mesh_sculpts([anim, ASSET], times,
                                           {hum.MESH: lambda t: hum.additive_offsets(poses[t], rest)})[hum.MESH]
    else:
        baked = generate.bake_mesh_sculpts([anim, files["dq_asset"]], times,
                                           {hum.MESH: lambda t: np.zeros_like(rest)})[hum.MESH]
    return np.stack([baked[t] for t in times])


def _stats(err: np.ndarray, diagonal: float, mm: float) -> dict[str, float]:
    return {"mean": float(err.mean()) / diagonal, "max": float(err.max()) / diagonal,
            "mean_mm": float(err.mean()) * mm, "max_mm": float(err.max()) * mm}


def run(folder: str, truths: tuple[str, ...] = hum.TRUTHS, methods: tuple[str, ...] = METHODS) -> dict:
    """Every truth x motion x method: errors against the truth; per fit its groups and round trip."""
    started = time.perf_counter()
    files = hum.write_shot_files(folder, ASSET)
    motions = _motions(folder, files)
    rest = whole.rest_points()
    diagonal = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    mm = 1000.0 * UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(ASSET))
    rows, fits = [], {}
    for truth in truths:
        written = {}
        for method in methods:
            if method not in FITS:
                continue
            tag, settings = FITS[method]
            t0 = time.perf_counter()
            result = api.fit(ASSET, [files[f"{tag}{truth}"]], settings)
            seconds = time.perf_counter() - t0
            path = os.path.join(folder, f"correctives_{truth}_{method}.usda".replace(" ", "_").replace(",", ""))
            api.write_correctives(result, path, allow_degraded=True)  # every method measured, degraded or not
            written[method] = path
            fits[f"{truth} / {method}"] = {
                "seconds": seconds, "examples": len(result.checks),
                "roundtrip_max": max(c.error for c in result.checks),
                "groups": [{"group": m.group, "drivers": [d.split("/")[-1] for d in m.drivers], "role": m.role,
                            "vertices": m.vertices} for m in result.meshes],
            }
        for motion in MOTIONS:
            anim, poses = motions[motion]
            times = sorted(poses)
            true = _truth(truth, files, anim, poses)
            for method in methods:
                if method == "plain skinning":
                    points = whole.bake([anim, ASSET], times)
                else:
                    tag = f"{truth}_{method}_{motion}".replace(" ", "_").replace(",", "")
                    points, _ = whole.stacked(written[method], anim, times, folder, tag)
                rows.append({"truth": truth, "motion": motion, "method": method, "frames": len(times),
                             **_stats(np.linalg.norm(points - true, axis=2), diagonal, mm)})
    return {"fixture": {"asset": os.path.relpath(ASSET), "points": len(rest), "diagonal_mm": diagonal * mm,
                        "sculpted_frames": list(hum.SHOT_SCULPTS), "shot_frames": hum.SCULPTED_SHOT_FRAMES,
                        "second_shot_frames": hum.SECOND_SHOT_FRAMES,
                        "one_joint_frames": list(hum.ONE_JOINT_RANGE)},
            "rows": rows, "fits": fits, "seconds": time.perf_counter() - started}


def row_of(report: dict, truth: str, motion: str, method: str) -> dict:
    (row,) = [r for r in report["rows"] if (r["truth"], r["motion"], r["method"]) == (truth, motion, method)]
    return row


def render(report: dict) -> str:
    fx = report["fixture"]
    lines = [f"Shot sculpts on {fx['asset']}: {fx['points']} points, diagonal {fx['diagonal_mm']:.0f} mm; sculpted "
             f"frames {', '.join(f'{t:g}' for t in fx['sculpted_frames'])} of {fx['shot_frames']}.", "",
             "| truth | motion | method | mean | max | mean mm | max mm |", "|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {r['truth']} | {r['motion']} | {r['method']} | {r['mean']:.2e} | {r['max']:.2e} | "
                     f"{r['mean_mm']:.4f} | {r['max_mm']:.3f} |")
    lines.append("")
    for name, fit in report["fits"].items():
        groups = "; ".join(f"{g['group']} ({', '.join(g['drivers'])}: {g['vertices']} points)" for g in fit["groups"])
        lines.append(f"{name}: {fit['seconds']:.1f} s, round trip max {fit['roundtrip_max']:.1e}; groups: {groups}")
    lines += ["", f"({report['seconds']:.1f} s)"]
    return "\n".join(lines)


ABOUT = (
    "Sculpts from any frame. The humanoid of `fixtures/humanoid/` in a shot where all seven regions move at once, "
    "each on its own rate and phase; ten of its 60 frames are sculpted, with two known truths: `additive` (each "
    "region's bulge, no combination term) and `dual quaternion` (the same character skinned with dual quaternions, "
    "the look a TD sculpts onto its linear-blend rig; not additive across joints). Measured on the sculpted shot, "
    "on motions nobody sculpted (one joint at a time, past the sculpted angles; a second shot with other rates and "
    "phases). Rows: plain skinning; the default fit of the ten shot sculpts; the same sculpts in one global group "
    "(`--group main`, which is what the default fit made of them before per-joint terms); for reference the "
    "default fit of eleven single-joint sculpts of the same truth. Errors per vertex over every frame, relative to "
    "the bounding-box diagonal (2268 mm)."
)


def tables(report: dict) -> list[dict]:
    from . import results

    out = []
    for truth in dict.fromkeys(r["truth"] for r in report["rows"]):
        rows = []
        for method in dict.fromkeys(r["method"] for r in report["rows"]):
            cells = [method]
            for motion in MOTIONS:
                r = row_of(report, truth, motion, method)
                cells += [f"{r['mean']:.2e}", f"{r['max']:.2e}"]
            rows.append(cells)
        fits = {k.split(" / ", 1)[1]: v for k, v in report["fits"].items() if k.startswith(f"{truth} / ")}
        notes = "; ".join(f"{method}: every example round-trips to {fit['roundtrip_max']:.1e} of the diagonal, "
                          f"{len(fit['groups'])} groups" for method, fit in fits.items())
        out.append(results.table(f"Shot sculpts, {truth} truth: vertex error against the truth",
                                 ["method", "sculpted shot: mean", "max", "one joint: mean", "max",
                                  "second shot: mean", "max"], rows, notes))
    return out


def main(argv: list[str] | None = None) -> None:
    from . import results

    parser = argparse.ArgumentParser(description="Shot sculpts on the humanoid: motions nobody sculpted.")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--record", default=results.path_of("shots"), help="where to write the results record")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        report = run(folder)
    print(json.dumps(report, indent=2, sort_keys=True) if args.json else render(report))
    results.write("shots", argv, ABOUT, tables(report), raw=report, path=args.record)


if __name__ == "__main__":
    main()
