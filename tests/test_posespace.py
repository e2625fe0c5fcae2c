"""Pose coordinates: rotation vectors relative to the bind pose, in the joint's bind frame."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf

from psdbake.model import posespace


def _gf(m: Gf.Matrix4d) -> np.ndarray:
    return np.array(m, dtype=np.float64)


def test_bind_pose_is_the_origin_and_rotation_is_its_rotation_vector():
    bind = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 1, 0), 30.0)) * Gf.Matrix4d().SetTranslate(Gf.Vec3d(1, 2, 3))
    posed = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(0, 0, 1), 50.0)) * bind  # 50 deg about the joint's own z
    x = posespace.pose_coordinates(np.array([_gf(bind)]), np.array([_gf(posed)]))
    np.testing.assert_allclose(x, [0.0, 0.0, np.radians(50.0)], atol=1e-12)
    x0 = posespace.pose_coordinates(np.array([_gf(bind)]), np.array([_gf(bind)]))
    np.testing.assert_allclose(x0, 0.0, atol=1e-12)


def test_scale_does_not_leak_into_the_rotation():
    bind = np.eye(4)
    posed = _gf(Gf.Matrix4d().SetScale(Gf.Vec3d(2, 3, 0.5)) * Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), 20.0)))
    x = posespace.pose_coordinates(np.array([bind]), np.array([posed]))
    np.testing.assert_allclose(x, [np.radians(20.0), 0.0, 0.0], atol=1e-12)


def test_stored_quaternions_give_the_same_coordinates():
    rng = np.random.default_rng(2)
    from scipy.spatial.transform import Rotation

    bind_r, posed_r = Rotation.random(4, random_state=3), Rotation.random(4, random_state=4)
    bind = np.tile(np.eye(4), (4, 1, 1))
    posed = np.tile(np.eye(4), (4, 1, 1))
    bind[:, :3, :3] = np.transpose(bind_r.as_matrix(), (0, 2, 1))  # row-vector convention
    posed[:, :3, :3] = np.transpose(posed_r.as_matrix(), (0, 2, 1))
    posed[:, 3, :3] = rng.normal(size=(4, 3))
    a = posespace.pose_coordinates(bind, posed)
    b = posespace.features(posespace.relative_from_quaternions(bind_r.as_quat(), posed))
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_swing_twist_recombines_and_isolates_the_twist():
    from scipy.spatial.transform import Rotation

    twist = Rotation.from_rotvec([0.7, 0.0, 0.0])
    swing = Rotation.from_rotvec([0.0, 0.4, -0.3])
    delta = swing * twist
    s, angle = posespace.swing_twist(delta, np.array([2.0, 0.0, 0.0]))
    np.testing.assert_allclose(angle, [0.7], atol=1e-12)
    recombined = (s * Rotation.from_rotvec([0.7, 0, 0])).as_matrix()
    np.testing.assert_allclose(recombined, delta.as_matrix().reshape(1, 3, 3), atol=1e-12)
    np.testing.assert_allclose(s.as_rotvec() @ [1.0, 0.0, 0.0], 0.0, atol=1e-12)  # swing is perpendicular


def test_quaternion_space_is_continuous_through_180_degrees():
    from scipy.spatial.transform import Rotation

    a = Rotation.from_rotvec([0.0, 0.0, np.pi - 1e-3])
    b = Rotation.from_rotvec([0.0, 0.0, -(np.pi - 1e-3)])  # 2e-3 rad away from a
    qa, qb = posespace.features(a, "quaternion"), posespace.features(b, "quaternion")
    # chordal distance 2 sqrt(2) sin(theta / 2) for the 2e-3 rad between them
    # pure float64 on features of size ~2 (measured 3e-17 off)
    assert np.linalg.norm(qa - qb) == pytest.approx(2 * np.sqrt(2) * np.sin(1e-3), rel=0, abs=1e-12)
    ra, rb = posespace.features(a), posespace.features(b)
    assert np.linalg.norm(ra - rb) > 6.0  # rotation vectors jump across the antipode
    np.testing.assert_allclose(posespace.features(Rotation.identity(), "quaternion"), 0.0, atol=1e-15)
