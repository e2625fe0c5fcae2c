"""Lockstep Powell finds the same minima as scipy's Powell, problem by problem."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from psdbake import powell


def _affine_problems(m: int, seed: int):
    rng = np.random.default_rng(seed)
    a = Rotation.random(m, random_state=seed).as_matrix() * rng.uniform(0.5, 2.0, (m, 1, 1))
    b = rng.normal(size=(m, 3))
    target = rng.normal(size=(m, 3))

    def posed(x):
        return np.einsum("kab,kb->ka", a, x) + b

    return posed, target, a


def _nonlinear_problems(m: int, seed: int):
    posed_lin, target, a = _affine_problems(m, seed)

    def posed(x):
        q = posed_lin(x)
        ang = 0.4 * np.tanh(q[:, 2])
        c, s = np.cos(ang), np.sin(ang)
        return np.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1], q[:, 2] + 0.1 * np.sin(q[:, 0])], axis=1)

    return posed, target, a


@pytest.mark.parametrize("kind", ["affine", "nonlinear"])
def test_same_minima_as_scipy_powell(kind):
    maker = _affine_problems if kind == "affine" else _nonlinear_problems
    posed, target, _ = maker(40, seed=3)
    res = powell.minimize_lockstep(lambda x: target - posed(x), np.zeros((40, 3)), atol=1e-11)
    assert np.all(res.status == powell.CONVERGED)
    for k in range(0, 40, 4):
        def f(d, k=k):
            x = np.zeros((40, 3))
            x[k] = d
            r = target[k] - posed(x)[k]
            return r @ r

        ref = minimize(f, np.zeros(3), method="Powell", options={"xtol": 1e-12, "ftol": 1e-20})
        # Both minimise a function whose minimum is 0 at a unique point: agree to 1e-8.
        np.testing.assert_allclose(res.x[k], ref.x, atol=1e-8, rtol=0)


def test_conjugate_directions_finish_a_quadratic_in_one_cycle():
    """With directions J^-1 e_j (conjugate for |J x - r|^2) an affine problem is solved by
    one cycle of three parabolic line minimisations: 3 calls each, plus the start."""
    posed, target, a = _affine_problems(500, seed=5)
    directions = np.transpose(np.linalg.inv(a), (0, 2, 1))
    res = powell.minimize_lockstep(
        lambda x: target - posed(x), np.zeros((500, 3)), directions=directions, jacobian=a, atol=1e-9
    )
    assert np.all(res.status == powell.CONVERGED)
    assert res.cycles == 1
    assert res.nfev <= 1 + 3 * 3  # budget: start + 3 line searches x 3 calls


def test_coordinate_directions_need_more_cycles_but_get_there():
    posed, target, _ = _affine_problems(200, seed=7)
    res = powell.minimize_lockstep(lambda x: target - posed(x), np.zeros((200, 3)), atol=1e-9)
    assert np.all(res.status == powell.CONVERGED)
    assert res.residual_norm.max() <= 1e-9


def test_unreachable_target_stalls_at_the_least_squares_point():
    """A rank-deficient map cannot reach the target: Powell stops at the closest point."""
    def posed(x):
        return np.stack([x[:, 0], x[:, 1], np.zeros(len(x))], axis=1)

    target = np.array([[1.0, 2.0, 3.0]] * 5)
    res = powell.minimize_lockstep(lambda x: target - posed(x), np.zeros((5, 3)), atol=1e-9)
    assert np.all(res.status == powell.STALLED)
    np.testing.assert_allclose(res.x[:, :2], target[:, :2], atol=1e-6)
    np.testing.assert_allclose(res.residual_norm, 3.0, atol=1e-6)


def test_nonfinite_trials_are_never_accepted():
    def residual(x):
        r = np.array([[1.0, 1.0, 1.0]]) - x
        r[np.linalg.norm(x, axis=1) > 2.0] = np.nan  # a black box that blows up far away
        return r

    res = powell.minimize_lockstep(residual, np.zeros((1, 3)), atol=1e-9)
    assert res.status[0] == powell.CONVERGED
    np.testing.assert_allclose(res.x[0], [1.0, 1.0, 1.0], atol=1e-9)


def test_problems_are_independent_of_their_neighbours():
    """Solving a problem alone or among others gives the same answer (lockstep only
    shares black-box calls)."""
    posed, target, _ = _nonlinear_problems(30, seed=11)
    together = powell.minimize_lockstep(lambda x: target - posed(x), np.zeros((30, 3)), atol=1e-11)
    alone = powell.minimize_lockstep(
        lambda x: _one(posed, target, x, 7),
        np.zeros((1, 3)), atol=1e-11,
    )
    np.testing.assert_allclose(together.x[7], alone.x[0], atol=1e-9)


def _one(posed, target, x, k):
    full = np.zeros((len(target), 3))
    full[k] = x[0]
    return (target - posed(full))[k : k + 1]
