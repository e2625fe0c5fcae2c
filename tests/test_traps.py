"""Issue 23's first-day traps, each reproduced with the command the TD typed, and what psdbake
does now: the right exit code, one line naming what is wrong (or the warning that says so),
inputs byte-identical and no half-written output."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import (
    CESIUM,
    CESIUM_EXAMPLES,
    bake,
    diagonal,
    digest,
    fixture,
    no_leftovers,
    points,
    pose_only,
    refused,
    run_cli,
    sculpt,
    warned,
)
from pxr import Sdf, Usd, UsdGeom, UsdSkel

EXIT_USAGE, EXIT_INPUT, EXIT_FIT, EXIT_OUTPUT, EXIT_MISSED = 2, 3, 4, 6, 7

HUMANOID = fixture("humanoid", "humanoid.usda")
H_EXAMPLES = fixture("humanoid", "humanoid_examples.usda")
H_ANIM = fixture("humanoid", "humanoid_anim.usda")
BODY = "/Humanoid/Geo/Body"
ARM, ARM_EXAMPLES, ARM_ANIM = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), fixture("arm_anim.usda")
TUBE = "/Arm/Geo/Tube"


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """The demo's files made as README says: CORRECTIVES and WEIGHTS of the humanoid's shot."""
    folder = tmp_path_factory.mktemp("traps")
    corr, weights = folder / "correctives.usda", folder / "weights.usda"
    assert run_cli("fit", HUMANOID, H_EXAMPLES, "-o", corr, "-q")[0] == 0
    assert run_cli("eval", HUMANOID, corr, "--anim", H_ANIM, "-o", weights, "-q")[0] == 0
    return {"folder": folder, "corr": str(corr), "weights": str(weights)}


def _asset_copy(tmp_path) -> str:
    path = tmp_path / "humanoid.usda"
    shutil.copy(HUMANOID, path)
    return str(path)


# 1. stack overwrote the asset: OUTPUT forgotten, the asset was the first positional argument


def test_1_stack_with_the_output_forgotten_touches_nothing(shot, tmp_path):
    asset = _asset_copy(tmp_path)
    before = digest([asset, shot["corr"], shot["weights"]])
    code, _, err = run_cli("stack", asset, shot["corr"], H_ANIM, shot["weights"])
    assert code == EXIT_USAGE and "Missing option '-o'" in err, err
    assert digest([asset, shot["corr"], shot["weights"]]) == before


def test_1_no_command_replaces_a_file_it_did_not_write(shot, tmp_path):
    """-o naming a file that is not this command's earlier output (an asset) is refused, exit 6,
    saying what the file is; --force replaces it knowingly."""
    victim = _asset_copy(tmp_path)  # an asset that is not an input of this stack
    before = digest([victim])
    refused(run_cli("stack", HUMANOID, shot["corr"], H_ANIM, shot["weights"], "-o", victim), EXIT_OUTPUT,
            names=[victim], says=r"exists and is a USD asset \(it defines a SkelRoot\), not a psdbake stack; give --force",
            inputs=before)
    assert run_cli("stack", HUMANOID, shot["corr"], H_ANIM, shot["weights"], "-o", victim, "--force", "-q")[0] == 0
    assert digest([victim]) != before
    # its own earlier output is replaced without a word
    assert run_cli("stack", HUMANOID, shot["corr"], H_ANIM, shot["weights"], "-o", victim, "-q")[0] == 0


@pytest.mark.parametrize("command", ["fit", "eval", "pose"])
def test_1_a_layer_of_another_kind_is_not_replaced(command, shot, tmp_path):
    """fit -o WEIGHTS, eval -o CORRECTIVES, pose -o CORRECTIVES: each a psdbake layer, but not
    the command's own kind."""
    target = tmp_path / "other.usda"
    shutil.copy(shot["weights"] if command == "fit" else shot["corr"], target)
    before = digest([target])
    argv = {"fit": ["fit", HUMANOID, H_EXAMPLES, "-o", target],
            "eval": ["eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", target],
            "pose": ["pose", HUMANOID, "--poses", H_EXAMPLES, "-o", target]}[command]
    kind = {"fit": "WEIGHTS layer", "eval": "CORRECTIVES layer", "pose": "CORRECTIVES layer"}[command]
    refused(run_cli(*argv), EXIT_OUTPUT, names=[str(target)], says=f"exists and is a psdbake {kind}, not a psdbake",
            inputs=before)


