"""Livox CustomMsg logs: written here with the drivers' real message definitions (MCAP with
ROS 2 CDR and with ROS 1 encoding, a ROS 1 .bag), read through LogReader and compared with an
independent decode (numpy over the serialized bytes, rosbags' deserializer); `mcl3d info`
and `mcl3d odometry` end to end; scans without points are counted and a log of only such
scans fails with one line.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.rosbag2 import Writer as Bag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from support import localize_world as world

from mcl3d.core import geometry
from mcl3d.io.logs import livox
from mcl3d.io.logs.reader import LogReader

N_SCANS = 5
STAMP0_NS = 1_700_000_000_123_456_789
TOPIC = "/livox/lidar"
# livox_ros_driver2/msg/CustomMsg.msg and CustomPoint.msg (Livox-SDK/livox_ros_driver2, msg/);
# livox_ros_driver/msg has the same two files with `Header header` for ROS 1.
CUSTOM_MSG = """# Livox publish pointcloud msg format.

std_msgs/Header header    # ROS standard message header
uint64 timebase          # The time of first point
uint32 point_num      # Total number of pointclouds
uint8  lidar_id      # Lidar device id number
uint8[3]  rsvd       # Reserved use
CustomPoint[] points    # Pointcloud data
"""
CUSTOM_POINT = """# Livox costom pointcloud format.

uint32 offset_time      # offset time relative to the base time
float32 x               # X axis, unit:m
float32 y               # Y axis, unit:m
float32 z               # Z axis, unit:m
uint8 reflectivity      # reflectivity, 0~255
uint8 tag               # livox tag
uint8 line              # laser number in lidar
"""
# a fork's definition with one more field: read through rosbags' objects, not the fast path
VARIANT_MSG = CUSTOM_MSG.replace("CustomPoint[] points", "uint8 point_type\nCustomPoint[] points")
HEADER_2 = "builtin_interfaces/Time stamp\nstring frame_id\n"
HEADER_1 = "uint32 seq\ntime stamp\nstring frame_id\n"
SEP = "=" * 80 + "\n"
# tag: 0 normal, 0x01 spatial noise (high), 0x02 spatial noise (moderate), 0x03 low
# confidence, 0x04/0x08 intensity noise (high/moderate), 0x10 second return
TAGS = np.array([0, 0x01, 0x02, 0x03, 0x04, 0x08, 0x10, 0x13], np.uint8)
NOISE = np.array([False, True, True, False, True, True, False, False])


def schema_text(package: str, ros1: bool, custom_msg: str = CUSTOM_MSG) -> str:
    """The full definition as recorders store it: the message, then each dependency."""
    if ros1:
        return (custom_msg.replace("std_msgs/Header", "Header") + SEP + "MSG: std_msgs/Header\n"
                + HEADER_1 + SEP + f"MSG: {package}/CustomPoint\n" + CUSTOM_POINT)
    return (custom_msg + SEP + "MSG: std_msgs/Header\n" + HEADER_2 + SEP
            + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n" + SEP
            + f"MSG: {package}/CustomPoint\n" + CUSTOM_POINT)


def typestore(package: str, ros1: bool, custom_msg: str = CUSTOM_MSG):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = get_types_from_msg(CUSTOM_POINT, f"{package}/msg/CustomPoint")
    types.update(get_types_from_msg(custom_msg.replace("std_msgs/Header", "std_msgs/msg/Header"),
                                    f"{package}/msg/CustomMsg"))
    store.register(types)
    return store


def point_rows(n_scans: int = N_SCANS, empty: tuple[int, ...] = ()) -> list[np.ndarray]:
    """Per scan, a structured array of CustomPoint values: ray-cast room points (a few zero),
    10 us apart, every tag class in turn, 4 lines."""
    scanner = world.Scanner(n_azimuth=40, noise_m=0.0)
    rows = []
    for k, T in enumerate(world.path(n_scans, step_m=0.1)):
        xyz = np.zeros((0, 3)) if k in empty else scanner.scan(T)
        raw = np.zeros(len(xyz), dtype=livox.point_dtype(aligned=True))
        raw["offset_time"] = np.arange(len(xyz)) * 10_000
        for i, axis in enumerate("xyz"):
            raw[axis] = xyz[:, i]
        raw["x"][5:len(raw):97] = raw["y"][5:len(raw):97] = raw["z"][5:len(raw):97] = 0.0
        raw["reflectivity"] = np.arange(len(xyz)) % 256
        raw["tag"] = TAGS[np.arange(len(xyz)) % len(TAGS)]
        raw["line"] = np.arange(len(xyz)) % 4
        rows.append(raw)
    return rows


def message(store, package: str, k: int, raw: np.ndarray, timebase_ns: int, ros1: bool):
    T = store.types
    stamp = STAMP0_NS + k * 100_000_000
    sec, nsec = divmod(stamp, 10**9)
    if ros1:
        header = T["std_msgs/msg/Header"](seq=k, stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=nsec), frame_id="livox_frame")
    else:
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=nsec), frame_id="livox_frame")
    Point = T[f"{package}/msg/CustomPoint"]
    points = [Point(offset_time=int(p["offset_time"]), x=float(p["x"]), y=float(p["y"]),
                    z=float(p["z"]), reflectivity=int(p["reflectivity"]), tag=int(p["tag"]),
                    line=int(p["line"])) for p in raw]
    return T[f"{package}/msg/CustomMsg"](header=header, timebase=timebase_ns,
                                         point_num=len(points), lidar_id=1,
                                         rsvd=np.zeros(3, np.uint8), points=points)


def ros2_dict(k: int, raw: np.ndarray, timebase_ns: int, custom_msg: str) -> dict:
    """A CustomMsg as mcap_ros2's writer takes it."""
    sec, nsec = divmod(STAMP0_NS + k * 100_000_000, 10**9)
    points = [{name: p[name].item() for name, _ in livox.POINT_FIELDS} for p in raw]
    extra = {"point_type": 1} if "point_type" in custom_msg else {}
    return {"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": "livox_frame"},
            "timebase": timebase_ns, "point_num": len(points), "lidar_id": 1, "rsvd": [0, 0, 0],
            "points": points, **extra}


