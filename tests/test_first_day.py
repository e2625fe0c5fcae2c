"""A TD's first day, scripted: README's sculptor loop on a symmetric character with only half
the poses sculpted (the left side and the neck), the usual mistakes on the way, the other side
made by mirror, and the stack typed in both layer orders. It ends with a stack that
UsdSkel.BakeSkinning shows reproducing every sculpt, the ones nobody sculpted included (their
mirror images), within the round-trip guarantee."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import sys

import humanoid
import numpy as np
import pytest
from conftest import bake, diagonal, digest, fixture, points, pose_only, refused, run_cli, sculpt
from pxr import Sdf

from psdbake import tolerances as tol

sys.path.insert(0, fixture("bad"))
import make_bad

LEFT_AND_NECK = (1.0, 2.0, 4.0, 5.0, 8.0, 9.0, 12.0)  # sculpted by the artist
RIGHT = (3.0, 6.0, 7.0, 10.0, 11.0, 13.0)  # left for mirror: their OBJs stay as pose wrote them
SYMMETRIC_COMBINATION = ("r_shoulder", "r_elbow", humanoid.Field("r_arm", (-30.0, 143.0, 0.0), 7.0, (0, 1, 0), 1.6))


@pytest.fixture(scope="module")
def character(tmp_path_factory):
    """The symmetric humanoid (tests/test_mirror.py's): an asset, the sculpts an artist would make
    at each pose (the truth) and the POSES layer the TD starts from."""
    folder = tmp_path_factory.mktemp("first_day")
    poses = dict(humanoid.EXAMPLE_POSES)
    poses[13.0] = humanoid.pose_of({"r_shoulder": 60.0, "r_elbow": 90.0})
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(humanoid.COMBINATIONS, "r_arm_raise_bend", SYMMETRIC_COMBINATION)
        asset = humanoid.build(str(folder / "humanoid.usda"))
        truth = humanoid.write_examples(str(folder / "truth.usda"), asset, poses)
    return {"folder": folder, "asset": asset, "truth": truth,
            "poses": humanoid.write_animation(str(folder / "poses.usda"), poses)}


def _ok(result) -> str:
    code, out, err = result
    assert code == 0, err
    return out


@pytest.mark.slow
def test_a_first_day(character, tmp_path, monkeypatch):
    asset, truth, poses = character["asset"], character["truth"], character["poses"]
    monkeypatch.chdir(tmp_path)  # the TD works in a shot folder, with relative paths as README shows
    inputs = digest([asset, truth, poses])

    # inspect the character: its joints and meshes
    out = _ok(run_cli("inspect", asset))
    assert "L_Elbow" in out and f"skinned <{humanoid.MESH}>" in out

    # 1. pose: one OBJ per mesh and pose
    _ok(run_cli("pose", asset, "--poses", poses, "-o", "to_sculpt.usda", "--obj-dir", "sculpt/", "-q"))
    manifest = json.loads((tmp_path / "sculpt" / "manifest.json").read_text())

    # 2. the artist sculpts half of them (left side and neck), saving each under its own name
    for entry in manifest["files"]:
        if entry["time"] in LEFT_AND_NECK:
            make_bad.sculpt_obj(str(tmp_path / "sculpt" / entry["file"]), sculpt(truth, humanoid.MESH, entry["time"]))

    # 3. sculpts, first with -o forgotten
    code, _, err = run_cli("sculpts", asset, "to_sculpt.usda", "--obj-dir", "sculpt/")
    assert code == 2 and "Missing option '-o'" in err
    out = _ok(run_cli("sculpts", asset, "to_sculpt.usda", "--obj-dir", "sculpt/", "-o", "sculpted.usda"))
    assert f"{len(manifest['files'])} OBJ file(s), {len(LEFT_AND_NECK)} with sculpted vertices" in out

    # 4. fit, first with the files in the other order (nothing written), then as README types it;
    # the right side's groups have no edited example: left out, each named
    refused(run_cli("fit", "sculpted.usda", asset, "-o", "correctives.usda"), 3, names=("sculpted.usda", asset),
            says=r"look given in the other order \(ASSET comes first\)", outputs=("correctives.usda",))
    code, out, err = run_cli("fit", asset, "sculpted.usda", "-o", "correctives.usda", "--report", "fit.json")
    assert code == 0, err
    for group in ("R_Elbow", "R_Knee", "R_Shoulder", "combo_R_Shoulder_R_Elbow"):
        assert f"group '{group}'" in err
    assert not json.loads((tmp_path / "fit.json").read_text())["degraded"]

    # 5. mirror, first with README's lower-case map (the joints are L_/R_), then right, in place
    refused(run_cli("mirror", asset, "correctives.usda", "--joints", "(^|/)l_=\\1r_", "-o", "correctives.usda"), 3,
            says="matches it only ignoring case")
    out = _ok(run_cli("mirror", asset, "correctives.usda", "--joints", "L_=R_", "-o", "correctives.usda"))
    assert "groups: added R_Elbow, R_Knee, R_Shoulder, combo_R_Shoulder_R_Elbow" in out
    names = [g["group"] for g in json.loads(_ok(run_cli("groups", "correctives.usda", "--json")))["groups"]]
    assert sorted(names) == ["L_Elbow", "L_Knee", "L_Shoulder", "Neck", "R_Elbow", "R_Knee", "R_Shoulder",
                             "combo_L_Shoulder_L_Elbow", "combo_R_Shoulder_R_Elbow"]

    # 6. eval over the poses, first with ASSET and CORRECTIVES swapped, then past their end (the 1001
    # trap), then as authored
    refused(run_cli("eval", "correctives.usda", asset, "--anim", poses, "-o", "weights.usda"), 3,
            names=("correctives.usda", asset), says="look given in the other order", outputs=("weights.usda",))
    refused(run_cli("eval", asset, "correctives.usda", "--anim", poses, "-o", "weights.usda", "--frames", "1001:1013"),
            3, says="authored over 1..13")
    _ok(run_cli("eval", asset, "correctives.usda", "--anim", poses, "-o", "weights.usda", "-q"))

    # 7. stack: OUTPUT forgotten (nothing written), then in USD's order and in README's
    before = digest([asset, "correctives.usda", "weights.usda"])
    assert run_cli("stack", asset, "correctives.usda", poses, "weights.usda")[0] == 2
    assert digest([asset, "correctives.usda", "weights.usda"]) == before
    _ok(run_cli("stack", "weights.usda", poses, "correctives.usda", asset, "-o", "usd_order.usda", "-q"))
    _ok(run_cli("stack", asset, "correctives.usda", poses, "weights.usda", "-o", "readme_order.usda", "-q"))
    layers = [Sdf.Layer.OpenAsAnonymous(str(tmp_path / f)) for f in ("usd_order.usda", "readme_order.usda")]
    assert list(layers[0].subLayerPaths) == list(layers[1].subLayerPaths)

    # 8. the stack, through BakeSkinning, gives every sculpt: the sculpted half and the mirrored half
    baked = bake([str(tmp_path / "usd_order.usda")], 1.0, 13.0)
    plain = bake([pose_only(truth), asset], 1.0, 13.0)
    for t in (*LEFT_AND_NECK, *RIGHT):
        target = sculpt(truth, humanoid.MESH, t)
        error = np.abs(points(baked, humanoid.MESH, t) - target).max() / diagonal(target)
        assert error <= tol.ROUNDTRIP_RTOL, (t, error)
        assert np.abs(points(plain, humanoid.MESH, t) - target).max() / diagonal(target) > 100 * tol.ROUNDTRIP_RTOL

    # 9. someone re-skins the asset with dual quaternions: eval says so, --strict refuses
    reskinned = tmp_path / "reskinned.usda"
    shutil.copy(asset, reskinned)
    layer = Sdf.Layer.FindOrOpen(str(reskinned))
    attr = layer.GetAttributeAtPath(f"{humanoid.MESH}.primvars:skel:skinningMethod") or Sdf.AttributeSpec(
        layer.GetPrimAtPath(humanoid.MESH), "primvars:skel:skinningMethod", Sdf.ValueTypeNames.Token,
        Sdf.VariabilityUniform)
    attr.default = "dualQuaternion"
    layer.Save()
    code, _, err = run_cli("eval", str(reskinned), "correctives.usda", "--anim", poses, "-o", "weights2.usda", "-q")
    assert code == 0 and "is now skinned with dualQuaternion" in err, err
    assert run_cli("eval", str(reskinned), "correctives.usda", "--anim", poses, "-o", "weights3.usda", "--strict")[0] == 3

    assert digest([asset, truth, poses]) == inputs  # nothing the TD gave was modified
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]


@pytest.mark.slow
def test_the_loop_after_sculpting_as_one_batch(character, tmp_path, monkeypatch):
    """Everything after the sculpting is one jobs file for the farm: sculpts, fit, mirror in place,
    a group renamed in place, eval, stack and export-gltf, into folders that do not exist yet.
    Each job runs after the jobs that write what it reads, and the outputs are byte-identical
    to the same commands typed one by one."""
    asset, truth, poses = character["asset"], character["truth"], character["poses"]
    farm, direct = tmp_path / "farm", tmp_path / "direct"  # one depth: the outputs' relative paths agree
    farm.mkdir()
    _ok(run_cli("pose", asset, "--poses", poses, "-o", str(farm / "to_sculpt.usda"), "--obj-dir",
                str(farm / "sculpt"), "-q"))
    manifest = json.loads((farm / "sculpt" / "manifest.json").read_text())
    for entry in manifest["files"]:
        if entry["time"] in LEFT_AND_NECK:
            make_bad.sculpt_obj(str(farm / "sculpt" / entry["file"]), sculpt(truth, humanoid.MESH, entry["time"]))
    jobs = farm / "jobs.toml"
    jobs.write_text(f"""
[defaults]
asset = "{asset}"

[[stack]]  # listed first: the order comes from the files, not the table order
output = "shot/shot.usda"
layers = ["{asset}", "out/correctives.usda", "{poses}", "shot/weights.usda"]

[[sculpts]]
examples = "to_sculpt.usda"
obj_dir = "sculpt"
output = "out/sculpted.usda"

[[fit]]
examples = ["out/sculpted.usda"]
output = "out/correctives.usda"

[[mirror]]
correctives = "out/correctives.usda"
joints = ["L_=R_"]
output = "out/correctives.usda"

[[groups]]
file = "out/correctives.usda"
rename = ["Neck=neck_fix"]

[[eval]]
correctives = "out/correctives.usda"
anim = "{poses}"
output = "shot/weights.usda"

[[export-gltf]]
correctives = "out/correctives.usda"
anim = "{poses}"
output = "shot/shot.glb"
""")
    code, out, err = run_cli("batch", str(jobs), "-j", "2", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert [j["status"] for j in summary["jobs"]] == ["ok"] * 7
    ran = [j["job"] for j in summary["jobs"]]
    for first, then in [("[[sculpts]] #1", "[[fit]] #1"), ("[[fit]] #1", "[[mirror]] #1"),
                        ("[[mirror]] #1", "[[groups]] #1"), ("[[groups]] #1", "[[eval]] #1"),
                        ("[[eval]] #1", "[[stack]] #1"), ("[[groups]] #1", "[[export-gltf]] #1")]:
        assert ran.index(first) < ran.index(then), ran
    names = [g["group"] for g in json.loads(_ok(run_cli("groups", str(farm / "out" / "correctives.usda"),
                                                           "--json")))["groups"]]
    assert "neck_fix" in names and "R_Elbow" in names and "Neck" not in names

    direct.mkdir()
    monkeypatch.chdir(direct)
    shutil.copytree(farm / "sculpt", direct / "sculpt")
    shutil.copy(farm / "to_sculpt.usda", direct / "to_sculpt.usda")
    for job in summary["jobs"]:  # the command lines the batch ran, typed in its folder
        _ok(run_cli(*shlex.split(job["command"])[1:]))
    for name in ("out/sculpted.usda", "out/correctives.usda", "shot/weights.usda", "shot/shot.usda", "shot/shot.glb"):
        assert (direct / name).read_bytes() == (farm / name).read_bytes(), name
