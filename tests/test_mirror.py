"""psdbake mirror (psdbake/mirroring/groups.py, posemirror.py, symmetry.py): one side's correctives
groups made into the other side's.

The ground truth is a symmetric humanoid: fixtures/humanoid.py's own generator, with its
right-side combination sculpted as the exact mirror image of the left one (the committed
fixture's right combination is sculpted at other angles, with another amplitude), written
at test time. Its rest points, joints and single-joint sculpts are mirror images (checked
below), so the mirrored left groups must reproduce the right sculpts, and drive the shot as
the groups fitted on the right sculpts do.
"""

from __future__ import annotations

import json
import os
import re
import shutil

import humanoid
import numpy as np
import pytest
from conftest import (
    bake,
    corrective_weights,
    diagonal,
    digest,
    points,
    refused,
    run_cli,
    sculpt,
    stage_of,
    without_provenance,
)
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from psdbake.mirroring.poses import COORDINATE_MAPS, driver_turns, rotations_of
from psdbake.mirroring.symmetry import reflection
from psdbake.model import posespace
from psdbake.model.rig import BindSpace

M = reflection("x")
RIGHT = {3.0: 2.0, 6.0: 4.0, 7.0: 5.0, 10.0: 8.0, 11.0: 9.0, 13.0: 12.0}  # right example -> its left mirror
SYMMETRIC_COMBINATION = ("r_shoulder", "r_elbow", humanoid.Field("r_arm", (-30.0, 143.0, 0.0), 7.0, (0, 1, 0), 1.6))
MEASURED: dict[str, float] = {}  # figures for the report (printed with -s)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The symmetric humanoid (asset, examples, shot), its default fit and the whole-layer mirror of
    that fit's left groups."""
    folder = tmp_path_factory.mktemp("mirror")
    poses = dict(humanoid.EXAMPLE_POSES)
    poses[13.0] = humanoid.pose_of({"r_shoulder": 60.0, "r_elbow": 90.0})  # the left combination's mirror
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(humanoid.COMBINATIONS, "r_arm_raise_bend", SYMMETRIC_COMBINATION)
        asset = humanoid.build(str(folder / "humanoid.usda"))
        examples = humanoid.write_examples(str(folder / "examples.usda"), asset, poses)
    anim = humanoid.write_animation(str(folder / "anim.usda"), humanoid.shot_poses())
    sculpt_poses = humanoid.write_animation(str(folder / "poses.usda"), poses)
    corr, mirrored = folder / "corr.usda", folder / "mirrored.usda"
    assert run_cli("fit", asset, examples, "-o", corr, "-q")[0] == 0
    before = digest([asset, examples, corr])
    result = run_cli("mirror", asset, corr, "--joints", "L_=R_", "-o", mirrored, "--json")
    assert result[0] == 0, result[2]
    assert digest([asset, examples, corr]) == before  # inputs never modified
    return {"folder": folder, "asset": asset, "examples": examples, "anim": anim, "poses": sculpt_poses,
            "corr": str(corr), "mirrored": str(mirrored), "result": result}


def test_the_fixture_is_mirror_symmetric(rig):
    """Rest points, joint positions and every right sculpt are mirror images of the left ones."""
    stage = Usd.Stage.Open(rig["asset"])
    rest = np.array(UsdGeom.Mesh(stage.GetPrimAtPath(humanoid.MESH)).GetPointsAttr().Get(), dtype=np.float64)
    dist, partner = cKDTree(rest).query(rest @ M)
    assert dist.max() <= 1e-12 * diagonal(rest) and len(set(partner)) == len(rest)
    bind = np.array(UsdSkel.Skeleton(stage.GetPrimAtPath(humanoid.SKEL)).GetBindTransformsAttr().Get())[:, 3, :3]
    leaves = [j.split("/")[-1] for j in humanoid.JOINTS]
    for i, leaf in enumerate(leaves):
        other = leaves.index(leaf.replace("L_", "R_") if leaf.startswith("L_") else leaf.replace("R_", "L_"))
        assert np.abs(bind[i] @ M - bind[other]).max() == 0.0, leaf
    for right, left in RIGHT.items():
        r, lf = sculpt(rig["examples"], humanoid.MESH, right), sculpt(rig["examples"], humanoid.MESH, left)
        assert np.abs(r[partner] - lf @ M).max() <= 1e-6 * diagonal(r), right