def write_mcap(path, rows, *, ros1: bool = False, package: str = "livox_ros_driver2",
               host_clock: bool = False, custom_msg: str = CUSTOM_MSG) -> None:
    """An MCAP of CustomMsg scans (ROS 2: serialized by mcap_ros2 from the .msg text; ROS 1: by
    rosbags); `host_clock`: timebase on a lidar clock (seconds since its boot) far from the
    header stamps."""
    timebases = [51_350_000_000 + k * 100_000_000 if host_clock else STAMP0_NS + k * 100_000_000
                 for k in range(len(rows))]
    if not ros1:
        with open(path, "wb") as f:
            writer = Ros2Writer(f)
            schema = writer.register_msgdef(f"{package}/msg/CustomMsg",
                                            schema_text(package, False, custom_msg))
            for k, raw in enumerate(rows):
                writer.write_message(TOPIC, schema, ros2_dict(k, raw, timebases[k], custom_msg),
                                     STAMP0_NS + k * 100_000_000)
            writer.finish()
        return
    store = typestore(package, ros1, custom_msg)
    with open(path, "wb") as f:
        writer = McapWriter(f)
        writer.start(profile="ros1", library="test_livox")
        schema = writer.register_schema(f"{package}/CustomMsg", "ros1msg",
                                        schema_text(package, True, custom_msg).encode())
        channel = writer.register_channel(TOPIC, "ros1", schema)
        for k, raw in enumerate(rows):
            stamp = STAMP0_NS + k * 100_000_000
            msg = message(store, package, k, raw, timebases[k], True)
            data = store.serialize_ros1(msg, f"{package}/msg/CustomMsg")
            writer.add_message(channel, stamp, bytes(data), stamp)
        writer.finish()


def numpy_decode(path, ros1: bool, counts: list[int]) -> list[np.ndarray]:
    """The points of each message: the last field, so its last bytes (CDR pads every point but
    the last to 20 bytes; ROS 1 packs 19), preceded by their uint32 count."""
    step = 19 if ros1 else 20
    out = []
    with open(path, "rb") as f:
        for (_s, _c, msg), count in zip(make_reader(f).iter_messages(), counts, strict=True):
            size = count * step - (0 if ros1 or count == 0 else 1)
            start = len(msg.data) - size
            assert int.from_bytes(msg.data[start - 4:start], "little") == count
            body = bytes(msg.data[start:]) + b"\0" * (count * step - size)
            out.append(np.frombuffer(body, livox.point_dtype(aligned=not ros1), count=count))
    return out


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("livox")
    rows = point_rows()
    write_mcap(folder / "ros2.mcap", rows)
    write_mcap(folder / "ros1.mcap", rows, ros1=True, package="livox_ros_driver")
    return folder, rows


