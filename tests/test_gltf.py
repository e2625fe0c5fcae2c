"""``psdbake export-gltf``: the .glb is valid glTF 2.0 (Khronos glTF-Validator) and, evaluated
independently here (morph targets, then linear-blend skinning with the animated joints),
reproduces Pixar's ``UsdSkel.BakeSkinning`` of ASSET + CORRECTIVES + ANIM + WEIGHTS at
every frame.

Tolerance: the glTF stores positions, offsets, joint TRS, inverse bind matrices and weights
as float32, and UsdSkel skins in float32 too: each side is off the exact result by a few
float32 ulps of the coordinates (2^-24 ~ 6e-8 relative, times a handful of products and
sums). 1e-5 of the mesh's bounding-box diagonal is psdbake's round-trip guarantee; the
measured worst case is ~1e-7 (the numbers are in test_round_trip's message).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import numpy as np
import pygltflib
import pytest
from conftest import CESIUM, CESIUM_EXAMPLES, ROOT, bake, digest, fixture, points, refused, run_cli, warned
from pxr import Sdf, Usd, UsdGeom, UsdSkel

VALIDATOR = os.path.join(ROOT, "tests", "gltf")
TOLERANCE = 1e-5  # of the bounding-box diagonal, see the module docstring


def _wrapper(folder, name: str, asset: str, up_axis: str | None = None, meters: float | None = None,
             inbetween: str | None = None) -> str:
    """An asset layer over a fixture: other stage metadata and/or a 0.5 inbetween on a BlendShape."""
    layer = Sdf.Layer.CreateNew(str(folder / name))
    layer.subLayerPaths.append(asset)
    if up_axis:
        layer.pseudoRoot.SetInfo("upAxis", up_axis)
    if meters:
        layer.pseudoRoot.SetInfo("metersPerUnit", meters)
    layer.Save()
    if inbetween:
        stage = Usd.Stage.Open(layer)
        shape = UsdSkel.BlendShape(stage.GetPrimAtPath(inbetween))
        count = len(shape.GetOffsetsAttr().Get())
        half = shape.CreateInbetween("half")
        half.SetWeight(0.5)
        half.SetOffsets([(0.0, 0.3 + 0.01 * i, 0.1) for i in range(count)])
        stage.GetRootLayer().Save()
    return layer.identifier


def _moving(folder, anim: str) -> str:
    """ANIM plus the arm's SkelRoot moving over the shot (the skeleton node is animated too)."""
    layer = Sdf.Layer.CreateNew(str(folder / "moving_anim.usda"))
    layer.subLayerPaths.append(anim)
    stage = Usd.Stage.Open(layer)
    op = stage.OverridePrim("/Arm").CreateAttribute("xformOp:translate", Sdf.ValueTypeNames.Double3)
    op.Set((10.0, 2.0, -3.0), 1.0)
    op.Set((12.0, 5.0, -1.0), 48.0)
    layer.Save()
    return layer.identifier


