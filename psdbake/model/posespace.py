"""Pose space: joint rotations relative to the bind pose, as coordinates for the RBF.

A pose is described, per driver joint j, by the rotation that takes the joint's
bind-pose local orientation to its current local orientation, expressed in the
joint's own bind frame (column-vector convention)::

    delta_j = R_bind_j^-1 R_j

and turned into coordinates by one of three pose spaces (``psd:poseSpace``):

- ``rotationVector`` (default): rotvec(delta_j), 3 numbers in radians; the bind pose is 0.
- ``swingTwist``: delta_j = swing . twist with twist about the unit axis a
  (``psd:twistAxis``, in the joint's bind frame) and swing about an axis
  perpendicular to a; coordinates [rotvec(swing), twist angle], 4 numbers in radians.
  Separates a forearm's twist from its bend, which production rigs drive apart.
- ``quaternion``: the quaternion (chordal) distance between rotations. Coordinates are
  R(delta_j) - I (9 numbers, row-major, the bind pose is 0); the Euclidean distance
  between two of them is 2 sqrt(2) sin(theta / 2) = 2 sqrt(2) sqrt(1 - (q1 . q2)^2),
  theta the angle between the rotations: the same for q and -q and continuous
  everywhere, where rotation vectors jump at 180 degrees.

The pose vector x is the concatenation over drivers in ``psd:drivers`` order; distances
between poses are Euclidean in x.

Input matrices follow Gf's row-vector convention (p' = p . M), as UsdSkel returns them;
this module is the one place that converts. Scale and translation are ignored: rows of
the 3x3 block are normalised (no shear, as UsdSkel joints) and a mirrored (negative
determinant) block is negated before the rotation is taken.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..arrays import Matrices, Quaternions, is_singular
from .quaternions import RotationLike, Rotations

#: Transform entries beyond float32's range: UsdSkel skins in float32, so such a joint or
#: prim transform cannot be evaluated (and squaring its entries overflows float64).
LARGEST_ENTRY = float(np.finfo(np.float32).max)


def undefined_rotations(matrices: Matrices) -> NDArray[np.bool_]:
    """Which transforms (..., 4, 4) have no rotation: a NaN/inf entry, an entry beyond
    float32's range, a zero-scale axis, or axes that do not span 3-D (a degenerate frame)."""
    m = np.asarray(matrices, dtype=np.float64)
    usable = np.all(np.isfinite(m), axis=(-2, -1)) & np.all(np.abs(np.nan_to_num(m)) <= LARGEST_ENTRY, axis=(-2, -1))
    return ~usable | is_singular(np.where(usable[..., None, None], m[..., :3, :3], 0.0))


def rotations(matrices: Matrices) -> Rotations:
    """Rotation part of row-vector transforms, as column-convention rotations (``quaternions``:
    scipy's ``Rotation`` without loading ``scipy.spatial``, bit for bit)."""
    m = np.asarray(matrices, dtype=np.float64)[..., :3, :3]
    norms = np.linalg.norm(m, axis=-1, keepdims=True)
    m = m / np.where(norms > 0, norms, 1.0)
    # A mirrored joint (negative scale, common in mirrored rigs) is a reflection: negating
    # the 3x3 block leaves a proper rotation; bind and posed frames flip alike, so delta is kept.
    m = np.where(np.linalg.det(m)[..., None, None] < 0, -m, m)
    return Rotations.from_matrix(np.swapaxes(m, -1, -2).reshape(-1, 3, 3))


def relative_rotations(bind_local: Matrices, local: Matrices) -> Rotations:
    """delta_j = R_bind_j^-1 R_j for each joint (the rotation away from the bind pose)."""
    return rotations(bind_local).inv() * rotations(local)


def relative_from_quaternions(bind_rotations: Quaternions, local: Matrices) -> Rotations:
    """As ``relative_rotations`` with the bind rotations given as stored quaternions."""
    return Rotations.from_quat(bind_rotations).inv() * rotations(local)


