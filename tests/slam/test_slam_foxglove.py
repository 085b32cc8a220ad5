"""`slam --result-mcap`, end to end on the tiny room log (cpu)."""

import csv

import numpy as np
import pytest
from support.foxglove_check import cloud_array, read_result

localize_world = pytest.importorskip("support.localize_world")

SCANS = 8
PARTICLES = 40


def test_slam_result_mcap_holds_every_channel(tmp_path, ti_runtime):
    from typer.testing import CliRunner

    from mcl3d.cli import app

    localize_world.write_log(tmp_path / "room.mcap", SCANS, odom=False)
    path, out = tmp_path / "result.mcap", tmp_path / "out"
    r = CliRunner().invoke(app, ["slam", str(tmp_path / "room.mcap"), "-o", str(out),
                                 "--particles", str(PARTICLES), "--seed", "1", "--backend",
                                 "cpu", "--result-mcap", str(path)])
    assert r.exit_code == 0, r.output
    msgs = read_result(path)  # every channel foxglove.*, every message decoded
    assert set(msgs) >= {"/map", "/scan", "/tf", "/estimate", "/estimate/covariance",
                         "/particles", "/hypotheses", "/keyframes", "/trajectories",
                         "/ground_truth", "/stats"}
    for topic in ("/scan", "/tf", "/estimate", "/particles", "/stats", "/hypotheses"):
        assert len(msgs[topic]) == SCANS, topic
    with open(out / "frames.csv") as f:
        last = list(csv.DictReader(f))[-1]
    est = msgs["/estimate"][-1].pose.position
    np.testing.assert_allclose([est.x, est.y, est.z],
                               [float(last[k]) for k in ("x", "y", "z")], atol=1e-4)
    particles = cloud_array(msgs["/particles"][-1])
    assert len(particles["x"]) == PARTICLES and particles["weight"].max() == pytest.approx(1.0)
    stats = {j.name: j.position for j in msgs["/stats"][-1].joints}
    assert stats["ess"] == pytest.approx(float(last["ess"]), rel=1e-3)
    keyframes = int(last["keyframes"])
    assert stats["keyframes"] == keyframes == len(msgs["/keyframes"][-1].poses)
    paths = msgs["/trajectories"][-1].entities  # one per hypothesis, ending at its particle
    assert len(paths) >= 1 and len(paths[0].lines[0].points) == keyframes + 1
    assert len(cloud_array(msgs["/map"][0])["x"]) > 500


def test_each_loop_is_published_once(tmp_path):
    """/loops adds each scan's loops to the scene (no deletion, an entity per loop scan), so
    a long run's result grows by its loops, not by their square."""
    from test_frame_store import random_frame

    from mcl3d.io.foxglove_results import ResultPublisher
    from mcl3d.slam.result_view import SlamView

    rng = np.random.default_rng(1)
    frames = [random_frame(rng, i) for i in range(25)]  # loops on scans 3, 10, 17, 24
    path = tmp_path / "result.mcap"
    with ResultPublisher(path, name="test") as pub:
        view = SlamView(pub)
        for frame in frames:
            view.publish_loops(frame)
    loop_frames = [f for f in frames if f.loop_keyframes]
    published = read_result(path)["/loops"]
    assert len(published) == len(loop_frames) == 4
    for n, (msg, frame) in enumerate(zip(published, loop_frames, strict=True)):
        assert not msg.deletions and [e.id for e in msg.entities] == [f"loop {n}"]
        points = msg.entities[0].lines[0].points
        assert len(points) == 2 * len(frame.loop_keyframes)  # this scan's loops only
        for k, T_rel in enumerate(frame.loop_relative):  # pose -> its loop keyframe
            start, end = points[2 * k], points[2 * k + 1]
            np.testing.assert_allclose([start.x, start.y, start.z],
                                       frame.T_world_lidar[:3, 3], atol=1e-9)
            T_kf = frame.T_world_lidar @ np.linalg.inv(T_rel)
            np.testing.assert_allclose([end.x, end.y, end.z], T_kf[:3, 3], atol=1e-9)
