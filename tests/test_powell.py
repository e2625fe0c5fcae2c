"""Lockstep Powell finds the same minima as scipy's Powell, problem by problem."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from psdbake import tolerances as tol
from psdbake.solver import powell


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


def _blocks(m: int, seed: int) -> np.ndarray:
    """3x3 blocks of every conditioning up to singular: rotations x singular values spread over
    seven decades x an overall scale over four, and Gaussian blocks."""
    rng = np.random.default_rng(seed)
    u = Rotation.random(m, random_state=seed).as_matrix()
    v = Rotation.random(m, random_state=seed + 1).as_matrix()
    s = np.exp(rng.uniform(np.log(1e-7), 0.0, (m, 3))) * np.exp(rng.uniform(-5.0, 5.0, (m, 1)))
    return np.concatenate([np.einsum("kab,kb,kcb->kac", u, s, v), rng.normal(size=(m, 3, 3))])


def test_conditioned_inverses_match_numpy_inv_on_the_blocks_they_accept():
    """The adjugate over the determinant against LU (np.linalg.inv). Their difference is rounding:
    the cofactors carry ~eps |J|^2 and the determinant ~eps |J|^3 of absolute error, so relative to
    J^-1 ~eps |J|_F^3 / |det J|, which the rcond test bounds by 1/rcond (measured: at most 0.46 of
    it over 1.2M such blocks; asserted within 4x, i.e. under 1e-9 at JACOBIAN_RCOND). That is far
    below the forward-difference Jacobian's own error (~1e-5, tolerances.JACOBIAN_STEP_RTOL)."""
    jac = _blocks(20000, seed=7)
    ok = powell.well_conditioned(jac, 1e-6)
    assert 0 < ok.sum() < len(jac)  # both kinds present
    jac = jac[ok]
    ours, lu = powell.conditioned_inverses(jac)[1], np.linalg.inv(jac)
    ratio = np.einsum("kab,kab->k", jac, jac) ** 1.5 / np.abs(np.linalg.det(jac))
    assert ratio.max() < 1e6 * (1 + 1e-9)
    rel = np.abs(ours - lu).max(axis=(1, 2)) / np.abs(lu).max(axis=(1, 2))
    np.testing.assert_array_less(rel, 4 * np.finfo(float).eps * ratio)
    # and it is an inverse: J J^-1 = I at the same rounding
    np.testing.assert_allclose(np.einsum("kab,kbc->kac", jac, ours), np.broadcast_to(np.eye(3), jac.shape),
                               rtol=0, atol=1e-8)


def test_det3_and_the_rcond_decision_match_numpy():
    """det3 (cofactors) against LU's determinant: both are off by rounding, a few eps |J|_F^3 (at
    most 8 eps measured over 400k such blocks; asserted within 32), the scale the rcond test
    compares |det J| with (1e-6 |J|_F^3, 1e8 times larger): so the invertible/singular decision
    is the same on every block but those within ~1e-8 of the threshold, and on all of these."""
    jac = _blocks(20000, seed=11)
    scale = np.einsum("kab,kab->k", jac, jac) ** 1.5
    np.testing.assert_array_less(np.abs(powell.det3(jac) - np.linalg.det(jac)), 32 * np.finfo(float).eps * scale)
    old = np.abs(np.linalg.det(jac)) > 1e-6 * np.maximum(scale, 1e-300)
    np.testing.assert_array_equal(powell.well_conditioned(jac, 1e-6), old)


def test_singular_and_nonfinite_blocks_are_refused_not_raised():
    """A zero-scale joint (a zero column), rank-one blocks, NaN and inf: never well conditioned,
    and refused without raising, as np.linalg.inv would."""
    jac = np.stack([np.diag([1.0, 1.0, 0.0]), np.outer([1.0, 2.0, 3.0], [0.5, -1.0, 2.0]), np.zeros((3, 3)),
                    np.full((3, 3), np.nan), np.diag([np.inf, 1.0, 1.0]), np.diag([1e200, 1e200, 1e200]),
                    np.eye(3)])
    np.testing.assert_array_equal(powell.well_conditioned(jac, 1e-6), [False] * 6 + [True])
    with np.errstate(all="raise"):
        ok, inv = powell.conditioned_inverses(jac, 1e-6)
    np.testing.assert_array_equal(ok, [False] * 6 + [True])
    np.testing.assert_array_equal(inv, [np.eye(3)])


def test_conditioned_inverses_are_well_conditioned_and_inverses_at_once():
    """One set of cofactors for both answers: the same mask as well_conditioned and inverses to
    rounding, on blocks spread over conditioning from a rotation to singular, with non-finite ones."""
    rng = np.random.default_rng(7)
    jac = rng.normal(size=(5000, 3, 3)) * np.logspace(0, -14, 5000)[:, None, None] ** rng.integers(0, 2, (5000, 1, 1))
    jac[:50, 2] = jac[:50, 0]  # singular
    jac[50:60, 1, 1] = np.nan
    jac[60:70, 0, 0] = np.inf
    ok, inv = powell.conditioned_inverses(jac, tol.JACOBIAN_RCOND)
    np.testing.assert_array_equal(ok, powell.well_conditioned(jac, tol.JACOBIAN_RCOND))
    assert 0 < ok.sum() < len(jac) and not ok[:70].any()
    np.testing.assert_allclose(np.einsum("kab,kbc->kac", jac[ok], inv), np.broadcast_to(np.eye(3), inv.shape),
                               atol=1e-6)
