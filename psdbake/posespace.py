"""Pose space: joint rotations relative to the bind pose, as coordinates for the RBF.

A pose is described, per driver joint j, by the rotation that takes the joint's
bind-pose local orientation to its current local orientation, expressed in the
joint's own bind frame (column-vector convention)::

    delta_j = R_bind_j^-1 R_j          x_j = rotvec(delta_j)  (radians, 3 numbers)

and the pose coordinate vector is x = concat(x_j over drivers) in the order of
``psd:drivers``. Distances between poses are Euclidean in x. The bind pose (the pose
at which UsdSkel skinning is the identity) is x = 0.

Input matrices follow Gf's row-vector convention (p' = p . M), as UsdSkel returns
them; this module is the one place that converts. Scale and translation are ignored:
rows of the 3x3 block are normalised (no shear, as UsdSkel joints) before the
rotation is taken.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Matrices = NDArray[np.float64]  # (j, 4, 4) Gf row-vector transforms
Quaternions = NDArray[np.float64]  # (j, 4) scalar-last (x, y, z, w), as scipy


def rotations(matrices: Matrices) -> Rotation:
    """Rotation part of row-vector transforms, as column-convention scipy rotations."""
    m = np.asarray(matrices, dtype=np.float64)[..., :3, :3]
    norms = np.linalg.norm(m, axis=-1, keepdims=True)
    m = m / np.where(norms > 0, norms, 1.0)
    return Rotation.from_matrix(np.swapaxes(m, -1, -2).reshape(-1, 3, 3))


def relative_rotations(bind_local: Matrices, local: Matrices) -> Rotation:
    """delta_j = R_bind_j^-1 R_j for each joint (the rotation away from the bind pose)."""
    return rotations(bind_local).inv() * rotations(local)


def pose_coordinates(bind_local: Matrices, local: Matrices) -> NDArray[np.float64]:
    """Pose coordinates x (3 j,) of driver joints: concatenated rotation vectors."""
    return relative_rotations(bind_local, local).as_rotvec().reshape(-1)


def pose_coordinates_from_quaternions(bind_rotations: Quaternions, local: Matrices) -> NDArray[np.float64]:
    """As ``pose_coordinates`` with the bind rotations given as stored quaternions."""
    delta = Rotation.from_quat(bind_rotations).inv() * rotations(local)
    return delta.as_rotvec().reshape(-1)


def rotated_joints(coordinates: NDArray[np.float64], atol: float) -> NDArray[np.bool_]:
    """Which joints rotate more than atol (radians) in any of the given poses.

    coordinates: (poses, 3 j) pose coordinates over all joints.
    """
    x = np.asarray(coordinates, dtype=np.float64)
    angles = np.linalg.norm(x.reshape(len(x), -1, 3), axis=2)
    return np.any(angles > atol, axis=0)
