"""Which keyframes a scan is registered against: those that hold the scan, not the nearest.

With a cropped (front-half) view, a keyframe next to the sensor that looked the other way
holds none of the scan, while one several metres ahead looking back holds most of it (the
paper-forest U-turns, where choosing by distance slipped 6° of yaw in one scan)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.geometry import se3, so3_exp, transform_points


@pytest.fixture(scope="module")
def odometry(backend):
    from mcl3d.core import runtime
    from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig

    runtime.init(backend)
    cfg = OdometryConfig(voxel_size_m=0.2, map_voxel_size_m=0.5, max_keyframes=4,
                         registration_keyframes=2, buckets_per_map=1 << 13, max_points=4096)
    return LidarOdometry(cfg)


def front_view(rng, T_world_lidar, world):
    """The world points within 10 m in front (+x) of the sensor, in its frame."""
    local = transform_points(np.linalg.inv(T_world_lidar), world)
    keep = (local[:, 0] > 0) & (np.linalg.norm(local, axis=1) < 10)
    return local[keep]


def test_keyframes_that_hold_the_scan_win_over_nearer_ones(odometry):
    rng = np.random.default_rng(3)
    world = rng.uniform([-12, -5, -1], [22, 5, 2], (8000, 3))
    facing_back = so3_exp([0.0, 0.0, np.pi])
    poses = {"here": se3(np.eye(3), [0.0, 0, 0]),          # saw x 0..10: the scan's view
             "beside, back": se3(facing_back, [0.5, 0, 0]),  # saw x -9.5..0.5
             "ahead, back": se3(facing_back, [10.0, 0, 0]),  # saw x 0..10 from the far end
             "far, back": se3(facing_back, [-6.0, 0, 0])}    # saw x -16..-6
    odometry.reset()
    g = odometry.gicp
    for T in poses.values():
        g.set_source(*_with_covs(front_view(rng, T, world)))
        odometry._insert_keyframe(T)
    T_scan = se3(np.eye(3), [0.3, 0.0, 0.0])
    g.set_source(*_with_covs(front_view(rng, T_scan, world)))
    chosen = {int(slot) for slot, *_ in odometry._registration_keyframes(T_scan)}
    names = list(poses)
    assert {names[s] for s in chosen} == {"here", "ahead, back"}
    # by distance alone the keyframe beside the sensor, facing away, would have been taken
    d = [np.linalg.norm(T[:3, 3] - T_scan[:3, 3]) for T in poses.values()]
    assert {names[i] for i in np.argsort(d)[:2]} == {"here", "beside, back"}


def _with_covs(points):
    return points, np.tile(np.eye(3), (len(points), 1, 1))
