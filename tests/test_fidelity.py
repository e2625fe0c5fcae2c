"""The paper's claim on psdbake's own output: interpolated in the rest pose, the
correction turns with the joint; interpolated in posed space, it keeps one direction."""

from __future__ import annotations

import numpy as np
from conftest import generate

from psdbake.report import comparison as compare

ANGLE_ATOL = 1e-3  # radians; float32 points put the true error near 1e-6


def _single_joint_rig(folder) -> tuple[str, str, str]:
    """fixtures/generate.hinge_rig, written into a test's folder."""
    return generate.hinge_rig(str(folder))


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
