"""fixtures/humanoid/: the committed files are the generator's, and its sculpts are ground truth."""

from __future__ import annotations

import os

import humanoid
import numpy as np
import pytest
from conftest import bake, fixture, pose_only, sculpt, stage_of
from pxr import UsdGeom, Vt

ASSET = fixture("humanoid", humanoid.ASSET)
EXAMPLES = fixture("humanoid", humanoid.EXAMPLES)
ANIM = fixture("humanoid", humanoid.ANIM_FILE)


def test_generator_reproduces_committed_files(tmp_path):
    written = humanoid.generate(str(tmp_path))
    assert [os.path.basename(p) for p in written] == [humanoid.ASSET, humanoid.EXAMPLES, humanoid.ANIM_FILE]
    for path in written:
        with open(path, "rb") as new, open(fixture("humanoid", os.path.basename(path)), "rb") as old:
            assert new.read() == old.read(), f"fixtures/humanoid/{os.path.basename(path)} is stale: " \
                                             "run python fixtures/humanoid.py"
    assert sum(os.path.getsize(p) for p in written) < 2_000_000


def test_fixture_layout():
    assert len(humanoid.REGIONS) >= 6 and len(humanoid.COMBINATIONS) >= 2
    assert len(humanoid.COMBINATION_EXAMPLES) >= 2
    for t in humanoid.SINGLE_EXAMPLES:  # one joint bent
        assert len([a for a in humanoid.EXAMPLE_ANGLES[t][1].values() if a]) == 1
    for t in humanoid.COMBINATION_EXAMPLES:  # a combination's two joints bent, nothing else
        bent = {r for r, a in humanoid.EXAMPLE_ANGLES[t][1].items() if a}
        assert any(bent == {a, b} for a, b, _ in humanoid.COMBINATIONS.values())
    for region in humanoid.REGIONS:  # every region has its single-joint sculpts
        assert any(region in humanoid.EXAMPLE_ANGLES[t][1] for t in humanoid.SINGLE_EXAMPLES)
    angles = humanoid.shot_angles()
    for region, (first, last) in humanoid.ONE_JOINT_FRAMES.items():
        for t in np.arange(first, last + 1):
            assert {r for r, a in angles[float(t)].items() if a} == {region}
    first, last = humanoid.ALL_TOGETHER_FRAMES
    assert first == humanoid.ONE_JOINT_RANGE[1] + 1 and max(angles) == last
    for t in np.arange(first, last + 1):
        assert all(a > 0 for a in angles[float(t)].values())


@pytest.mark.parametrize("t", sorted(humanoid.EXAMPLE_POSES))
def test_sculpt_is_skinning_of_rest_plus_truth(t):
    """Each sculpt is Pixar's BakeSkinning of rest + the true offsets at its pose (float32 round-off)."""
    stage = stage_of([pose_only(EXAMPLES), ASSET])
    attr = UsdGeom.PointBased(stage.GetPrimAtPath(humanoid.MESH)).GetPointsAttr()
    rest = np.array(attr.Get(), dtype=np.float64)
    offsets = humanoid.truth_offsets(humanoid.EXAMPLE_POSES[t], humanoid.rest_points())
    attr.Set(Vt.Vec3fArray.FromNumpy((rest + offsets).astype(np.float32)))
    baked = np.array(UsdGeom.PointBased(bake(stage, t).GetPrimAtPath(humanoid.MESH)).GetPointsAttr().Get(t),
                     dtype=np.float64)
    expected = sculpt(EXAMPLES, humanoid.MESH, t)
    atol = 16 * float(np.spacing(np.float32(np.abs(expected).max())))
    np.testing.assert_allclose(baked, expected, rtol=0, atol=atol)
    assert np.abs(offsets).max() > 0.5  # every example is sculpted (cm)


def test_combination_terms_vanish_at_single_joint_examples():
    points = humanoid.rest_points()
    for t in humanoid.SINGLE_EXAMPLES:
        angles = humanoid.angles_of(humanoid.EXAMPLE_POSES[t])
        for name, off in humanoid.combination_offsets(angles, points).items():
            assert not off.any(), f"combination {name} is on at single-joint example t={t:g}"
    for t in humanoid.COMBINATION_EXAMPLES:
        angles = humanoid.angles_of(humanoid.EXAMPLE_POSES[t])
        assert max(np.abs(off).max() for off in humanoid.combination_offsets(angles, points).values()) > 0.5
