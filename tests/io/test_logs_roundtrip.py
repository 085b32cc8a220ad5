"""LogWriter -> LogReader round trips (synthetic, real PCD scans + KITTI poses, ROS 2 bag folder).

Real data: hdl32_pair (BSD-3-Clause / MIT), pandar64_static (Apache-2.0),
ouster_os1_128_lb_n3 poses (BSD-3-Clause).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mcl3d.core.errors import OutputExistsError
from mcl3d.core.geometry import se3_from_tq, tq_from_se3
from mcl3d.io.logs.cloud_files import read_cloud_file
from mcl3d.io.logs.messages import Imu, Odometry, PointCloud, PoseStamped, Transform
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import LogWriter

T0 = 1_700_000_000_000_000_000


def requantized(T: np.ndarray) -> np.ndarray:
    """A pose as stored in a message (translation + quaternion), bitwise what the reader returns."""
    return se3_from_tq(*tq_from_se3(T))


def random_pose(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return se3_from_tq(rng.normal(size=3) * 10, q / np.linalg.norm(q))


def synthetic_log(path: Path, seed: int = 0):
    rng = np.random.default_rng(seed)
    written = {"points": [], "imu": [], "odom": [], "gt": []}
    with LogWriter(path) as w:
        tf = [Transform(T0, "base_link", "lidar", random_pose(rng)),
              Transform(T0, "base_link", "imu", random_pose(rng))]
        w.write_tf("/tf_static", tf)
        written["tf"] = tf
        for k in range(3):
            stamp = T0 + k * 100_000_000
            n = 200 + k
            cloud = PointCloud(stamp, "lidar", rng.normal(size=(n, 3)).astype(np.float32) * 20,
                               rng.uniform(0, 0.1, n).astype(np.float32),
                               {"intensity": rng.uniform(0, 1, n).astype(np.float32),
                                "ring": rng.integers(0, 64, n).astype(np.uint16)})
            w.write_points("/lidar/points", cloud)
            written["points"].append(cloud)
            for j in range(10):
                imu = Imu(stamp + j * 10_000_000, "imu", rng.normal(size=3), rng.normal(size=3),
                          None if k == 0 else rng.normal(size=4))
                w.write_imu("/imu/data", imu)
                written["imu"].append(imu)
            odom = Odometry(stamp, "odom", "base_link", random_pose(rng), rng.normal(size=6),
                            rng.normal(size=(6, 6)))
            w.write_odometry("/odom", odom)
            written["odom"].append(odom)
            gt = PoseStamped(stamp, "map", random_pose(rng))
            w.write_pose("/ground_truth", gt)
            written["gt"].append(gt)
    return written


def test_every_message_type_round_trips_exactly(tmp_path):
    path = tmp_path / "log.mcap"
    written = synthetic_log(path)
    with LogReader(path) as r:
        assert (r.topics.points, r.topics.imu, r.topics.odom, r.topics.gt) == (
            "/lidar/points", "/imu/data", "/odom", "/ground_truth")
        assert [r.count(k) for k in ("points", "imu", "odom", "gt")] == [3, 30, 3, 3]
        got = {"points": [], "imu": [], "odom": [], "gt": []}
        stamps = []
        for kind, msg in r.messages():
            got[kind].append(msg)
            stamps.append(msg.stamp_ns)
        assert stamps == sorted(stamps)
        tf = r.static_transforms()
        gt_stamps, gt_poses = r.ground_truth()

    for a, b in zip(written["points"], got["points"], strict=True):
        assert (b.stamp_ns, b.frame_id, b.n_dropped) == (a.stamp_ns, a.frame_id, 0)
        assert b.points.tobytes() == a.points.tobytes()
        assert b.times_s.tobytes() == a.times_s.tobytes()
        assert b.fields.keys() == a.fields.keys()
        for name in a.fields:
            assert b.fields[name].dtype == a.fields[name].dtype
            assert b.fields[name].tobytes() == a.fields[name].tobytes()
    for a, b in zip(written["imu"], got["imu"], strict=True):
        assert (b.stamp_ns, b.frame_id) == (a.stamp_ns, a.frame_id)
        assert b.angular_velocity.tobytes() == a.angular_velocity.tobytes()
        assert b.linear_acceleration.tobytes() == a.linear_acceleration.tobytes()
        if a.orientation_xyzw is None:
            assert b.orientation_xyzw is None
        else:
            assert b.orientation_xyzw.tobytes() == a.orientation_xyzw.tobytes()
    for a, b in zip(written["odom"], got["odom"], strict=True):
        assert (b.stamp_ns, b.frame_id, b.child_frame_id) == (a.stamp_ns, "odom", "base_link")
        assert b.twist.tobytes() == a.twist.tobytes()
        assert b.pose_covariance.tobytes() == a.pose_covariance.tobytes()
        assert b.T_frame_child.tobytes() == requantized(a.T_frame_child).tobytes()
        np.testing.assert_allclose(b.T_frame_child, a.T_frame_child, atol=1e-12)
    for a, b in zip(written["gt"], got["gt"], strict=True):
        assert (b.stamp_ns, b.frame_id) == (a.stamp_ns, "map")
        assert b.T.tobytes() == requantized(a.T).tobytes()
    np.testing.assert_array_equal(gt_stamps, [p.stamp_ns for p in written["gt"]])
    np.testing.assert_array_equal(gt_poses, [requantized(p.T) for p in written["gt"]])
    assert [(t.parent_frame, t.child_frame, t.stamp_ns) for t in tf] == [
        (t.parent_frame, t.child_frame, t.stamp_ns) for t in written["tf"]]
    for a, b in zip(written["tf"], tf, strict=True):
        assert b.T_parent_child.tobytes() == requantized(a.T_parent_child).tobytes()


def test_output_is_byte_deterministic_and_readable_by_ros2_tools(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    synthetic_log(tmp_path / "a.mcap", seed=3)
    synthetic_log(tmp_path / "b.mcap", seed=3)
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    with open(tmp_path / "a.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {"sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu",
                                "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
                                "tf2_msgs/msg/TFMessage"}
        assert all(s.encoding == "ros2msg" for s in schemas.values())
        assert "\nMSG: std_msgs/Header\n" in schemas["sensor_msgs/msg/PointCloud2"].data.decode()
        decoded = [(c.topic, m) for _s, c, _m, m in reader.iter_decoded_messages()]
    clouds = [m for t, m in decoded if t == "/lidar/points"]
    assert [f.name for f in clouds[0].fields] == ["x", "y", "z", "intensity", "ring", "t"]
    assert clouds[0].width == 200 and clouds[0].header.frame_id == "lidar"


def test_writer_is_atomic_and_refuses_to_overwrite(tmp_path):
    path = tmp_path / "log.mcap"
    with pytest.raises(RuntimeError), LogWriter(path) as w:
        w.write_pose("/ground_truth", PoseStamped(1, "map", np.eye(4)))
        raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []
    with LogWriter(path) as w:
        w.write_pose("/ground_truth", PoseStamped(1, "map", np.eye(4)))
    with pytest.raises(OutputExistsError, match="allow overwriting"):
        LogWriter(path)
    with LogWriter(path, force=True) as w:
        w.write_pose("/gt", PoseStamped(2, "map", np.eye(4)))
    with LogReader(path) as r:
        assert r.topics.gt == "/gt"


def test_real_scans_and_kitti_poses_round_trip(tmp_path, shared_data):
    from mcl3d.io.trajectory import read_kitti

    pcds = sorted((shared_data / "hdl32_pair").glob("*.pcd"))
    pcds += sorted((shared_data / "pandar64_static" / "top_center_lidar").glob("*.pcd"))
    assert len(pcds) == 4
    poses = read_kitti(shared_data / "ouster_os1_128_lb_n3" /
                       "OS-1-128_v2.3.0_1024x10_lb_n3_poses_kitti.txt").poses
    clouds = []
    for k, pcd in enumerate(pcds):
        cloud = read_cloud_file(pcd)
        cloud.stamp_ns = T0 + k * 100_000_000
        cloud.frame_id = "lidar"
        clouds.append(cloud)
    path = tmp_path / "real.mcap"
    with LogWriter(path) as w:
        for k, cloud in enumerate(clouds):
            w.write_points("/lidar/points", cloud)
            if k < len(poses):
                w.write_pose("/ground_truth", PoseStamped(cloud.stamp_ns, "map", poses[k]))
    with LogReader(path) as r:
        scans = list(r.scans())
        stamps, T_map_lidar = r.ground_truth()
    assert [len(s) for s in scans] == [len(c) for c in clouds]
    for a, b in zip(clouds, scans, strict=True):
        assert b.points.tobytes() == a.points.tobytes()
        assert b.fields.keys() == a.fields.keys()
        for name in a.fields:
            assert b.fields[name].tobytes() == a.fields[name].tobytes()
        if a.times_s is None:
            assert b.times_s is None
        else:
            assert b.times_s.tobytes() == a.times_s.tobytes()
    np.testing.assert_array_equal(stamps, [c.stamp_ns for c in clouds[:3]])
    np.testing.assert_array_equal(T_map_lidar, requantized(poses))
    np.testing.assert_allclose(T_map_lidar, poses, atol=1e-6)


@pytest.mark.parametrize("storage", ["SQLITE3", "MCAP"])
def test_ros2_bag_folder_and_ros1_bag(tmp_path, storage):
    from rosbags.rosbag1 import Writer as Bag1Writer
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Bag2Writer
    from rosbags.typesys import Stores, get_typestore

    from mcl3d.io.logs import ros_types as rt

    ros2 = rt.ros2_typestore()
    cloud = PointCloud(T0, "lidar", np.arange(30, dtype=np.float32).reshape(10, 3) + 1,
                       np.linspace(0, 0.1, 10, dtype=np.float32), {})
    imu = Imu(T0 + 5, "imu", np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 9.81]))
    plugin = getattr(StoragePlugin, storage)
    with Bag2Writer(tmp_path / "bag2", version=8, storage_plugin=plugin) as w:
        c = w.add_connection("/points", rt.POINTCLOUD2, typestore=ros2)
        i = w.add_connection("/imu", rt.IMU, typestore=ros2)
        w.write(c, T0, ros2.serialize_cdr(rt.from_pointcloud(ros2, cloud, "x"), rt.POINTCLOUD2))
        w.write(i, T0 + 5, ros2.serialize_cdr(rt.from_imu(ros2, imu), rt.IMU))

    ros1 = get_typestore(Stores.ROS1_NOETIC)
    msg2 = rt.from_pointcloud(ros2, cloud, "x")
    T = ros1.types
    msg1 = T[rt.POINTCLOUD2](
        header=T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](
            sec=T0 // 10**9, nanosec=T0 % 10**9), frame_id="lidar"),
        height=1, width=10, fields=[T["sensor_msgs/msg/PointField"](
            name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
            for f in msg2.fields],
        is_bigendian=False, point_step=msg2.point_step, row_step=msg2.row_step, data=msg2.data,
        is_dense=True)
    with Bag1Writer(tmp_path / "log.bag") as w:
        c = w.add_connection("/points", rt.POINTCLOUD2, typestore=ros1)
        w.write(c, T0, ros1.serialize_ros1(msg1, rt.POINTCLOUD2))

    for path, fmt in ((tmp_path / "bag2", f"ROS 2 bag folder ({storage.lower()})"),
                      (tmp_path / "log.bag", "ROS 1 bag")):
        with LogReader(path) as r:
            assert r.source.format == fmt
            assert r.topics.points == "/points" and r.count("points") == 1
            (scan,) = list(r.scans())
            assert scan.stamp_ns == T0 and scan.frame_id == "lidar"
            assert scan.points.tobytes() == cloud.points.tobytes()
            assert scan.times_s.tobytes() == cloud.times_s.tobytes()
            if r.topics.imu:
                (got,) = [m for _k, m in r.messages(("imu",))]
                assert got.angular_velocity.tobytes() == imu.angular_velocity.tobytes()


@pytest.mark.parametrize("layout", ["unchunked_no_summary", "no_statistics"])
def test_mcap_without_index_or_statistics(tmp_path, layout):
    from mcap.writer import IndexType, Writer

    from mcl3d.io.logs import ros_types as rt

    store = rt.ros2_typestore()
    options = {"no_statistics": {"use_statistics": False},
               "unchunked_no_summary": {"use_chunking": False, "index_types": IndexType.NONE,
                                        "repeat_channels": False, "repeat_schemas": False,
                                        "use_statistics": False, "use_summary_offsets": False}}
    path = tmp_path / "plain.mcap"
    imus = [Imu(T0 + k * 10**7, "imu", np.array([k, 0.0, 0.0]), np.ones(3)) for k in range(5)]
    with open(path, "wb") as f:
        w = Writer(f, **options[layout])
        w.start("ros2", "test")
        text, _ = store.generate_msgdef(rt.IMU, ros_version=2)
        channel = w.register_channel("/imu", "cdr",
                                     w.register_schema(rt.IMU, "ros2msg", text.encode()))
        for m in imus:
            data = bytes(store.serialize_cdr(rt.from_imu(store, m), rt.IMU))
            w.add_message(channel, m.stamp_ns, data, m.stamp_ns)
        w.finish()
    with LogReader(path) as r:
        assert r.topics.imu == "/imu" and r.count("imu") == 5
        assert (r.source.start_ns, r.source.end_ns) == (T0, T0 + 4 * 10**7)
        got = [m.angular_velocity[0] for _k, m in r.messages(("imu",))]
    assert got == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_odometry_ground_truth_is_not_taken_as_odometry(tmp_path):
    path = tmp_path / "gt_odom.mcap"
    rng = np.random.default_rng(5)
    poses = [random_pose(rng) for _ in range(3)]
    with LogWriter(path) as w:
        for k, T in enumerate(poses):
            odom = Odometry(T0 + k, "map", "lidar", T, np.zeros(6), np.eye(6))
            w.write_odometry("/sim/groundtruth", odom)
            w.write_odometry("/odom", Odometry(T0 + k, "odom", "base", np.eye(4), np.zeros(6),
                                               np.eye(6)))
    with LogReader(path) as r:
        assert (r.topics.gt, r.topics.odom) == ("/sim/groundtruth", "/odom")
        stamps, T_map_lidar = r.ground_truth()
        poses_back = [m for _k, m in r.messages(("gt",))]
    assert stamps.tolist() == [T0, T0 + 1, T0 + 2]
    assert all(isinstance(p, PoseStamped) and p.frame_id == "map" for p in poses_back)
    np.testing.assert_array_equal(T_map_lidar, requantized(np.stack(poses)))