def test_1_a_read_only_published_file_is_not_replaced(shot, tmp_path):
    """A psdbake output locked 0444 (published) is refused, exit 6, unless --force."""
    out = tmp_path / "weights.usda"
    assert run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", out, "-q")[0] == 0
    out.chmod(0o444)
    before = digest([out])
    refused(run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", out), EXIT_OUTPUT, names=[str(out)],
            says=r"is read-only \(mode 0444", inputs=before)
    assert run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", out, "--force", "-q")[0] == 0


# 2. stack in USD's order (strongest first) lost the correctives


def _sublayers(path) -> list[str]:
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    return list(layer.subLayerPaths)


def test_2_stack_orders_layers_by_role_whatever_the_order_given(shot, tmp_path):
    weakest_first, usd_order = tmp_path / "a.usda", tmp_path / "b.usda"
    assert run_cli("stack", HUMANOID, shot["corr"], H_ANIM, shot["weights"], "-o", weakest_first, "-q")[0] == 0
    code, out, err = run_cli("stack", shot["weights"], H_ANIM, shot["corr"], HUMANOID, "-o", usd_order)
    assert code == 0, err
    assert _sublayers(weakest_first) == _sublayers(usd_order)
    assert [p.rsplit("/", 1)[-1] for p in _sublayers(usd_order)] == [
        "weights.usda", "humanoid_anim.usda", "correctives.usda", "humanoid.usda"]  # subLayers: strongest first
    assert "(WEIGHTS) > " in out and "(ASSET)" in out
    baked_a, baked_b = bake([str(weakest_first)], 40.0), bake([str(usd_order)], 40.0)
    plain = bake([H_ANIM, HUMANOID], 40.0)
    assert np.array_equal(points(baked_a, BODY, 40.0), points(baked_b, BODY, 40.0))
    assert np.abs(points(baked_b, BODY, 40.0) - points(plain, BODY, 40.0)).max() > 1e-3  # the correctives act


def test_2_stack_refuses_contradictions(shot, tmp_path):
    second = tmp_path / "correctives_again.usda"
    shutil.copy(shot["corr"], second)
    refused(run_cli("stack", HUMANOID, shot["corr"], second, H_ANIM, "-o", tmp_path / "v.usda"), EXIT_INPUT,
            names=[BODY], says="hide the other's", outputs=[tmp_path / "v.usda"])
    refused(run_cli("stack", HUMANOID, H_EXAMPLES, "-o", tmp_path / "v.usda"), EXIT_INPUT,
            names=[H_EXAMPLES], says="is an EXAMPLES layer", outputs=[tmp_path / "v.usda"])


# 3. a failed fit exited 0 (CesiumMan through Delta Mush), and -q printed nothing


@pytest.mark.slow
def test_3_a_degraded_fit_fails_and_minus_q_still_says_why(tmp_path):
    out, report = tmp_path / "c.usda", tmp_path / "fit.json"
    code, stdout, err = run_cli("fit", CESIUM, CESIUM_EXAMPLES, "-o", out, "--deformer", "psdbake.delta_mush:delta_mush",
                                "--report", report, "-q")
    assert code == EXIT_MISSED and not out.exists() and stdout == "", err
    lines = err.strip().splitlines()
    assert lines[-1].startswith("psdbake: error:") and "not written" in lines[-1] and "--allow-degraded" in lines[-1]
    assert any("DEGRADED" in ln for ln in lines[:-1])
    assert json.loads(report.read_text())["written"] is False
    no_leftovers([out])


# 4. --frames outside the animation wrote the held last pose


