"""Pose coordinates: rotation vectors relative to the bind pose, in the joint's bind frame."""

from __future__ import annotations

import numpy as np
from pxr import Gf

from psdbake import posespace


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
    b = posespace.pose_coordinates_from_quaternions(bind_r.as_quat(), posed)
    np.testing.assert_allclose(a, b, atol=1e-12)