def expected(raw: np.ndarray, base_ns: int = 0):
    keep = (raw["x"] != 0) | (raw["y"] != 0) | (raw["z"] != 0)
    keep &= ~NOISE[np.arange(len(raw)) % len(TAGS)]
    xyz = np.stack([raw["x"], raw["y"], raw["z"]], axis=1)[keep]
    times = (raw["offset_time"][keep] + base_ns) * 1e-9
    return keep, xyz, times


@pytest.mark.parametrize("name", ["ros2.mcap", "ros1.mcap"])
def test_reader_matches_numpy_decode(logs, name):
    folder, rows = logs
    independent = numpy_decode(folder / name, name == "ros1.mcap", [len(r) for r in rows])
    with LogReader(folder / name) as reader:
        assert reader.topics.points == TOPIC and reader.count("points") == N_SCANS
        clouds = list(reader.scans())
    assert len(clouds) == N_SCANS
    for k, (cloud, raw, ref) in enumerate(zip(clouds, rows, independent, strict=True)):
        assert np.array_equal(ref, raw)  # the bytes hold what was written
        keep, xyz, times = expected(ref)
        assert 0 < keep.sum() < len(ref) and cloud.n_dropped == len(ref) - keep.sum()
        assert cloud.stamp_ns == STAMP0_NS + k * 100_000_000 and cloud.frame_id == "livox_frame"
        assert np.array_equal(cloud.points, xyz)
        np.testing.assert_allclose(cloud.times_s, times, rtol=1e-6, atol=1e-9)
        assert np.array_equal(cloud.fields["ring"], ref["line"][keep])
        assert np.array_equal(cloud.fields["reflectivity"], ref["reflectivity"][keep])
        assert set(np.unique(cloud.fields["tag"])) == {0, 0x03, 0x10, 0x13}


def test_fast_decoders_match_rosbags_deserializer(logs):
    folder, _rows = logs
    for name, ros1, package in (("ros2.mcap", False, "livox_ros_driver2"),
                                ("ros1.mcap", True, "livox_ros_driver")):
        store = typestore(package, ros1)
        typ = f"{package}/msg/CustomMsg"
        with open(folder / name, "rb") as f:
            for _s, _c, msg in make_reader(f).iter_messages():
                ours = (livox.decode_ros1 if ros1 else livox.decode_cdr)(msg.data)
                theirs = livox.from_message(store.deserialize_ros1(msg.data, typ) if ros1
                                            else store.deserialize_cdr(msg.data, typ))
                assert (ours.stamp_ns, ours.frame_id, ours.timebase_ns) == (
                    theirs.stamp_ns, theirs.frame_id, theirs.timebase_ns)
                assert np.array_equal(ours.points, theirs.points.astype(ours.points.dtype))
        assert livox.standard_layout(store.fielddefs, typ)


def test_ros1_bag_and_lidar_clock_timebase(tmp_path):
    rows = point_rows(n_scans=2)
    store = typestore("livox_ros_driver", ros1=True)
    typ = "livox_ros_driver/msg/CustomMsg"
    bag = tmp_path / "livox.bag"
    with Bag1Writer(bag) as writer:
        conn = writer.add_connection(TOPIC, typ, typestore=store)
        for k, raw in enumerate(rows):
            msg = message(store, "livox_ros_driver", k, raw, STAMP0_NS + k * 10**8 + 2_000, True)
            writer.write(conn, STAMP0_NS + k * 10**8, store.serialize_ros1(msg, typ))
    with LogReader(bag) as reader:
        clouds = list(reader.scans())
    for cloud, raw in zip(clouds, rows, strict=True):
        _keep, xyz, times = expected(raw, base_ns=2_000)  # timebase 2 us after the stamp
        assert np.array_equal(cloud.points, xyz)
        np.testing.assert_allclose(cloud.times_s, times, rtol=1e-6, atol=1e-9)
    write_mcap(tmp_path / "host.mcap", rows, host_clock=True)
    with LogReader(tmp_path / "host.mcap") as reader:
        for cloud, raw in zip(reader.scans(), rows, strict=True):
            np.testing.assert_allclose(cloud.times_s, expected(raw)[2], rtol=1e-6, atol=1e-9)