@pytest.mark.parametrize("command", ["eval", "export-gltf"])
def test_4_frames_outside_the_authored_range_are_refused(command, shot, tmp_path):
    out = tmp_path / ("w.usda" if command == "eval" else "s.glb")
    argv = [command, HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", out, "--frames", "200:300"]
    refused(run_cli(*argv), EXIT_INPUT, names=[H_ANIM, "</Humanoid/Skel/Anim>"],
            says=r"authored over 1\.\.100.*--hold", outputs=[out])
    warned(run_cli(*argv[:-1], "90:110", "--hold"), says=r"\(--hold\).*hold its first or last pose", outputs=[out])


# 5. no provenance: correctives fitted on one rig evaluated on another without a word


@pytest.fixture(scope="module")
def arm_correctives(tmp_path_factory):
    folder = tmp_path_factory.mktemp("provenance")
    corr = folder / "c.usda"
    assert run_cli("fit", ARM, ARM_EXAMPLES, "-o", corr, "-q")[0] == 0
    return str(corr)


@pytest.mark.parametrize(("other", "says"), [
    ("arm_dqs.usda", r"fitted with classicLinear skinning, and is now skinned with dualQuaternion"),
    ("arm_rest.usda", r"its skeleton's joints or bind/rest transforms differ"),
])
def test_5_correctives_evaluated_on_another_rig_warn_and_strict_refuses(other, says, arm_correctives, tmp_path):
    out = tmp_path / "w.usda"
    line = warned(run_cli("eval", fixture(other), arm_correctives, "--anim", ARM_ANIM, "-o", out),
                  names=[arm_correctives, fixture(other), "arm_lbs.usda"], says=says, outputs=[out])
    assert "--strict" in line
    out.unlink()
    refused(run_cli("eval", fixture(other), arm_correctives, "--anim", ARM_ANIM, "-o", out, "--strict"), EXIT_INPUT,
            names=[arm_correctives, "arm_lbs.usda"], says=says, outputs=[out])


def test_5_every_output_records_its_provenance(shot):
    data = Sdf.Layer.FindOrOpen(shot["weights"]).customLayerData["psdbake"]
    assert data["kind"] == "weights" and data["command"].startswith("psdbake eval ")
    assert data["inputs"]["asset"]["path"].endswith("fixtures/humanoid/humanoid.usda")
    assert len(data["inputs"]["correctives"]["sha256"]) == 64
    assert data["rig"][BODY]["skinningMethod"] == "classicLinear"
    corr = Sdf.Layer.FindOrOpen(shot["corr"]).customLayerData["psdbake"]
    assert corr["kind"] == "correctives" and corr["groups"]["L_Elbow"]["origin"] == "fit"
    assert "/tmp" not in json.dumps({k: str(v) for k, v in corr.items()})  # relative paths only


# 6. groups vanished or doubled


def test_6_driver_without_group_is_named_for_its_joint_and_a_later_group_fit_replaces_it(tmp_path):
    out = tmp_path / "c.usda"
    code, stdout, err = run_cli("fit", HUMANOID, H_EXAMPLES, "--driver", "L_Elbow", "-o", out)
    assert code == 0, err
    groups = json.loads(run_cli("groups", out, "--json")[1])["groups"]
    assert [g["group"] for g in groups] == ["L_Elbow"]
    code, stdout, err = run_cli("fit", HUMANOID, H_EXAMPLES, "--driver", "L_Elbow", "--group", "L_Elbow",
                                "--kernel", "linear", "-o", out)
    assert code == 0 and "groups: replaced L_Elbow" in stdout, err
    # README's lower-case spelling of the same group: refused, naming the existing one
    refused(run_cli("fit", HUMANOID, H_EXAMPLES, "--driver", "L_Elbow", "--group", "l_elbow", "-o", out), EXIT_INPUT,
            says="already has group 'L_Elbow': did you mean L_Elbow")


def test_6_groups_lists_removes_and_renames(shot, tmp_path):
    corr = tmp_path / "correctives.usda"
    shutil.copy(shot["corr"], corr)
    code, out, _ = run_cli("groups", corr)
    assert code == 0 and "9 group(s) on 1 mesh(es)" in out and "gated by L_Elbow, L_Shoulder" in out
    refused(run_cli("groups", corr, "--remove", "L_Elbow"), EXIT_INPUT,
            says="combination 'combo_L_Shoulder_L_Elbow' is gated by it")
    assert run_cli("groups", corr, "--remove", "combo_L_Shoulder_L_Elbow", "--remove", "L_Elbow", "-q")[0] == 0
    assert run_cli("groups", corr, "--rename", "Neck=neck_fix", "-q")[0] == 0
    names = [g["group"] for g in json.loads(run_cli("groups", corr, "--json")[1])["groups"]]
    assert "L_Elbow" not in names and "neck_fix" in names and "Neck" not in names
    stage = Usd.Stage.Open(str(corr))
    assert any(str(c).startswith("psd_neck_fix_") for c in stage.GetPrimAtPath(BODY).GetAttribute(
        "skel:blendShapes").Get())


def test_6_mirror_keeps_sculpted_groups_and_says_so(shot, tmp_path):
    """The fit holds R_Elbow fitted from sculpts: mirror L_=R_ replaces the mirrorable groups it
    made before, but leaves R_Elbow alone, warning with its origin, unless --replace-sculpted."""
    corr = tmp_path / "correctives.usda"
    shutil.copy(shot["corr"], corr)
    code, out, err = run_cli("mirror", HUMANOID, corr, "--joints", "L_=R_", "-o", corr)
    assert code == 0, err
    assert "kept 4 group(s) fitted from sculpts instead of their mirror: R_Elbow (fit of" in err
    refused(run_cli("mirror", HUMANOID, corr, "--joints", "L_=R_", "--group", "L_Elbow", "-o", corr), EXIT_OUTPUT,
            says="group 'R_Elbow' there was fitted from sculpts")
    code, out, err = run_cli("mirror", HUMANOID, corr, "--joints", "L_=R_", "--group", "L_Elbow", "-o", corr,
                             "--replace-sculpted")
    assert code == 0 and "replaced R_Elbow (fit of" in out, err


# 7. discovery


def test_7_inspect_names_joints_and_spells_out_poses():
    code, out, _ = run_cli("inspect", HUMANOID)
    assert code == 0 and "      Hips\n" in out and "              L_Elbow\n" in out
    code, out, _ = run_cli("inspect", H_EXAMPLES, "--asset", HUMANOID)
    assert "t=5: L_Elbow 120°" in out and "t=12: L_Elbow 90°, L_Shoulder 60°" in out
    info = json.loads(run_cli("inspect", HUMANOID, "--json")[1])
    assert "Hips/Spine/Chest/L_Shoulder/L_Elbow" in info["skeletons"][0]["joint_paths"]


def test_7_names_short_or_long_with_did_you_mean(tmp_path):
    refused(run_cli("fit", HUMANOID, H_EXAMPLES, "--driver", "l_elbow", "-o", tmp_path / "c.usda"), EXIT_INPUT,
            names=["--driver 'l_elbow'"], says="did you mean Hips/Spine/Chest/L_Shoulder/L_Elbow")
    assert run_cli("fit", HUMANOID, H_EXAMPLES, "--mesh", "Body", "-o", tmp_path / "c.usda", "-q")[0] == 0
    refused(run_cli("fit", HUMANOID, H_EXAMPLES, "--mesh", "Bdy", "-o", tmp_path / "d.usda"), EXIT_INPUT,
            says="did you mean /Humanoid/Geo/Body")


@pytest.mark.parametrize(("rule", "says"), [
    ("L_=r_", r"maps to 'Hips/Spine/Chest/r_Shoulder/r_Elbow'.*did you mean Hips/Spine/Chest/R_Shoulder/R_Elbow"),
    ("Left=Right", r"driver 'Hips/Spine/Chest/L_Shoulder/L_Elbow' has no partner"),
    ("(^|/)l_=\\1r_", r"matches it only ignoring case"),
])
def test_7_mirror_names_the_joint_that_did_not_map(rule, says, shot, tmp_path):
    refused(run_cli("mirror", HUMANOID, shot["corr"], "--joints", rule, "-o", tmp_path / "m.usda"), EXIT_INPUT,
            says=says, outputs=[tmp_path / "m.usda"])


# 8. an inconsistent surface


@pytest.mark.parametrize("command", ["stack", "inspect", "groups"])
def test_8_every_command_takes_quiet_verbose_and_json(command, shot, tmp_path):
    argv = {"stack": ["stack", HUMANOID, shot["corr"], "-o", tmp_path / "v.usda"], "inspect": ["inspect", HUMANOID],
            "groups": ["groups", shot["corr"]]}[command]
    assert run_cli(*argv, "-q")[:2] == (0, "")
    assert run_cli(*argv, "-v")[0] == 0
    json.loads(run_cli(*argv, "--json")[1])


def test_8_pose_takes_poses_frames_and_mesh(tmp_path):
    out = tmp_path / "to_sculpt.usda"
    code, stdout, err = run_cli("pose", HUMANOID, "--poses", H_ANIM, "--frames", "40:42", "--mesh", "Body", "-o", out,
                                "--json")
    assert code == 0, err
    assert json.loads(stdout)["times"] == [40.0, 41.0, 42.0]


def test_8_eval_verbose_says_which_correctives_fire(shot, tmp_path):
    code, out, _ = run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", tmp_path / "w.usda", "-v")
    assert code == 0 and "psd_L_Elbow_Geo_Body_00_pos" in out and "at frame" in out


# 9. several skeletons in one file


def _two_skeletons(tmp_path) -> tuple[str, str]:
    """The arm, plus a second SkelRoot </Head> skinned by its own skeleton (joints joint1..), as
    a Blender export of several characters; EXAMPLES sculpt the arm's poses and also the head,
    whose skeleton stays at its bind pose (rest = bind)."""
    asset = tmp_path / "two.usda"
    layer = Sdf.Layer.CreateNew(str(asset))
    layer.TransferContent(Sdf.Layer.FindOrOpen(ARM))
    assert Sdf.CopySpec(layer, "/Arm", layer, "/Head")
    layer.GetAttributeAtPath("/Head/Skel.joints").default = ["joint1", "joint1/joint2", "joint1/joint2/joint3",
                                                             "joint1/joint2/joint3/joint4"]
    layer.Save()
    examples = tmp_path / "two_examples.usda"
    ex = Sdf.Layer.CreateNew(str(examples))
    ex.TransferContent(Sdf.Layer.FindOrOpen(ARM_EXAMPLES))
    ex.Save()
    stage = Usd.Stage.Open(str(examples))
    arm = Usd.Stage.Open(ARM)
    rest = np.array(UsdGeom.Mesh(arm.GetPrimAtPath(TUBE)).GetPointsAttr().Get(), dtype=np.float64)
    head_anim = stage.DefinePrim("/Head/Skel/Anim", "SkelAnimation")  # no joints: every joint at rest = bind
    UsdSkel.BindingAPI.Apply(stage.OverridePrim("/Head/Skel")).CreateAnimationSourceRel().SetTargets(
        [head_anim.GetPath()])
    bumped = rest.copy()
    bumped[:8, 1] += 0.05
    pts = UsdGeom.Mesh(stage.OverridePrim("/Head/Geo/Tube")).CreatePointsAttr()
    for t in (1.0, 2.0, 3.0):
        pts.Set(bumped.astype(np.float32).tolist(), t)
    stage.Save()
    return str(asset), str(examples)


def test_9_a_mesh_whose_skeleton_never_moves_is_skipped_not_fatal(tmp_path):
    asset, examples = _two_skeletons(tmp_path)
    out = tmp_path / "c.usda"
    code, _, err = run_cli("fit", asset, examples, "-o", out, "-q")
    assert code == 0, err
    assert "</Head/Geo/Tube>: every example is at the bind pose of its skeleton </Head/Skel>" in err
    written = Sdf.Layer.FindOrOpen(str(out))
    assert written.GetAttributeAtPath(f"{TUBE}.psd:groups") and not written.GetPrimAtPath("/Head/Geo/Tube")


def test_9_a_driver_of_another_skeleton_points_at_mesh(tmp_path):
    asset, examples = _two_skeletons(tmp_path)
    code, _, err = run_cli("fit", asset, examples, "--driver", "Elbow", "-o", tmp_path / "c.usda", "-q")
    assert code == 0 and "</Head/Geo/Tube>: skipped: its skeleton </Head/Skel> has no joint 'Elbow'" in err, err
    refused(run_cli("fit", asset, examples, "--driver", "Elbow", "--mesh", "/Head/Geo/Tube", "-o", tmp_path / "d.usda"),
            EXIT_INPUT, says=r"is not a joint of skeleton </Head/Skel>.*it is a joint of </Arm/Skel>.*--mesh")


def test_9_inspect_counts_blend_shape_weight_samples():
    info = json.loads(run_cli("inspect", fixture("character", "character_anim.usda"), "--json")[1])
    (anim,) = info["animations"]
    assert anim["blend_shape_samples"] > 0 and anim["samples"] >= anim["blend_shape_samples"]


# 10. the points cache could not be opened on its own


def test_10_a_self_contained_points_cache_opens_alone(shot, tmp_path):
    cache, plain_cache = tmp_path / "cache.usda", tmp_path / "plain.usda"
    assert run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", tmp_path / "w.usda", "--points-cache",
                   cache, "--self-contained", "-q")[0] == 0
    alone = Usd.Stage.Open(str(cache))
    mesh = UsdGeom.Mesh(alone.GetPrimAtPath(BODY))
    assert len(mesh.GetFaceVertexCountsAttr().Get()) > 0 and mesh.GetPointsAttr().GetNumTimeSamples() == 100
    stacked = bake([str(tmp_path / "w.usda"), H_ANIM, shot["corr"], HUMANOID], 40.0)
    assert np.abs(np.array(mesh.GetPointsAttr().Get(40.0)) - points(stacked, BODY, 40.0)).max() <= \
        1e-6 * diagonal(points(stacked, BODY, 40.0))
    assert run_cli("eval", HUMANOID, shot["corr"], "--anim", H_ANIM, "-o", tmp_path / "w2.usda", "--points-cache",
                   plain_cache, "-q")[0] == 0
    assert "overrides to stack over ASSET" in Sdf.Layer.FindOrOpen(str(plain_cache)).documentation


