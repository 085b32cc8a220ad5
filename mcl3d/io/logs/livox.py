"""Livox `CustomMsg` scans (livox_ros_driver2 in ROS 2 and ROS 1, livox_ros_driver in ROS 1).

The message: `std_msgs/Header header`, `uint64 timebase` (ns, the first point's time),
`uint32 point_num`, `uint8 lidar_id`, `uint8[3] rsvd`, `CustomPoint[] points`; a
`CustomPoint` is `uint32 offset_time` (ns after `timebase`), `float32 x, y, z` (m),
`uint8 reflectivity`, `uint8 tag`, `uint8 line` (the laser: the scan's ring).

Per-point times (`times_s`) are relative to the header stamp, as for PointCloud2:
`timebase + offset_time - stamp`. livox_ros_driver2 stamps a message with its timebase;
drivers patched to stamp with the host clock leave `timebase` on the lidar's clock, so when
the two lie more than `SAME_CLOCK_NS` apart the stamp is taken as the first point's time
(`offset_time` alone, as FAST-LIO reads it).

Tag (Livox point-cloud protocol; Avia, Horizon, Tele, HAP, MID-360): bits 0-1 the point's
property from its spatial position, bits 2-3 from its intensity (00 normal, 01 noise with
high confidence, 10 noise with moderate confidence, 11 noise with low confidence, reserved
for intensity), bits 4-5 the return number. Points whose spatial or intensity property is
noise with high or moderate confidence (01, 10: rain, fog, dust, stray returns) are dropped
and counted in `n_dropped`, like zero or non-finite points; low-confidence and every
return number are kept.

Messages are decoded straight from their bytes (CDR or ROS 1) with numpy when their
definition is the standard one (`standard_layout`): a 20k-point scan takes ~1.2 ms instead
of 60-100 ms through per-point message objects (2-core Xeon), which stay the path for other
definitions.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from rosbags.typesys import get_types_from_msg

from mcl3d.core.errors import PointCloudError
from mcl3d.io.logs.messages import PointCloud

CUSTOM_MSG_TYPES = ("livox_ros_driver2/msg/CustomMsg", "livox_ros_driver/msg/CustomMsg")
SAME_CLOCK_NS = 1_000_000_000
NOISE_CLASSES = (0b01, 0b10)  # high and moderate confidence noise (tag bits 0-1 and 2-3)
POINT_FIELDS = (("offset_time", "u4"), ("x", "f4"), ("y", "f4"), ("z", "f4"),
                ("reflectivity", "u1"), ("tag", "u1"), ("line", "u1"))
_MSG_LAYOUT = [("header", "Header"), ("timebase", "uint64"), ("point_num", "uint32"),
               ("lidar_id", "uint8"), ("rsvd", ("ARRAY", "uint8", 3)),
               ("points", ("SEQUENCE", "CustomPoint", 0))]
POINT_LAYOUT = [("offset_time", "uint32"), ("x", "float32"), ("y", "float32"),
                 ("z", "float32"), ("reflectivity", "uint8"), ("tag", "uint8"),
                 ("line", "uint8")]
_CDR_HEADER = 4  # encapsulation kind (2 bytes) + options (2 bytes)
# livox_ros_driver2's msg/CustomMsg.msg and msg/CustomPoint.msg, for ROS 2 bags that do not
# embed definitions (sqlite3 bags before Iron)
_ROS2_DEFINITIONS = {
    "livox_ros_driver2/msg/CustomPoint": "uint32 offset_time\nfloat32 x\nfloat32 y\n"
                                         "float32 z\nuint8 reflectivity\nuint8 tag\nuint8 line\n",
    "livox_ros_driver2/msg/CustomMsg": "std_msgs/msg/Header header\nuint64 timebase\n"
                                       "uint32 point_num\nuint8 lidar_id\nuint8[3] rsvd\n"
                                       "livox_ros_driver2/msg/CustomPoint[] points\n",
}


@dataclass
class LivoxScan:
    """One CustomMsg with its points as a structured array of `POINT_FIELDS`."""

    stamp_ns: int
    frame_id: str
    timebase_ns: int
    points: np.ndarray


def ros2_types() -> dict:
    """The livox_ros_driver2 message types, to register in a rosbags type store."""
    types: dict = {}
    for name, text in _ROS2_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    return types


def point_dtype(order: str = "<", aligned: bool = False) -> np.dtype:
    """CustomPoint as serialized: packed (19 bytes, ROS 1) or CDR-aligned (20 bytes)."""
    offsets = [0, 4, 8, 12, 16, 17, 18]
    return np.dtype({"names": [n for n, _ in POINT_FIELDS],
                     "formats": [(order if t != "u1" else "|") + t for _, t in POINT_FIELDS],
                     "offsets": offsets, "itemsize": 20 if aligned else 19})


def _shape(desc) -> object:
    kind, rest = desc
    if kind.name == "BASE":
        return rest[0]
    if kind.name == "NAME":
        return rest.split("/")[-1]
    return (kind.name, _shape(rest[0]), rest[1])


def standard_layout(fielddefs: dict, msgtype: str) -> bool:
    """Whether `msgtype` (as registered in a rosbags type store) has the documented fields, so
    the numpy decoders below read it correctly."""
    fields = fielddefs.get(msgtype, ([], []))[1]
    if [(n, _shape(d)) for n, d in fields] != _MSG_LAYOUT:
        return False
    point_type = fields[-1][1][1][0][1]
    point_fields = fielddefs.get(point_type, ([], []))[1]
    return [(n, _shape(d)) for n, d in point_fields] == POINT_LAYOUT


def _points(raw: bytes, pos: int, count: int, dtype: np.dtype, where: str) -> np.ndarray:
    """`count` points starting at byte `pos` (the last CDR point has no trailing padding)."""
    used = 19 if count else 0
    need = pos + dtype.itemsize * max(count - 1, 0) + used
    if len(raw) < need:
        raise PointCloudError(f"{where}: the message holds {len(raw)} bytes, but its {count} "
                              f"points need {need}; the message is truncated")
    body = bytes(raw[pos:pos + dtype.itemsize * count])
    body += b"\0" * (dtype.itemsize * count - len(body))
    return np.frombuffer(body, dtype=dtype, count=count)


def decode_cdr(raw: bytes, where: str = "CustomMsg") -> LivoxScan:
    """A ROS 2 (CDR) CustomMsg of the standard layout, from its serialized bytes."""
    order = "<" if raw[1] == 1 else ">"

    def align(pos: int, size: int) -> int:
        return _CDR_HEADER + -(-(pos - _CDR_HEADER) // size) * size

    try:
        sec, nanosec, length = struct.unpack_from(order + "iII", raw, _CDR_HEADER)
        pos = _CDR_HEADER + 12
        frame_id = bytes(raw[pos:pos + max(length - 1, 0)]).decode("utf-8", "replace")
        pos = align(pos + length, 8)
        timebase, _point_num = struct.unpack_from(order + "QI", raw, pos)
        pos = align(pos + 16, 4)
        (count,) = struct.unpack_from(order + "I", raw, pos)
    except struct.error:
        raise PointCloudError(f"{where}: the message is truncated before its points") from None
    points = _points(raw, pos + 4, count, point_dtype(order, aligned=True), where)
    return LivoxScan(sec * 1_000_000_000 + nanosec, frame_id, timebase, points)


def decode_ros1(raw: bytes, where: str = "CustomMsg") -> LivoxScan:
    """A ROS 1 CustomMsg of the standard layout, from its serialized bytes."""
    try:
        _seq, sec, nsec, length = struct.unpack_from("<IIII", raw, 0)
        frame_id = bytes(raw[16:16 + length]).decode("utf-8", "replace")
        pos = 16 + length
        timebase, _point_num = struct.unpack_from("<QI", raw, pos)
        (count,) = struct.unpack_from("<I", raw, pos + 16)
    except struct.error:
        raise PointCloudError(f"{where}: the message is truncated before its points") from None
    points = _points(raw, pos + 20, count, point_dtype("<"), where)
    return LivoxScan(sec * 1_000_000_000 + nsec, frame_id, timebase, points)


def from_message(msg) -> LivoxScan:
    """A CustomMsg decoded by rosbags (any definition with the documented fields)."""
    stamp = msg.header.stamp  # rosbags gives ROS 1 times as sec/nanosec too
    rows = [tuple(getattr(p, name) for name, _ in POINT_FIELDS) for p in msg.points]
    return LivoxScan(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec), msg.header.frame_id,
                     int(msg.timebase), np.array(rows, dtype=point_dtype(aligned=True)))


def noise(tag: np.ndarray) -> np.ndarray:
    """True where the tag marks noise with high or moderate confidence (module docstring)."""
    spatial, intensity = tag & 0b11, (tag >> 2) & 0b11
    return np.isin(spatial, NOISE_CLASSES) | np.isin(intensity, NOISE_CLASSES)


def to_pointcloud(msg) -> PointCloud:
    """The scan's sound points with times relative to its stamp, `line` as `ring`."""
    scan = msg if isinstance(msg, LivoxScan) else from_message(msg)
    raw = scan.points
    xyz = np.stack([raw["x"], raw["y"], raw["z"]], axis=1).astype(np.float32)
    keep = (np.isfinite(xyz).all(axis=1) & (xyz != 0).any(axis=1)
            & ~noise(raw["tag"]))
    base = scan.timebase_ns - scan.stamp_ns
    if abs(base) > SAME_CLOCK_NS:
        base = 0
    times = ((raw["offset_time"][keep].astype(np.int64) + base) * 1e-9).astype(np.float32)
    fields = {"reflectivity": raw["reflectivity"][keep].copy(), "tag": raw["tag"][keep].copy(),
              "ring": raw["line"][keep].copy()}
    return PointCloud(stamp_ns=scan.stamp_ns, frame_id=scan.frame_id, points=xyz[keep],
                      times_s=times, fields=fields, n_dropped=int(len(raw) - keep.sum()),
                      height=1, width=len(raw))


def fast_decoder(fielddefs: dict, msgtype: str, cdr: bool) -> Callable | None:
    """`decode_cdr` or `decode_ros1` for a CustomMsg type of the standard layout, else None."""
    if msgtype not in CUSTOM_MSG_TYPES or not standard_layout(fielddefs, msgtype):
        return None
    return decode_cdr if cdr else decode_ros1
