"""The three commands end to end, as a user runs them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, bake_stack, diagonal, fixture, generate, sculpt
from pxr import Sdf, Usd

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
POSES, ANIM = fixture("arm_poses.usda"), fixture("arm_anim.usda")
SWIRL = os.path.join(ROOT, "tests", "data", "swirl_deformer.py") + ":factory"


def test_pose_writes_plain_skinning_and_the_pose(run, tmp_path):
    out = tmp_path / "to_sculpt.usda"
    code, stdout, err = run("pose", ASSET, "--anim", POSES, "-o", out)
    assert code == 0, err
    assert "3 time code" in stdout
    for t in (1.0, 2.0, 3.0):
        ours = sculpt(str(out), generate.MESH, t)
        # the pose layer alone (over ASSET) is enough for Pixar's bake to pose the same way
        pixar = bake_stack([POSES, ASSET], t)[generate.MESH]
        assert np.abs(ours - pixar).max() <= 1e-6 * diagonal(pixar)  # float32 round-off of both
    # fitting the unsculpted poses finds nothing to correct: a clear refusal
    code, _, err = run("fit", ASSET, out, "-o", tmp_path / "c.usda")
    assert code == 4 and "no example differs from plain skinning" in err
    assert not (tmp_path / "c.usda").exists()


def test_fit_report_and_summary(run, tmp_path):
    out, report = tmp_path / "corr.usda", tmp_path / "report.json"
    code, stdout, err = run("fit", ASSET, EXAMPLES, "-o", out, "--report", report)
    assert code == 0, err
    assert "wrote" in stdout and "max/diag" in stdout
    data = json.loads(report.read_text())
    ex = data["meshes"][0]["examples"]
    assert [e["time"] for e in ex] == [1.0, 2.0, 3.0]
    for e in ex:
        assert e["vertices_solved"] > 0 and e["evaluations"] > 0 and e["missed"] == 0
        assert e["max_residual_rel"] <= 1e-6
    assert data["meshes"][0]["drivers"] == ["Shoulder/Elbow", "Shoulder/Elbow/Wrist"]


def test_outputs_are_byte_identical_across_runs(run, tmp_path):
    for ext in ("usda", "usdc"):
        outs = []
        for k in range(2):
            corr, weights = tmp_path / f"c{k}.{ext}", tmp_path / f"w{k}.{ext}"
            assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
            assert run("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "-q")[0] == 0
            outs.append((corr.read_bytes(), weights.read_bytes()))
        assert outs[0] == outs[1]


def test_eval_frames_and_points_cache_match_bakeskinning_of_the_stack(run, tmp_path):
    corr, weights, cache = tmp_path / "c.usda", tmp_path / "w.usda", tmp_path / "cache.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    code, _, err = run("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "--frames", "10:20", "--points-cache", cache)
    assert code == 0, err
    layer = Sdf.Layer.FindOrOpen(str(weights))
    times = layer.ListTimeSamplesForPath(Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights"))
    assert list(times) == [float(f) for f in range(10, 21)]
    for t in (10.0, 15.0, 20.0):
        pixar = bake_stack([str(weights), ANIM, str(corr), ASSET], t)[generate.MESH]
        cached = sculpt(str(cache), generate.MESH, t)
        assert np.abs(cached - pixar).max() <= 1e-6 * diagonal(pixar)
    # the cache needs no UsdSkel: its SkelRoot is an Xform
    stage = Usd.Stage.Open(str(cache))
    assert stage.GetPrimAtPath(generate.ROOT).GetTypeName() == "Xform"


def test_existing_blend_shapes_are_kept_everywhere(run, tmp_path):
    asset = tmp_path / "arm_flex.usda"
    generate.build_arm(str(asset), generate.ArmSpec(blend_shapes=True))
    poses = tmp_path / "poses.usda"
    generate.write_animation(str(poses), generate.EXAMPLE_POSES, blend_shapes={1.0: 0.5, 2.0: 1.0, 3.0: 0.0})
    sculpts = generate.bake_sculpt(str(asset), str(poses), [1.0, 2.0, 3.0], generate.example_offsets(generate.ArmSpec()))
    examples = tmp_path / "examples.usda"
    generate.write_examples(str(examples), str(poses), sculpts)
    corr, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    assert run("fit", asset, examples, "-o", corr, "-q")[0] == 0
    assert run("eval", asset, corr, "--anim", poses, "-o", weights, "-q")[0] == 0
    stage = Usd.Stage.Open(str(corr))
    channels = list(stage.GetPrimAtPath(generate.MESH).GetAttribute("skel:blendShapes").Get())
    assert channels[0] == "flex" and len(channels) == 4
    wlayer = Sdf.Layer.FindOrOpen(str(weights))
    anim = wlayer.GetPrimAtPath(generate.ANIM)
    assert anim.properties["blendShapes"].default[0] == "flex"
    for t, w in ((1.0, 0.5), (2.0, 1.0)):
        # the animation's own channel keeps its exact weight
        assert wlayer.QueryTimeSample(anim.properties["blendShapeWeights"].path, t)[0] == pytest.approx(w, abs=0)
        baked = bake_stack([str(weights), _points_removed(examples), str(corr), str(asset)], t)[generate.MESH]
        target = sculpts[t]
        assert np.abs(baked - target).max() <= 1e-5 * diagonal(target)


_KEEP = []


def _points_removed(examples) -> str:
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(examples)))
    prim = layer.GetPrimAtPath(generate.MESH)
    prim.RemoveProperty(prim.properties["points"])
    _KEEP.append(layer)
    return layer.identifier


def test_deformer_chain_in_pose_fit_eval(run, tmp_path):
    """Sculpts made through a non-linear deformer are inverted through it (no closed form)."""
    to_sculpt = tmp_path / "to_sculpt.usda"
    assert run("pose", ASSET, "--anim", POSES, "-o", to_sculpt, "--deformer", SWIRL, "-q")[0] == 0
    # an artist's sculpt: move a third of the vertices of each pose a little
    layer = Sdf.Layer.FindOrOpen(str(to_sculpt))
    path = Sdf.Path(generate.MESH).AppendProperty("points")
    rng = np.random.default_rng(4)
    for t in layer.ListTimeSamplesForPath(path):
        pts = np.array(layer.QueryTimeSample(path, t), dtype=np.float64)
        moved = rng.random(len(pts)) < 0.33
        pts[moved] += rng.normal(scale=0.01, size=(moved.sum(), 3))
        layer.SetTimeSample(path, t, pts.astype(np.float32).tolist())
    layer.Save()
    corr, report = tmp_path / "c.usda", tmp_path / "r.json"
    code, _, err = run("fit", ASSET, to_sculpt, "-o", corr, "--deformer", SWIRL, "--report", report, "-q")
    assert code == 0, err
    for ex in json.loads(report.read_text())["meshes"][0]["examples"]:
        assert ex["missed"] == 0 and ex["max_residual_rel"] <= 1e-5


def test_console_script_and_module_entry_points():
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    for cmd in ([exe, "--help"], [sys.executable, "-m", "psdbake", "--version"]):
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([exe, "fit", "missing.usda", "nope.usda", "-o", "x.usda"], capture_output=True, text=True)
    assert proc.returncode == 3
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert "missing.usda: file not found" in proc.stderr


def test_inputs_are_never_modified(run, tmp_path):
    before = {p: Path(p).read_bytes() for p in (ASSET, EXAMPLES, ANIM)}
    corr = tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    assert run("eval", ASSET, corr, "--anim", ANIM, "-o", tmp_path / "w.usda", "-q")[0] == 0
    assert {p: Path(p).read_bytes() for p in before} == before



def test_jobs_do_not_change_the_output(run, tmp_path):
    """Examples solved in worker processes give byte-identical CORRECTIVES."""
    outs = []
    for jobs in ("1", "2"):
        out = tmp_path / f"c{jobs}.usdc"
        code, _, err = run("fit", ASSET, EXAMPLES, fixture("arm_lbs_examples.usda"), "-o", out, "-j", jobs, "-q")
        assert code == 4 and "same pose" in err  # the same file twice: duplicate poses, named
        code, _, err = run("fit", ASSET, EXAMPLES, "-o", out, "-j", jobs, "-q")
        assert code == 0, err
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


@pytest.mark.parametrize("space", [["--pose-space", "quaternion"], ["--pose-space", "swingTwist", "--twist-axis", "1", "0", "0"]])
def test_pose_spaces_are_stored_and_reproduced_by_eval(run, tmp_path, space):
    """Whatever the pose space, eval (reading only psd:) gives each example weight 1 at its
    own pose, and the round trip through BakeSkinning still reproduces the sculpts."""
    corr, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q", *space)[0] == 0
    assert run("eval", ASSET, corr, "--anim", POSES, "-o", weights, "-q")[0] == 0
    layer = Sdf.Layer.FindOrOpen(str(weights))
    path = Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights")
    for k, t in enumerate((1.0, 2.0, 3.0)):
        np.testing.assert_allclose(layer.QueryTimeSample(path, t), np.eye(3)[k], atol=1e-6)  # float32 storage
    assert Usd.Stage.Open(str(corr)).GetPrimAtPath(generate.MESH).GetAttribute("psd:main:poseSpace").Get() == space[1]


def test_clamp_and_normalize_are_explicit_stored_options(run, tmp_path):
    plain, clamped = tmp_path / "p.usda", tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", plain, "-q")[0] == 0
    assert run("fit", ASSET, EXAMPLES, "-o", clamped, "-q", "--clamp-weights", "--normalize-weights")[0] == 0
    w = {}
    for name, corr in (("plain", plain), ("clamped", clamped)):
        out = tmp_path / f"w_{name}.usda"
        assert run("eval", ASSET, corr, "--anim", ANIM, "-o", out, "-q")[0] == 0
        layer = Sdf.Layer.FindOrOpen(str(out))
        path = Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights")
        w[name] = np.array([layer.QueryTimeSample(path, t) for t in layer.ListTimeSamplesForPath(path)])
    assert w["plain"].min() < 0.0  # cardinal Gaussian weights do go negative: nothing hides it by default
    assert w["clamped"].min() >= 0.0 and w["clamped"].sum(axis=1).max() <= 1.0 + 1e-6


def test_inspect_reports_what_a_file_holds(run, tmp_path):
    corr = tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    code, out, _ = run("inspect", corr, "--json")
    info = json.loads(out)
    assert code == 0 and info["correctives"][0]["mesh"] == generate.MESH
    assert info["correctives"][0]["drivers"] == ["Shoulder/Elbow", "Shoulder/Elbow/Wrist"]
    assert info["correctives"][0]["group"] == "main"
    assert sorted(info["correctives"][0]["offsets"]) == ["psd_main_00", "psd_main_01", "psd_main_02"]
    code, out, _ = run("inspect", EXAMPLES)
    assert code == 0 and "examples of </Arm/Geo/Tube> at time codes 1, 2, 3" in out
    code, out, _ = run("inspect", ASSET, "--json")
    assert json.loads(out)["meshes"][0]["influences"] == 4
