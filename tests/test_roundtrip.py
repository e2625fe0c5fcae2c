"""The product: ASSET + CORRECTIVES + ANIM + WEIGHTS, baked by Pixar's own UsdSkel code,
reproduces every sculpt. Tolerance 1e-5 of the mesh's bounding-box diagonal: the inverse
stops at 1e-6 and the rest is float32 storage of offsets and float32 skinning (each
~1e-7 of the coordinates)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CESIUM, CESIUM_EXAMPLES, bake, diagonal, fixture, generate, points, pose_only, sculpt

from psdbake.tolerances import ROUNDTRIP_RTOL

RIGS = {
    "lbs_4_influences_transforms_geombind": ("arm_lbs.usda", "arm_lbs_examples.usda", generate.MESH),
    "dual_quaternion": ("arm_dqs.usda", "arm_dqs_examples.usda", generate.MESH),
    "rest_differs_from_bind": ("arm_rest.usda", "arm_rest_examples.usda", generate.MESH),
    "cesiumman_usdz": (CESIUM, CESIUM_EXAMPLES, generate.CESIUM_MESH),
}


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_bake_of_stack_reproduces_every_sculpt(rig, run, tmp_path):
    asset, examples, mesh = RIGS[rig]
    asset, examples = fixture(asset), fixture(examples)
    corr, weights = tmp_path / "corr.usda", tmp_path / "weights.usda"
    code, _, err = run("fit", asset, examples, "-o", corr, "-q")
    assert code == 0, err
    # The examples layer carries the poses, so it serves as ANIM for its own time codes.
    code, _, err = run("eval", asset, corr, "--anim", examples, "-o", weights, "-q")
    assert code == 0, err
    from pxr import Sdf

    times = Sdf.Layer.FindOrOpen(examples).ListTimeSamplesForPath(Sdf.Path(mesh).AppendProperty("points"))
    assert len(times) >= 2
    for t in times:
        # ANIM here is the examples layer minus nothing: its points samples would be
        # skinned again, so the stack uses the asset's rest points via a points block.
        baked = points(bake([str(weights), pose_only(examples), str(corr), asset], t), mesh, t)
        target = sculpt(examples, mesh, t)
        err_rel = np.abs(baked - target).max() / diagonal(target)
        assert err_rel <= ROUNDTRIP_RTOL, f"{rig} t={t}: {err_rel:.2e}"
        # and the correctives are what makes it so: plain skinning is far off
        plain = points(bake([pose_only(examples), asset], t), mesh, t)
        assert np.abs(plain - target).max() / diagonal(target) > 100 * ROUNDTRIP_RTOL
