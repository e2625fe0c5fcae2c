"""Posed points as USD stores them (``psdbake.usd.posedpoints``): the points cache's and pose's
fast path is the black box's float64 output rounded to float32, byte for byte, with its exact
extent; and the points cache is Pixar's ``UsdSkel.BakeSkinning`` of the stack within float32
round-off. A weights-only eval never needs the correctives' offsets."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import ROOT, bake, fixture, generate, points
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from psdbake import api
from psdbake.deformers import load_deformers
from psdbake.errors import InputError
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.posedpoints import PosedPoints, RestPoints
from psdbake.usd.read import Scene

ASSET, EXAMPLES, ANIM = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), fixture("arm_anim.usda")
SWIRL = os.path.join(ROOT, "tests", "data", "swirl_deformer.py") + ":factory"
MESH = generate.MESH


def _bits(values) -> np.ndarray:
    """float32 values as their bit patterns: equal arrays are equal byte for byte (-0 is not +0)."""
    return np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)


@pytest.fixture(scope="module")
def flexing(tmp_path_factory):
    """An arm with an existing blend shape, animated: the black box applies it before skinning."""
    d = tmp_path_factory.mktemp("flex")
    asset, anim = d / "arm_flex.usda", d / "anim.usda"
    generate.build_arm(str(asset), generate.ArmSpec(blend_shapes=True))
    generate.write_animation(str(anim), generate.EXAMPLE_POSES, blend_shapes={1.0: 0.5, 2.0: 1.0, 3.0: 0.25})
    return str(asset), str(anim)


@pytest.mark.parametrize("case", ["lbs", "dqs", "blend shapes", "deformer"])
def test_posed_points_are_the_black_box_rounded_to_float32(case, flexing):
    """Points and extent equal ``vec3f_array(box(rest))`` and the float32 of its min / max, bit
    for bit: the mesh sits under transforms (skel -> local is a rotation, scale and shift)."""
    asset, anim = {"lbs": (ASSET, ANIM), "dqs": (fixture("arm_dqs.usda"), ANIM), "blend shapes": flexing,
                   "deformer": (ASSET, ANIM)}[case]
    chain = load_deformers([SWIRL]) if case == "deformer" else []
    scene = Scene([anim, asset])
    rest = scene.rest_points(MESH)
    shared = RestPoints(rest)
    for t in scene.animation_times(MESH):
        expected = SkinningBlackBox(scene, MESH, t, chain)(rest)
        posed = SkinningBlackBox(scene, MESH, t, chain).posed(shared)
        assert np.array_equal(_bits(posed.points), _bits(expected)), t
        assert np.array_equal(_bits(posed.extent), _bits(np.stack([expected.min(axis=0), expected.max(axis=0)]))), t


def test_each_frame_gets_its_own_points():
    """The fast path writes into a VtArray it has just made: an earlier frame's points and the
    rest points are never written over by a later frame."""
    scene = Scene([ANIM, ASSET])
    rest = RestPoints(scene.rest_points(MESH))
    before = rest.float32.copy()
    first = SkinningBlackBox(scene, MESH, 1.0).posed(rest)
    kept = np.array(first.points)
    SkinningBlackBox(scene, MESH, 2.0).posed(rest)
    assert np.array_equal(_bits(first.points), _bits(kept))
    assert np.array_equal(rest.float32, before)


def test_a_zero_bound_keeps_the_sign_the_whole_array_gives():
    """Per-axis bounds taken axis by axis equal ``min(axis=0)`` of the (n, 3) array except for
    which of +0 and -0 is kept (they differ in about half of these draws): a zero bound is taken
    as the whole array gives it, on both paths (skinned points, a deformer's output)."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        pts = np.abs(rng.normal(size=(int(rng.integers(2, 200)), 3))) * rng.choice([-1.0, 1.0], size=3)
        zero = rng.random(pts.shape) < 0.3
        pts[zero] = np.where(rng.random(pts.shape) < 0.5, -0.0, 0.0)[zero]
        expected = _bits(np.stack([pts.min(axis=0), pts.max(axis=0)]))
        assert np.array_equal(_bits(PosedPoints.of(pts).extent), expected)
        rest = RestPoints(pts)
        local = np.ascontiguousarray(pts.T)
        stored = RestPoints.stored(rest.vt(), local, local.min(axis=1), local.max(axis=1))
        assert np.array_equal(_bits(stored.extent), expected)
        assert np.array_equal(_bits(stored.points), _bits(pts))


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """CORRECTIVES fitted on the arm, the 48-frame shot's weights and points cache."""
    d = tmp_path_factory.mktemp("posed")
    corr, anim = str(d / "corr.usda"), str(d / "anim.usda")
    api.write_correctives(api.fit(ASSET, [EXAMPLES]), corr)
    generate.write_animation(anim, generate.shot_poses(48))
    weights = api.evaluate(ASSET, corr, anim)
    path = api.write_weights(weights, str(d / "weights.usda"))
    return {"corr": corr, "anim": anim, "weights": weights, "weights_path": path,
            "cache": api.points_cache_layer(weights)}


def test_points_cache_is_bakeskinning_of_the_stack_and_extents_are_exact(shot):
    """Every frame: |cache - BakeSkinning| within float32 round-off of the coordinates (measured
    0 here, 4e-9 of the diagonal on the 100k bench rig), and the extent is [min, max] of the
    cached points exactly."""
    stage = bake([shot["weights_path"], shot["anim"], shot["corr"], ASSET], 1.0, 48.0)
    path = Sdf.Path(MESH)
    for t in range(1, 49):
        cached = np.array(shot["cache"].QueryTimeSample(path.AppendProperty("points"), float(t)), dtype=np.float32)
        pixar = points(stage, MESH, float(t), np.float32)
        ulp = np.spacing(np.abs(pixar).max())
        assert np.abs(cached.astype(np.float64) - pixar).max() <= 2 * ulp, t
        extent = np.array(shot["cache"].QueryTimeSample(path.AppendProperty("extent"), float(t)), dtype=np.float32)
        assert np.array_equal(_bits(extent), _bits(np.stack([cached.min(axis=0), cached.max(axis=0)]))), t


def test_weights_only_eval_needs_no_offsets(shot, tmp_path):
    """eval's weights come from the psd: data and the shapes' pointIndices alone: the same
    CORRECTIVES with every offset removed gives the same weights."""
    layer = Sdf.Layer.FindOrOpen(shot["corr"])
    stripped = Sdf.Layer.CreateAnonymous(".usda")
    stripped.TransferContent(layer)
    removed = []

    def strip(path: Sdf.Path) -> None:
        if path.IsPropertyPath() and path.name in ("offsets", "normalOffsets"):
            removed.append(path)

    stripped.Traverse(Sdf.Path.absoluteRootPath, strip)
    for path in removed:
        stripped.GetPrimAtPath(path.GetPrimPath()).RemoveProperty(stripped.GetPropertyAtPath(path))
    assert removed
    path = str(tmp_path / "corr_without_offsets.usda")
    stripped.Export(path)
    again = api.evaluate(ASSET, path, shot["anim"])
    for ours, theirs in zip(again.animations, shot["weights"].animations, strict=True):
        assert ours.channels == theirs.channels
        assert np.array_equal(ours.weights, theirs.weights)


@pytest.mark.parametrize("name", ["offsets", "pointIndices"])
def test_eval_checks_the_types_of_what_it_reads(name, shot, tmp_path):
    """A shape attribute authored with another value type: the weights never read offsets, so
    eval writes them as before and the points cache (UsdSkel applies the offsets) refuses
    them; pointIndices, which eval reads, are refused by eval, naming the attribute."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(shot["corr"]))
    shape = next(p for p in layer.GetPrimAtPath(MESH).nameChildren if p.typeName == "BlendShape")
    old = shape.attributes[name]
    value = {"offsets": Vt.Vec3dArray(len(old.default)), "pointIndices": Vt.FloatArray(len(old.default))}[name]
    shape.RemoveProperty(old)
    Sdf.AttributeSpec(shape, name, Sdf.ValueTypeNames.Double3Array if name == "offsets" else Sdf.ValueTypeNames.FloatArray,
                      Sdf.VariabilityUniform).default = value
    path = str(tmp_path / "corr_retyped.usda")
    layer.Export(path)
    says = f"<{shape.path}.{name}>: authored as"
    if name == "pointIndices":
        with pytest.raises(InputError, match=says):
            api.evaluate(ASSET, path, shot["anim"])
        return
    again = api.evaluate(ASSET, path, shot["anim"])
    for ours, theirs in zip(again.animations, shot["weights"].animations, strict=True):
        assert np.array_equal(ours.weights, theirs.weights)
    with pytest.raises(InputError, match=says):
        api.points_cache_layer(again)


def test_rest_points_made_once_are_rounded_as_usdskel_takes_them():
    rest = Scene([ASSET]).rest_points(MESH)
    made = RestPoints(rest)
    assert np.array_equal(np.asarray(made.vt()), rest.astype(np.float32))
    assert isinstance(made.vt(), Vt.Vec3fArray)


@pytest.mark.parametrize("moving", ["/Arm/Geo", "/Arm/Skel"])
def test_points_cache_follows_time_varying_transforms(moving, shot, tmp_path):
    """A static skel -> mesh transform is worked out once per mesh (the points cache's speed);
    an animated one, on the mesh's parent or on the skeleton, at every frame: the cache is
    still BakeSkinning of the stack frame by frame."""
    anim = tmp_path / "moving.usda"
    layer = Sdf.Layer.CreateNew(str(anim))
    layer.subLayerPaths.append(shot["anim"])
    stage = Usd.Stage.Open(layer)
    op = UsdGeom.Xformable(stage.OverridePrim(moving)).AddTranslateOp(opSuffix="moving")
    for t in range(1, 49):
        op.Set(Gf.Vec3d(0.05 * t, -0.02 * t, 0.001 * t * t), Usd.TimeCode(t))
    layer.Save()
    weights = api.evaluate(ASSET, shot["corr"], str(anim))
    cache = api.points_cache_layer(weights)
    baked = bake([api.write_weights(weights, str(tmp_path / "weights.usda")), str(anim), shot["corr"], ASSET], 1.0, 48.0)
    path = Sdf.Path(MESH).AppendProperty("points")
    still = np.array(shot["cache"].QueryTimeSample(path, 48.0), dtype=np.float32)
    for t in range(1, 49):
        cached = np.array(cache.QueryTimeSample(path, float(t)), dtype=np.float32)
        pixar = points(baked, MESH, float(t), np.float32)
        assert np.abs(cached.astype(np.float64) - pixar).max() <= 2 * np.spacing(np.abs(pixar).max()), t
    # either moves the points in the mesh's space (the last frame against the still shot's)
    assert np.abs(cached.astype(np.float64) - still).max() > 1.0
