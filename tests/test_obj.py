"""The sculptor's loop through OBJ (issue 14): ``pose --obj-dir`` -> a sculpt application ->
``sculpts`` -> ``fit`` -> ``eval``.

A script stands in for the sculptor (``make_bad.sculpt_obj``): it rewrites each OBJ's ``v``
lines with known sculpt positions and keeps every other byte, as an application exporting
the same topology with the vertex order kept does. Pixar's ``UsdSkel.BakeSkinning`` of
ASSET + CORRECTIVES + ANIM + WEIGHTS must then give the edited OBJ points at every example
pose within 1e-5 of the bounding-box diagonal (as tests/test_roundtrip.py for EXAMPLES
written in USD), on the arm, the whole character and CesiumMan. Unedited OBJs must read
back bit for bit, every refusal of the bad-input catalogue (``fixtures/bad/obj/``) must be
one line naming the file, and the OBJ folder follows ``compare``'s folder policy.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import character
import numpy as np
import pytest
from conftest import (
    CESIUM,
    CESIUM_EXAMPLES,
    bake,
    diagonal,
    digest,
    fixture,
    generate,
    points,
    pose_only,
    refused,
    sculpt,
    warned,
    without_provenance,
)
from pxr import Sdf, Usd, UsdGeom, Vt

from psdbake.sculpting.obj import check
from psdbake.sculpting.obj.faces import MeshFaces
from psdbake.sculpting.obj.read import read_obj
from psdbake.sculpting.obj.text import obj_text

BAD = fixture("bad")
sys.path.insert(0, BAD)
import make_bad  # noqa: E402  (fixtures/bad/make_bad.py)

from psdbake.tolerances import ROUNDTRIP_RTOL  # noqa: E402

EXIT_INPUT, EXIT_OUTPUT = 3, 6
ASSET, POSED = os.path.join(BAD, "good_asset.usda"), os.path.join(BAD, "good_posed.usda")
GOOD_EXAMPLES = os.path.join(BAD, "good_examples.usda")
OBJ = os.path.join(BAD, make_bad.OBJ_DIR)
MESH = make_bad.MESH
ARM, ARM_POSES, ARM_EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_poses.usda"), fixture("arm_lbs_examples.usda")


def layer_points(path: str, mesh: str, time: float) -> np.ndarray:
    """The points sample exactly as stored (float32)."""
    value = Sdf.Layer.FindOrOpen(str(path)).QueryTimeSample(Sdf.Path(mesh).AppendProperty("points"), time)
    return np.array(value, dtype=np.float32)


def manifest(obj_dir) -> dict:
    with open(os.path.join(obj_dir, "manifest.json"), encoding="utf-8") as fh:
        return json.load(fh)


def ok(result) -> str:
    code, out, err = result
    assert code == 0, err
    return out


# --- float32 digits: what pose writes reads back bit for bit -----------------------------

def test_float32_values_round_trip_bit_exactly_through_tinyobjloader(tmp_path):
    """10^5 float32 values of every binade (subnormals, +-0, the largest finite) written with
    '%.9g' read back through tinyobjloader as the very same bits."""
    rng = np.random.default_rng(14)
    bits = rng.integers(0, 2**32, 100_002, dtype=np.uint64).astype(np.uint32)
    values = bits.view(np.float32)
    values = values[np.isfinite(values)]
    special = np.array([0.0, -0.0, 1e-45, -1e-45, 1.1754942e-38, 3.4028235e38, -3.4028235e38, 0.1, 1 / 3], np.float32)
    values = np.concatenate([special, values])
    values = values[: len(values) // 3 * 3].reshape(-1, 3)
    path = tmp_path / "values.obj"
    empty = np.zeros(0, dtype=np.int64)
    path.write_text(obj_text(values, MeshFaces(len(values), empty, empty), "values"), encoding="utf-8")
    back = read_obj(str(path), "values.obj").points
    assert back.dtype == np.float32 and back.shape == values.shape
    assert np.array_equal(back.view(np.uint32), values.view(np.uint32))


@pytest.mark.parametrize(("line", "says"), [
    ("v nan 0 0", r"'nan' is not finite"), ("v inf 0 0", r"'inf' is not finite"),
    ("v 1e39 0 0", r"beyond float32"), ("v abc 0 0", r"'abc' is not a number"), ("v 1,5 0 0", r"'1,5' is not a number"),
    ("v 1 2", r"needs three coordinates"), ("v 1_0 0 0", r"reads as 1\.0"),
])
def test_what_tinyobjloader_would_read_as_zero_is_refused(line, says, tmp_path):
    """tinyobjloader 2.0.0rc13 reads nan, inf and typos as 0 without a word: psdbake checks
    every v line's numbers against what it read."""
    path = tmp_path / "bad.obj"
    path.write_text(f"v 0 0 0\n{line}\nv 1 1 1\nf 1 2 3\n", encoding="utf-8")
    with pytest.raises(Exception, match=says) as exc:
        read_obj(str(path), "bad.obj")
    assert "line 2" in str(exc.value)


