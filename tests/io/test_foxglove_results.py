"""The Foxglove result publisher: every channel decodes with the SDK's schemas and holds what
was published; the file is all or nothing; the live server advertises the channels to a
WebSocket client and sends the map to a client that subscribes late."""

import base64
import json
import time

import numpy as np
import pytest
from support.foxglove_check import cloud_array, decode, read_result

from mcl3d.core import geometry
from mcl3d.core.errors import Mcl3dError, RunInterrupted
from mcl3d.io.foxglove_messages import ELLIPSOID_SIGMA
from mcl3d.io.foxglove_results import (
    CHANNELS,
    MAX_PARTICLES,
    ResultPublisher,
    StartAligned,
    nearest_pose,
    open_results,
)

STAMP = 1_700_000_000_250_000_000


def pose(x, y, yaw):
    return geometry.se3(geometry.rpy_to_rot(0.0, 0.0, yaw), np.array([x, y, 0.5]))


def publish_everything(pub: ResultPublisher) -> None:
    rng = np.random.default_rng(0)
    T = pose(1.0, 2.0, 0.3)
    cov = np.diag([1e-4, 1e-4, 4e-4, 0.04, 0.01, 0.0025])
    pub.publish_map(STAMP, rng.uniform(-5, 5, (500, 3)))
    pub.publish_estimate(STAMP, T, cov, rng.uniform(-5, 5, (300, 3)))
    pub.publish_particles(STAMP, rng.uniform(-5, 5, (12_000, 3)), rng.uniform(0, 2, 12_000))
    pub.publish_hypotheses(STAMP, [(pose(4.0, 1.0, 2.0), cov, 0.3)])
    pub.publish_ground_truth(STAMP, pose(1.1, 2.0, 0.3))
    pub.publish_stats(STAMP, {"ess": 812.5, "error_m": None, "hypotheses": 2})
    pub.log(STAMP, "warning", "motion source dropped")
    pub.publish_keyframes(STAMP, np.stack([pose(0, 0, 0), pose(1, 0, 0), T]))
    pub.publish_loops(STAMP, np.array([[[1.0, 2.0, 0.5], [0.0, 0.0, 0.5]]]))
    pub.publish_trajectories(STAMP, [np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0.5]]),
                                     np.array([[0, 0, 0], [4, 1, 0.5]])])


def test_every_channel_decodes_with_the_sdk_schemas(tmp_path):
    path = tmp_path / "result.mcap"
    with ResultPublisher(path, name="test") as pub:
        publish_everything(pub)
    msgs = read_result(path)  # asserts foxglove.* protobuf schemas on every channel
    assert set(msgs) == set(CHANNELS)
    est = msgs["/estimate"][0]
    assert est.frame_id == "map" and est.timestamp.seconds == STAMP // 10**9
    assert est.timestamp.nanos == 250_000_000
    assert est.pose.position.x == pytest.approx(1.0) and est.pose.position.z == 0.5
    assert est.pose.orientation.z == pytest.approx(np.sin(0.15))
    tf = msgs["/tf"][0].transforms[0]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("map", "lidar")
    scan = msgs["/scan"][0]  # lidar-frame points, placed in the map by the cloud's pose
    assert len(cloud_array(scan)["x"]) == 300 and scan.frame_id == "map"
    assert scan.pose.position.y == pytest.approx(2.0)
    particles = cloud_array(msgs["/particles"][0])
    assert len(particles["x"]) == MAX_PARTICLES
    assert particles["weight"].max() <= 1.0 and particles["weight"].min() >= 0.0
    sphere = msgs["/estimate/covariance"][0].entities[0].spheres[0]
    # 2 sigma semi-axes: the largest is along x (0.2 m std), turned with the pose
    assert max(sphere.size.x, sphere.size.y, sphere.size.z) == pytest.approx(
        2 * ELLIPSOID_SIGMA * 0.2)
    hyp = msgs["/hypotheses"][0].entities[0]
    assert hyp.texts[0].text == "30%" and hyp.arrows[0].pose.position.x == pytest.approx(4.0)
    stats = {j.name: j.position for j in msgs["/stats"][0].joints}
    assert stats == {"ess": 812.5, "hypotheses": 2.0}  # None left out
    log = msgs["/log"][0]
    assert log.message == "motion source dropped" and log.level == 3  # WARNING
    assert len(msgs["/keyframes"][0].poses) == 3
    assert len(msgs["/loops"][0].entities[0].lines[0].points) == 2
    assert len(msgs["/trajectories"][0].entities) == 2
    assert len(cloud_array(msgs["/map"][0])["z"]) == 500