CASES = {
    # the arm: transforms on the SkelRoot (animated here), Skeleton, mesh parent and mesh, a
    # geomBindTransform; restated Z-up in decimetres, so the axis and unit conversion is exercised too
    "arm_zup": lambda tmp: (_wrapper(tmp, "arm_zup.usda", fixture("arm_lbs.usda"), "Z", 0.1),
                            [fixture("arm_lbs_examples.usda")], _moving(tmp, fixture("arm_anim.usda"))),
    # three meshes: one with its own skel:joints order, one with an existing animated blend shape
    # (given a 0.5 inbetween here: two morph targets whose weights UsdSkel's sub-shape rule sets)
    "character": lambda tmp: (_wrapper(tmp, "character.usda", fixture("character", "character.usda"),
                                       inbetween="/Character/Geo/Brow/raise"),
                              [fixture("character", "character_l_elbow_examples.usda")],
                              fixture("character", "character_anim.usda")),
    "cesiumman": lambda tmp: (CESIUM, [CESIUM_EXAMPLES], CESIUM),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def exported(request, tmp_path_factory):
    """(case, asset, correctives, anim, weights, glb) after fit, eval and export-gltf."""
    tmp = tmp_path_factory.mktemp(request.param)
    asset, examples, anim = CASES[request.param](tmp)
    correctives, weights, glb = tmp / "correctives.usda", tmp / "weights.usda", tmp / "shot.glb"
    for args in (("fit", asset, *examples, "-o", correctives),
                 ("eval", asset, correctives, "--anim", anim, "-o", weights),
                 ("export-gltf", asset, correctives, "--anim", anim, "-o", glb)):
        rc, _, err = run_cli(*args)
        assert rc == 0, err
    assert not err, err  # nothing to warn about here: linear skinning, weights summing to 1
    return request.param, asset, str(correctives), anim, str(weights), str(glb)


# --- reading the glb back, independently of psdbake/export/gltf.py -------------------------------

class Glb:
    def __init__(self, path: str) -> None:
        self.doc = pygltflib.GLTF2.load_binary(path)
        self.blob = self.doc.binary_blob()

    def accessor(self, index: int) -> np.ndarray:
        a = self.doc.accessors[index]
        dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[a.componentType]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
        out = np.zeros((a.count, width), dtype=dtype)
        if a.bufferView is not None:
            view = self.doc.bufferViews[a.bufferView]
            assert view.byteStride in (None, 0)
            out = np.frombuffer(self.blob, dtype, a.count * width, view.byteOffset + (a.byteOffset or 0))
            out = out.reshape(a.count, width).copy()
        if a.sparse is not None:
            s = a.sparse
            idx_type = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[s.indices.componentType]
            iv, vv = self.doc.bufferViews[s.indices.bufferView], self.doc.bufferViews[s.values.bufferView]
            idx = np.frombuffer(self.blob, idx_type, s.count, iv.byteOffset + (s.indices.byteOffset or 0))
            values = np.frombuffer(self.blob, dtype, s.count * width, vv.byteOffset + (s.values.byteOffset or 0))
            out[idx.astype(np.int64)] = values.reshape(s.count, width)
        return out.astype(np.float64) if dtype == np.float32 else out.astype(np.int64)

    def tracks(self) -> dict[tuple[int, str], tuple[np.ndarray, np.ndarray]]:
        out = {}
        for animation in self.doc.animations:
            for channel in animation.channels:
                sampler = animation.samplers[channel.sampler]
                assert sampler.interpolation == "LINEAR"
                out[(channel.target.node, channel.target.path)] = (self.accessor(sampler.input)[:, 0],
                                                                   self.accessor(sampler.output))
        return out


def _sample(track: tuple[np.ndarray, np.ndarray], t: float, width: int) -> np.ndarray:
    """glTF LINEAR sampling (normalised lerp for quaternions; exact at the keys)."""
    times, values = track
    values = values.reshape(len(times), -1)
    k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 1))
    if k + 1 < len(times) and t > times[k]:
        a = (t - times[k]) / (times[k + 1] - times[k])
        v = (1 - a) * values[k] + a * values[k + 1]
        return v / np.linalg.norm(v) if width == 4 else v
    return values[k]


