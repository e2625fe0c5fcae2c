"""Corrective weights from stored driver data: pose coordinates -> cardinal RBF -> gates ->
options -> channels.

The numerics of ``eval`` (and of ``compare``), from the documented ``psd:`` attributes alone,
as a third party would evaluate them (docs/reference/psd-schema.md, "The weights formula").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from . import posespace
from .channels import channel_weights
from .data import DriverData
from .quaternions import RotationLike, Rotations
from .rbf import KERNELS, CardinalRbf


def rbf_from_driver_data(data: DriverData) -> CardinalRbf:
    if data.kernel not in KERNELS:
        raise InputError(f"psd:kernel {data.kernel!r} is unknown")
    return CardinalRbf(
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
    """Weights (f, s) of one group that no other group gates, for driver local transforms
    (f, d, 4, 4): pose coordinates, cardinal RBF, then the stored clamp/normalise options."""
    return weights_of_rotations(data, relative_rotations(data, local), len(local))


def relative_rotations(data: DriverData, local: NDArray[np.float64]) -> Rotations:
    """The group's drivers' rotations (f * d) away from their stored bind rotations, for
    their local transforms (f, d, 4, 4)."""
    f = len(local)
    return posespace.relative_from_quaternions(np.tile(data.bind_rotations, (f, 1)), local.reshape(-1, 4, 4))


def gate_activation(data: DriverData, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f,) product over the group's v3 gates of clamp(x_j . g_j / g_j . g_j, 0, 1): x_j the gate
    driver's pose coordinates, g_j its gate pose. 1 without gates; 0 whenever a gate driver
    is at its bind pose (x_j = 0), 1 once every gate driver reaches its gate pose."""
    width = posespace.POSE_SPACES[data.pose_space].width
    out = np.ones(len(x))
    for gate, pose in zip(data.gates, data.gate_poses, strict=True):
        j = list(data.drivers).index(gate)
        xj = x[:, j * width : (j + 1) * width]
        out = out * np.clip(xj @ pose / float(pose @ pose), 0.0, 1.0)
    return out


def ramp_gate(data: DriverData, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f,) product over the group's ramp gates (v5) of min(1, |x_j| / r_j): |x_j| the norm of
    the gate driver's pose coordinates, r_j its radius. 1 without ramp gates; 0 whenever a gate
    driver is at its bind pose, 1 once each is at least its radius from it, in any direction."""
    width = posespace.POSE_SPACES[data.pose_space].width
    out = np.ones(len(x))
    for gate, radius in zip(data.ramp_gates, data.ramp_radii, strict=True):
        j = list(data.drivers).index(gate)
        out = out * np.minimum(1.0, np.linalg.norm(x[:, j * width : (j + 1) * width], axis=1) / float(radius))
    return out


def pose_coordinates(data: DriverData, delta: RotationLike, f: int) -> NDArray[np.float64]:
    """(f, width * d): the group's pose-space coordinates of its drivers' rotations (f * d)."""
    width = posespace.POSE_SPACES[data.pose_space].width
    return posespace.features(delta, data.pose_space, data.twist_axis).reshape(f, width * len(data.drivers))


def rbf_weights(data: DriverData, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f, s): the group's cardinal RBF at pose coordinates x (times its v3 gates and its v5
    ramp gates), before group gates and options."""
    w = rbf_from_driver_data(data).weights(x)
    if len(data.gates):
        w = w * gate_activation(data, x)[:, None]
    if len(data.ramp_gates):
        w = w * ramp_gate(data, x)[:, None]
    return w


def activation(raw: NDArray[np.float64], x: NDArray[np.float64], directions: NDArray[np.float64]
               ) -> NDArray[np.float64]:
    """(f, c) a gate group's activation toward each of c combination shapes: max(0, the sum
    of its RBF weights raw (f, s)) -- 0 at bind, 1 at every one of its examples (cardinal
    weights), so it grows as its own correctives do -- times max(0, cos) of its pose
    coordinates x (f, m) with each shape's unit direction (c, m), so a joint sculpted both ways
    (a shoulder raised and lowered) gates only the combinations on its side."""
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    cos = np.divide(x @ directions.T, norm, out=np.zeros((len(x), len(directions))), where=norm > 0)
    return np.maximum(0.0, raw.sum(axis=1))[:, None] * np.maximum(0.0, cos)


def gate_slices(groups: dict[str, DriverData], data: DriverData) -> list[slice]:
    """Which columns of ``data.gate_directions`` (shapes x coordinates) belong to each gate
    group (its pose width times its drivers)."""
    out, start = [], 0
    for gate in data.gate_groups:
        other = groups[gate]
        stop = start + posespace.POSE_SPACES[other.pose_space].width * len(other.drivers)
        out.append(slice(start, stop))
        start = stop
    return out