def test_whole_layer_mirror_reports_what_it_mirrored_and_skipped(rig):
    _, out, _ = rig["result"]
    payload = json.loads(out)
    pairs = sorted((g["source"], g["group"]) for g in payload["groups"])
    assert pairs == [("L_Elbow", "R_Elbow"), ("L_Knee", "R_Knee"), ("L_Shoulder", "R_Shoulder"),
                     ("combo_L_Shoulder_L_Elbow", "combo_R_Shoulder_R_Elbow")]
    skipped = [re.search(r"group '(\w+)'", s).group(1) for s in payload["skipped"]]  # type: ignore[union-attr]
    assert skipped == ["Neck", "R_Elbow", "R_Knee", "R_Shoulder", "combo_R_Shoulder_R_Elbow"]
    assert all("has no partner under --joints 'L_=R_'" in s for s in payload["skipped"])
    for g in payload["groups"]:
        assert g["worst_vertex_rel"] <= 1e-12 and g["worst_joint_rel"] == 0.0 and g["vertices"] > 50
    combo = next(g for g in payload["groups"] if g["group"].startswith("combo"))
    assert combo["gate_groups"] == ["R_Elbow", "R_Shoulder"]
    code, out, _ = run_cli("mirror", rig["asset"], rig["corr"], "--joints", "L_=R_", "-o", rig["mirrored"])
    assert code == 0 and "4 group(s) mirrored about the x plane" in out and "skipped 5 group(s)" in out


def test_mirrored_groups_reproduce_the_right_sculpts(rig, tmp_path):
    """BakeSkinning of ASSET + mirrored CORRECTIVES + POSES + WEIGHTS at each right example's pose
    gives that sculpt within 1e-5 of the diagonal, the combination included (the left ones too)."""
    weights = tmp_path / "weights.usda"
    assert run_cli("eval", rig["asset"], rig["mirrored"], "--anim", rig["poses"], "-o", weights, "-q")[0] == 0
    stage = bake(stage_of([str(weights), rig["poses"], rig["mirrored"], rig["asset"]]), 1.0, 13.0)
    errors = {}
    for t in sorted(humanoid.EXAMPLE_POSES):
        target = sculpt(rig["examples"], humanoid.MESH, t)
        errors[t] = float(np.abs(points(stage, humanoid.MESH, t) - target).max() / diagonal(target))
    assert max(errors.values()) <= 1e-5, errors
    MEASURED["round trip, right examples / diagonal"] = max(errors[t] for t in RIGHT)


def test_mirrored_weights_match_the_groups_fitted_on_the_right_sculpts(rig, tmp_path):
    """Over the humanoid's shot (both arms and legs move), each mirrored right corrective's weight b
    equals the weight of the same corrective fitted on the right sculpts (default fit) within 1e-6."""
    times = sorted(humanoid.shot_angles())
    b = {}
    for name in ("corr", "mirrored"):
        out = tmp_path / f"{name}_weights.usda"
        assert run_cli("eval", rig["asset"], rig[name], "--anim", rig["anim"], "-o", out, "-q")[0] == 0
        b[name] = corrective_weights(rig["asset"], rig[name], out, humanoid.ANIM, times)
    right = sorted(s for s in b["corr"] if s.startswith(("psd_R_", "psd_combo_R_")))
    assert len(right) == 6 and set(right) <= set(b["mirrored"])
    worst = max(float(np.abs(b["corr"][s] - b["mirrored"][s]).max()) for s in right)
    assert worst <= 1e-6, worst
    assert min(float(np.abs(b["corr"][s]).max()) for s in right) > 0.5  # the shot drives every one of them
    MEASURED["weights vs right fit, max |db|"] = worst


