"""Black-box call budgets of the inverse (counts, not seconds) on the small bench rig.

The bench rig (``benchmarks.rigs``, 1.3k points, 8 example poses, a third of the tube
sculpted) in its three variants: LBS and DQS are affine per vertex, so the linearised
start meets tolerance after 1 detection + 3 Jacobian + 1 check calls; LBS followed by
the twist-and-bulge deformer is non-linear but uncoupled, and the Broyden refresh of the
per-vertex Jacobian finishes it in a handful of calls where Powell alone spent ~70. LBS
followed by Delta Mush couples vertices: the coupled inverse (``psdbake.solver.coupled``) on the
same coarse rig, where LBS folds the elbow.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from benchmarks import rigs
from psdbake.solver import coupled, powell
from psdbake.solver.inverse import invert_example, invert_example_with

#: Calls per example: exact for the affine skinning methods, a ceiling for the non-linear chain.
BUDGET = {"lbs": 5, "dqs": 5}
NONLINEAR_MAX_CALLS = 12


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    folder = str(tmp_path_factory.mktemp("budget"))
    poses_layer, poses = rigs.write_poses(folder)
    return {v: rigs.build(folder, v, "1.3k", poses, poses_layer) for v in ("lbs", "dqs", "lbs+bulge", "lbs+deltamush")}


def _solve(rig, t, **switches):
    box = rig.blackbox(rig.scene(), t)
    res = invert_example_with(box, rig.rest, rig.sculpts[t], **switches) if switches else \
        invert_example(box, rig.rest, rig.sculpts[t])
    assert res.evaluations == box.evaluations  # every call is counted
    return res


def _within_tolerance(res):
    assert len(res.indices) > 100
    assert np.all(res.status == powell.CONVERGED), powell.STATUS_NAMES
    assert res.max_residual <= res.atol


@pytest.mark.parametrize("variant", ["lbs", "dqs"])
def test_affine_skinning_takes_exactly_five_calls(bench, variant):
    rig = bench[variant]
    for t in rig.times:
        res = _solve(rig, t)
        _within_tolerance(res)
        assert res.evaluations == BUDGET[variant], (t, res.evaluations)
        assert res.qn_steps == 0 and res.cycles == 0


@pytest.mark.slow
def test_nonlinear_uncoupled_chain_within_twelve_calls(bench):
    rig = bench["lbs+bulge"]
    calls = []
    for t in rig.times:
        res = _solve(rig, t)
        old = _solve(rig, t, quasi_newton=False)  # Powell alone after the linearised start
        _within_tolerance(res)
        _within_tolerance(old)
        assert res.evaluations <= NONLINEAR_MAX_CALLS, (t, res.evaluations)
        assert res.evaluations < old.evaluations / 4, (t, res.evaluations, old.evaluations)
        # Broyden alone finishes this smooth chain: no Powell cycle is needed.
        assert res.cycles == 0 and res.evaluations == 5 + res.qn_steps
        calls.append(res.evaluations)
    assert np.mean(calls) <= 9.0, calls  # measured 8.4


def test_same_inputs_same_bytes(bench):
    rig = bench["lbs+bulge"]
    t = rig.times[3]
    a, b = _solve(rig, t), _solve(rig, t)
    assert a.offsets.tobytes() == b.offsets.tobytes() and a.evaluations == b.evaluations


# --- the quasi-Newton phase of minimize_lockstep on analytic problems ---------------------

def _warped(m: int, seed: int):
    """Affine per problem, then a smooth non-linear warp: uncoupled and locally invertible."""
    rng = np.random.default_rng(seed)
    a = Rotation.random(m, random_state=seed).as_matrix() * rng.uniform(0.5, 2.0, (m, 1, 1))
    target = rng.normal(size=(m, 3))

    def posed(x):
        q = np.einsum("kab,kb->ka", a, x)
        ang = 0.4 * np.tanh(q[:, 2])
        c, s = np.cos(ang), np.sin(ang)
        return np.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1], q[:, 2] + 0.1 * np.sin(q[:, 0])], axis=1)

    return (lambda x: target - posed(x)), a


def test_broyden_steps_converge_where_powell_needs_cycles():
    residual, a = _warped(200, seed=4)
    x0 = np.zeros((200, 3))
    directions = np.transpose(np.linalg.inv(a), (0, 2, 1))
    qn = powell.minimize_lockstep(residual, x0, directions=directions, jacobian=a, atol=1e-9, quasi_newton=True)
    old = powell.minimize_lockstep(residual, x0, directions=directions, jacobian=a, atol=1e-9)
    assert np.all(qn.status == powell.CONVERGED) and np.all(old.status == powell.CONVERGED)
    np.testing.assert_allclose(qn.x, old.x, atol=1e-8, rtol=0)  # the same unique minimum
    assert qn.nfev < old.nfev / 2, (qn.nfev, old.nfev)
    assert 1 <= qn.qn_steps <= powell.QN_MAX_STEPS  # measured 22-28 calls against Powell's 185-208


def test_a_wrong_model_falls_back_to_powell():
    """A model pointing the wrong way: every quasi-Newton step is rejected (never accepted
    uphill), the vertices hand over to Powell's line searches and still converge."""
    residual, a = _warped(50, seed=9)
    wrong = -a  # predicts the opposite of what the black box does
    res = powell.minimize_lockstep(residual, np.zeros((50, 3)), jacobian=wrong, atol=1e-9, quasi_newton=True)
    assert np.all(res.status == powell.CONVERGED)
    assert res.cycles >= 1