def apply_options(data: DriverData, w: NDArray[np.float64]) -> NDArray[np.float64]:
    """The stored clamp and normalise options."""
    if data.clamp_weights:
        w = np.clip(w, 0.0, 1.0)
    if data.normalize_weights:
        w = w / np.maximum(1.0, w.sum(axis=1, keepdims=True))
    return w


def weights_of_rotations(data: DriverData, delta: RotationLike, f: int) -> NDArray[np.float64]:
    """Weights (f, s) of a group without group gates, for its drivers' rotations away from
    their bind pose (f * d rotations)."""
    if data.gate_groups:
        raise ValueError("a combination gated by other groups needs their weights: use group_weights")
    return apply_options(data, rbf_weights(data, pose_coordinates(data, delta, f)))


def group_weights(groups: Sequence[tuple[str, DriverData]], delta_of: Callable[[DriverData], RotationLike], f: int
                  ) -> dict[str, NDArray[np.float64]]:
    """group -> weights (f, s) of one mesh's groups, combinations included: a group's RBF
    weights times the ``activation`` of each group in its ``gate_groups`` (a facial rig's
    combination shape: the product of its components), then its options.

    delta_of(data): the rotations (f * d) of that group's drivers away from their bind pose."""
    x = {g: pose_coordinates(data, delta_of(data), f) for g, data in groups}
    raw = {g: rbf_weights(data, x[g]) for g, data in groups}
    by_name = dict(groups)
    out = {}
    for g, data in groups:
        w = raw[g]
        for gate, part in zip(data.gate_groups, gate_slices(by_name, data), strict=True):
            w = w * activation(raw[gate], x[gate], np.asarray(data.gate_directions)[:, part])
        out[g] = apply_options(data, w)
    return out


def column_weights_of_local(groups: Sequence[tuple[str, DriverData]], local: NDArray[np.float64],
                            joints: Sequence[str]) -> dict[str, NDArray[np.float64]]:
    """group -> its correctives' weights b (f, s) (``group_weights``) for every joint's local
    transforms (f, J, 4, 4), skeleton order ``joints``: ``channels.channel_weights`` makes them
    the written channels."""
    return group_weights(groups, lambda data: relative_rotations(data, local[:, _index(joints, data)]), len(local))


def weights_at_pose(groups: Sequence[tuple[str, DriverData]], pose: NDArray[np.float64], joints: Sequence[str]
                    ) -> dict[str, NDArray[np.float64]]:
    """group -> written channel weights (1, c) at an example's pose: every joint's rotation
    away from bind, (J, 4) quaternions in skeleton order ``joints``."""
    b = group_weights(groups, lambda data: Rotations.from_quat(pose[_index(joints, data)]), 1)
    return {g: channel_weights(data, b[g]) for g, data in groups}


def _index(joints: Sequence[str], data: DriverData) -> list[int]:
    return [list(joints).index(d) for d in data.drivers]


def sampled_ranges(groups: Sequence[tuple[str, DriverData]], count: int, anchors: Mapping[str, NDArray[np.float64]],
                   seed: int = 0) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """group -> (min, max) per output column of its weights b over sampled poses of every
    driver joint of the mesh's groups (one draw per joint, shared by the groups it drives;
    a fixed seed, so a fit is deterministic): what the weights actually reach, where the
    interval bound (``channels.weight_range``) can be loose by orders of magnitude.

    Poses are drawn where shots go, between and across the sculpts: each joint independently
    takes one of its ``anchors`` (its example rotations away from bind, (k, 4) quaternions; the
    bind pose is always one) turned by a factor in [0, 1.5] (up to half again past the
    sculpt), so every mix of joints the examples bend appears; a quarter of the draws are
    uniform over SO(3), for poses far from every sculpt."""
    from scipy.spatial.transform import Rotation  # fit only: eval's imports stay clear of scipy.spatial

    joints = sorted({d for _, data in groups for d in data.drivers})
    rng = np.random.default_rng(seed)
    near, far = count - count // 4, count // 4
    draws = {}
    for j in joints:
        rotvecs = Rotation.from_quat(np.concatenate([[[0.0, 0.0, 0.0, 1.0]], anchors.get(j, np.zeros((0, 4)))])).as_rotvec()
        pick = rotvecs[rng.integers(0, len(rotvecs), near)] * rng.uniform(0.0, 1.5, (near, 1))
        draws[j] = Rotation.concatenate([Rotation.identity(), Rotation.from_rotvec(pick),
                                         Rotation.random(far, random_state=rng)])
    n = count + 1

    def delta_of(data: DriverData) -> RotationLike:
        quats = np.stack([draws[d].as_quat() for d in data.drivers], axis=1)  # (n, d, 4), frame-major
        return Rotation.from_quat(quats.reshape(-1, 4))

    return {g: (b.min(axis=0), b.max(axis=0)) for g, b in group_weights(groups, delta_of, n).items()}