def test_the_same_inputs_give_the_same_bytes(rig, tmp_path):
    """The same command again (the layer records its command line): the same bytes."""
    again = tmp_path / "again.usda"
    assert run_cli("mirror", rig["asset"], rig["corr"], "--joints", "L_=R_", "-o", again, "-q")[0] == 0
    first = again.read_bytes()
    assert run_cli("mirror", rig["asset"], rig["corr"], "--joints", "L_=R_", "-o", again, "-q")[0] == 0
    assert again.read_bytes() == first
    assert without_provenance(again) == without_provenance(rig["mirrored"])


def _geom_bind_variant(asset: str, path: str) -> str:
    """The asset with a non-uniform, rotated, translated geomBindTransform and its rest points
    moved so that they land where they were in skeleton space: the same skinning, so the same
    sculpts, but offsets that mirror only through geomBindTransform."""
    shutil.copy(asset, path)
    stage = Usd.Stage.Open(path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(humanoid.MESH))
    geom = Gf.Matrix4d().SetScale(Gf.Vec3d(1.0, 2.0, 0.5)) * Gf.Matrix4d().SetRotate(
        Gf.Rotation(Gf.Vec3d(0.3, 1.0, 0.2), 30.0)) * Gf.Matrix4d().SetTranslate(Gf.Vec3d(5.0, -20.0, 3.0))
    rest = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    g = np.array(geom)
    mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(((rest - g[3, :3]) @ np.linalg.inv(g[:3, :3])).astype(np.float32)))
    UsdSkel.BindingAPI(mesh.GetPrim()).GetGeomBindTransformAttr().Set(geom)
    stage.GetRootLayer().Save()
    return path


def test_one_group_mirrored_in_place_through_a_geom_bind_transform(rig, tmp_path):
    """fit --group l_elbow on the left sculpts, mirror it into the same layer as r_elbow: the layer
    keeps l_elbow and gains r_elbow, which reproduces the right elbow sculpts and drives the shot as
    fit --group r_elbow on the right sculpts does."""
    asset = _geom_bind_variant(rig["asset"], str(tmp_path / "geom_bind.usda"))
    corr, hand = tmp_path / "corr.usda", tmp_path / "hand.usda"
    ex = rig["examples"]
    assert run_cli("fit", asset, ex, "--group", "l_elbow", "--driver", "L_Elbow", "-o", corr, "-q")[0] == 0
    assert run_cli("fit", asset, ex, "--group", "r_elbow", "--driver", "R_Elbow", "-o", hand, "-q")[0] == 0
    code, _, err = run_cli("mirror", asset, corr, "--group", "l_elbow", "--as", "r_elbow", "--joints",
                           r"(^|/)L_=\1R_", "-o", corr, "-q")
    assert code == 0, err
    written = Usd.Stage.Open(str(corr))
    assert list(written.GetPrimAtPath(humanoid.MESH).GetAttribute("psd:groups").Get()) == ["l_elbow", "r_elbow"]
    times = sorted(humanoid.shot_angles())
    b = {}
    for name, layer_path in (("mirrored", corr), ("hand", hand)):
        out = tmp_path / f"{name}_w.usda"
        assert run_cli("eval", asset, layer_path, "--anim", rig["anim"], "-o", out, "-q")[0] == 0
        b[name] = corrective_weights(asset, layer_path, out, humanoid.ANIM, times)
    for s in ("psd_r_elbow_Geo_Body_00", "psd_r_elbow_Geo_Body_01"):
        assert float(np.abs(b["hand"][s] - b["mirrored"][s]).max()) <= 1e-6, s
    weights = tmp_path / "w.usda"
    assert run_cli("eval", asset, corr, "--anim", rig["poses"], "-o", weights, "-q")[0] == 0
    stage = bake(stage_of([str(weights), rig["poses"], str(corr), asset]), 4.0, 7.0)
    for t in (4.0, 5.0, 6.0, 7.0):
        target = sculpt(ex, humanoid.MESH, t)
        assert np.abs(points(stage, humanoid.MESH, t) - target).max() <= 1e-5 * diagonal(target), t


