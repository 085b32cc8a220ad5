"""Deskewing again with the registered motion (LidarOdometry._redeskew): a sensor nodding in
pitch faster than constant velocity predicts is tracked closer than with the predicted motion
alone, and a steady sensor is not registered twice."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.geometry import se3, so3_exp, so3_log

SWEEP_S = 0.1  # a 10 Hz spinning lidar, stamped at the sweep's start
HALF_ROOM = np.array([6.13, 3.37, 1.61])  # faces off the voxel grid


def room_points(rng, n):
    """`n` points on the inside of a box room (the world frame)."""
    p = rng.uniform(-HALF_ROOM, HALF_ROOM, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * HALF_ROOM[axis]
    return p


def motion(t, nod_deg, nod_hz):
    """Pitch (rad) and position of a sensor walking along x at 0.8 m/s and nodding."""
    t = np.asarray(t, np.float64)
    pitch = np.radians(nod_deg) * np.sin(2 * np.pi * nod_hz * t)
    position = np.stack([-2.0 + 0.8 * t, np.zeros_like(t), np.zeros_like(t)], axis=-1)
    return pitch, position


def pose_at(t, nod_deg, nod_hz):
    """T_world_lidar at time `t` (s)."""
    pitch, position = motion(t, nod_deg, nod_hz)
    return se3(so3_exp([0.0, float(pitch), 0.0]), position)


def sweep(rng, stamp_s, nod_deg, nod_hz, n=4000):
    """One sweep: each point seen at the time the beam passes its azimuth, from the pose of
    that moment (lidar frame), and its time after the stamp."""
    world = room_points(rng, n)
    centre = pose_at(stamp_s, nod_deg, nod_hz)[:3, 3]
    azimuth = np.arctan2(world[:, 1] - centre[1], world[:, 0] - centre[0])
    times = (azimuth + np.pi) / (2 * np.pi) * SWEEP_S
    pitch, position = motion(stamp_s + times, nod_deg, nod_hz)
    d = world - position  # rotate by -pitch about y: R_y(pitch)^T d
    c, s = np.cos(pitch), np.sin(pitch)
    points = np.stack([c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]], axis=1)
    return points, times


def run(odometry, nod_deg, nod_hz, scans=12):
    """(median rotation error in degrees of the stamps' poses relative to the second scan's,
    the scans deskewed again). Relative: the first scan, not deskewed, fixes the world frame
    only to within its sweep's nod."""
    rng = np.random.default_rng(4)
    poses, truth, again = [], [], []
    for k in range(scans):
        points, times = sweep(rng, k * SWEEP_S, nod_deg, nod_hz)
        frame = odometry.step(points, times, k * 100_000_000)
        poses.append(frame.T_world_lidar)
        truth.append(pose_at(k * SWEEP_S, nod_deg, nod_hz))
        if frame.redeskewed:
            again.append(k)
    errors = []
    for k in range(2, scans):
        est = (np.linalg.inv(poses[1]) @ poses[k])[:3, :3]
        true = (np.linalg.inv(truth[1]) @ truth[k])[:3, :3]
        errors.append(np.degrees(np.linalg.norm(so3_log(true.T @ est))))
    return float(np.median(errors)), again


@pytest.fixture(scope="module")
def make_odometry(backend):
    from mcl3d.core import runtime
    from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig

    runtime.init(backend)

    def make(**overrides):
        return LidarOdometry(OdometryConfig(
            use_imu=False, voxel_size_m=0.2, map_voxel_size_m=0.5, max_keyframes=3,
            buckets_per_map=1 << 13, max_points=4096, **overrides))
    return make


def test_nodding_sensor_is_tracked_closer_when_deskewed_again(make_odometry):
    off, off_again = run(make_odometry(redeskew_rotation_deg=1e9, redeskew_translation_m=1e9),
                         nod_deg=2.0, nod_hz=2.0)
    on, on_again = run(make_odometry(), nod_deg=2.0, nod_hz=2.0)
    assert off_again == [] and len(on_again) >= 6
    assert on < 0.5 * off, (on, off)


def test_steady_sensor_is_registered_once(make_odometry):
    _, again = run(make_odometry(), nod_deg=0.0, nod_hz=2.0)
    assert again == []


def test_the_second_scan_is_not_deskewed_again(make_odometry):
    """Its map is the first scan, skewed by a motion not known then: the second, deskewed with
    the registered motion, would match it worse than left skewed alike."""
    _, again = run(make_odometry(), nod_deg=2.0, nod_hz=2.0, scans=3)
    assert 1 not in again
