"""Conditioning is a design property: the RBF system is checked before anything is solved,
the automatic sigma keeps it well-conditioned as examples grow, and no kernel/sigma/degree
combination ends in anything but an exact model, a ``PsdWarning`` or a one-line ``FitError``.

Pure numpy (no USD): pose coordinates are made directly.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import pytest

from psdbake import tolerances as tol
from psdbake.errors import FitError, PsdWarning
from psdbake.fitting import rbf_fit as rbf

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)


#: Exactness at the examples: b_s(c_i) = [i == s] within this (float32 weights: see tolerances).
ATOL = tol.CARDINAL_ATOL
SIGMAS = {"tiny": 1e-3, "default": None, "huge": 1e3}


def _random_poses(count: int, seed: int) -> np.ndarray:
    """count poses of two rotation-vector joints (6 coordinates), the bind pose first."""
    rng = np.random.default_rng(seed)
    poses = rng.uniform(-1.5, 1.5, (count, 6))
    poses[0] = 0.0
    return poses


def _bench_poses(count: int) -> np.ndarray:
    """benchmarks.rigs.example_poses(count) as pose coordinates (elbow about z, wrist about x),
    the bind pose first: the bench's example distribution without building the rig."""
    poses = np.zeros((count + 1, 6))
    for i in range(count):
        poses[i + 1, 2] = math.radians(20.0 + 140.0 * i / max(count - 1, 1))
        poses[i + 1, 3] = math.radians(60.0 * math.sin(1.3 * i))
    return poses


def _labels(count: int) -> list[str]:
    return ["bind"] + [f"e@{k}" for k in range(1, count)]


def _outcome(poses: np.ndarray, **kw) -> str:
    """'exact', 'warned' or 'refused'; anything else (another exception or warning, a model
    that is not exact at the examples) fails the test."""
    labels = _labels(len(poses))
    outputs = list(range(1, len(poses))) or [0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            model = rbf.fit_cardinal(poses, outputs, labels, **kw)
        except FitError as exc:
            msg = str(exc)
            assert "\n" not in msg and msg, msg
            assert "internal" not in msg
            assert any(opt in msg for opt in ("--sigma", "--kernel", "--degree", "--smoothing", "examples")), msg
            assert not caught, [str(w.message) for w in caught]
            return "refused"
    others = [w for w in caught if not issubclass(w.category, PsdWarning)]
    assert not others, [f"{w.category.__name__}: {w.message}" for w in others]
    w = model.weights(poses)
    np.testing.assert_allclose(w, np.eye(len(poses))[:, outputs], rtol=0, atol=ATOL)
    assert np.isfinite(model.condition)
    return "warned" if caught else "exact"


@pytest.mark.parametrize("count", [1, 2, 8, 64, 200])
def test_every_kernel_sigma_degree_is_exact_warned_or_refused(count):
    """Every kernel x sigma {tiny, default, huge} x degree {-1, 0, 1, 2} over random poses: an
    exact model, a PsdWarning with an exact model, or a one-line FitError naming the option."""
    poses = _random_poses(count, seed=count)
    seen = {}
    for kernel in sorted(rbf.KERNELS):
        for sname, sigma in SIGMAS.items():
            for degree in (-1, 0, 1, 2):
                seen[(kernel, sname, degree)] = _outcome(poses, kernel=kernel, sigma=sigma, degree=degree)
    # the default Gaussian is never refused, however many examples
    assert seen[("gaussian", "default", -1)] == "exact"


@pytest.mark.parametrize("count", [8, 32, 128])  # 500: benchmarks/conditioning.py
def test_automatic_sigma_stays_well_conditioned_on_bench_poses(count):
    poses = _bench_poses(count)
    plan = rbf.plan_rbf(poses, None, _labels(len(poses)))
    assert plan.ok and not plan.warnings
    assert plan.condition <= tol.RBF_COND_TARGET
    assert plan.cardinal_error <= ATOL
    # the largest sigma on the grid: one quarter octave wider is above the target
    if plan.sigma < rbf.auto_sigma(plan.centers):
        wider = rbf.plan_rbf(poses, None, _labels(len(poses)), sigma=plan.sigma / tol.RBF_SIGMA_STEP,
                             raise_problem=False)
        assert not wider.ok or wider.condition > tol.RBF_COND_TARGET


def test_automatic_sigma_is_unchanged_for_sparse_example_sets():
    """benchmarks/fidelity.py's examples (elbow 90, 135, twist 70, bind): the mean pairwise distance."""
    poses = np.zeros((4, 6))
    poses[1, 2], poses[2, 2], poses[3, 3] = math.radians(90), math.radians(135), math.radians(70)
    plan = rbf.plan_rbf(poses, [1, 2, 3], _labels(4))
    assert plan.sigma == rbf.auto_sigma(poses) and plan.sigma_rule == "mean pairwise distance"
    assert plan.condition < 100


def test_bad_sigma_fails_before_any_solve_in_well_under_a_second():
    """The issue's case: the old default (mean pairwise distance) at 128 and 500 examples."""
    for count in (128, 500):
        poses = _bench_poses(count)
        started = time.perf_counter()
        with pytest.raises(FitError, match=r"numerically singular \(condition number .*--sigma") as info:
            rbf.plan_rbf(poses, None, _labels(len(poses)), sigma=rbf.auto_sigma(poses))
        # 128 poses: well under a second (500: ~0.3 s idle, but threaded BLAS on a loaded 2-core machine
        # can take seconds for any 500 x 500 eigenvalue problem, so only the message is checked there)
        assert count > 128 or time.perf_counter() - started < 1.0
        assert info.value.exit_code == 4 and "\n" not in str(info.value)


def test_ill_conditioned_but_exact_is_a_warning_naming_the_condition_number():
    poses = _bench_poses(32)  # the old default sigma here: condition number 6.8e8
    with pytest.warns(PsdWarning, match=r"condition number 6\.\de\+08.*exact at the examples"):
        model = rbf.fit_cardinal(poses, list(range(1, 33)), _labels(33), sigma=rbf.auto_sigma(poses))
    assert model.condition > tol.RBF_COND_TARGET
    np.testing.assert_allclose(model.weights(poses), np.eye(33)[:, 1:], atol=ATOL)


def test_plan_then_fit_is_the_same_model_and_carries_the_condition_number():
    poses = _bench_poses(32)
    plan = rbf.plan_rbf(poses, None, _labels(33), where="arm.usda </Arm> group main")
    model = rbf.fit_cardinal(poses, [2, 5], _labels(33), plan=plan)
    again = rbf.fit_cardinal(poses, [2, 5], _labels(33))
    assert model.sigma == again.sigma == plan.sigma and model.condition == plan.condition
    np.testing.assert_array_equal(model.coefficients, again.coefficients)
    assert model.coefficients.shape == (33, 2)


def test_problem_is_returned_instead_of_raised_on_request():
    poses = _bench_poses(8)
    plan = rbf.plan_rbf(poses, None, _labels(9), kernel="cubic", degree=0, where="a.usda </M>", raise_problem=False)
    assert not plan.ok and plan.problem is not None
    assert plan.problem.startswith("a.usda </M>: ") and "--degree" in plan.problem
    with pytest.raises(FitError):
        plan.model([1])


def test_too_few_poses_for_the_polynomial_names_degree():
    poses = _random_poses(5, seed=3)
    with pytest.raises(FitError, match=r"28 monomials, more than the 5 poses.*--degree"):
        rbf.plan_rbf(poses, None, _labels(5), degree=2)
