"""`mcl3d info` end to end (subprocess, as a user runs it) and bad input as a new user tries it.

Real data: ouster_os1_64_mcap (MIT licence).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mcl3d.core.errors import LogFormatError, PointCloudError, TopicError
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.messages import Imu, PointCloud, PoseStamped
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import LogWriter

T0 = 1_700_000_000_000_000_000
POINTFIELD_TYPES = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32",
                    7: "float32", 8: "float64"}  # sensor_msgs/PointField constants


def mcl3d(*args: str, cwd=None, columns: str | None = "200") -> subprocess.CompletedProcess:
    env = {"PATH": ""} if columns is None else {"COLUMNS": columns, "PATH": ""}
    return subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=120)


def info_json(*args: str) -> dict:
    """`mcl3d info --json`: exit 0, and stdout is exactly one JSON document."""
    result = mcl3d("info", *args, "--json")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def mcap_summary(path) -> tuple[dict[str, tuple[str, int]], int, int]:
    """Topic -> (schema name, message count), start and end ns, from the mcap library alone."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    stats = summary.statistics
    topics: dict[str, tuple[str, int]] = {}
    for c in summary.channels.values():  # a topic may have several channels
        count = topics.get(c.topic, ("", 0))[1] + stats.channel_message_counts.get(c.id, 0)
        topics[c.topic] = (summary.schemas[c.schema_id].name, count)
    return topics, stats.message_start_time, stats.message_end_time


def assert_one_line_error(result: subprocess.CompletedProcess, *words: str) -> None:
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    for word in words:
        assert word in lines[0], lines[0]


def cloud(stamp: int, n: int = 20) -> PointCloud:
    points = np.arange(3 * n, dtype=np.float32).reshape(n, 3) + 1
    return PointCloud(stamp, "lidar", points, np.linspace(0, 0.1, n, dtype=np.float32),
                      {"ring": np.arange(n, dtype=np.uint16)})


def imu(stamp: int) -> Imu:
    return Imu(stamp, "imu", np.zeros(3), np.array([0.0, 0.0, 9.81]))


@pytest.fixture
def small_log(tmp_path):
    path = tmp_path / "small.mcap"
    with LogWriter(path) as w:
        for k in range(5):
            stamp = T0 + k * 100_000_000
            w.write_points("/lidar/points", cloud(stamp))
            w.write_imu("/imu/data", imu(stamp))
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", np.eye(4)))
    return path


def test_info_on_the_real_ouster_mcap(shared_data):
    result = mcl3d("info", shared_data / "ouster_os1_64_mcap" / "test.mcap")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "MCAP (ros1)" in out and "0.183 s" in out
    assert "2020-06-22T13:40:42.605Z" in out
    row = next(line for line in out.splitlines() if "/os1_cloud_node/points " in line)
    assert "sensor_msgs/PointCloud2" in row and " 2 " in row and "os1_lidar" in row
    row = next(line for line in out.splitlines() if "/os1_cloud_node/imu " in line)
    assert "sensor_msgs/Imu" in row and " 17 " in row and "os1_imu" in row
    assert "organized 64 x 2048" in out
    assert "t:uint32" in out and "ring:uint8" in out and "range:uint32" in out
    assert "min 45716, mean 45762, max 45809" in out
    assert "first 2 scans decoded" in out


def test_info_on_a_written_log(small_log):
    result = mcl3d("info", small_log)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "MCAP (ros2)" in out and "mcl3d" in out and "0.400 s" in out
    row = next(line for line in out.splitlines() if "/lidar/points " in line)
    assert " 5 " in row and "10.0" in row and "lidar" in row
    assert "unorganized, 20 points" in out and "first 3 scans decoded" in out
    assert "field 't'" in out
    gt = next(line for line in out.splitlines() if line.strip("│ ").startswith("gt "))
    assert "/ground_truth" in gt