def test_mirrored_blend_shapes_are_the_right_fit_normal_offsets_included(rig, tmp_path):
    """With authored vertex normals (so normalOffsets and 1-ring pointIndices): the mirrored group's
    correctives are the ones fitted on the right sculpts, vertex for vertex."""
    from psdbake.fitting.groups import read_correctives
    from psdbake.mirroring.groups import column_shapes

    rest = humanoid.rest_points()
    normals = np.zeros_like(rest)
    for part in humanoid.PARTS:  # radial: each tube's exact normal, mirror-symmetric like the tubes
        span, axis = humanoid.part_slices()[part.name], np.asarray(part.axis, dtype=np.float64)
        rel = rest[span] - np.asarray(part.start)
        radial = rel - np.outer(rel @ axis, axis)
        normals[span] = radial / np.linalg.norm(radial, axis=1, keepdims=True)

    def author_normals(stage):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(humanoid.MESH))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)

    asset = _edited_asset(rig, tmp_path / "normals.usda", author_normals)
    left, right, mirrored = (tmp_path / f"{n}.usda" for n in ("left", "right", "mirrored"))
    for side, out in (("L", left), ("R", right)):
        code, _, err = run_cli("fit", asset, rig["examples"], "--group", f"{side.lower()}_elbow", "--driver",
                               f"{side}_Elbow", "-o", out, "-q")
        assert code == 0, err
    code, _, err = run_cli("mirror", asset, left, "--group", "l_elbow", "--as", "r_elbow", "--joints", "L_=R_",
                           "-o", mirrored, "-q")
    assert code == 0, err
    fitted = column_shapes(*read_correctives(asset, str(right))[humanoid.MESH]["r_elbow"])
    made = column_shapes(*read_correctives(asset, str(mirrored))[humanoid.MESH]["r_elbow"])
    assert [s.name for s in made] == [s.name for s in fitted]
    for a, b in zip(fitted, made, strict=True):
        assert b.normal_offsets is not None and a.normal_offsets is not None
        np.testing.assert_array_equal(a.indices, b.indices)  # the sculpt's 1-ring included
        assert np.abs(a.offsets - b.offsets).max() <= 1e-7 * diagonal(rest)
        assert np.abs(a.normal_offsets - b.normal_offsets).max() <= 1e-5


def _edited_asset(rig, path, edit) -> str:
    shutil.copy(rig["asset"], path)
    stage = Usd.Stage.Open(str(path))
    edit(stage)
    stage.GetRootLayer().Save()
    return str(path)


def test_an_asymmetric_rig_is_refused_naming_the_joints(rig, tmp_path):
    def move_right_elbow(stage):
        skel = UsdSkel.Skeleton(stage.GetPrimAtPath(humanoid.SKEL))
        bind = list(skel.GetBindTransformsAttr().Get())
        i = humanoid.JOINTS.index("Hips/Spine/Chest/R_Shoulder/R_Elbow")
        bind[i] = Gf.Matrix4d(bind[i]).SetTranslateOnly(Gf.Vec3d(-46.0, 143.0, 0.0))
        skel.GetBindTransformsAttr().Set(bind)

    asset = _edited_asset(rig, tmp_path / "asym_rig.usda", move_right_elbow)
    out = tmp_path / "out.usda"
    inputs = digest([asset, rig["corr"]])
    line = refused(run_cli("mirror", asset, rig["corr"], "--group", "L_Elbow", "--joints", "L_=R_", "-o", out), 3,
                   names=["asym_rig.usda", f"<{humanoid.SKEL}>", "R_Elbow'", "L_Elbow'"],
                   says=r"not mirror-symmetric about the x plane", outputs=[out], inputs=inputs)
    assert "tolerance 0.0001" in line