# the half-sculpted set, and the round trip through the client


def test_half_the_poses_sculpted_fits_the_edited_ones_and_names_the_rest(tmp_path):
    """Only the left side's examples are sculpted (the right ones equal plain skinning): the fit
    writes the left groups, warns naming each right group left out, and the stack reproduces the
    left sculpts through BakeSkinning."""
    half = tmp_path / "half.usda"
    layer = Sdf.Layer.CreateNew(str(half))
    layer.TransferContent(Sdf.Layer.FindOrOpen(H_EXAMPLES))
    plain = bake([pose_only(H_EXAMPLES), HUMANOID], 1.0, 13.0)
    right = (3.0, 6.0, 7.0, 10.0, 11.0, 13.0)
    for t in right:
        layer.SetTimeSample(Sdf.Path(BODY).AppendProperty("points"), t, points(plain, BODY, t, np.float32).tolist())
    layer.Save()
    out, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    code, _, err = run_cli("fit", HUMANOID, half, "-o", out, "-q")
    assert code == 0, err
    for group in ("R_Elbow", "R_Knee", "R_Shoulder"):
        assert f"group '{group}': none of its" in err
    for t in right:  # each unedited example named, and kept (a zero corrective at its pose)
        assert f"half.usda <{BODY}>: example at time {t:g} equals plain skinning; it is kept as a zero example" in err
    assert run_cli("eval", HUMANOID, out, "--anim", half, "-o", weights, "-q")[0] == 0
    baked = bake([str(weights), pose_only(str(half)), str(out), HUMANOID], 1.0, 13.0)
    for t in (1.0, 2.0, 4.0, 5.0, 8.0, 9.0, 12.0):
        target = sculpt(H_EXAMPLES, BODY, t)
        assert np.abs(points(baked, BODY, t) - target).max() / diagonal(target) <= 1e-5, t
    # the other side by mirror: its groups appear, and the right sculpts (of the full,
    # symmetric EXAMPLES) come back at their single-joint poses
    both, mirrored = tmp_path / "both.usda", tmp_path / "w_both.usda"
    code, _, err = run_cli("mirror", HUMANOID, out, "--joints", "L_=R_", "-o", both, "-q")
    assert code == 0, err
    assert run_cli("eval", HUMANOID, both, "--anim", H_EXAMPLES, "-o", mirrored, "-q")[0] == 0
    baked = bake([str(mirrored), pose_only(H_EXAMPLES), str(both), HUMANOID], 1.0, 13.0)
    for t in (3.0, 6.0, 7.0, 10.0, 11.0):  # the single-joint ones (t=13 bends the right arm unlike the left's)
        target = sculpt(H_EXAMPLES, BODY, t)
        assert np.abs(points(baked, BODY, t) - target).max() / diagonal(target) <= 1e-5, t
