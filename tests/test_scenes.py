"""Scene shapes (tests/scenes.py builds them from the arm rig): a mesh with its own
``skel:joints``, nested SkelRoots and instanced SkelRoots, through pose, fit, eval and the
points cache, checked against Pixar's ``UsdSkel.BakeSkinning``.

Tolerances, relative to the mesh's bounding-box diagonal: the product (ASSET + CORRECTIVES
+ ANIM + WEIGHTS) reproduces each sculpt within 1e-5 (the inverse stops at 1e-6, the rest
is float32 storage and float32 skinning; as tests/test_roundtrip.py); plain skinning misses
it by more than 100x that (the sculpts move points by ~3% of the diagonal); psdbake's own
skinning (pose, points cache) matches Pixar's within 1e-6 (both run UsdSkel in float32).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scenes
from conftest import bake, corrective_weights, diagonal, fixture, generate, points, sculpt, stage_of
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel
from scipy.spatial.transform import Rotation

import psdbake
from psdbake.usd.read import Scene

ROUNDTRIP_RTOL, SKINNING_RTOL, PLAIN_MIN = 1e-5, 1e-6, 1e-3


def _fit_eval_cache(run, built: scenes.Built, tmp, *extra: str) -> tuple[str, str, str]:
    corr, weights, cache = (str(tmp / n) for n in ("corr.usda", "weights.usda", "cache.usda"))
    code, _, err = run("fit", built.asset, built.examples, "-o", corr, "-q", *extra)
    assert code == 0, err
    code, _, err = run("eval", built.asset, corr, "--anim", built.anim, "-o", weights, "--points-cache", cache, "-q")
    assert code == 0, err
    return corr, weights, cache


def _check_product(built: scenes.Built, corr: str, weights: str, cache: str) -> None:
    """Every sculpt reproduced by Pixar's bake of the stack; plain skinning far from it;
    the points cache equal to that bake."""
    meshes = sorted(built.sculpts)
    for t in scenes.TIMES:
        baked_stack, plain_stack = bake([weights, built.anim, corr, built.asset], t), bake([built.anim, built.asset], t)
        for mesh in meshes:
            target, baked, plain = built.sculpts[mesh][t], points(baked_stack, mesh, t), points(plain_stack, mesh, t)
            diag = diagonal(target)
            assert np.abs(baked - target).max() <= ROUNDTRIP_RTOL * diag, (mesh, t)
            assert np.abs(plain - target).max() >= PLAIN_MIN * diag, (mesh, t)
            assert np.abs(sculpt(cache, mesh, t) - baked).max() <= SKINNING_RTOL * diag, (mesh, t)


def _check_pose(run, built: scenes.Built, tmp) -> None:
    """``psdbake pose`` writes Pixar's plain skinning for every mesh at every pose."""
    out = str(tmp / "to_sculpt.usda")
    code, _, err = run("pose", built.asset, "--anim", built.anim, "-o", out, "-q")
    assert code == 0, err
    meshes = sorted(built.sculpts)
    for t in scenes.TIMES:
        plain_stack = bake([built.anim, built.asset], t)
        for mesh in meshes:
            plain = points(plain_stack, mesh, t)
            assert np.abs(sculpt(out, mesh, t) - plain).max() <= SKINNING_RTOL * diagonal(plain)


