"""The paper's claim on psdbake's own output: interpolated in the rest pose, the
correction turns with the joint; interpolated in posed space, it keeps one direction."""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from psdbake import compare

ANGLE_ATOL = 1e-3  # radians; float32 points put the true error near 1e-6


def _single_joint_rig(folder) -> tuple[str, str, str]:
    """A quad rigidly bound to joint 'Root/Bend' (rotates about z); the artist moves one
    vertex at 90 degrees; the animation sweeps 0..90 degrees."""
    asset = str(folder / "asset.usda")
    stage = Usd.Stage.CreateNew(asset)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdSkel.Root.Define(stage, "/R")
    skel = UsdSkel.Skeleton.Define(stage, "/R/Skel")
    skel.CreateJointsAttr(["Root", "Root/Bend"])
    ident = Gf.Matrix4d(1)
    skel.CreateBindTransformsAttr([ident, ident])
    skel.CreateRestTransformsAttr([ident, ident])
    mesh = UsdGeom.Mesh.Define(stage, "/R/Quad")
    mesh.CreatePointsAttr([(1, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([Sdf.Path("/R/Skel")])
    binding.CreateJointIndicesPrimvar(False, 1).Set(Vt.IntArray([1, 1, 1, 1]))
    binding.CreateJointWeightsPrimvar(False, 1).Set(Vt.FloatArray([1, 1, 1, 1]))
    binding.CreateGeomBindTransformAttr(ident)
    stage.GetRootLayer().Save()

    def anim_layer(path: str, degrees: dict[float, float]) -> str:
        layer = Sdf.Layer.CreateNew(path)
        st = Usd.Stage.Open(layer)
        spec = Sdf.CreatePrimInLayer(layer, "/R/Skel/Anim")
        spec.specifier, spec.typeName = Sdf.SpecifierDef, "SkelAnimation"
        anim = UsdSkel.Animation(st.GetPrimAtPath("/R/Skel/Anim"))
        anim.CreateJointsAttr(["Root/Bend"])
        anim.CreateTranslationsAttr([Gf.Vec3f(0, 0, 0)])
        anim.CreateScalesAttr([Gf.Vec3h(1, 1, 1)])
        rot = anim.CreateRotationsAttr()
        for t, deg in degrees.items():
            q = Gf.Rotation(Gf.Vec3d(0, 0, 1), deg).GetQuat()
            rot.Set([Gf.Quatf(q.GetReal(), Gf.Vec3f(q.GetImaginary()))], t)
        UsdSkel.BindingAPI.Apply(st.OverridePrim("/R/Skel")).CreateAnimationSourceRel().SetTargets(
            [Sdf.Path("/R/Skel/Anim")]
        )
        layer.Save()
        return path

    examples = anim_layer(str(folder / "examples.usda"), {1.0: 90.0})
    # sculpt at 90 degrees: plain skinning takes (1,1,0) to (-1,1,0); the artist pulls it in the bend plane
    layer = Sdf.Layer.FindOrOpen(examples)
    st = Usd.Stage.Open(layer)
    sculpt = [(0, 1, 0), (0, 2, 0), (-1, 2, 0), (-1.3, 1.2, 0.0)]
    UsdGeom.Mesh(st.OverridePrim("/R/Quad")).CreatePointsAttr().Set(sculpt, 1.0)
    layer.Save()
    anim = anim_layer(str(folder / "anim.usda"), {float(f): 9.0 * (f - 1) for f in range(1, 12)})
    return asset, examples, anim


def test_inverse_correction_turns_with_the_joint_forward_does_not(tmp_path):
    asset, examples, anim = _single_joint_rig(tmp_path)
    result = compare.compare(asset, [examples], anim)
    m = result.meshes[0]
    assert list(m.corrected) == [3]
    forward, inverse = compare.correction_turn(m, 3, reference=len(m.times) - 1)
    joint = m.driver_angles[:, 0]
    live = ~np.isnan(inverse)
    assert live.sum() == len(joint) - 1  # every frame but the bind pose has a correction
    # inverse PSD: the correction has turned by exactly the joint's angle away from 90 degrees
    np.testing.assert_allclose(inverse[live], joint[-1] - joint[live], atol=ANGLE_ATOL)
    # forward PSD: one fixed direction throughout
    np.testing.assert_allclose(forward[live], 0.0, atol=ANGLE_ATOL)
    # same weights for both: at the example pose both reproduce the sculpt
    np.testing.assert_allclose(m.inverse[-1, 3], [-1.3, 1.2, 0.0], atol=1e-6)
    np.testing.assert_allclose(m.forward[-1, 3], [-1.3, 1.2, 0.0], atol=1e-6)


def test_ground_truth_table_inverse_beats_forward_and_ssd(tmp_path):
    """benchmarks/fidelity.py, default settings, non-linear (sin) bulge: inverse PSD's mean
    error at the intermediate poses is at most a third of forward PSD's, and its worst
    vertex is better than both forward PSD's and plain skinning's."""
    from benchmarks import fidelity

    rows = {(r.settings, r.method): r for r in fidelity.run(str(tmp_path), truths=("sin",))}
    ssd, fwd, inv = (rows[("gaussian", m)] for m in ("SSD", "forward PSD", "inverse PSD"))
    assert inv.mean <= fwd.mean / 3
    assert inv.max < fwd.max and inv.max < ssd.max
