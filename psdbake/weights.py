"""Corrective weights from stored driver data: pose coordinates -> cardinal RBF -> options.

The numerics of ``eval`` (and of ``compare``), from the documented ``psd:`` attributes alone,
as a third party would evaluate them (README: "To evaluate at a frame without psdbake").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from . import posespace, rbf
from .errors import InputError
from .usd.schema import DriverData


def rbf_from_driver_data(data: DriverData) -> rbf.CardinalRbf:
    if data.kernel not in rbf.KERNELS:
        raise InputError(f"psd:kernel {data.kernel!r} is unknown")
    return rbf.CardinalRbf(
        centers=data.centers, kernel=data.kernel, sigma=data.sigma, degree=data.degree,
        smoothing=data.smoothing, coefficients=data.coefficients, powers=data.powers,
        shift=data.shift, scale=data.scale, dims=data.dims,
    )


def check_driver_transforms(local: NDArray[np.float64], times, drivers: Sequence[str], label: str) -> None:
    """Driver transforms (f, d, 4, 4) must be finite with no zero-scale axis: else no pose."""
    bad = posespace.undefined_rotations(local)
    if bad.any():
        f, d = (int(i[0]) for i in np.nonzero(bad))
        raise InputError(
            f"{label}: joint {drivers[d]!r} has a NaN, infinite or zero-scale transform at time {float(times[f]):g}"
        )


def driver_weights(data: DriverData, local: NDArray[np.float64]) -> NDArray[np.float64]:
    """Weights (f, s) of the stored correctives for driver local transforms (f, d, 4, 4):
    pose coordinates, cardinal RBF, then the stored clamp/normalise options."""
    f = len(local)
    delta = posespace.relative_from_quaternions(np.tile(data.bind_rotations, (f, 1)), local.reshape(-1, 4, 4))
    return weights_of_rotations(data, delta, f)


def gate_activation(data: DriverData, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f,) product over the group's gates of clamp(x_j . g_j / g_j . g_j, 0, 1): x_j the gate
    driver's pose coordinates, g_j its gate pose. 1 without gates; 0 whenever a gate driver
    is at its bind pose (x_j = 0), 1 once every gate driver reaches its gate pose."""
    width = posespace.POSE_SPACES[data.pose_space].width
    out = np.ones(len(x))
    for gate, pose in zip(data.gates, data.gate_poses, strict=True):
        j = list(data.drivers).index(gate)
        xj = x[:, j * width : (j + 1) * width]
        out = out * np.clip(xj @ pose / float(pose @ pose), 0.0, 1.0)
    return out


def weights_of_rotations(data: DriverData, delta: Rotation, f: int) -> NDArray[np.float64]:
    """Weights (f, s) for the drivers' rotations away from their bind pose (f * d rotations)."""
    width = posespace.POSE_SPACES[data.pose_space].width
    x = posespace.features(delta, data.pose_space, data.twist_axis).reshape(f, width * len(data.drivers))
    w = rbf_from_driver_data(data).weights(x) * gate_activation(data, x)[:, None]
    if data.clamp_weights:
        w = np.clip(w, 0.0, 1.0)
    if data.normalize_weights:
        w = w / np.maximum(1.0, w.sum(axis=1, keepdims=True))
    return w