def test_an_asymmetric_mesh_is_refused_naming_the_vertices(rig, tmp_path):
    rest = humanoid.rest_points()
    arm = humanoid.part_slices()["r_arm"]
    near = np.arange(arm.start, arm.stop)
    near = near[(np.abs(rest[near, 0] + 38.0) < 2.0) & (rest[near, 2] > 3.0)][:3]  # right elbow, facing +z
    partners = cKDTree(rest).query(rest[near] @ M)[1]

    def move(stage):
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(humanoid.MESH)).GetPointsAttr()
        pts = np.array(attr.Get(), dtype=np.float32)
        pts[near, 1] += 0.5  # cm
        attr.Set(Vt.Vec3fArray.FromNumpy(pts))

    asset = _edited_asset(rig, tmp_path / "asym_mesh.usda", move)
    out = tmp_path / "out.usda"
    line = refused(run_cli("mirror", asset, rig["corr"], "--group", "L_Elbow", "--joints", "L_=R_", "-o", out), 3,
                   names=["asym_mesh.usda", f"<{humanoid.MESH}>", *(f"{int(p)} (" for p in partners)],
                   says=r"3 of the \d+ vertices the group moves have no vertex at their mirror image", outputs=[out])
    assert "group 'L_Elbow'" in line


def test_a_driver_without_a_partner_is_refused(rig, tmp_path):
    out = tmp_path / "out.usda"
    refused(run_cli("mirror", rig["asset"], rig["corr"], "--group", "L_Elbow", "--as", "R_Elbow", "--joints",
                    "Left=Right", "-o", out), 3,
            names=["corr.usda", f"<{humanoid.MESH}>", "'Hips/Spine/Chest/L_Shoulder/L_Elbow'"],
            says=r"has no partner under --joints 'Left=Right'", outputs=[out])
    refused(run_cli("mirror", rig["asset"], rig["corr"], "--group", "Neck", "--as", "Neck2", "--joints", "L_=R_",
                    "-o", out), 3, names=["'Hips/Spine/Chest/Neck'"], says="has no partner", outputs=[out])


@pytest.mark.parametrize(("args", "code", "says"), [
    (["--as", "R_Elbow"], 3, r"--as 'R_Elbow': needs group"),
    (["--group", "nope"], 3, r"no correctives group 'nope'"),
    (["--group", "L_Elbow", "--joints", "x_=y_"], 3, r"has no partner"),
    (["--joints", "(=R_"], 3, r"--joints '\(=R_': REGEX is not a regular expression"),
    (["--group", "L_Elbow", "--joints", "L_Shoulder/L_Elbow$=R_Shoulder/R_Elbow"], 3,
     r"group 'L_Elbow' keeps its name under --joints .*: name the mirrored group with --as"),
])
def test_bad_settings_are_refused(rig, tmp_path, args, code, says):
    out = tmp_path / "out.usda"
    joints = [] if "--joints" in args else ["--joints", "L_=R_"]
    refused(run_cli("mirror", rig["asset"], rig["corr"], *joints, *args, "-o", out), code, says=says, outputs=[out])


def test_the_output_may_not_be_the_asset(rig, tmp_path):
    asset = tmp_path / "asset.usda"
    shutil.copy(rig["asset"], asset)
    before = digest([asset])
    refused(run_cli("mirror", asset, rig["corr"], "--joints", "L_=R_", "-o", asset), 6, says="also an input",
            inputs=before)


# --- the maths -------------------------------------------------------------------------------------