def test_file_is_all_or_nothing(tmp_path):
    path = tmp_path / "result.mcap"
    with pytest.raises(ValueError), ResultPublisher(path) as pub:
        pub.publish_ground_truth(STAMP, np.eye(4))
        raise ValueError("the run failed")
    assert not path.exists() and not list(tmp_path.iterdir())
    with pytest.raises(RunInterrupted), ResultPublisher(path) as pub:  # Ctrl-C keeps it
        pub.publish_ground_truth(STAMP, np.eye(4))
        raise RunInterrupted("interrupted")
    assert len(read_result(path)["/ground_truth"]) == 1
    with pytest.raises(Mcl3dError, match="already exists"):
        ResultPublisher(path)
    with open_results(None, None, False, "test") as nothing:
        assert nothing is None


def test_ground_truth_helpers():
    stamps = np.array([0, 100, 200], np.int64)
    poses = np.stack([pose(i, 0, 0) for i in range(3)])
    assert nearest_pose(stamps, poses, 140)[0, 3] == 1.0
    assert nearest_pose(stamps, poses, 160)[0, 3] == 2.0
    assert nearest_pose(stamps, poses, 10**9) is None
    align = StartAligned()
    T_run0 = pose(0, 0, 0)
    np.testing.assert_allclose(align(T_run0, pose(5, 5, 1.0)), T_run0, atol=1e-12)
    moved = align(T_run0, pose(5, 5, 1.0) @ pose(1, 0, 0))
    np.testing.assert_allclose(moved[:3, 3], [1.0, 0.0, 1.0], atol=1e-12)  # z: 0.5 + 0.5


def test_live_server_advertises_channels_and_resends_the_map():
    from websockets.sync.client import connect

    with ResultPublisher(None, 0, name="test") as pub:
        publish_everything(pub)
        url = f"ws://127.0.0.1:{pub.server.port}"
        with connect(url, subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo" and info["name"] == "mcl3d test"
            channels = {}
            while len(channels) < len(CHANNELS):
                msg = json.loads(ws.recv(timeout=10))
                assert msg["op"] == "advertise"
                channels.update({c["topic"]: c for c in msg["channels"]})
            assert set(channels) == set(CHANNELS)
            for c in channels.values():
                assert c["schemaName"].startswith("foxglove.") and c["encoding"] == "protobuf"
                assert base64.b64decode(c["schema"])  # a FileDescriptorSet
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 7, "channelId": channels["/map"]["id"]}]}))
            deadline = time.monotonic() + 10
            while not pub._requests.pending.is_set() and time.monotonic() < deadline:
                time.sleep(0.01)
            pub.publish_estimate(STAMP + 1, np.eye(4))  # the next update resends the map
            frame = ws.recv(timeout=10)
    # MessageData: opcode 1, subscription id, log time, then the map cloud itself
    assert isinstance(frame, bytes) and frame[0] == 1
    assert int.from_bytes(frame[1:5], "little") == 7
    assert int.from_bytes(frame[5:13], "little") == STAMP + 1
    cloud = decode("foxglove.PointCloud", base64.b64decode(channels["/map"]["schema"]),
                   frame[13:])
    assert len(cloud_array(cloud)["x"]) == 500


def test_busy_port_is_one_clear_error():
    with ResultPublisher(None, 0) as first, pytest.raises(Mcl3dError) as err:
        ResultPublisher(None, first.server.port).__enter__()
    assert err.value.setting == "live_port" and "choose a free port" in str(err.value)


def test_layout_shows_our_channels():
    import re
    from pathlib import Path

    layout = json.loads((Path(__file__).parents[2] / "docs" / "foxglove-layout.json").read_text())
    panels = layout["configById"]
    three_d = next(v for k, v in panels.items() if k.startswith("3D!"))
    assert set(three_d["topics"]) <= set(CHANNELS) and "/particles" in three_d["topics"]
    assert three_d["topics"]["/particles"]["colorField"] == "weight"
    plotted = [p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]]
    assert {re.match(r"(/\w+)\.", p).group(1) for p in plotted} == {"/stats"}
    assert next(v for k, v in panels.items() if k.startswith("RosOut!"))["topicToRender"] == "/log"
    ids = re.findall(r'"(\w+![\w]+)"', json.dumps(layout["layout"]))
    assert sorted(ids) == sorted(panels)


def test_live_without_a_subscriber_builds_no_message(monkeypatch):
    from mcl3d.io import foxglove_messages

    def no_build(*args, **kwargs):
        raise AssertionError("a message was built for nobody")

    monkeypatch.setattr(foxglove_messages, "point_cloud", no_build)
    with ResultPublisher(None, 0) as pub:
        pub.publish_particles(STAMP, np.zeros((10, 3)), np.ones(10))
        pub.publish_estimate(STAMP, np.eye(4), None, np.zeros((10, 3)))
    assert set(pub._channels) == {"/particles", "/tf", "/estimate", "/scan"}  # advertised
