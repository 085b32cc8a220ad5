"""Faults real recorders produce (issue #22), injected into a short simulated log: a scan
published twice, a scan stamped 0.25 s back, 20 NaN IMU samples, NaN odometry and ground
truth. `odometry` and `slam` run to the end, write everything and count the faults."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from mcl3d.cli import app

DUPLICATED, BACK = 5, 12  # scan indices
NAN_IMU = range(40, 60)  # IMU sample indices
NAN_ODOM, NAN_GT = (3, 17), (8, 21)


@pytest.fixture(scope="module")
def faulty_log(tmp_path_factory):
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.logs.writer import LogWriter
    from mcl3d.sim.pipeline import TOPICS, SimulateRequest, run

    d = tmp_path_factory.mktemp("faults")
    clean, faulty = d / "clean.mcap", d / "faulty.mcap"
    run(SimulateRequest(world="office", sensor="vlp16", trajectory="ground", duration_s=5.0,
                        seed=3, output=clean))
    with LogReader(clean) as reader, LogWriter(faulty) as w:
        w.write_tf(TOPICS["tf_static"], reader.static_transforms())
        counts = dict.fromkeys(("points", "imu", "odom", "gt"), 0)
        for kind, msg in reader.messages():
            k, counts[kind] = counts[kind], counts[kind] + 1
            _write_with_faults(w, kind, k, msg)
    return faulty


def _write_with_faults(w, kind: str, k: int, msg) -> None:
    from mcl3d.sim.pipeline import TOPICS

    received = msg.stamp_ns
    if kind == "points":
        if k == BACK:
            msg.stamp_ns -= 250_000_000
        w.write_points(TOPICS["points"], msg, log_ns=received)
        if k == DUPLICATED:
            w.write_points(TOPICS["points"], msg, log_ns=received + 1)
    elif kind == "imu":
        if k in NAN_IMU:
            msg.angular_velocity = np.full(3, np.nan)
        w.write_imu(TOPICS["imu"], msg)
    elif kind == "odom":
        if k in NAN_ODOM:
            msg.T_frame_child = np.full((4, 4), np.nan)
        w.write_odometry(TOPICS["odom"], msg)
    else:
        if k in NAN_GT:
            msg.T = np.full((4, 4), np.nan)
        w.write_pose(TOPICS["gt"], msg)


def test_odometry_survives_recorder_faults(faulty_log, tmp_path, ti_runtime):
    from mcl3d.io.trajectory import read_tum

    out = tmp_path / "odo"
    result = CliRunner().invoke(app, ["odometry", str(faulty_log), "-o", str(out),
                                      "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    assert "20 IMU samples dropped with NaN or inf" in result.output
    assert "1 scan dropped with a stamp before the previous one" in result.output
    assert len(read_tum(out / "odometry.tum")) == 49  # 50 scans, one stamped back
    summary = json.loads((out / "odometry_summary.json").read_text())
    assert summary["scans"] == 49
    assert {k: v["count"] for k, v in summary["faults"].items()} == {
        "scan_repeated_stamp": 1, "scan_stamp_back": 1, "imu_not_finite": 20,
        "ground_truth_not_finite": 2}
    assert summary["evaluation"]["ate"]["translation_m"]["rmse"] < 0.05


def test_slam_survives_recorder_faults(faulty_log, tmp_path, ti_runtime):
    out = tmp_path / "slam"
    result = CliRunner().invoke(app, ["slam", str(faulty_log), "-o", str(out), "--particles",
                                      "100", "--max-scans", "15", "--seed", "1",
                                      "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    assert "1 scan dropped with the same stamp as the previous one" in result.output
    summary = json.loads((out / "slam_summary.json").read_text())
    assert summary["scans"] == 15
    assert summary["faults"]["scan_repeated_stamp"]["count"] == 1
    assert summary["faults"]["scan_stamp_back"]["count"] == 1
    assert len((out / "frames.csv").read_text().splitlines()) == 16