def _rotation(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def skinned_points(glb: Glb, t: float) -> dict[str, np.ndarray]:
    """Every skinned mesh's world-space points at time t (seconds), by its USD path (extras)."""
    doc, tracks = glb.doc, glb.tracks()
    parent = {c: i for i, node in enumerate(doc.nodes) for c in (node.children or [])}
    local = []
    for i, node in enumerate(doc.nodes):
        assert node.matrix is None
        tr = _sample(tracks[(i, "translation")], t, 3) if (i, "translation") in tracks else node.translation or [0, 0, 0]
        q = _sample(tracks[(i, "rotation")], t, 4) if (i, "rotation") in tracks else node.rotation or [0, 0, 0, 1]
        sc = _sample(tracks[(i, "scale")], t, 3) if (i, "scale") in tracks else node.scale or [1, 1, 1]
        m = np.eye(4)
        m[:3, :3] = _rotation(np.asarray(q, dtype=np.float64)) * np.asarray(sc, dtype=np.float64)
        m[:3, 3] = tr
        local.append(m)
    world = []
    for i in range(len(doc.nodes)):
        m, j = local[i], i
        while j in parent:
            j = parent[j]
            m = local[j] @ m
        world.append(m)
    out = {}
    for i, node in enumerate(doc.nodes):
        if node.mesh is None:
            continue
        mesh = doc.meshes[node.mesh]
        (prim,) = mesh.primitives
        attrs = prim.attributes
        pos = glb.accessor(attrs.POSITION)
        targets = prim.targets or []
        if targets:
            w = _sample(tracks[(i, "weights")], t, 1) if (i, "weights") in tracks else np.asarray(mesh.weights)
            for weight, target in zip(w, targets, strict=True):
                pos = pos + weight * glb.accessor(target["POSITION"] if isinstance(target, dict) else target.POSITION)
        skin = doc.skins[node.skin]
        ibm = glb.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major storage
        joint_mats = np.stack([world[j] for j in skin.joints]) @ ibm
        homog = np.hstack([pos, np.ones((len(pos), 1))])
        acc = np.zeros((len(pos), 4))
        k = 0
        while getattr(attrs, f"JOINTS_{k}", None) is not None:
            joints, weights = glb.accessor(getattr(attrs, f"JOINTS_{k}")), glb.accessor(getattr(attrs, f"WEIGHTS_{k}"))
            for c in range(4):
                acc += weights[:, c:c + 1] * np.einsum("nij,nj->ni", joint_mats[joints[:, c]], homog)
            k += 1
        out[node.extras["usdPath"]] = acc[:, :3]
    return out


def _conversion(asset: str) -> np.ndarray:
    """Stage world -> glTF world (Y up, meters), from the asset's own metadata."""
    stage = Usd.Stage.Open(asset, Usd.Stage.LoadNone)
    c = np.eye(4) * UsdGeom.GetStageMetersPerUnit(stage)
    c[3, 3] = 1.0
    if UsdGeom.GetStageUpAxis(stage) == "Z":
        c = c @ np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    return c


# --- the tests -----------------------------------------------------------------------------

def validate(path: str) -> dict:
    if not os.path.isdir(os.path.join(VALIDATOR, "node_modules", "gltf-validator")):
        pytest.fail("the glTF-Validator is not installed: run make test (or npm ci --prefix tests/gltf)")
    done = subprocess.run(["node", os.path.join(VALIDATOR, "validate.mjs"), path], capture_output=True, text=True,
                          check=True, timeout=120)
    return json.loads(done.stdout)


@pytest.mark.slow
def test_khronos_validator_finds_nothing(exported):
    report = validate(exported[-1])
    issues = report["issues"]
    assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), issues["messages"]
    assert report["info"]["hasSkins"] and report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1


def test_round_trip_matches_usdskel_bake(exported):
    case, asset, correctives, anim, weights, path = exported
    glb = Glb(path)
    stage = Usd.Stage.Open(anim, Usd.Stage.LoadNone)
    fps = stage.GetTimeCodesPerSecond()
    times = sorted({float(t) for t in Sdf.Layer.FindOrOpen(weights).ListAllTimeSamples()})
    seconds = sorted({float(s) for tr in glb.tracks().values() for s in tr[0]})
    # one keyframe per time code, on USD's timeline (time code t at t / fps seconds), so an
    # importer keying second s at frame s * fps (Blender) keeps the frame numbers
    assert np.allclose(np.array(seconds) * fps, times, atol=1e-3)
    layers = [weights, *([anim] if anim != asset else []), correctives, asset]
    baked = bake(layers, times[0], times[-1])
    convert = _conversion(asset)
    worst = 0.0
    for t, s in zip(times, seconds, strict=True):
        ours = skinned_points(glb, s)
        assert ours
        for mesh, got in ours.items():
            local = points(baked, mesh, t)
            m = np.array(UsdGeom.Xformable(baked.GetPrimAtPath(mesh)).ComputeLocalToWorldTransform(t)).reshape(4, 4)
            world = local @ m[:3, :3] + m[3, :3]
            expected = world @ convert[:3, :3].T + convert[:3, 3]
            diag = float(np.linalg.norm(expected.max(axis=0) - expected.min(axis=0)))
            worst = max(worst, float(np.abs(got - expected).max()) / diag)
    print(f"{case}: max |glTF - BakeSkinning| = {worst:.3g} of the bounding-box diagonal")
    assert worst <= TOLERANCE, f"{case}: {worst:.3g} of the diagonal"


