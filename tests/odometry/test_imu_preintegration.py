"""IMU preintegration against an analytic trajectory (exact specific force and rates)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import InputError
from mcl3d.core.geometry import rotation_angle, se3, so3_exp
from mcl3d.odometry.imu_preintegration import GRAVITY_MPS2, gravity_from_static, preintegrate

G_WORLD = np.array([0.0, 0.0, -GRAVITY_MPS2])
W_BODY = np.array([0.3, -0.2, 0.5])  # R(t) = Exp(W t): constant body rate W


def pose(t):
    p = np.array([np.sin(t), np.cos(2 * t), 0.1 * t * t])
    return se3(so3_exp(W_BODY * t), p)


def velocity(t):
    return np.array([np.cos(t), -2 * np.sin(2 * t), 0.2 * t])


def accel(t):
    return np.array([-np.sin(t), -4 * np.cos(2 * t), 0.2])


def samples(t0, t1, rate_hz):
    stamps = np.arange(t0, t1, 1.0 / rate_hz)
    gyro = np.tile(W_BODY, (len(stamps), 1))
    f = np.array([pose(t)[:3, :3].T @ (accel(t) - G_WORLD) for t in stamps])
    return stamps, gyro, f


def test_prediction_matches_the_true_trajectory():
    t0, t1 = 0.3, 0.8
    stamps, gyro, f = samples(t0 - 0.01, t1 + 0.01, 2000.0)
    pre = preintegrate(stamps, gyro, f, t0, t1)
    T1, v1 = pre.predict(pose(t0), velocity(t0), G_WORLD)
    truth = pose(t1)
    assert np.linalg.norm(T1[:3, 3] - truth[:3, 3]) < 2e-3
    assert rotation_angle(T1[:3, :3].T @ truth[:3, :3]) < 1e-6  # constant rate: exact
    assert np.linalg.norm(v1 - velocity(t1)) < 5e-3
    v0 = pre.velocity_at_start(pose(t0), truth, G_WORLD)  # inverts the position equation
    assert np.linalg.norm(v0 - velocity(t0)) < 5e-3


def test_biases_are_removed():
    t0, t1 = 0.0, 0.5
    stamps, gyro, f = samples(t0, t1, 1000.0)
    bg, ba = np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.05, -0.2])
    clean = preintegrate(stamps, gyro, f, t0, t1)
    biased = preintegrate(stamps, gyro + bg, f + ba, t0, t1, gyro_bias=bg, accel_bias=ba)
    np.testing.assert_allclose(biased.delta_rot, clean.delta_rot, atol=1e-12)
    np.testing.assert_allclose(biased.delta_p, clean.delta_p, atol=1e-12)


def test_partial_intervals_hold_the_last_sample():
    stamps = np.array([0.0, 0.1])
    gyro = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])
    pre = preintegrate(stamps, gyro, np.zeros((2, 3)), 0.05, 0.25)
    # 0.05 s at 1 rad/s, then 0.15 s at 2 rad/s (the last sample holds past its stamp)
    assert rotation_angle(pre.delta_rot) == pytest.approx(0.05 + 0.3)


def test_gravity_from_static_and_bad_input():
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    at_rest = np.tile(R.T @ -G_WORLD, (10, 1))  # specific force in the IMU frame
    np.testing.assert_allclose(gravity_from_static(at_rest, R), G_WORLD, atol=1e-9)
    with pytest.raises(InputError, match="m/s"):
        gravity_from_static(np.zeros((3, 3)), np.eye(3))
    with pytest.raises(InputError, match="finite"):
        preintegrate([0.0], [[np.nan, 0, 0]], [[0, 0, 9.8]], 0.0, 0.1)
    with pytest.raises(InputError, match="N stamps"):
        preintegrate([], np.zeros((0, 3)), np.zeros((0, 3)), 0.0, 0.1)
