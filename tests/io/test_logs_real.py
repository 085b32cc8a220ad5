"""The real ROS 1-encoded Ouster OS1-64 MCAP (ouster_os1_64_mcap, MIT licence)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.io.logs.reader import LogReader


@pytest.fixture
def ouster_mcap(shared_data):
    return shared_data / "ouster_os1_64_mcap" / "test.mcap"


def test_ouster_clouds_decode_with_valid_points_and_range(ouster_mcap):
    with LogReader(ouster_mcap) as r:
        assert r.topics.points == "/os1_cloud_node/points"
        assert r.count("points") == 2
        scans = list(r.scans())
    assert len(scans) == 2
    for scan in scans:
        assert (scan.height, scan.width, scan.frame_id) == (64, 2048, "os1_lidar")
        assert 45_000 < len(scan) < 46_500  # about 45.7k valid (non-zero) returns
        assert len(scan) + scan.n_dropped == 64 * 2048
        assert set(scan.fields) == {"intensity", "reflectivity", "ring", "noise", "range"}
        assert scan.fields["ring"].min() == 0 and scan.fields["ring"].max() == 63
        range_m = scan.fields["range"].astype(np.float64) * 1e-3  # uint32 millimetres
        assert range_m.min() > 0
        assert 1.3 < np.median(range_m) < 1.7 and 14.0 < range_m.max() < 15.0
        # the points are the ranges in the lidar frame: |p| matches the range field
        np.testing.assert_allclose(np.linalg.norm(scan.points, axis=1), range_m, atol=1e-4)
        # per-point `t` is uint32 ns since the scan start: within one 10 Hz sweep
        assert scan.times_s.min() >= 0 and 0.09 < scan.times_s.max() < 0.1
    assert scans[1].stamp_ns - scans[0].stamp_ns == pytest.approx(0.1e9, rel=0.05)


def test_ouster_imu_and_static_transforms(ouster_mcap):
    with LogReader(ouster_mcap) as r:
        assert r.topics.imu == "/os1_cloud_node/imu" and r.count("imu") == 17
        imus = [m for _k, m in r.messages(("imu",))]
        frames = {(t.parent_frame, t.child_frame) for t in r.static_transforms()}
        T_lidar_imu = r.static_transform("os1_lidar", "os1_imu")
    assert len(imus) == 17 and all(m.frame_id == "os1_imu" for m in imus)
    gravity = np.median([np.linalg.norm(m.linear_acceleration) for m in imus])
    assert 9.0 < gravity < 10.5
    assert frames == {("os1_sensor", "os1_imu"), ("os1_sensor", "os1_lidar")}
    # lidar is rotated 180 deg about z and 36.18 mm above the sensor origin
    np.testing.assert_allclose(T_lidar_imu[:3, 3], [-0.006253, 0.011775, 0.007645 - 0.03618],
                               atol=1e-9)
    np.testing.assert_allclose(T_lidar_imu[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)


def test_ouster_messages_stream_in_log_time_order(ouster_mcap):
    with LogReader(ouster_mcap) as r:
        kinds = [k for k, _m in r.messages(("points", "imu"))]
    assert kinds.count("points") == 2 and kinds.count("imu") == 17
