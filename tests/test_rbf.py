"""Cardinal RBF weights: exact at the examples, zero at the bind pose, the stored
formula equals scipy's, and ill-posed example sets are named."""

from __future__ import annotations

import numpy as np
import pytest

from psdbake.errors import FitError
from psdbake.fitting import rbf_fit as rbf

CENTERS = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 1.2, 0.3], [0.7, 0.7, -0.4]])
LABELS = ["bind", "a@1", "b@2", "c@3"]
# 12 poses: enough for a quadratic polynomial term in 3-D (10 monomials)
MANY = np.vstack([np.zeros(3), np.random.default_rng(0).uniform(-1.5, 1.5, (11, 3))])
MANY_LABELS = ["bind"] + [f"e@{k}" for k in range(1, 12)]


@pytest.mark.parametrize("kernel", sorted(rbf.KERNELS))
@pytest.mark.parametrize("degree", [None, 2])
def test_cardinal_and_stored_formula_match_scipy(kernel, degree):
    outputs = list(range(1, 12))
    model = rbf.fit_cardinal(MANY, outputs, MANY_LABELS, kernel=kernel, degree=degree)
    # cardinal: b_s(c_i) = [i == s]; the bind pose (no column) gets all zeros
    np.testing.assert_allclose(model.weights(MANY), np.eye(12)[:, 1:], atol=1e-8)
    from scipy.interpolate import RBFInterpolator

    x = np.random.default_rng(1).normal(size=(20, 3))
    ref = RBFInterpolator(MANY, np.eye(12)[:, 1:], kernel=kernel, epsilon=1 / model.sigma, degree=model.degree)
    np.testing.assert_allclose(model.weights(x), ref(x), atol=1e-10)


def test_auto_sigma_is_mean_pairwise_distance():
    pts = np.array([[0.0], [1.0], [3.0]])
    assert rbf.auto_sigma(pts) == pytest.approx((1.0 + 3.0 + 2.0) / 3.0, abs=1e-12)
    assert rbf.auto_sigma(pts[:1]) == 1.0


def test_gaussian_kernel_has_no_polynomial_by_default():
    model = rbf.fit_cardinal(CENTERS, [1, 2, 3], LABELS)
    assert model.kernel == "gaussian" and model.degree == -1 and len(model.powers) == 0
    # far from every example the correction fades out
    assert np.abs(model.weights(np.array([[20.0, 20.0, 20.0]]))).max() < 1e-12


def test_duplicate_poses_name_both_examples():
    centers = np.vstack([CENTERS, CENTERS[2] + 1e-6])
    with pytest.raises(FitError, match=r"b@2 and dup@9"):
        rbf.fit_cardinal(centers, [1, 2, 3, 4], [*LABELS, "dup@9"])


def test_kernel_needing_a_polynomial_refuses_too_low_a_degree():
    with pytest.raises(FitError, match="degree of at least 1"):
        rbf.fit_cardinal(CENTERS, [1, 2, 3], LABELS, kernel="thin_plate_spline", degree=0)


def test_smoothing_loosens_the_self_weight():
    model = rbf.fit_cardinal(CENTERS, [1, 2, 3], LABELS, smoothing=1.0)
    assert model.weights(CENTERS[1:2])[0, 0] < 0.99