def test_info_on_a_ros2_bag_folder(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = rt.ros2_typestore()
    with Writer(tmp_path / "bag", version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        c = w.add_connection("/points", rt.POINTCLOUD2, typestore=store)
        for k in range(3):
            msg = rt.from_pointcloud(store, cloud(T0 + k * 10**8), "test")
            w.write(c, T0 + k * 10**8, store.serialize_cdr(msg, rt.POINTCLOUD2))
    result = mcl3d("info", tmp_path / "bag")
    assert result.returncode == 0, result.stderr
    assert "ROS 2 bag folder (sqlite3)" in result.stdout
    assert "unorganized, 20 points" in result.stdout


def first_cloud(path, topic: str):
    """The first message of a cloud topic, decoded by the mcap and rosbags libraries alone."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    with open(path, "rb") as f:
        _schema, _channel, message = next(make_reader(f).iter_messages(topics=[topic]))
    return get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(message.data,
                                                             "sensor_msgs/msg/PointCloud2")


def _same_type(mcap_schema: str, msgtype: str) -> bool:
    return mcap_schema.replace("/msg/", "/") == msgtype.replace("/msg/", "/")


def test_info_json_on_a_written_log(small_log):
    doc = info_json(small_log)
    assert doc["schema"] == "mcl3d.info/1" and doc["path"] == str(small_log)
    assert doc["format"] == "MCAP (ros2)" and doc["profile"] == "ros2"
    assert doc["size_bytes"] == small_log.stat().st_size
    topics, start_ns, end_ns = mcap_summary(small_log)
    assert (doc["start_ns"], doc["end_ns"]) == (start_ns, end_ns) == (T0, T0 + 400_000_000)
    assert doc["start_utc"] == "2023-11-14T22:13:20.000000000Z"
    assert doc["end_utc"] == "2023-11-14T22:13:20.400000000Z"
    assert doc["duration_ns"] == 400_000_000 and doc["duration_s"] == pytest.approx(0.4)
    assert doc["message_count"] == sum(n for _, n in topics.values()) == 15
    by_name = {t["name"]: t for t in doc["topics"]}
    assert set(by_name) == set(topics)
    for name, (schema, count) in topics.items():
        assert _same_type(schema, by_name[name]["type"]) and by_name[name]["count"] == count
    points = by_name["/lidar/points"]
    assert points["rate_hz"] == pytest.approx(10.0) and points["frame_ids"] == ["lidar"]
    cloud = points["cloud"]
    assert (cloud["organized"], cloud["height"], cloud["width"]) == (False, 1, 20)
    first = first_cloud(small_log, "/lidar/points")
    assert (cloud["height"], cloud["width"]) == (first.height, first.width)
    assert [(f["name"], f["datatype"], f["count"]) for f in cloud["fields"]] == [
        (f.name, POINTFIELD_TYPES[f.datatype], f.count) for f in first.fields]
    assert cloud["time_field"] == "t" and cloud["time_span_s"] == pytest.approx(0.1)
    assert cloud["scans_decoded"] == 3
    assert cloud["valid_points"] == {"min": 20, "mean": 20.0, "max": 20}
    assert by_name["/imu/data"]["cloud"] is None and by_name["/imu/data"]["frame_ids"] == ["imu"]
    assert doc["selection"] == {
        "points": {"topic": "/lidar/points", "problem": None, "setting": None, "flag": None},
        "imu": {"topic": "/imu/data", "problem": None, "setting": None, "flag": None},
        "odom": {"topic": None, "problem": None, "setting": None, "flag": None},
        "gt": {"topic": "/ground_truth", "problem": None, "setting": None, "flag": None}}


def test_info_json_agrees_with_the_tables_on_the_real_ouster_mcap(shared_data):
    log = shared_data / "ouster_os1_64_mcap" / "test.mcap"
    doc = info_json(log)
    tables = mcl3d("info", log).stdout
    topics, start_ns, end_ns = mcap_summary(log)
    assert (doc["start_ns"], doc["end_ns"]) == (start_ns, end_ns)
    assert doc["start_utc"][:23] + "Z" in tables and f"{doc['duration_s']:.3f} s" in tables
    assert doc["format"] == "MCAP (ros1)" and f"messages │ {doc['message_count']}" in tables
    for topic in doc["topics"]:
        assert topic["count"] == topics[topic["name"]][1]
        row = next(line for line in tables.splitlines() if f" {topic['name']} " in line)
        rate = "-" if topic["rate_hz"] is None else f"{topic['rate_hz']:.1f}"
        assert f" {topic['count']} " in row and f" {rate} " in row
        assert all(frame in row for frame in topic["frame_ids"])
    cloud = next(t["cloud"] for t in doc["topics"] if t["name"] == "/os1_cloud_node/points")
    assert f"organized {cloud['height']} x {cloud['width']}" in tables
    valid = cloud["valid_points"]
    assert f"min {valid['min']}, mean {valid['mean']:.0f}, max {valid['max']}" in tables
    assert {"name": "ring", "datatype": "uint8", "count": 1} in cloud["fields"]


def test_info_json_names_the_problem_and_its_flag(tmp_path):
    path = tmp_path / "two.mcap"
    with LogWriter(path) as w:
        w.write_points("/front/points", cloud(T0))
        w.write_points("/rear/points", cloud(T0 + 1))
    points = info_json(path)["selection"]["points"]
    assert points["topic"] is None and points["setting"] == "points_topic"
    assert points["flag"] == "--points-topic"
    assert "/front/points, /rear/points" in points["problem"] and "choose one" in points["problem"]
    chosen = info_json(path, "--points-topic", "/rear/points")["selection"]["points"]
    assert chosen == {"topic": "/rear/points", "problem": None, "setting": None, "flag": None}


def test_piped_tables_keep_long_names_whole(tmp_path):
    topic = "/sensors/lidar_front_left_upper/velodyne_points_motion_compensated_filtered"
    frame = "vehicle_front_left_upper_velodyne_hdl32e_sensor_optical_frame"
    path = tmp_path / ("a_rather_long_recording_name_from_the_test_drive_" + "x" * 40 + ".mcap")
    with LogWriter(path) as w:
        for k in range(3):
            c = cloud(T0 + k * 100_000_000)
            w.write_points(topic, PointCloud(c.stamp_ns, frame, c.points, c.times_s, c.fields))
    for columns in (None, "80", "40"):
        result = mcl3d("info", path, columns=columns)
        assert result.returncode == 0, result.stderr
        out = result.stdout
        row = next(line for line in out.splitlines() if f" {topic} " in line)
        assert "sensor_msgs/PointCloud2" in row and frame in row and " 3 " in row
        assert f"Point cloud {topic} " in out and str(path) in out


def test_json_of_bad_input_is_one_red_line(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("these are my notes, not a log\n")
    result = mcl3d("info", bad, "--json")
    assert_one_line_error(result, "notes.mcap", "not an MCAP file")
    assert result.stdout == ""


def test_truncated_mcap(small_log, tmp_path):
    """A log cut in its data section is read up to the cut (its format says so); one cut in its
    summary lost nothing; one cut before its first message stops with one line."""
    data = small_log.read_bytes()
    data_end = data.index(bytes([0x0F]) + (4).to_bytes(8, "little"))  # the DataEnd record
    for cut, data_lost in ((data_end - 5, True), (len(data) - 3, False)):
        bad = tmp_path / "cut.mcap"
        bad.write_bytes(data[:cut])
        result = mcl3d("info", bad, "--json")
        assert result.returncode == 0, result.stderr
        assert ("truncated or damaged at byte" in json.loads(result.stdout)["format"]) == data_lost
        with LogReader(bad) as reader:
            assert (reader.faults.truncation is not None) == data_lost
    bad.write_bytes(data[:40])
    before = sorted(tmp_path.iterdir())
    assert_one_line_error(mcl3d("info", bad), "cut.mcap", "truncated")
    assert sorted(tmp_path.iterdir()) == before
    with pytest.raises(LogFormatError, match="truncated"):
        LogReader(bad)


def test_corrupt_mcap_body(small_log, tmp_path):
    data = bytearray(small_log.read_bytes())
    data[200:len(data) - 400] = bytes(len(data) - 600)
    bad = tmp_path / "zeroed.mcap"
    bad.write_bytes(bytes(data))
    assert_one_line_error(mcl3d("info", bad), "zeroed.mcap", "corrupt")


def test_text_file_renamed_mcap(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("these are my notes, not a log\n")
    assert_one_line_error(mcl3d("info", bad), "notes.mcap", "not an MCAP file")
    assert_one_line_error(mcl3d("info", tmp_path / "missing.mcap"), "missing.mcap", "no such")
    bag = tmp_path / "notes.bag"
    bag.write_text("hello\n")
    assert_one_line_error(mcl3d("info", bag), "notes.bag", "not a ROS 1 bag")


def test_log_without_pointcloud2(tmp_path):
    path = tmp_path / "imu_only.mcap"
    with LogWriter(path) as w:
        w.write_imu("/imu/data", imu(T0))
    with LogReader(path) as r, pytest.raises(TopicError, match="no point cloud"):
        next(r.scans())
    result = mcl3d("info", path)  # describing such a log is fine; it says no cloud topic is used
    assert result.returncode == 0 and "points │ -" in result.stdout
    assert_one_line_error(mcl3d("info", path, "--points-topic", "/imu/data"), "/imu/data",
                          "holds sensor_msgs/Imu", "not sensor_msgs/PointCloud2")
    assert_one_line_error(mcl3d("info", path, "--points-topic", "/points"), "/points",
                          "not in the log")
    out = tmp_path / "odometry"  # a command that needs clouds stops, and writes nothing
    assert_one_line_error(mcl3d("odometry", path, "-o", out, "--backend", "cpu"),
                          "no point cloud", "--points-topic")
    assert list(tmp_path.iterdir()) == [path]


def test_two_pointcloud2_topics_need_points_topic(tmp_path):
    path = tmp_path / "two.mcap"
    with LogWriter(path) as w:
        w.write_points("/front/points", cloud(T0))
        w.write_points("/rear/points", cloud(T0 + 1))
    with LogReader(path) as r:
        with pytest.raises(TopicError, match=r"/front/points, /rear/points.*choose one") as exc:
            next(r.scans())
        assert exc.value.setting == "points_topic"
        with pytest.raises(TopicError, match="choose one"):
            r.count("points")
    with LogReader(path, points_topic="/rear/points") as r:
        assert [s.stamp_ns for s in r.scans()] == [T0 + 1]
    result = mcl3d("info", path)
    assert result.returncode == 0
    assert "choose one (--points-topic)" in result.stdout
    out = tmp_path / "odometry"
    assert_one_line_error(mcl3d("odometry", path, "-o", out, "--backend", "cpu"),
                          "/front/points, /rear/points", "--points-topic")
    assert list(tmp_path.iterdir()) == [path]


def test_cloud_without_xyz(tmp_path):
    from mcap.writer import Writer

    store = rt.ros2_typestore()
    T = store.types
    msg = T[rt.POINTCLOUD2](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                        frame_id="radar"),
        height=1, width=2, fields=[T["sensor_msgs/msg/PointField"](name="intensity", offset=0,
                                                                    datatype=7, count=1)],
        is_bigendian=False, point_step=4, row_step=8, data=np.zeros(8, np.uint8), is_dense=True)
    path = tmp_path / "noxyz.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="test")
        text, _ = store.generate_msgdef(rt.POINTCLOUD2, ros_version=2)
        schema = writer.register_schema(rt.POINTCLOUD2, "ros2msg", text.encode())
        channel = writer.register_channel("/radar/points", "cdr", schema)
        writer.add_message(channel, 10**9, bytes(store.serialize_cdr(msg, rt.POINTCLOUD2)), 10**9)
        writer.finish()
    before = sorted(tmp_path.iterdir())
    assert_one_line_error(mcl3d("info", path), "/radar/points", "no x/y/z field")
    assert sorted(tmp_path.iterdir()) == before
    with LogReader(path) as r, pytest.raises(PointCloudError, match="no x/y/z"):
        next(r.scans())


def test_ground_truth_missing_is_a_topic_error(tmp_path):
    path = tmp_path / "nogt.mcap"
    with LogWriter(path) as w:
        w.write_points("/lidar/points", cloud(T0))
        w.write_pose("/pose", PoseStamped(T0, "map", np.eye(4)))
    with LogReader(path) as r, pytest.raises(TopicError, match=r"no ground-truth .* topic in"):
        r.ground_truth()
    with LogReader(path, gt_topic="/pose") as r:
        stamps, poses = r.ground_truth()
    assert stamps.tolist() == [T0] and poses.shape == (1, 4, 4)