def test_ros2_bag_without_embedded_definitions(tmp_path):
    """sqlite3 bags before Iron store no message definitions: livox_ros_driver2's are known."""
    rows = point_rows(n_scans=2)
    store = typestore("livox_ros_driver2", ros1=False)
    typ = "livox_ros_driver2/msg/CustomMsg"
    with Bag2Writer(tmp_path / "bag", version=8) as writer:
        conn = writer.add_connection(TOPIC, typ, typestore=store)
        for k, raw in enumerate(rows):
            msg = message(store, "livox_ros_driver2", k, raw, STAMP0_NS + k * 10**8, False)
            writer.write(conn, STAMP0_NS + k * 10**8, store.serialize_cdr(msg, typ))
    with sqlite3.connect(next((tmp_path / "bag").glob("*.db3"))) as db:
        db.execute("DELETE FROM message_definitions")
    with LogReader(tmp_path / "bag") as reader:
        clouds = list(reader.scans())
    for cloud, raw in zip(clouds, rows, strict=True):
        assert np.array_equal(cloud.points, expected(raw)[1])


def test_other_definition_is_read_through_message_objects(tmp_path):
    rows = point_rows(n_scans=2)
    write_mcap(tmp_path / "fork.mcap", rows, custom_msg=VARIANT_MSG)
    store = typestore("livox_ros_driver2", False, VARIANT_MSG)
    assert not livox.standard_layout(store.fielddefs, "livox_ros_driver2/msg/CustomMsg")
    with LogReader(tmp_path / "fork.mcap") as reader:
        clouds = list(reader.scans())
    for cloud, raw in zip(clouds, rows, strict=True):
        keep, xyz, times = expected(raw)
        assert np.array_equal(cloud.points, xyz)
        np.testing.assert_allclose(cloud.times_s, times, rtol=1e-6, atol=1e-9)
        assert np.array_equal(cloud.fields["ring"], raw["line"][keep])


def mcl3d(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], capture_output=True,
                          text=True, env={"COLUMNS": "200", "PATH": ""}, timeout=300)


def test_info_and_odometry_end_to_end(logs, tmp_path):
    folder, rows = logs
    info = mcl3d("info", folder / "ros2.mcap", "--json")
    assert info.returncode == 0, info.stderr
    doc = json.loads(info.stdout)
    topic = doc["topics"][0]
    assert topic["name"] == TOPIC and topic["type"] == "livox_ros_driver2/msg/CustomMsg"
    assert topic["count"] == N_SCANS and topic["frame_ids"] == ["livox_frame"]
    cloud = topic["cloud"]
    assert cloud["time_field"] == "offset_time" and cloud["width"] == len(rows[0])
    assert [f["name"] for f in cloud["fields"]] == [n for n, _ in livox.POINT_LAYOUT]
    assert cloud["valid_points"]["max"] == max(expected(r)[0].sum() for r in rows[:3])
    assert doc["selection"]["points"]["topic"] == TOPIC
    run = mcl3d("odometry", folder / "ros1.mcap", "-o", tmp_path / "odo")
    assert run.returncode == 0, run.stderr
    tum = (tmp_path / "odo" / "odometry.tum").read_text().splitlines()
    poses = [line.split() for line in tum if line and not line.startswith("#")]
    assert len(poses) == N_SCANS
    path = world.path(N_SCANS, step_m=0.1)
    truth = (geometry.se3_inverse(path[0]) @ path[-1])[:3, 3]
    np.testing.assert_allclose([float(v) for v in poses[-1][1:4]], truth, atol=0.03)


def test_messages_without_points(tmp_path):
    some = tmp_path / "some_empty.mcap"
    write_mcap(some, point_rows(empty=(1, 3)))
    with LogReader(some) as reader:
        clouds = list(reader.scans())
        assert len(clouds) == N_SCANS - 2
        assert reader.faults.count("scan_empty") == 2
    only = tmp_path / "only_empty.mcap"
    write_mcap(only, point_rows(n_scans=3, empty=(0, 1, 2)))
    result = mcl3d("odometry", only, "-o", tmp_path / "out")
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
    assert f"no scan on {TOPIC}" in lines[0]
    assert not (tmp_path / "out").exists()
