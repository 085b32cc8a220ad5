"""Group properties of the SE(3) helpers, checked against scipy's Rotation."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mcl3d.core import geometry as g


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def random_poses(rng, n):
    return g.se3(g.random_rotations(rng, n), rng.normal(scale=5.0, size=(n, 3)))


def test_quaternion_matches_scipy(rng):
    q = Rotation.random(50, random_state=3).as_quat()  # (x, y, z, w)
    np.testing.assert_allclose(g.quat_to_rot(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
    back = g.rot_to_quat(g.quat_to_rot(q))
    q_pos = np.where(q[:, 3:4] < 0, -q, q)
    np.testing.assert_allclose(back, q_pos, atol=1e-12)


def test_so3_exp_log_match_scipy(rng):
    w = rng.normal(size=(100, 3))
    w *= (rng.uniform(0, np.pi - 1e-3, 100) / np.linalg.norm(w, axis=1))[:, None]
    np.testing.assert_allclose(g.so3_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-9)


def test_so3_log_near_identity_and_pi():
    tiny = np.array([1e-12, -2e-12, 3e-12])
    np.testing.assert_allclose(g.so3_log(g.so3_exp(tiny)), tiny, atol=1e-15)
    near_pi = np.array([0.0, 0.0, np.pi - 1e-9])
    assert abs(np.linalg.norm(g.so3_log(g.so3_exp(near_pi))) - (np.pi - 1e-9)) < 1e-6


def test_se3_group_properties(rng):
    A, B, C = random_poses(rng, 3)
    np.testing.assert_allclose(g.se3_inverse(A) @ A, np.eye(4), atol=1e-12)
    np.testing.assert_allclose((A @ B) @ C, A @ (B @ C), atol=1e-9)
    np.testing.assert_allclose(A @ g.relative_se3(A, B), B, atol=1e-9)


def test_se3_exp_log_roundtrip(rng):
    xi = np.concatenate([rng.normal(scale=0.8, size=(40, 3)), rng.normal(size=(40, 3))], axis=1)
    np.testing.assert_allclose(g.se3_log(g.se3_exp(xi)), xi, atol=1e-9)


def test_se3_exp_rotation_first_right_perturbation(rng):
    T = random_poses(rng, 1)[0]
    xi = np.array([0.0, 0.0, 0.0, 0.1, 0.0, 0.0])  # pure translation along the body x axis
    moved = T @ g.se3_exp(xi)
    np.testing.assert_allclose(moved[:3, 3], T[:3, 3] + 0.1 * T[:3, 0], atol=1e-12)


def test_interpolation_endpoints_and_midpoint(rng):
    A, B = random_poses(rng, 2)
    np.testing.assert_allclose(g.interpolate_se3(A, B, 0.0), A, atol=1e-9)
    np.testing.assert_allclose(g.interpolate_se3(A, B, 1.0), B, atol=1e-9)
    mid = g.interpolate_se3(A, B, 0.5)
    d1 = g.rotation_angle(mid[:3, :3].T @ A[:3, :3])
    d2 = g.rotation_angle(mid[:3, :3].T @ B[:3, :3])
    assert abs(d1 - d2) < 1e-9


def test_rpy_matches_scipy_extrinsic_xyz():
    rpy = np.array([0.3, -0.4, 2.0])
    expected = Rotation.from_euler("xyz", rpy).as_matrix()
    np.testing.assert_allclose(g.rpy_to_rot(*rpy), expected, atol=1e-12)
    np.testing.assert_allclose(g.rot_to_rpy(expected), rpy, atol=1e-12)


def test_random_rotations_are_uniform(rng):
    R = g.random_rotations(rng, 20000)
    # Haar measure: the angle density is (1 - cos t) / pi, so E[angle] = pi/2 + 2/pi.
    assert abs(g.rotation_angle(R).mean() - (np.pi / 2 + 2 / np.pi)) < 0.02
    # and each body axis is uniform on the sphere: mean z-component ~ 0, mean z^2 ~ 1/3
    assert abs(R[:, 2, 2].mean()) < 0.02 and abs((R[:, 2, 2] ** 2).mean() - 1 / 3) < 0.01