def test_correctives_are_animated_morph_targets(exported):
    """Every BlendShape channel is a morph target (named in extras.targetNames), sparse where
    that is smaller, and the correctives' weights are not all zero over the shot."""
    case, *_, path = exported
    glb = Glb(path)
    tracks = glb.tracks()
    names = [n for mesh in glb.doc.meshes for n in (mesh.extras or {}).get("targetNames", [])]
    assert any(n.startswith("psd_") for n in names)
    sparse = dense = 0
    for i, node in enumerate(glb.doc.nodes):
        if node.mesh is None or not glb.doc.meshes[node.mesh].primitives[0].targets:
            continue
        targets = glb.doc.meshes[node.mesh].primitives[0].targets
        accessors = [glb.doc.accessors[t["POSITION"]] for t in targets]
        for a in accessors:
            if a.sparse is not None:
                sparse += 1
                assert a.bufferView is None and a.sparse.count < a.count
            else:
                dense += 1
        weights = tracks[(i, "weights")][1].reshape(-1, len(targets))
        assert np.abs(weights).max() > 0.05
    assert sparse >= 1, f"{case}: no corrective stored sparse"
    if case == "character":
        assert "brow_raise:half" in names and "brow_raise" in names


def test_same_inputs_same_bytes(exported, tmp_path):
    _, asset, correctives, anim, _, path = exported
    again = tmp_path / "again.glb"
    rc, _, err = run_cli("export-gltf", asset, correctives, "--anim", anim, "-o", again, "-q")
    assert rc == 0, err
    with open(path, "rb") as a, open(again, "rb") as b:
        assert a.read() == b.read()


# --- refusals ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def arm_correctives(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("arm")
    out = tmp / "correctives.usda"
    rc, _, err = run_cli("fit", fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), "-o", out, "-q")
    assert rc == 0, err
    return str(out)


def test_anim_without_skeleton_animation_is_refused(arm_correctives, tmp_path):
    out = tmp_path / "shot.glb"
    bad = fixture("bad", "anim_not_bound.usda")
    before = digest([bad, arm_correctives])
    refused(run_cli("export-gltf", fixture("arm_lbs.usda"), arm_correctives, "--anim", bad, "-o", out), 3,
            names=[bad, "</Arm/Skel>"], says="no SkelAnimation bound", outputs=[out], inputs=before)


def test_output_that_is_an_input_is_refused(arm_correctives, tmp_path):
    anim = tmp_path / "anim.usda"
    shutil.copy(fixture("arm_anim.usda"), anim)
    link = tmp_path / "anim.glb"
    os.symlink(anim, link)
    before = digest([anim])
    refused(run_cli("export-gltf", fixture("arm_lbs.usda"), arm_correctives, "--anim", anim, "-o", link), 6,
            names=[str(link)], says="also an input", inputs=before)


def test_wrong_extension_and_failed_runs_leave_no_file(arm_correctives, tmp_path):
    refused(run_cli("export-gltf", fixture("arm_lbs.usda"), arm_correctives, "--anim", fixture("arm_anim.usda"),
                    "-o", tmp_path / "shot.gltf"), 6, says=r"must end in \.glb", outputs=[tmp_path / "shot.gltf"])
    old = tmp_path / "old.glb"
    assert run_cli("export-gltf", fixture("arm_lbs.usda"), arm_correctives, "--anim", fixture("arm_anim.usda"),
                   "-o", old, "-q")[0] == 0
    earlier = old.read_bytes()
    refused(run_cli("export-gltf", fixture("arm_lbs.usda"), arm_correctives, "--anim", fixture("bad", "anim_not_bound.usda"),
                    "-o", old), 3, says="no SkelAnimation bound")
    assert old.read_bytes() == earlier
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]


def test_dual_quaternion_skinning_is_exported_with_a_warning(tmp_path):
    """glTF has only linear-blend skinning: a DQS mesh exports (valid) and says so."""
    asset, out = fixture("arm_dqs.usda"), tmp_path / "shot.glb"
    correctives = tmp_path / "correctives.usda"
    rc, _, err = run_cli("fit", asset, fixture("arm_dqs_examples.usda"), "-o", correctives, "-q")
    assert rc == 0, err
    warned(run_cli("export-gltf", asset, correctives, "--anim", fixture("arm_anim.usda"), "-o", out),
           names=["</Arm/Geo/Tube>"], says="dualQuaternion.*glTF skins linearly", outputs=[out])
    issues = validate(str(out))["issues"]
    assert (issues["numErrors"], issues["numWarnings"]) == (0, 0), issues["messages"]