@pytest.mark.parametrize("space", sorted(posespace.POSE_SPACES))
def test_each_pose_space_maps_conjugation_linearly(space):
    """For every pose space, the coordinates of P Delta P^-1 are COORDINATE_MAPS[space](P) times
    Delta's (Delta recovered from its coordinates by rotations_of, conjugated, its coordinates
    recomputed), the map is an isometry, and swingTwist's axis turns with P."""
    assert set(COORDINATE_MAPS) == set(posespace.POSE_SPACES)
    rng = np.random.default_rng(7)
    axis = np.array([1.0, 0.2, -0.3])
    for _ in range(20):
        p = Rotation.random(random_state=rng).as_matrix()
        delta = Rotation.from_rotvec(rng.normal(size=3) * 0.8)
        x = posespace.features(delta, space, axis)
        again = rotations_of(x, space, axis)
        assert float((again * delta.inv()).magnitude()[0]) < 1e-9
        turned = Rotation.from_matrix(p) * again * Rotation.from_matrix(p).inv()
        expected = posespace.features(turned, space, p @ axis)
        mapping = COORDINATE_MAPS[space](p)
        np.testing.assert_allclose(mapping @ x, expected, atol=1e-9)
        np.testing.assert_allclose(mapping.T @ mapping, np.eye(len(x)), atol=1e-12)


def test_mirrored_turns_give_the_mirrored_skinning_whatever_the_bind_orientations():
    """A chain root -> L1 -> L2 and its partner root -> R1 -> R2 at mirrored positions but with
    unrelated bind orientations: posing L1, L2 by Delta and R1, R2 by P Delta P^-1 gives the R
    joints the mirror images of the L joints' skinning transforms (M S M)."""
    rng = np.random.default_rng(3)
    names = ["Root", "Root/L1", "Root/L1/L2", "Root/R1", "Root/R1/R2"]
    parents = np.array([-1, 0, 1, 0, 3])
    pos = {0: np.array([0.0, 1.0, 0.5]), 1: np.array([1.0, 1.2, 0.1]), 2: np.array([2.0, 0.7, 0.4])}
    pos[3], pos[4] = pos[1] @ M, pos[2] @ M
    world = np.zeros((5, 4, 4))  # row-vector (Gf) bind transforms, column-vector below
    column = []
    for j in range(5):
        c = np.eye(4)
        c[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        c[:3, 3] = pos[j]
        column.append(c)
        world[j] = c.T
    bind = BindSpace(mesh="/M", skeleton="/S", skel_root="/", joints=tuple(names), parents=parents, bind_world=world,
                     bind_local=world, geom_bind=np.eye(4), rest=np.zeros((0, 3)))
    turns = driver_turns(bind, {"Root/L1": "Root/R1", "Root/L1/L2": "Root/R1/R2"}, M)
    deltas = {1: Rotation.random(random_state=rng).as_matrix(), 2: Rotation.random(random_state=rng).as_matrix()}
    deltas[3] = turns["Root/L1"] @ deltas[1] @ turns["Root/L1"].T
    deltas[4] = turns["Root/L1/L2"] @ deltas[2] @ turns["Root/L1/L2"].T

    def skinning(j: int) -> np.ndarray:  # posed world . bind world^-1, each local turned by its delta
        posed = {0: column[0]}
        for k in range(1, 5):
            local = np.linalg.inv(column[parents[k]]) @ column[k]
            turn = np.eye(4)
            turn[:3, :3] = deltas[k]
            posed[k] = posed[parents[k]] @ local @ turn
        return posed[j] @ np.linalg.inv(column[j])

    m4 = np.eye(4)
    m4[:3, :3] = M
    for left, right in ((1, 3), (2, 4)):
        np.testing.assert_allclose(m4 @ skinning(left) @ m4, skinning(right), atol=1e-12)


def test_report_figures(rig):
    """Not a check: prints what the tests above measured (pytest -s)."""
    for name, value in MEASURED.items():
        print(f"{name}: {value:.3g}")
    assert os.path.exists(rig["mirrored"])
