"""Ground-truth fidelity: SSD vs forward PSD vs inverse PSD against a known deformation.

The arm's true shape at pose (elbow angle theta, wrist twist tau) is UsdSkel skinning of
the rest shape plus a rest-space corrective whose size follows a smooth function of the
pose: a biceps bulge growing with g(theta) and a forearm corrective following sin(tau)
(``fixtures/generate.elbow_bulge``). Examples are taken at a few poses (the bind pose
implicit); at >= 20 other poses the three methods are compared to the truth with the
same RBF weights, so the table isolates the space in which examples are interpolated.

Rows: the non-linear truth (g = sin) with the default Gaussian kernel and with a linear
polynomial term, and a truth that grows linearly in theta (g = theta / 90 deg), where
both PSDs share the RBF's own interpolation error.

Run: ``python -m benchmarks.fidelity`` (``make fidelity``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "fixtures"))

import generate  # noqa: E402

from psdbake.report import comparison as compare  # noqa: E402
from psdbake.settings import FitSettings  # noqa: E402
from psdbake.usd.blackbox import SkinningBlackBox  # noqa: E402
from psdbake.usd.read import Scene  # noqa: E402

#: Example poses: (elbow degrees, wrist twist degrees).
EXAMPLES = {1.0: (90.0, 0.0), 2.0: (135.0, 0.0), 3.0: (0.0, 70.0)}


def test_poses(count: int = 24) -> dict[float, tuple[float, float]]:
    """Intermediate poses inside the examples' span: half sweep the elbow 10..150 deg (no
    twist), half sweep the wrist twist 5..65 deg (elbow straight)."""
    half = count // 2
    out = {}
    for k in range(half):
        out[float(k + 1)] = (10.0 + 140.0 * k / (half - 1), 0.0)
    for k in range(count - half):
        out[float(half + k + 1)] = (0.0, 5.0 + 60.0 * k / (count - half - 1))
    return out


def _anim(path: str, poses: dict[float, tuple[float, float]]) -> str:
    return generate.write_animation(
        path, {t: {"Elbow": ((0, 0, 1), e), "Wrist": ((1, 0, 0), w)} for t, (e, w) in poses.items()}
    )


GROWTH: dict[str, Callable[[float], float]] = {
    "sin": lambda deg: math.sin(math.radians(deg)),
    "linear": lambda deg: deg / 90.0,
}


def _truth_offsets(spec: generate.ArmSpec, growth: Callable[[float], float]):
    """Rest-space truth: a forearm muscle that swells with growth(elbow) next to the elbow
    (where the skin follows the elbow's rotation) and a wrist-twist corrective."""
    bind = generate.tube_points(spec.rings, spec.segments)
    g = np.array(generate.geom_bind_matrix())[:3, :3]
    x, y, z = bind.T
    near_elbow = np.exp(-(((x - 2.6) / 0.45) ** 2)) * np.clip(y / generate.RADIUS + 0.3, 0.0, None)
    radial = np.stack([np.zeros_like(x), y, z], axis=1) / generate.RADIUS
    swell = 0.25 * near_elbow[:, None] * radial

    def offsets(elbow: float, wrist: float) -> np.ndarray:
        twist = generate.elbow_bulge(bind, 0.0, wrist)  # the forearm twist part alone
        return (growth(elbow) * swell + twist) @ np.linalg.inv(g)

    return offsets


@dataclass(frozen=True)
class Row:
    truth: str
    settings: str
    method: str
    mean: float  # mean over poses of the mean vertex error / diagonal
    max: float  # max vertex error over all poses / diagonal


def run(folder: str, truths=("sin", "linear")) -> list[Row]:
    spec = generate.ArmSpec()
    asset = generate.build_arm(os.path.join(folder, "arm.usda"), spec)
    poses_path = _anim(os.path.join(folder, "example_poses.usda"), EXAMPLES)
    shot = test_poses()
    anim = _anim(os.path.join(folder, "test_poses.usda"), shot)
    rows: list[Row] = []
    for truth in truths:
        offsets = _truth_offsets(spec, GROWTH[truth])
        sculpts = {}
        scene = Scene([poses_path, asset])
        rest = scene.rest_points(generate.MESH)
        for t, (e, w) in EXAMPLES.items():
            sculpts[t] = SkinningBlackBox(scene, generate.MESH, t)(rest + offsets(e, w))
        examples = generate.write_examples(os.path.join(folder, f"examples_{truth}.usda"), poses_path, sculpts)
        shot_scene = Scene([anim, asset])
        truth_pts = np.stack(
            [SkinningBlackBox(shot_scene, generate.MESH, t)(rest + offsets(e, w)) for t, (e, w) in shot.items()]
        )
        for label, settings in (("gaussian", FitSettings()), ("gaussian + linear", FitSettings(degree=1))):
            m = compare.compare(asset, [examples], anim, settings).meshes[0]
            for method, pts in (("SSD", m.ssd), ("forward PSD", m.forward), ("inverse PSD", m.inverse)):
                err = np.linalg.norm(pts - truth_pts, axis=2) / m.diagonal
                rows.append(Row(truth, label, method, float(err.mean(axis=1).mean()), float(err.max())))
    return rows


def table(rows: list[Row]) -> str:
    lines = [f"{'truth':<8} {'RBF':<18} {'method':<12} {'mean err/diag':>14} {'max err/diag':>13}"]
    for r in rows:
        lines.append(f"{r.truth:<8} {r.settings:<18} {r.method:<12} {r.mean:>14.3e} {r.max:>13.3e}")
    return "\n".join(lines)


ABOUT = (
    "The arm's true shape at pose (elbow θ, wrist twist τ) is UsdSkel skinning of the rest shape plus a "
    "rest-space forearm muscle swelling with g(θ) and a twist corrective following sin τ. Examples at elbow "
    "90° and 135° and twist 70° (bind pose implicit); 24 intermediate poses (12 elbow 10→150°, 12 twist "
    "5→65°). Forward and inverse PSD use the same RBF weights, so the rows differ only in the space the "
    "examples are interpolated in. Errors relative to the bounding-box diagonal: the mean over poses of "
    "the mean vertex error, and the largest vertex error over all poses."
)
TRUTH_LABEL = {"sin": "g = sin θ", "linear": "g = θ / 90°"}


def tables(rows: list[Row]) -> list[dict]:
    """The ground-truth table of the results record."""
    from . import results

    cells = [[TRUTH_LABEL.get(r.truth, r.truth), r.settings, r.method, f"{r.mean:.2e}", f"{r.max:.2e}"] for r in rows]
    return [results.table("Ground truth: SSD, forward PSD and inverse PSD", ["truth", "RBF", "method", "mean error",
                                                                                  "max error"], cells)]


def main(argv: list[str] | None = None) -> None:
    from . import results

    parser = argparse.ArgumentParser(description="Ground-truth fidelity table (SSD / forward / inverse PSD).")
    parser.add_argument("--json", default=results.path_of("fidelity"), help="where to write the results record")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        rows = run(folder)
    print(f"Arm rig, examples at elbow 90 and 135 deg and wrist twist 70 deg (bind pose implicit); "
          f"{len(test_poses())} intermediate poses; errors vs the true deformation.")
    print(table(rows))
    results.write("fidelity", argv, ABOUT, tables(rows), raw=[dataclasses.asdict(r) for r in rows], path=args.json)


if __name__ == "__main__":
    main()
