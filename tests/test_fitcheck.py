"""After every fit, the product through a client's composition at each example (psdbake/fitting/fitcheck.py):
a fit whose product misses an example is degraded and exits 7, writing only its report, unless
--allow-degraded; -q never hides why. Animated rest points are refused up front, and the check
catches that class of input on its own too."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import fixture, generate
from pxr import Usd, UsdGeom

from psdbake import api
from psdbake import tolerances as tol
from psdbake.usd import validate

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
EXIT_DEGRADED = 7


def _animated_rest(tmp_path) -> str:
    """The arm with its mesh points animated at the examples' time codes (a cached simulation
    exported over the rest): UsdSkel skins those points, not the default ones."""
    path = str(tmp_path / "animated_rest.usda")
    shutil.copy(ASSET, path)
    stage = Usd.Stage.Open(path)
    attr = UsdGeom.Mesh(stage.GetPrimAtPath("/Arm/Geo/Tube")).GetPointsAttr()
    rest = np.array(attr.Get(), dtype=np.float64)
    for t in (1.0, 2.0, 3.0):
        attr.Set((rest * (1.0 + 0.01 * t)).astype(np.float32).tolist(), t)
    stage.Save()
    return path


def test_animated_rest_points_are_refused(run, tmp_path):
    asset = _animated_rest(tmp_path)
    out = tmp_path / "c.usda"
    code, _, err = run("fit", asset, EXAMPLES, "-o", out)
    assert code == 3 and not out.exists(), err
    assert err.count("\n") == 1 and "</Arm/Geo/Tube.points>" in err and "rest points are animated (3 time sample" in err


def test_the_check_catches_animated_rest_points_on_its_own(monkeypatch, tmp_path):
    """With the up-front refusal switched off, the inverse (which works on the default rest)
    is exact, yet the product through UsdSkel misses every example: all three degraded."""
    monkeypatch.setattr(validate, "require_static_rest", lambda scene, mesh: None)
    result = api.fit(_animated_rest(tmp_path), [EXAMPLES])
    assert result.missed == 0
    assert len(result.degraded) == 3 and min(c.error for c in result.degraded) > 1e-3


def test_a_good_fit_reproduces_every_example_through_the_client():
    result = api.fit(ASSET, [EXAMPLES])
    assert len(result.checks) == 3 and not result.degraded
    assert max(c.error for c in result.checks) <= tol.ROUNDTRIP_RTOL  # measured 1.7e-6: float32 offsets and skinning


SNAPPING_DEFORMER = """
import numpy as np
from psdbake.delta_mush import make


_mush = make()


def snap(stage, mesh_path, time):
    inner = _mush(stage, mesh_path, time)
    return lambda points: np.round(inner(points) / 1e-3) * 1e-3
"""


@pytest.mark.parametrize("quiet", [[], ["-q"]])
def test_a_degraded_fit_exits_7_writes_only_its_report_and_says_why(quiet, run, tmp_path):
    """A deck whose output snaps to a 1e-3 grid (tests/test_coupled.py's: far above the fit
    tolerance) cannot reach sculpts off the grid: the fit fails with exit 7, the CORRECTIVES
    are not written, the report is (written: false), and the warnings that say why reach
    stderr even with -q."""
    folder = tmp_path
    asset, examples = _regions_rig(folder)
    deformer = folder / "snapping.py"
    deformer.write_text(SNAPPING_DEFORMER)
    chain = ("--deformer", f"{deformer}:snap")
    out, report = folder / "c.usda", folder / "fit.json"
    code, stdout, err = run("fit", asset, examples, *chain, "-o", out, "--report", report, *quiet)
    assert code == EXIT_DEGRADED and not out.exists(), err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("psdbake: error:") and "not written: the product does not reproduce" in lines[-1]
    assert "--allow-degraded" in lines[-1]
    assert any("vertices missed the fit tolerance" in ln for ln in lines[:-1])  # what explains it
    data = json.loads(report.read_text())
    missed = sum("DEGRADED: the product misses example" in ln for ln in lines)
    assert data["written"] is False and len(data["degraded"]) == missed >= 1
    assert (stdout == "") == bool(quiet)
    assert all(e["reproduced"] is not None for m in data["meshes"] for e in m["examples"])
    # knowingly: written, exit 0, still warned
    code, _, err = run("fit", asset, examples, *chain, "-o", out, "--allow-degraded", "-q")
    assert code == 0 and out.exists() and err.count("DEGRADED") == missed


def test_smoothing_approximates_by_request_and_is_not_degraded(run, tmp_path):
    out = tmp_path / "c.usda"
    code, _, err = run("fit", ASSET, EXAMPLES, "-o", out, "--smoothing", "5", "-q")
    assert code == 0 and out.exists(), err
    assert "--smoothing 5: the product approximates the examples" in err


def _regions_rig(folder) -> tuple[str, str]:
    """tests/test_regions.py's arm, sculpted with known offsets: elbow, wrist, both."""
    import test_regions as regions

    asset = generate.build_arm(str(folder / "arm.usda"), generate.ArmSpec(rings=12, segments=8))
    poses = generate.write_animation(str(folder / "poses.usda"), regions.POSES)
    rest = generate.tube_points(12, 8)
    sculpts = generate.bake_sculpt(asset, poses, sorted(regions.POSES), lambda t: regions._offsets(rest, regions.POSES[t]))
    return asset, generate.write_examples(str(folder / "examples.usda"), poses, sculpts)

