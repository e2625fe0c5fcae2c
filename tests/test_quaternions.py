"""``psdbake.model.quaternions`` and ``rbf_model.distances`` against SciPy, to the last bits.

eval computes pose coordinates and RBF distances without SciPy (its import cost ~0.3 s of
every start-up, issue 16), and its outputs must keep their bytes: so each operation is held
to ``scipy.spatial.transform.Rotation`` / ``scipy.spatial.distance.cdist`` within 4 ulps (the
same bits with SciPy 1.17), on random input and on the inputs where the
compiled code branches (small angles, half turns, each pivot of ``from_matrix``, matrices
that need SVD orthogonalisation, w = 0).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from psdbake.model import posespace
from psdbake.model.quaternions import Rotations
from psdbake.model.rbf import distances

#: SciPy is not pinned, and a later release may reorder a few floating-point operations: the
#: comparison allows 4 ulps of values of order one (measured with SciPy 1.17: 0, every bit the
#: same, signed zeros included; byte-identical outputs are checked by benchmarks.outputs).
ULPS = 4 * np.finfo(np.float64).eps


def _same_bits(a, b) -> None:
    a, b = np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(b, dtype=np.float64)
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=ULPS, atol=ULPS)


def _quaternions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Unnormalised quaternions: generic, tiny vector parts (small-angle branch), w = 0 and w < 0."""
    q = rng.normal(size=(n, 4))
    q[: n // 4, :3] *= 10.0 ** rng.uniform(-12, -2, (n // 4, 1))
    q[n // 4 : n // 2, 3] = 0.0
    q[n // 2 : n // 2 + 3] = [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -1.0], [0.0, 0.0, -1.0, 0.0]]
    return q


def _matrices(rng: np.random.Generator, n: int) -> np.ndarray:
    """Rotation matrices as pose space sees them: exact, float32-rounded (not orthogonal to
    1e-12: SVD first), near the identity and near half turns (the trace and each diagonal pivot)."""
    exact = Rotation.random(n, random_state=rng).as_matrix()
    small = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 10.0 ** rng.uniform(-9, -1, (n, 1))).as_matrix()
    axes = rng.normal(size=(n, 3))
    half = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1, keepdims=True) * (np.pi - 1e-7)).as_matrix()
    mats = np.concatenate([exact, small, half, np.eye(3)[None]])
    return np.concatenate([mats, mats.astype(np.float32).astype(np.float64)])


@pytest.mark.parametrize("seed", range(4))
def test_from_matrix_and_from_quat(seed):
    rng = np.random.default_rng(seed)
    mats = _matrices(rng, 200)
    _same_bits(Rotations.from_matrix(mats).as_quat(), Rotation.from_matrix(mats).as_quat())
    _same_bits(Rotations.from_matrix(mats[:1]).as_quat(), Rotation.from_matrix(mats[:1]).as_quat())
    q = _quaternions(rng, 200)
    _same_bits(Rotations.from_quat(q).as_quat(), Rotation.from_quat(q).as_quat())


@pytest.mark.parametrize("seed", range(4))
def test_operations(seed):
    rng = np.random.default_rng(seed)
    p, q = _quaternions(rng, 200), _quaternions(rng, 200)[::-1]
    ours, theirs = Rotations.from_quat(q), Rotation.from_quat(q)
    _same_bits(ours.inv().as_quat(), theirs.inv().as_quat())
    _same_bits(ours.as_matrix(), theirs.as_matrix())
    _same_bits(ours.as_rotvec(), theirs.as_rotvec())
    _same_bits(ours.magnitude(), theirs.magnitude())
    _same_bits((Rotations.from_quat(p) * ours).as_quat(), (Rotation.from_quat(p) * theirs).as_quat())
    _same_bits((Rotations.from_quat(p[:1]) * ours).as_quat(), (Rotation.from_quat(p[:1]) * theirs).as_quat())
    _same_bits((ours * Rotations.from_quat(p[:1])).as_quat(), (theirs * Rotation.from_quat(p[:1])).as_quat())
    _same_bits((ours.inv() * ours).as_rotvec(), (theirs.inv() * theirs).as_rotvec())  # ~identity: the series


def _reference_features(bind: np.ndarray, local: np.ndarray, space: str, axis) -> np.ndarray:
    """Pose coordinates as posespace computed them with SciPy's Rotation (before issue 16)."""
    def rotations(matrices):
        m = np.asarray(matrices, dtype=np.float64)[..., :3, :3]
        norms = np.linalg.norm(m, axis=-1, keepdims=True)
        m = m / np.where(norms > 0, norms, 1.0)
        m = np.where(np.linalg.det(m)[..., None, None] < 0, -m, m)
        return Rotation.from_matrix(np.swapaxes(m, -1, -2).reshape(-1, 3, 3))

    delta = Rotation.from_quat(bind).inv() * rotations(local)
    if space == "rotationVector":
        return delta.as_rotvec().reshape(-1)
    if space == "quaternion":
        return (delta.as_matrix().reshape(-1, 3, 3) - np.eye(3)).reshape(-1)
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    q = delta.as_quat().reshape(-1, 4)
    proj = (q[:, :3] @ a)[:, None] * a
    twist_q = np.concatenate([proj, q[:, 3:4]], axis=1)
    norm = np.linalg.norm(twist_q, axis=1, keepdims=True)
    twist_q = np.where(norm > 1e-12, twist_q / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 0.0, 1.0])
    angle = 2.0 * np.arctan2(twist_q[:, :3] @ a, twist_q[:, 3])
    angle = (angle + np.pi) % (2.0 * np.pi) - np.pi
    swing = Rotation.from_quat(q) * Rotation.from_quat(twist_q).inv()
    return np.concatenate([swing.as_rotvec().reshape(-1, 3), angle[:, None]], axis=1).reshape(-1)


@pytest.mark.parametrize("space", sorted(posespace.POSE_SPACES))
def test_pose_coordinates_keep_their_bits(space):
    """What eval computes from stored bind quaternions and animated transforms (scaled,
    float32-rounded, mirrored), in every pose space."""
    rng = np.random.default_rng(7)
    n = 300
    bind = Rotation.random(n, random_state=rng).as_quat()
    local = np.zeros((n, 4, 4))
    local[:, :3, :3] = _matrices(rng, n // 6)[:n] * rng.uniform(0.5, 2.0, (n, 1, 1))
    local[: n // 10, :3, :3] *= -1.0  # mirrored joints
    local[:, 3, 3] = 1.0
    axis = [0.3, 1.0, -0.2] if space == "swingTwist" else None
    ours = posespace.features(posespace.relative_from_quaternions(bind, local), space, axis)
    _same_bits(ours, _reference_features(bind, local, space, axis))
    _same_bits(posespace.features(Rotation.from_quat(bind), space, axis),  # SciPy rotations still accepted
               posespace.features(Rotations.from_quat(bind), space, axis))


@pytest.mark.parametrize("seed", range(3))
def test_distances_are_cdist(seed):
    rng = np.random.default_rng(seed)
    for rows, centres, dims in [(1, 1, 1), (3, 5, 3), (4, 9, 6), (37, 8, 9), (250, 19, 27)]:
        x, c = rng.normal(size=(rows, dims)), rng.normal(size=(centres, dims))
        c[0] = x[0]  # a zero distance
        _same_bits(distances(x, c), cdist(x, c))
        _same_bits(distances(c, c), cdist(c, c))


def test_refusals_match_scipy():
    with pytest.raises(ValueError, match="zero norm"):
        Rotations.from_quat([[0.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="Non-positive determinant"):
        Rotations.from_matrix(-np.eye(3))
