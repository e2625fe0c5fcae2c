"""The black-box inverse on real UsdSkel black boxes: closed-form LBS oracle, scipy's
Powell per vertex, a non-linear deformer, and the evaluation budget."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import CESIUM, CESIUM_EXAMPLES, ROOT, fixture, generate, sculpt

from benchmarks import references
from psdbake.deformers import load_deformers
from psdbake.solver.inverse import invert_example
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.read import Scene

LBS_RIGS = {
    "arm_lbs": (fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), generate.MESH),
    "arm_rest": (fixture("arm_rest.usda"), fixture("arm_rest_examples.usda"), generate.MESH),
    "cesiumman": (CESIUM, CESIUM_EXAMPLES, generate.CESIUM_MESH),
}


def _setup(asset, examples, mesh, t, deformers=()):
    scene = Scene([examples, asset])
    rest = Scene([asset]).rest_points(mesh)
    return scene, rest, sculpt(examples, mesh, t), SkinningBlackBox(scene, mesh, t, deformers)


@pytest.mark.parametrize("rig", sorted(LBS_RIGS))
def test_offsets_match_the_closed_form_lbs_inverse(rig):
    asset, examples, mesh = LBS_RIGS[rig]
    t = 12.0 if rig == "cesiumman" else 3.0
    scene, rest, target, box = _setup(asset, examples, mesh, t)
    res = invert_example(box, rest, target)
    assert len(res.indices) > 0 and len(res.missed) == 0
    exact = references.closed_form_lbs(references.lbs_matrices(scene.stage, mesh, t), rest, target, res.indices)
    # Both inverses see float32 data: the skinned points carry ~1e-7 relative error,
    # amplified by the conditioning of the skinning matrices; 1e-5 of the diagonal bounds it.
    assert np.abs(res.offsets - exact).max() <= 1e-5 * res.diagonal
    assert res.max_residual <= 1e-6 * res.diagonal


def test_lockstep_agrees_with_scipy_powell_per_vertex():
    asset, examples, mesh = LBS_RIGS["arm_lbs"]
    _, rest, target, box = _setup(asset, examples, mesh, 1.0)
    res = invert_example(box, rest, target)
    sample = res.indices[:: max(1, len(res.indices) // 5)][:5]
    for v in sample:
        ref, nfev = references.literal_powell(box, rest, target, int(v))
        mine = res.offsets[np.searchsorted(res.indices, v)]
        # float32 black box: the objective is flat below ~1e-7 of the diagonal
        np.testing.assert_allclose(mine, ref, atol=2e-6 * res.diagonal, rtol=0)
        assert nfev > 50  # the literal method pays ~100+ whole-mesh calls per vertex


def test_evaluation_budget_on_lbs_and_dqs():
    """Deterministic budget: 1 detection call + 3 Jacobian calls + 1 linearised start; a
    Powell cycle (3 line searches x 3 calls) only if the start misses tolerance."""
    for name in ("arm_lbs", "arm_dqs"):
        asset, examples = fixture(f"{name}.usda"), fixture(f"{name}_examples.usda")
        for t in (1.0, 2.0, 3.0):
            _, rest, target, box = _setup(asset, examples, generate.MESH, t)
            res = invert_example(box, rest, target)
            assert len(res.missed) == 0
            assert res.evaluations <= 14, (name, t, res.evaluations)
            assert res.evaluations == box.evaluations


# A non-linear, position-dependent deformer with no closed-form inverse (also used by test_cli).
SWIRL = os.path.join(ROOT, "tests", "data", "swirl_deformer.py") + ":factory"


def test_nonlinear_deformer_chain_is_inverted_to_tolerance():
    asset = fixture("arm_lbs.usda")
    poses = fixture("arm_poses.usda")
    scene = Scene([poses, asset])
    rest = scene.rest_points(generate.MESH)
    box = SkinningBlackBox(scene, generate.MESH, 1.0, load_deformers([SWIRL]))
    rng = np.random.default_rng(0)
    truth = np.zeros_like(rest)
    moved = rng.random(len(rest)) < 0.4
    truth[moved] = rng.normal(scale=0.02, size=(moved.sum(), 3))
    target = box(rest + truth).astype(np.float32).astype(np.float64)
    res = invert_example(box, rest, target)
    assert len(res.missed) == 0
    assert res.max_residual <= 1e-5 * res.diagonal
    linear_only = references.one_shot_linearisation(box, rest, target, res.indices, 1e-2 * res.diagonal)[0]
    lin_res = np.linalg.norm(target[res.indices] - box(_with(rest, res.indices, linear_only))[res.indices], axis=1)
    assert res.max_residual < lin_res.max()  # Powell improves on the one-shot linearisation


def _with(rest, idx, d):
    out = rest.copy()
    out[idx] += d
    return out


def test_vertices_the_artist_did_not_move_get_no_corrective():
    asset, examples, mesh = LBS_RIGS["arm_lbs"]
    _, rest, _, box = _setup(asset, examples, mesh, 1.0)
    target = box(rest).astype(np.float32).astype(np.float64)
    target[5] += [0.0, 0.01, 0.0]
    res = invert_example(box, rest, target)
    assert list(res.indices) == [5]