def _one_line_error(code: int, err: str, *needles: str) -> None:
    assert code == 3, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("psdbake: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# --- 1. a mesh with its own skel:joints --------------------------------------------------

@pytest.fixture(scope="module")
def own(tmp_path_factory) -> scenes.Built:
    return scenes.own_joints(str(tmp_path_factory.mktemp("own_joints")))


def test_own_joints_pose_fit_eval_cache_and_bake(own, run, tmp_path):
    _check_pose(run, own, tmp_path)
    _check_product(own, *_fit_eval_cache(run, own, tmp_path))


def test_own_joints_pose_space_and_drivers_are_in_skeleton_order(own, run, tmp_path):
    """The mesh lists Wrist, Shoulder, Elbow; poses, drivers and weights still follow the
    skeleton's order (Shoulder, Elbow, Wrist, Hand), as UsdSkel's own joint mapper does."""
    result = psdbake.fit(own.asset, [own.examples], psdbake.FitSettings(group="main"))
    (mesh,) = result.meshes
    for example in mesh.examples:
        pose = generate.EXAMPLE_POSES[example.time]
        for j, joint in enumerate(generate.JOINTS):
            axis, degrees = pose.get(joint.split("/")[-1], ((1, 0, 0), 0.0))
            expected = Rotation.from_rotvec(np.radians(degrees) * np.array(axis, dtype=np.float64))
            assert (Rotation.from_quat(example.pose[j]) * expected.inv()).magnitude() < 1e-6, (example.time, joint)
    assert mesh.drivers == ("Shoulder/Elbow", "Shoulder/Elbow/Wrist")  # the joints the examples rotate
    corr, weights = str(tmp_path / "c.usda"), str(tmp_path / "w.usda")
    assert run("fit", own.asset, own.examples, "-o", corr, "-q", "--driver", "Wrist", "--driver", "Elbow")[0] == 0
    stage = Usd.Stage.Open(corr)
    drivers = [a for a in stage.GetPrimAtPath(generate.MESH).GetAttributes() if a.GetName().endswith(":drivers")]
    assert [list(a.Get()) for a in drivers] == [["Shoulder/Elbow", "Shoulder/Elbow/Wrist"]]
    assert run("eval", own.asset, corr, "--anim", own.anim, "-o", weights, "-q")[0] == 0
    # cardinal RBF: at example k's pose, corrective k weighs 1 and the others 0
    b = corrective_weights(own.asset, corr, weights, generate.ANIM, scenes.TIMES)
    w = np.stack([b[s] for s in sorted(b)], axis=1)
    assert np.abs(w - np.eye(3)).max() < 1e-6


def test_own_joints_naming_a_joint_the_skeleton_lacks_is_refused(own, run, tmp_path):
    """UsdSkel maps an unknown ``skel:joints`` entry to nothing and leaves its points
    unskinned, silently; psdbake refuses it."""
    asset = tmp_path / "unknown_joint.usda"
    layer = Sdf.Layer.FindOrOpen(own.asset)
    layer.Export(str(asset))
    stage = Usd.Stage.Open(str(asset))
    UsdSkel.BindingAPI(stage.GetPrimAtPath(generate.MESH)).GetJointsAttr().Set(
        ["Shoulder/Elbow/Wrist", "Shoulder", "Shoulder/Elbow/Ulna"])
    stage.GetRootLayer().Save()
    out = tmp_path / "c.usda"
    code, _, err = run("fit", asset, own.examples, "-o", out)
    _one_line_error(code, err, f"<{generate.MESH}.skel:joints>", "'Shoulder/Elbow/Ulna'", f"<{generate.SKEL}>")
    assert not out.exists()


# --- 2. nested SkelRoots -----------------------------------------------------------------

@pytest.fixture(scope="module")
def nested(tmp_path_factory) -> scenes.Built:
    return scenes.nested(str(tmp_path_factory.mktemp("nested")))


def test_nested_skelroots_are_owned_by_the_outermost(nested):
    """UsdSkel's traversal from the outer SkelRoot reaches the prop's prims with the
    bindings inherited from above the inner SkelRoot: the Sleeve is bound to the
    character's skeleton, which a traversal from the inner SkelRoot alone would not see."""
    scene = Scene([nested.anim, nested.asset])
    found = {m.path: (m.skeleton, m.skel_root) for m in scene.skinned_meshes()}
    assert found == {
        generate.MESH: (generate.SKEL, generate.ROOT),
        scenes.PROP_MESH: (scenes.PROP_SKEL, generate.ROOT),
        scenes.SLEEVE: (generate.SKEL, generate.ROOT),
    }
    assert scene.skel_roots == [generate.ROOT, scenes.PROP]
    cache = UsdSkel.Cache()
    inner = UsdSkel.Root(scene.stage.GetPrimAtPath(scenes.PROP))
    cache.Populate(inner, Usd.PrimDefaultPredicate)
    alone = {str(q.GetPrim().GetPath()) for b in cache.ComputeSkelBindings(inner, Usd.PrimDefaultPredicate)
             for q in b.GetSkinningTargets()}
    assert alone == {scenes.PROP_MESH}


def test_nested_skelroots_pose_fit_eval_cache_and_bake(nested, run, tmp_path):
    _check_pose(run, nested, tmp_path)
    corr, weights, cache = _fit_eval_cache(run, nested, tmp_path)
    _check_product(nested, corr, weights, cache)
    # each animation drives its own meshes' channels, never one name twice
    layer = Sdf.Layer.FindOrOpen(weights)
    for anim, meshes in ((generate.ANIM, 2), (scenes.PROP_ANIM, 1)):
        channels = list(layer.GetPrimAtPath(anim).attributes["blendShapes"].default)
        assert len(channels) == len(set(channels)) >= 3 * meshes  # 3 correctives per mesh, 1-2 channels each
    # the cache needs no UsdSkel: both SkelRoots become Xforms (else UsdSkel would skin the
    # prop's cached points again), and a bake over cache + asset leaves every point in place
    stack = stage_of([cache, nested.asset])
    assert not [p for p in stack.Traverse() if p.IsA(UsdSkel.Root)]
    assert {stack.GetPrimAtPath(p).GetTypeName() for p in (generate.ROOT, scenes.PROP)} == {"Xform"}
    meshes = sorted(nested.sculpts)
    rebaked = bake(stack, 2.0)
    for mesh in meshes:
        assert np.array_equal(points(rebaked, mesh, 2.0), sculpt(cache, mesh, 2.0))


def test_nested_skelroots_outputs_are_byte_identical(nested, run, tmp_path):
    outputs = []
    for k in range(2):
        folder = tmp_path / str(k)
        folder.mkdir()
        outputs.append([Path(p).read_bytes() for p in _fit_eval_cache(run, nested, folder)])
    assert outputs[0] == outputs[1]


# --- 3. instanced SkelRoots --------------------------------------------------------------

@pytest.fixture(scope="module")
def arm(tmp_path_factory) -> scenes.Built:
    return scenes.arm(str(tmp_path_factory.mktemp("instanced")))


def test_writing_over_an_instance_is_refused(arm, run, tmp_path):
    """Opinions over instance proxies are ignored by composition, so psdbake refuses to
    write examples, correctives or a points cache for a mesh inside an instance, naming the
    instance and the asset to run it on instead."""
    shot = scenes.instanced_shot(str(tmp_path), arm.asset)
    mesh = "/World/CharA" + generate.MESH[len(generate.ROOT):]
    # why: a sublayer's points over the instance proxy do not reach the composed stage
    over = Sdf.Layer.CreateAnonymous(".usda")
    Sdf.CreatePrimInLayer(over, mesh)
    Sdf.AttributeSpec(over.GetPrimAtPath(mesh), "points", Sdf.ValueTypeNames.Point3fArray).default = [(9, 9, 9)]
    stage = stage_of([over.identifier, shot])
    assert stage.GetPrimAtPath(mesh).IsInstanceProxy()
    assert UsdGeom.Mesh(stage.GetPrimAtPath(mesh)).GetPointsAttr().Get()[0] != Gf.Vec3f(9, 9, 9)
    needles = (f"<{mesh}>", "instance </World/CharA>", f"@{arm.asset}@</Arm>", "instanceable = false")
    out = tmp_path / "out.usda"
    _one_line_error(*run("pose", shot, "--anim", shot, "-o", out)[::2], *needles)
    examples = scenes.write_examples(str(tmp_path / "instance_examples.usda"), shot, {mesh: arm.sculpts[generate.MESH]})
    _one_line_error(*run("fit", shot, examples, "-o", out)[::2], *needles)
    corr, corrected = tmp_path / "corr.usda", str(tmp_path / "arm_corrected.usda")
    assert run("fit", arm.asset, arm.examples, "-o", corr, "-q")[0] == 0
    assert run("stack", arm.asset, corr, "-o", corrected)[0] == 0
    shot = scenes.instanced_shot(str(tmp_path), corrected, name="corrected_shot.usda")
    cache = tmp_path / "cache.usda"
    code, _, err = run("eval", shot, corr, "--anim", shot, "-o", out, "--points-cache", cache)
    _one_line_error(code, err, *needles[:2], f"@{corrected}@</Arm>")
    assert not out.exists() and not cache.exists()
    # meshes inside an instance under an ordinary SkelRoot: the same
    geo = scenes.meshes_in_instance(str(tmp_path))
    _one_line_error(*run("pose", geo, "--anim", geo, "-o", out)[::2], f"<{generate.MESH}>", "instance </Arm/Geo>",
                    "geo.usda@</Geo>")


def test_an_animation_inside_an_instance_is_refused(arm, run, tmp_path):
    """Weights for an animation inside the prototype would be authored over an instance
    proxy (or, worse, at the prototype's path): refused, naming the instance's animation."""
    corr, posed = str(tmp_path / "corr.usda"), str(tmp_path / "posed_arm.usda")
    assert run("fit", arm.asset, arm.examples, "-o", corr, "-q")[0] == 0
    assert run("stack", arm.asset, corr, arm.anim, "-o", posed)[0] == 0  # the animation comes with the asset
    shot = scenes.instanced_shot(str(tmp_path), posed, animate=False)
    out = tmp_path / "weights.usda"
    code, _, err = run("eval", shot, tmp_path / "corr.usda", "--anim", shot, "-o", out)
    _one_line_error(code, err, "SkelAnimation </World/CharA/Skel/Anim>", "instance </World/CharA>",
                    "skel:animationSource on </World/CharA>")
    assert not out.exists()


def test_instanced_characters_show_their_corrected_shape(arm, run, tmp_path):
    """The supported workflow: fit the instanced asset itself, reference the corrected asset
    (``psdbake stack``) from the shot, and eval the shot, whose instances each bind their own
    SkelAnimation. Instancing is kept; each instance shows the sculpt of the pose it plays."""
    corr, corrected = str(tmp_path / "corr.usda"), str(tmp_path / "arm_corrected.usda")
    assert run("fit", arm.asset, arm.examples, "-o", corr, "-q")[0] == 0
    assert run("stack", arm.asset, corr, "-o", corrected)[0] == 0
    shot = scenes.instanced_shot(str(tmp_path), corrected)
    weights = str(tmp_path / "weights.usda")
    code, _, err = run("eval", shot, corr, "--anim", shot, "-o", weights, "-q")
    assert code == 0, err
    # WEIGHTS holds each instance's own animation, nothing inside an instance
    authored = []
    Sdf.Layer.FindOrOpen(weights).Traverse("/", lambda p: authored.append(str(p)) if p.IsPrimPath() else None)
    assert sorted(authored) == ["/World", "/World/Anims", *sorted(scenes.INSTANCES.values())]
    instanced = stage_of([weights, shot])
    plain_shot = scenes.instanced_shot(str(tmp_path), arm.asset, name="plain_shot.usda")
    meshes = {root: root + generate.MESH[len(generate.ROOT):] for root in scenes.INSTANCES}
    for root, mesh in meshes.items():
        assert instanced.GetPrimAtPath(root).IsInstance() and instanced.GetPrimAtPath(mesh).IsInstanceProxy()
        assert [str(p) for p in UsdSkel.BindingAPI(instanced.GetPrimAtPath(root)).GetAnimationSourceRel().GetTargets()
                ] == [scenes.INSTANCES[root]]
    for t in scenes.TIMES:
        # BakeSkinning refuses instances: bake the same layers with the instances made
        # ordinary, which changes nothing here since no layer authors inside an instance
        flat, plain = bake(scenes.deinstanced([weights, shot]), t), bake(scenes.deinstanced([plain_shot]), t)
        for root, mesh in meshes.items():
            target = arm.sculpts[generate.MESH][t if root.endswith("A") else scenes.B_ORDER[t]]
            baked = points(flat, mesh, t)
            assert np.abs(baked - target).max() <= ROUNDTRIP_RTOL * diagonal(target), (root, t)
            off = points(plain, mesh, t) - target
            assert np.abs(off).max() >= PLAIN_MIN * diagonal(target), (root, t)
            # and the instance itself composes the corrective channels that were baked
            ours = UsdSkel.BindingAPI(instanced.GetPrimAtPath(mesh)).GetBlendShapesAttr().Get()
            assert len(ours) >= 3 and list(ours) == list(UsdSkel.BindingAPI(flat.GetPrimAtPath(mesh)).GetBlendShapesAttr().Get())


def test_an_anim_at_30_fps_keeps_its_time_codes(run, tmp_path):
    """ANIM authored at 30 time codes per second over a 24 fps asset: eval's WEIGHTS carry
    ANIM's own time codes (USD would rescale them by 24/30 under a root at the default rate),
    and the stack ASSET + CORRECTIVES + ANIM + WEIGHTS, opened as ``stack`` writes it, bakes
    each sculpt at its own pose."""
    asset, examples = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
    anim = tmp_path / "anim30.usda"
    layer = Sdf.Layer.FindOrOpen(fixture("arm_poses.usda"))  # the examples' poses, no sculpted points
    copy = Sdf.Layer.CreateNew(str(anim))
    copy.TransferContent(layer)
    copy.timeCodesPerSecond = copy.framesPerSecond = 30.0
    copy.Save()
    corr, weights, shot = tmp_path / "c.usda", tmp_path / "w.usda", tmp_path / "shot.usda"
    assert run("fit", asset, examples, "-o", corr, "-q")[0] == 0
    assert run("eval", asset, corr, "--anim", anim, "-o", weights, "-q")[0] == 0
    times = list(Sdf.Layer.FindOrOpen(str(weights)).ListTimeSamplesForPath(
        Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights")))
    assert times == [1.0, 2.0, 3.0]
    assert run("stack", asset, corr, anim, weights, "-o", shot)[0] == 0
    stage = bake(Usd.Stage.Open(str(shot)), 1.0, 3.0)  # as a viewer opens it: its own rate
    for t in (1.0, 2.0, 3.0):
        target = sculpt(examples, generate.MESH, t)
        assert np.abs(points(stage, generate.MESH, t) - target).max() <= 1e-5 * diagonal(target), t
