"""MCAP writer for ROS 2 (CDR) logs that `ros2 bag`, Foxglove and mcl3d's reader all read.

Schemas are `ros2msg` text with dependent types appended after '=====' / 'MSG: pkg/Type'
separators, as rosbag2 writes them. The output is byte-deterministic: no wall-clock time is
stored (log_time = publish_time = header stamp, unless a receive time `log_ns` is given, as
a recorder stamps it), the library string is fixed, and chunking
and compression settings are constant. The file appears only when the writer closes cleanly.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from mcl3d import __version__
from mcl3d.core.errors import InputError
from mcl3d.core.outputs import atomic_path, check_writable
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.messages import Imu, Odometry, PointCloud, PoseStamped, Transform

CHUNK_SIZE = 4 * 1024 * 1024


class LogWriter:
    """Context manager writing one ROS 2 MCAP log; see the module docstring."""

    def __init__(self, path: Path, *, force: bool = False, chunk_size: int = CHUNK_SIZE):
        self.path = Path(path)
        self._chunk_size = chunk_size  # bytes of records per chunk (a recorder's setting)
        check_writable(self.path, force)
        self._stack: contextlib.ExitStack | None = None
        self._mcap = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._sequence: dict[str, int] = {}

    def __enter__(self) -> LogWriter:
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        stream = self._stack.enter_context(open(tmp, "wb"))
        self._mcap = McapWriter(stream, chunk_size=self._chunk_size,
                                compression=CompressionType.ZSTD)
        self._mcap.start(profile="ros2", library=f"mcl3d {__version__}")
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._stack is not None
        try:
            if exc_type is None:
                self._mcap.finish()
        finally:
            self._stack.__exit__(exc_type, exc, tb)
            self._stack = None

    def _write(self, topic: str, msgtype: str, msg, stamp: int, log_ns: int | None = None
               ) -> None:
        if self._mcap is None or self._stack is None:
            raise RuntimeError("use LogWriter as a context manager: `with LogWriter(path) as w:`")
        store = rt.ros2_typestore()
        if topic not in self._channels:
            if msgtype not in self._schemas:
                text, _ = store.generate_msgdef(msgtype, ros_version=2)
                self._schemas[msgtype] = self._mcap.register_schema(
                    name=msgtype, encoding="ros2msg", data=text.encode())
            channel = self._mcap.register_channel(topic=topic, message_encoding="cdr",
                                                  schema_id=self._schemas[msgtype])
            self._channels[topic] = (channel, msgtype)
            self._sequence[topic] = 0
        channel, existing = self._channels[topic]
        if existing != msgtype:
            raise InputError(f"{self.path}: topic {topic} already holds {rt.short_type(existing)}; "
                             f"cannot also write {rt.short_type(msgtype)} to it")
        if stamp < 0:
            raise InputError(f"{self.path}: negative stamp {stamp} ns on {topic}")
        data = store.serialize_cdr(msg, msgtype)
        log_time = int(stamp if log_ns is None else log_ns)
        self._mcap.add_message(channel_id=channel, log_time=log_time, publish_time=log_time,
                               sequence=self._sequence[topic], data=bytes(data))
        self._sequence[topic] += 1

    def write_points(self, topic: str, cloud: PointCloud, log_ns: int | None = None) -> None:
        """Write a cloud as PointCloud2: x y z float32, its fields, per-point time as `t` (s)."""
        msg = rt.from_pointcloud(rt.ros2_typestore(), cloud, f"{self.path} topic {topic}")
        self._write(topic, rt.POINTCLOUD2, msg, cloud.stamp_ns, log_ns)

    def write_imu(self, topic: str, imu: Imu, log_ns: int | None = None) -> None:
        self._write(topic, rt.IMU, rt.from_imu(rt.ros2_typestore(), imu), imu.stamp_ns, log_ns)

    def write_odometry(self, topic: str, odom: Odometry, log_ns: int | None = None) -> None:
        self._write(topic, rt.ODOMETRY, rt.from_odometry(rt.ros2_typestore(), odom),
                    odom.stamp_ns, log_ns)

    def write_pose(self, topic: str, pose: PoseStamped, log_ns: int | None = None) -> None:
        self._write(topic, rt.POSE_STAMPED, rt.from_pose(rt.ros2_typestore(), pose),
                    pose.stamp_ns, log_ns)

    def write_tf(self, topic: str, transforms: list[Transform]) -> None:
        """Write one tf2_msgs/TFMessage ('/tf_static' for extrinsics); stamped by its first."""
        if not transforms:
            raise InputError(f"{self.path}: write_tf on {topic} needs at least one transform")
        msg = rt.from_transforms(rt.ros2_typestore(), transforms)
        self._write(topic, rt.TF_MESSAGE, msg, min(tf.stamp_ns for tf in transforms))
