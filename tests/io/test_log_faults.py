"""Faults inside a recording (issue #22): repeated and backwards stamps, NaN/inf messages and
empty scans are dropped where the log is read, counted by kind with their first stamps, and
counted once however many passes read them."""

from __future__ import annotations

import numpy as np

from mcl3d.io.logs.faults import format_stamp
from mcl3d.io.logs.messages import Imu, Odometry, PointCloud, PoseStamped
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import LogWriter

T0 = 1_317_000_015_000_000_000
PERIOD = 100_000_000


def _faulty_log(path):
    """Ten scans with one published twice, one stamped 0.25 s back (received in order), one
    empty; IMU with three NaN samples and one going back; NaN odometry and ground truth."""
    rng = np.random.default_rng(0)
    with LogWriter(path) as w:
        for k in range(10):
            stamp = T0 + k * PERIOD
            pts = rng.normal(size=(50, 3)).astype(np.float32) * 10
            cloud = PointCloud(stamp - (250_000_000 if k == 6 else 0), "lidar",
                               pts[:0] if k == 8 else pts, None)
            w.write_points("/lidar/points", cloud, log_ns=stamp)
            if k == 3:
                w.write_points("/lidar/points", cloud, log_ns=stamp + 1)
            for j in range(5):
                gyro = np.full(3, np.nan) if k == 4 and j < 3 else rng.normal(size=3)
                back = k == 5 and j == 2
                w.write_imu("/imu/data", Imu(stamp + j * 20_000_000 - back * 30_000_000, "imu",
                                             gyro, rng.normal(size=3)),
                            log_ns=stamp + j * 20_000_000)
            T = np.eye(4)
            T[0, 3] = np.inf if k == 2 else k
            w.write_odometry("/odom", Odometry(stamp, "odom", "base_link", T, np.zeros(6),
                                               np.eye(6)))
            T = np.eye(4)
            T[1, 3] = np.nan if k == 7 else k
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", T))


def test_faulty_messages_are_dropped_and_counted_once(tmp_path):
    path = tmp_path / "faults.mcap"
    _faulty_log(path)
    with LogReader(path) as reader:
        for _ in range(2):  # a second pass finds the same faults: counted once
            got: dict[str, list[int]] = {"points": [], "imu": [], "odom": [], "gt": []}
            for kind, msg in reader.messages():
                got[kind].append(msg.stamp_ns)
        gt_stamps, _ = reader.ground_truth()
        faults = reader.faults.as_dict()
        warnings = reader.faults.warnings()
    scans = [T0 + k * PERIOD for k in range(10) if k not in (6, 8)]
    assert got["points"] == scans
    assert len(got["imu"]) == 50 - 3 - 1 and got["imu"] == sorted(set(got["imu"]))
    assert len(got["odom"]) == 9 and len(got["gt"]) == 9 and len(gt_stamps) == 9
    assert {k: v["count"] for k, v in faults.items()} == {
        "scan_repeated_stamp": 1, "scan_stamp_back": 1, "scan_empty": 1, "imu_not_finite": 3,
        "imu_stamp_back": 1, "odometry_not_finite": 1, "ground_truth_not_finite": 1}
    assert faults["scan_stamp_back"]["first_stamps_ns"] == [T0 + 6 * PERIOD - 250_000_000]
    assert faults["imu_not_finite"]["first_stamps_ns"] == [T0 + 4 * PERIOD + j * 20_000_000
                                                           for j in range(3)]
    assert len(warnings) == 7
    assert "1 scan dropped with the same stamp as the previous one (at 1317000015.300000000 s)" \
        in warnings


def test_stamps_are_formatted_exactly():
    assert format_stamp(1_317_000_015_300_000_000) == "1317000015.300000000"
    assert format_stamp(5) == "0.000000005" and format_stamp(-1_500_000_000) == "-1.500000000"


def test_a_clean_log_has_no_faults(tmp_path):
    path = tmp_path / "clean.mcap"
    with LogWriter(path) as w:
        for k in range(3):
            w.write_points("/lidar/points", PointCloud(T0 + k * PERIOD, "lidar",
                                                       np.ones((4, 3), np.float32), None))
    with LogReader(path) as reader:
        assert len(list(reader.scans())) == 3
        assert reader.faults.as_dict() == {} and reader.faults.warnings() == []