def test_reader_keeps_polygons_negative_indices_and_vertex_order(tmp_path):
    path = tmp_path / "seam.obj"
    path.write_text("v 0 0 0 1 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nvt 0 0\nvt 1 0\nvt 1 1\n"
                    "o a\nf 1/1 2/2 3/3 4/1\no b\nf 2/2 5/3 -3/1\n", encoding="utf-8")
    obj = read_obj(str(path), "seam.obj")
    assert obj.points[:, 0].tolist() == [0, 1, 1, 0, 2]
    assert obj.counts.tolist() == [4, 3]
    assert obj.indices.tolist() == [0, 1, 2, 3, 1, 4, 2]


# --- pose --obj-dir -------------------------------------------------------------------------

def test_pose_writes_one_obj_per_mesh_and_time_code_exactly_as_examples(run, tmp_path):
    examples, objs = tmp_path / "posed.usda", tmp_path / "objs"
    out = ok(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", examples, "--obj-dir", objs, "--json"))
    summary = json.loads(out)
    names = [f"Arm.Geo.Tube@{t:04d}.obj" for t in (1, 2, 3)]
    assert summary["obj_files"] == names
    assert sorted(os.listdir(objs)) == [*names, "manifest.json"]
    data = manifest(objs)
    assert [(f["file"], f["mesh"], f["time"], f["points"], f["faces"]) for f in data["files"]] == [
        (n, MESH, float(t), 16, 12) for n, t in zip(names, (1, 2, 3), strict=True)]
    assert data["sources"]["examples"] == str(examples)
    for t, name in zip((1, 2, 3), names, strict=True):
        obj = read_obj(str(objs / name), name)
        assert np.array_equal(obj.points.view(np.uint32), layer_points(examples, MESH, t).view(np.uint32))
        stage = Usd.Stage.Open(ASSET)
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
        assert obj.counts.tolist() == list(mesh.GetFaceVertexCountsAttr().Get())
        assert obj.indices.tolist() == list(mesh.GetFaceVertexIndicesAttr().Get())
    # without --obj-dir, the same EXAMPLES (but for the command line each records)
    plain = tmp_path / "plain.usda"
    ok(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", plain, "-q"))
    assert without_provenance(plain) == without_provenance(examples)


def _asset_with_uvs(tmp_path, interpolation: str, indexed: bool, left_handed: bool) -> str:
    """The catalogue's good asset with a texCoord2f primvar and, optionally, leftHanded faces
    (edited in a copy: the fixture's layer, open in this process, stays as it is on disk)."""
    copy = Sdf.Layer.CreateAnonymous(".usda")
    copy.TransferContent(Sdf.Layer.FindOrOpen(ASSET))
    stage = Usd.Stage.Open(copy)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
    corners = len(mesh.GetFaceVertexIndicesAttr().Get())
    n = corners if interpolation == "faceVarying" else 16
    values = [(0.01 * i, 0.5 + 0.02 * i) for i in range(7 if indexed else n)]
    pv = UsdGeom.PrimvarsAPI(mesh.GetPrim()).CreatePrimvar("uv", Sdf.ValueTypeNames.TexCoord2fArray, interpolation)
    pv.Set(Vt.Vec2fArray(values))
    if indexed:
        pv.SetIndices(Vt.IntArray([(3 * i) % 7 for i in range(n)]))
    if left_handed:
        mesh.GetOrientationAttr().Set(UsdGeom.Tokens.leftHanded)
    path = str(tmp_path / f"asset_{interpolation}_{indexed}_{left_handed}.usda")
    copy.Export(path)
    return path


@pytest.mark.parametrize(("interpolation", "indexed", "left_handed"), [
    ("vertex", False, False), ("faceVarying", False, False), ("faceVarying", True, True), ("vertex", True, True),
])
def test_uvs_and_winding(interpolation, indexed, left_handed, run, tmp_path):
    """vt per point or corner (indexed primvars keep their values and indices); a leftHanded
    mesh's faces are reversed in the OBJ, and read back they are the asset's again."""
    asset = _asset_with_uvs(tmp_path, interpolation, indexed, left_handed)
    examples, objs = tmp_path / "posed.usda", tmp_path / "objs"
    ok(run("pose", asset, "--anim", GOOD_EXAMPLES, "-o", examples, "--obj-dir", objs, "-q"))
    stage = Usd.Stage.Open(asset)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
    counts = list(mesh.GetFaceVertexCountsAttr().Get())
    indices = list(mesh.GetFaceVertexIndicesAttr().Get())
    pv = UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("uv")
    values = np.array(pv.Get(), dtype=np.float32)
    slots = list(pv.GetIndices()) if indexed else list(range(len(values)))
    text = (objs / "Arm.Geo.Tube@0001.obj").read_text(encoding="utf-8").splitlines()
    vt = np.array([[float(x) for x in ln.split()[1:]] for ln in text if ln.startswith("vt ")], dtype=np.float32)
    assert np.array_equal(vt, values)
    faces = [[tuple(int(x) - 1 for x in c.split("/")) for c in ln.split()[1:]] for ln in text if ln.startswith("f ")]
    start = 0
    for k, face in zip(counts, faces, strict=True):
        usd = list(range(start, start + k))
        obj_order = [usd[0], *reversed(usd[1:])] if left_handed else usd
        assert [v for v, _ in face] == [indices[c] for c in obj_order]
        uv_of = (lambda c: slots[c]) if interpolation == "faceVarying" else (lambda c: slots[indices[c]])
        assert [t for _, t in face] == [uv_of(c) for c in obj_order]
        start += k
    out = tmp_path / "sculpted.usda"
    ok(run("sculpts", asset, examples, "--obj-dir", objs, "-o", out, "-q"))
    for t in (1, 2, 3):
        assert np.array_equal(layer_points(out, MESH, t).view(np.uint32), layer_points(examples, MESH, t).view(np.uint32))


def test_obj_dir_policy(run, tmp_path):
    """Created if missing; filled again when it holds pose's manifest (unedited files replaced,
    stale ones removed); a foreign folder, a file, or a sculpt it would replace: exit 6."""
    examples, objs = tmp_path / "posed.usda", tmp_path / "deep" / "objs"
    ok(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", examples, "--obj-dir", objs, "-q"))
    before = digest(objs / f for f in os.listdir(objs))
    (objs / "notes.txt").write_text("the artist's notes", encoding="utf-8")  # not ours: left alone
    ok(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", examples, "--obj-dir", objs, "-q"))
    assert digest(objs / f for f in os.listdir(objs) if f != "notes.txt") == before
    assert (objs / "notes.txt").exists()
    # fewer poses: the file of time code 3 goes
    two = tmp_path / "two.usda"
    layer = Sdf.Layer.FindOrOpen(GOOD_EXAMPLES)
    copy = Sdf.Layer.CreateAnonymous(".usda")
    copy.TransferContent(layer)
    for attr in (Sdf.Path(make_bad.ANIM_PRIM).AppendProperty("rotations"), Sdf.Path(MESH).AppendProperty("points")):
        copy.EraseTimeSample(attr, 3.0)
    copy.Export(str(two))
    ok(run("pose", ASSET, "--anim", two, "-o", examples, "--obj-dir", objs, "-q"))
    assert sorted(os.listdir(objs)) == ["Arm.Geo.Tube@0001.obj", "Arm.Geo.Tube@0002.obj", "manifest.json", "notes.txt"]
    # a sculpted file is never replaced
    make_bad.sculpt_obj(str(objs / "Arm.Geo.Tube@0001.obj"), layer_points(GOOD_EXAMPLES, MESH, 1.0))
    kept = digest([examples, *(objs / f for f in os.listdir(objs))])
    refused(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", examples, "--obj-dir", objs), EXIT_OUTPUT,
            names=["Arm.Geo.Tube@0001.obj"], says=r"changed since psdbake pose wrote it", inputs=kept)
    # a folder of someone else's, a file
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "a.obj").write_text("v 0 0 0\n", encoding="utf-8")
    out = tmp_path / "e.usda"
    refused(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", out, "--obj-dir", foreign), EXIT_OUTPUT,
            names=[str(foreign)], says=r"not empty and holds no psdbake OBJ manifest", outputs=[out])
    refused(run("pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", out, "--obj-dir", examples), EXIT_OUTPUT,
            names=[str(examples)], says=r"not a folder", outputs=[out])


@pytest.mark.slow
def test_interrupted_before_the_commit_leaves_nothing(tmp_path):
    """SIGTERM with EXAMPLES, every OBJ and the manifest written to temporary files (psdbake's
    commit hook holds the run there): exit 130, no EXAMPLES, and the folder it made is gone."""
    examples, objs, marker = tmp_path / "posed.usda", tmp_path / "objs", tmp_path / "marker"
    env = {**os.environ, "PSDBAKE_PAUSE_AT": f"commit:{marker}"}
    proc = subprocess.Popen([sys.executable, "-m", "psdbake", "pose", ASSET, "--anim", GOOD_EXAMPLES, "-o", str(examples),
                             "--obj-dir", str(objs)], env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.stderr else ""
        time.sleep(0.01)
    assert len([f for f in os.listdir(objs) if ".tmp" in f]) == 4  # three OBJs and the manifest, unrenamed
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert (proc.returncode, err.strip()) == (130, "psdbake: interrupted")
    assert not examples.exists() and not objs.exists()
    assert sorted(os.listdir(tmp_path)) == ["marker"]


def test_failed_pose_leaves_no_folder(run, tmp_path):
    out, objs = tmp_path / "e.usda", tmp_path / "objs"
    refused(run("pose", os.path.join(BAD, "no_skelroot.usda"), "--anim", GOOD_EXAMPLES, "-o", out, "--obj-dir", objs),
            EXIT_INPUT, names=["no_skelroot.usda"], outputs=[out])
    assert not objs.exists()


# --- sculpts: the catalogue ----------------------------------------------------------------

#: obj/<case> -> (file named, says)
OBJ_DEFECTS = {
    "reordered_vertices": ("Arm.Geo.Tube@0002.obj", r"vertices re-ordered: .*renumbered.*keeping the vertex order"),
    "retriangulated_faces": ("Arm.Geo.Tube@0002.obj", r"faces re-triangulated: 24 faces \(24 triangles\), the asset's "
                                                      r"mesh has 12 faces \(12 quads\)"),
    "wrong_vertex_count": ("Arm.Geo.Tube@0002.obj", r"17 vertices, the asset's mesh has 16"),
    "nan_coordinate": ("Arm.Geo.Tube@0002.obj", r"line \d+: coordinate 'nan' is not finite"),
    "centimetres": ("Arm.Geo.Tube@0001.obj", r"looks like centimetres vs metres: scale 100x; use --scale 0\.01$"),
    "z_up": ("Arm.Geo.Tube@0001.obj", r"exported Z-up; use --up-axis Z$"),
    "far": ("Arm.Geo.Tube@0002.obj", r"not near the posed mesh \(median vertex distance [\d.]+, 0\.5 of its diagonal\)"),
    "missing_file": ("Arm.Geo.Tube@0002.obj", r"missing \(listed in manifest\.json"),
    "no_pose_time": ("Arm.Geo.Tube@0005.obj", r"good_posed\.usda has no pose at time code 5"),
    "unlisted_no_pose_time": ("Arm.Geo.Tube@0005.obj", r"time code 5: .*good_posed\.usda has no pose there"),
}


def test_catalogue_has_a_case_per_defect():
    assert set(OBJ_DEFECTS) == set(make_bad.OBJ_CASES_BY_NAME)


@pytest.mark.parametrize("case", sorted(OBJ_DEFECTS))
def test_bad_obj(case, run, tmp_path):
    name, says = OBJ_DEFECTS[case]
    folder = os.path.join(OBJ, case)
    out = tmp_path / "sculpted.usda"
    inputs = digest([ASSET, POSED, *(os.path.join(folder, f) for f in os.listdir(folder))])
    names = [os.path.join(folder, name)] + ([] if case.startswith("unlisted") else [f"<{MESH}>"])
    refused(run("sculpts", ASSET, POSED, "--obj-dir", folder, "-o", out), EXIT_INPUT, names=names, says=says,
            outputs=[out], inputs=inputs)


def test_good_catalogue_baseline(run, tmp_path):
    """obj/good/ reads back as good_examples.usda's sculpts, bit for bit, and fits."""
    out, corr = tmp_path / "sculpted.usda", tmp_path / "corr.usda"
    payload = json.loads(ok(run("sculpts", ASSET, POSED, "--obj-dir", os.path.join(OBJ, "good"), "-o", out, "--json")))
    assert [(f["time"], f["edited"], f["points"]) for f in payload["files"]] == [(t, True, 16) for t in (1.0, 2.0, 3.0)]
    for f in payload["files"]:
        target = layer_points(GOOD_EXAMPLES, MESH, f["time"]).astype(np.float64)
        d = np.linalg.norm(target - layer_points(POSED, MESH, f["time"]), axis=1)
        assert f["moved"] == int((d > 1e-6 * diagonal(layer_points(POSED, MESH, f["time"]))).sum()) > 0
        assert f["max_displacement"] == pytest.approx(d.max(), rel=1e-12)
        assert np.array_equal(layer_points(out, MESH, f["time"]), layer_points(GOOD_EXAMPLES, MESH, f["time"]))
    ok(run("fit", ASSET, out, "-o", corr, "-q"))


@pytest.mark.parametrize(("case", "flags"), [("centimetres", ["--scale", "0.01"]), ("z_up", ["--up-axis", "Z"]),
                                             ("z_up", ["--up-axis", "z"])])
def test_flags_undo_the_export(case, flags, run, tmp_path):
    out = tmp_path / "sculpted.usda"
    ok(run("sculpts", ASSET, POSED, "--obj-dir", os.path.join(OBJ, case), "-o", out, *flags, "-q"))
    for t in (1.0, 2.0, 3.0):
        back, target = layer_points(out, MESH, t), layer_points(GOOD_EXAMPLES, MESH, t)
        if case == "z_up":  # a quarter turn only moves and negates coordinates: exact
            assert np.array_equal(back, target)
        else:
            assert np.abs(back - target).max() <= 1e-6 * diagonal(target.astype(np.float64))


def test_flags_given_in_vain_are_named(run, tmp_path):
    out = tmp_path / "sculpted.usda"
    refused(run("sculpts", ASSET, POSED, "--obj-dir", os.path.join(OBJ, "good"), "-o", out, "--up-axis", "Z"),
            EXIT_INPUT, names=["Arm.Geo.Tube@0001.obj"], says=r"the OBJ as written is near it: drop --scale and --up-axis",
            outputs=[out])
    for bad in ("0", "-1", "nan", "inf"):
        refused(run("sculpts", ASSET, POSED, "--obj-dir", os.path.join(OBJ, "good"), "-o", out, "--scale", bad),
                EXIT_INPUT, names=["--scale"], says=r"positive", outputs=[out])


@pytest.mark.parametrize(("factor", "units"), [(k, name) for k, name in check.UNITS])
@pytest.mark.parametrize("turn", ["", "Z", "other"])
def test_every_unit_and_turn_is_named(factor, units, turn):
    posed = layer_points(POSED, MESH, 2.0).astype(np.float64)
    matrix = {"": np.eye(3), "Z": check.up_rotation("Y", "Z"), "other": check.up_rotation("Z", "Y")}[turn]
    raw = factor * (layer_points(GOOD_EXAMPLES, MESH, 2.0).astype(np.float64) @ matrix)
    assert check.explain(raw, posed, "Y") == (factor, turn)
    with pytest.raises(Exception, match=units if turn != "other" else "the other way") as exc:
        check.check_placement(raw, raw, posed, "Y", "x.obj")
    if turn == "Z":
        assert f"--up-axis Z --scale {1 / factor:.4g}" in str(exc.value)


def test_faces_changed_is_not_a_renumbering():
    faces = MeshFaces(4, np.array([3, 3]), np.array([0, 1, 2, 0, 2, 3]))
    from psdbake.sculpting.obj.read import ObjMesh

    pts = np.zeros((4, 3), np.float32)
    with pytest.raises(Exception, match=r"faces changed: face 2 has other vertices.*vertex 2, the asset's 1"):
        check.check_topology(ObjMesh(pts, np.array([3, 3]), np.array([0, 1, 2, 1, 2, 3])), faces, "x.obj")
    with pytest.raises(Exception, match=r"faces changed: 1 faces \(1 quads\).*has 2 faces \(2 triangles\)"):
        check.check_topology(ObjMesh(pts, np.array([4]), np.array([0, 1, 2, 3])), faces, "x.obj")
    with pytest.raises(Exception, match=r"vertices re-ordered"):
        check.check_topology(ObjMesh(pts, np.array([3, 3]), np.array([1, 0, 2, 1, 2, 3])), faces, "x.obj")


def _copy_good(tmp_path):
    folder = tmp_path / "objs"
    shutil.copytree(os.path.join(OBJ, "good"), folder)
    return folder


def test_unlisted_objs(run, tmp_path):
    folder, out = _copy_good(tmp_path), tmp_path / "sculpted.usda"
    shutil.copy(folder / "Arm.Geo.Tube@0002.obj", folder / "Arm.Geo.Tube@0002 (copy).obj")
    warned(run("sculpts", ASSET, POSED, "--obj-dir", folder, "-o", out), names=["Arm.Geo.Tube@0002 (copy).obj"],
           says=r"ignored: not listed in manifest\.json", outputs=[out])
    shutil.copy(folder / "Arm.Geo.Tube@0002.obj", folder / "Arm.Other@0002.obj")
    refused(run("sculpts", ASSET, POSED, "--obj-dir", folder, "-o", tmp_path / "b.usda"), EXIT_INPUT,
            names=["Arm.Other@0002.obj"], says=r"not listed in manifest\.json", outputs=[tmp_path / "b.usda"])


@pytest.mark.parametrize(("edit", "says"), [
    (lambda d: d["files"][0].update(file="../good_asset.usda"), r"is not a name psdbake pose writes"),
    (lambda d: d["files"][0].update(mesh="/Arm/Nothing"), r"not a skinned mesh of"),
    (lambda d: d["files"][1].update(time=1.0), r"same file or mesh and time code"),
    (lambda d: d.update(command="compare"), r"not a psdbake OBJ manifest"),
])
def test_tampered_manifest(edit, says, run, tmp_path):
    folder, out = _copy_good(tmp_path), tmp_path / "sculpted.usda"
    data = manifest(folder)
    edit(data)
    (folder / "manifest.json").write_text(json.dumps(data), encoding="utf-8")
    refused(run("sculpts", ASSET, POSED, "--obj-dir", folder, "-o", out), EXIT_INPUT, says=says, outputs=[out])


def test_no_manifest_no_folder_and_output_is_input(run, tmp_path):
    out = tmp_path / "sculpted.usda"
    refused(run("sculpts", ASSET, POSED, "--obj-dir", tmp_path, "-o", out), EXIT_INPUT,
            names=["manifest.json"], says=r"not found", outputs=[out])
    refused(run("sculpts", ASSET, POSED, "--obj-dir", tmp_path / "none", "-o", out), EXIT_INPUT,
            says=r"no such folder", outputs=[out])
    kept = digest([POSED])
    refused(run("sculpts", ASSET, POSED, "--obj-dir", os.path.join(OBJ, "good"), "-o", POSED), EXIT_OUTPUT,
            says=r"also an input", inputs=kept)


def test_examples_not_the_posed_file_warns(run, tmp_path):
    other, out = tmp_path / "posed_again.usdc", tmp_path / "sculpted.usda"
    Sdf.Layer.FindOrOpen(POSED).Export(str(other))
    warned(run("sculpts", ASSET, other, "--obj-dir", os.path.join(OBJ, "good"), "-o", out), names=[str(other)],
           says=r"not the EXAMPLES file psdbake pose wrote", outputs=[out])


def test_sculpts_is_deterministic_and_unedited_objs_read_back_bit_for_bit(run, tmp_path):
    examples, objs = tmp_path / "posed.usda", tmp_path / "objs"
    ok(run("pose", ARM, "--anim", ARM_POSES, "-o", examples, "--obj-dir", objs, "-q"))
    a = tmp_path / "a.usda"
    ok(run("sculpts", ARM, examples, "--obj-dir", objs, "-o", a, "-q"))
    first = a.read_bytes()
    ok(run("sculpts", ARM, examples, "--obj-dir", objs, "-o", a, "-q"))
    assert a.read_bytes() == first
    for t in (1.0, 2.0, 3.0):
        assert np.array_equal(layer_points(a, generate.MESH, t).view(np.uint32),
                              layer_points(examples, generate.MESH, t).view(np.uint32))


# --- the loop, end to end ------------------------------------------------------------------

def _sculptor(objs, targets: dict[tuple[str, float], np.ndarray]) -> dict[tuple[str, float], np.ndarray]:
    """Edit the OBJs the targets name (v lines only); returns every file's points, as the
    OBJs now hold them (edited or not), by (mesh, time)."""
    held = {}
    for f in manifest(objs)["files"]:
        key = (f["mesh"], f["time"])
        path = os.path.join(objs, f["file"])
        if key in targets:
            make_bad.sculpt_obj(path, targets[key])
        held[key] = read_obj(path, f["file"]).points.astype(np.float64)
    return held


def _loop(run, tmp_path, asset, poses, name, targets):
    """pose --obj-dir -> sculptor -> sculpts: (SCULPTED_EXAMPLES, points held by the OBJs)."""
    posed, objs, sculpted = tmp_path / f"{name}_posed.usda", tmp_path / f"{name}_objs", tmp_path / f"{name}_sculpted.usda"
    ok(run("pose", asset, "--anim", poses, "-o", posed, "--obj-dir", objs, "-q"))
    held = _sculptor(objs, targets)
    payload = json.loads(ok(run("sculpts", asset, posed, "--obj-dir", objs, "-o", sculpted, "--json")))
    for f in payload["files"]:
        key = (f["mesh"], f["time"])
        assert np.array_equal(layer_points(sculpted, *key), held[key].astype(np.float32))
        assert f["edited"] == (key in targets) and (f["moved"] > 0) == (key in targets)
    return sculpted, held


def _check_bake(stack, plain, held, edited, times, label) -> float:
    """The stack baked at each time gives every OBJ's points (edited or not) within
    ROUNDTRIP_RTOL of its diagonal, and plain skinning (``plain``) misses every edited one by
    100x that: the correctives make it so. Returns the worst error."""
    worst = 0.0
    for t in times:
        baked, bare = bake(stack, t), bake(plain, t)
        for (mesh, at), target in held.items():
            if at == t:
                err = np.abs(points(baked, mesh, t) - target).max() / diagonal(target)
                assert err <= ROUNDTRIP_RTOL, f"{label} {mesh} t={t}: {err:.2e}"
                worst = max(worst, err)
                if (mesh, at) in edited:
                    assert np.abs(points(bare, mesh, t) - target).max() / diagonal(target) > 100 * ROUNDTRIP_RTOL
    return worst


def test_round_trip_arm(run, tmp_path):
    targets = {(generate.MESH, t): sculpt(ARM_EXAMPLES, generate.MESH, t) for t in (1.0, 2.0, 3.0)}
    sculpted, held = _loop(run, tmp_path, ARM, ARM_POSES, "arm", targets)
    corr, weights = tmp_path / "corr.usda", tmp_path / "weights.usda"
    ok(run("fit", ARM, sculpted, "-o", corr, "-q"))
    ok(run("eval", ARM, corr, "--anim", ARM_POSES, "-o", weights, "-q"))
    worst = _check_bake([str(weights), ARM_POSES, str(corr), ARM], [ARM_POSES, ARM], held, targets, (1.0, 2.0, 3.0), "arm")
    print(f"arm: max round-trip error {worst:.2e} of the diagonal")


@pytest.mark.slow
def test_round_trip_cesiumman(run, tmp_path):
    mesh = generate.CESIUM_MESH
    times = [float(t) for t in Sdf.Layer.FindOrOpen(CESIUM_EXAMPLES).ListTimeSamplesForPath(
        Sdf.Path(mesh).AppendProperty("points"))]
    targets = {(mesh, t): sculpt(CESIUM_EXAMPLES, mesh, t) for t in times}
    sculpted, held = _loop(run, tmp_path, CESIUM, CESIUM_EXAMPLES, "cesium", targets)
    text = (tmp_path / "cesium_objs" / manifest(tmp_path / "cesium_objs")["files"][0]["file"]).read_text()
    assert "\nvt " in text and "/" in text.split("\nf ", 1)[1].split()[0]  # its UVs (primvars:st, vertex) came along
    corr, weights = tmp_path / "corr.usda", tmp_path / "weights.usda"
    ok(run("fit", CESIUM, sculpted, "-o", corr, "-q"))
    ok(run("eval", CESIUM, corr, "--anim", CESIUM_EXAMPLES, "-o", weights, "-q"))
    anim = pose_only(CESIUM_EXAMPLES)
    worst = _check_bake([str(weights), anim, str(corr), CESIUM], [anim, CESIUM], held, targets, times, "cesiumman")
    print(f"cesiumman: max round-trip error {worst:.2e} of the diagonal")


@pytest.mark.slow
def test_round_trip_character(run, tmp_path):
    """Every example set through OBJ: only its sculpted meshes' OBJs are edited, the others
    (the brow with its own blend shape, the sleeve or body at the other set's poses) go
    back unedited and must come out of the stack as plain UsdSkel puts them."""
    asset = fixture("character", "character.usda")
    sculpted, held, targets = {}, {}, {}
    for name, spec in sorted(character.EXAMPLE_SETS.items()):
        poses = fixture("character", spec["file"])
        targets[name] = {(m, float(t)): sculpt(poses, m, t) for m in spec["meshes"] for t in spec["poses"]}
        sculpted[name], held[name] = _loop(run, tmp_path, asset, poses, name, targets[name])
    corr = tmp_path / "corr.usda"
    for group, sets in sorted(character.FIT_GROUPS.items()):
        meshes = sorted({m for s in sets for m in character.EXAMPLE_SETS[s]["meshes"]})
        ok(run("fit", asset, *(sculpted[s] for s in sets), "--group", group, *(a for m in meshes for a in ("--mesh", m)),
               "-o", corr, "-q"))
    worst = 0.0
    for name, spec in sorted(character.EXAMPLE_SETS.items()):
        poses, weights = fixture("character", spec["file"]), tmp_path / f"{name}_weights.usda"
        ok(run("eval", asset, corr, "--anim", poses, "-o", weights, "-q"))
        anim = pose_only(poses)
        worst = max(worst, _check_bake([str(weights), anim, str(corr), asset], [anim, asset], held[name], targets[name],
                                       sorted(float(t) for t in spec["poses"]), f"character {name}"))
    print(f"character: max round-trip error {worst:.2e} of the diagonal")