def test_broyden_update_satisfies_the_secant_equation():
    rng = np.random.default_rng(2)
    jac = rng.normal(size=(10, 3, 3))
    step, decrease = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
    mask = np.arange(10) % 2 == 0
    before = jac.copy()
    powell.broyden_update(jac, mask, step, decrease, np.full(10, 1e-12))
    np.testing.assert_allclose(np.einsum("kab,kb->ka", jac[mask], step[mask]), decrease[mask], atol=1e-12)
    assert np.array_equal(jac[~mask], before[~mask])  # frozen problems keep their model
    # orthogonal to the step, the model is unchanged (the least change that fits the secant)
    ortho = np.cross(step, rng.normal(size=(10, 3)))
    np.testing.assert_allclose(np.einsum("kab,kb->ka", jac, ortho), np.einsum("kab,kb->ka", before, ortho),
                               atol=1e-12)


#: Calls per example of the coupled inverse on the coarse rig with Delta Mush (10 iterations):
#: the issue's goal at every size. Measured: 38, 29, 25 and 29 calls at elbow 60, 120, 140
#: and 160 degrees, where LBS folds the inner elbow (they were 364, 372, 407 and 428, with
#: 574, 387 and 26 vertices above the tolerance on the first three).
COUPLED_MAX_CALLS = 40


@pytest.mark.parametrize("time", [3.0, 6.0, 7.0, 8.0])
def test_coupled_chain_on_a_coarse_folded_rig_within_forty_calls(bench, time):
    rig = bench["lbs+deltamush"]
    box = rig.blackbox(rig.scene(), time)
    res = coupled.invert(box, rig.rest, rig.sculpts[time], neighbours=lambda: _adjacency(rig))
    assert res.evaluations == box.evaluations  # every call is counted
    assert res.regime == "coupled, from the smooth start"
    assert res.evaluations <= COUPLED_MAX_CALLS, res.evaluations
    # every residual within atol, checked by running the whole chain on rest + offsets
    moved = rig.rest.copy()
    moved[res.indices] += res.offsets
    residual = np.linalg.norm(rig.sculpts[time][res.indices] - rig.blackbox(rig.scene(), time)(moved)[res.indices], axis=1)
    assert len(res.indices) > 500 and residual.max() <= res.atol, (residual.max(), res.atol)


#: The coarse rig's 80 and 100 degree elbows, where the smooth start's finish stalls with a few
#: vertices just above the tolerance at the fold (11 and 36 of about 580, at up to 7e-6 of the
#: diagonal): the local polish measures their own columns of the chain's Jacobian and brings
#: every vertex within it. Measured: 113 and 184 calls.
POLISHED_MAX_CALLS = {4.0: 120, 5.0: 190}


@pytest.mark.parametrize("time", sorted(POLISHED_MAX_CALLS))
def test_a_fold_the_finish_leaves_a_few_vertices_above_is_polished(bench, time):
    rig = bench["lbs+deltamush"]
    box = rig.blackbox(rig.scene(), time)
    res = coupled.invert(box, rig.rest, rig.sculpts[time], neighbours=lambda: _adjacency(rig))
    assert res.evaluations == box.evaluations  # every call is counted
    assert res.regime == "coupled, from the smooth start" + coupled.POLISHED
    assert res.evaluations <= POLISHED_MAX_CALLS[time], res.evaluations
    moved = rig.rest.copy()
    moved[res.indices] += res.offsets
    residual = np.linalg.norm(rig.sculpts[time][res.indices] - rig.blackbox(rig.scene(), time)(moved)[res.indices], axis=1)
    assert len(res.indices) > 500 and residual.max() <= res.atol and not len(res.missed), (residual.max(), res.atol)


#: The 13k rig's 60 degree elbow: the finish leaves 3 vertices at about twice the tolerance, which
#: their own columns cannot bring within it (the least-squares step on 9 unknowns trades them
#: against the hundreds just inside it). Their edge neighbours' columns finish it: 85 calls
#: measured, where the slower stages had taken it to 118.
NEIGHBOURS_MAX_CALLS = 100


def test_few_vertices_their_own_columns_cannot_move_are_polished_with_their_neighbours(tmp_path):
    poses_layer, poses = rigs.write_poses(str(tmp_path))
    rig = rigs.build(str(tmp_path), "lbs+deltamush", "13k", poses, poses_layer)
    time = next(t for t in rig.times if poses[t]["Elbow"][1] == 60.0)
    box = rig.blackbox(rig.scene(), time)
    res = coupled.invert(box, rig.rest, rig.sculpts[time], neighbours=lambda: _adjacency(rig))
    assert res.evaluations == box.evaluations <= NEIGHBOURS_MAX_CALLS, res.evaluations
    assert res.regime == "coupled, from the smooth start" + coupled.POLISHED  # not the slower stages
    moved = rig.rest.copy()
    moved[res.indices] += res.offsets
    residual = np.linalg.norm(rig.sculpts[time][res.indices] - rig.blackbox(rig.scene(), time)(moved)[res.indices], axis=1)
    assert len(res.indices) > 4000 and residual.max() <= res.atol, (residual.max(), res.atol)


def _adjacency(rig):
    from psdbake.solver.smoothbasis import edge_adjacency
    from psdbake.usd.meshrest import rest_mesh

    return edge_adjacency(rest_mesh(rig.scene().stage, rigs.MESH)[1])