def swing_twist(delta: RotationLike, axis: NDArray[np.float64]) -> tuple[Rotations, NDArray[np.float64]]:
    """delta = swing * twist, twist about axis; returns (swing, signed twist angle)."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    q = delta.as_quat().reshape(-1, 4)
    proj = (q[:, :3] @ a)[:, None] * a
    twist_q = np.concatenate([proj, q[:, 3:4]], axis=1)
    norm = np.linalg.norm(twist_q, axis=1, keepdims=True)
    twist_q = np.where(norm > 1e-12, twist_q / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 0.0, 1.0])
    twist = Rotations.from_quat(twist_q)
    angle = 2.0 * np.arctan2(twist_q[:, :3] @ a, twist_q[:, 3])
    angle = (angle + np.pi) % (2.0 * np.pi) - np.pi
    return Rotations.from_quat(q) * twist.inv(), angle


def _rotation_vector(delta: Rotations, twist_axis: NDArray[np.float64] | None) -> NDArray[np.float64]:
    return delta.as_rotvec().reshape(-1)


def _chordal(delta: Rotations, twist_axis: NDArray[np.float64] | None) -> NDArray[np.float64]:
    return (delta.as_matrix().reshape(-1, 3, 3) - np.eye(3)).reshape(-1)


def _swing_twist(delta: Rotations, twist_axis: NDArray[np.float64] | None) -> NDArray[np.float64]:
    if twist_axis is None:
        raise ValueError("swingTwist pose space needs a twist axis")
    swing, twist = swing_twist(delta, twist_axis)
    return np.concatenate([swing.as_rotvec().reshape(-1, 3), twist[:, None]], axis=1).reshape(-1)


@dataclass(frozen=True)
class PoseSpace:
    """One way of turning a driver's rotation into RBF coordinates (``psd:poseSpace``)."""

    width: int  # coordinates per driver
    coordinates: Callable[[Rotations, NDArray[np.float64] | None], NDArray[np.float64]]
    needs_twist_axis: bool = False
    bound: float = np.pi  # no coordinate of any rotation exceeds this in magnitude (channels.py)


#: The pose spaces, keyed by their ``psd:poseSpace`` token (``names.POSE_SPACE_NAMES``, checked by
#: tests/test_layering.py): the CLI's choices, the fit's and the reader's validation all read these, so a new
#: pose space is one name there and one entry here.
POSE_SPACES: dict[str, PoseSpace] = {
    "rotationVector": PoseSpace(3, _rotation_vector),
    "swingTwist": PoseSpace(4, _swing_twist, needs_twist_axis=True),
    "quaternion": PoseSpace(9, _chordal, bound=2.0),  # entries of R - I
}


def features(delta: RotationLike, space: str = "rotationVector", twist_axis=None) -> NDArray[np.float64]:
    """Pose coordinates of the joints' relative rotations, concatenated: (width j,). delta may
    be scipy's ``Rotation`` too (the same quaternions, so the same coordinates)."""
    if space not in POSE_SPACES:
        raise ValueError(f"unknown pose space {space!r}: choose one of {', '.join(POSE_SPACES)}")
    return POSE_SPACES[space].coordinates(Rotations(delta.as_quat()), twist_axis)


def pose_coordinates(bind_local: Matrices, local: Matrices, space: str = "rotationVector",
                     twist_axis=None) -> NDArray[np.float64]:
    """Pose coordinates x of the given joints (bind and current local transforms)."""
    return features(relative_rotations(bind_local, local), space, twist_axis)


def rotated_joints(deltas: NDArray[np.float64], atol: float) -> NDArray[np.bool_]:
    """Which joints rotate more than atol (radians) in any of the given poses.

    deltas: (poses, j, 4) relative rotations as quaternions.
    """
    q = np.asarray(deltas, dtype=np.float64)
    angles = 2.0 * np.arctan2(np.linalg.norm(q[..., :3], axis=-1), np.abs(q[..., 3]))
    return np.any(angles > atol, axis=0)

def active_joints(poses: NDArray[np.float64], angle: float = tol.ACTIVE_JOINT_ANGLE) -> list[frozenset[int]]:
    """Per example pose (j, 4) quaternions: the joints turned more than angle from bind."""
    q = np.asarray(poses, dtype=np.float64)
    turned = 2.0 * np.arctan2(np.linalg.norm(q[..., :3], axis=-1), np.abs(q[..., 3])) > angle
    return [frozenset(int(j) for j in np.nonzero(row)[0]) for row in turned]
