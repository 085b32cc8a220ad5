"""`odometry --result-mcap`, end to end on the tiny room log (cpu)."""

import numpy as np
import pytest
from support.foxglove_check import cloud_array, read_result

localize_world = pytest.importorskip("support.localize_world")

SCANS = 8


def test_odometry_result_mcap_holds_every_channel(tmp_path, ti_runtime):
    from typer.testing import CliRunner

    from mcl3d.cli import app
    from mcl3d.io.trajectory import read_tum

    localize_world.write_log(tmp_path / "room.mcap", SCANS, odom=False)
    path = tmp_path / "result.mcap"
    r = CliRunner().invoke(app, ["odometry", str(tmp_path / "room.mcap"), "-o",
                                 str(tmp_path / "out"), "--backend", "cpu", "--result-mcap",
                                 str(path)])
    assert r.exit_code == 0, r.output
    msgs = read_result(path)  # every channel foxglove.*, every message decoded
    assert set(msgs) >= {"/map", "/scan", "/tf", "/estimate", "/keyframes", "/ground_truth",
                         "/stats"}
    for topic in ("/scan", "/tf", "/estimate", "/stats"):
        assert len(msgs[topic]) == SCANS, topic
    est = msgs["/estimate"][-1].pose.position
    last = read_tum(tmp_path / "out" / "odometry.tum").poses[-1]
    np.testing.assert_allclose([est.x, est.y, est.z], last[:3, 3], atol=1e-6)
    assert len(msgs["/keyframes"][-1].poses) >= 1
    # the ground truth is tied to the run's frame at the first scan: the drift stays small
    errors = [{j.name: j.position for j in m.joints}.get("error_m") for m in msgs["/stats"]]
    assert max(e for e in errors if e is not None) < 0.1
    assert len(cloud_array(msgs["/map"][0])["x"]) > 500  # the keyframe scans
