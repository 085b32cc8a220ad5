"""ROS message objects (as decoded by `rosbags`, ROS 1 or ROS 2) <-> mcl3d message dataclasses.

`rosbags` decodes ROS 1 and ROS 2 messages into objects with the same attribute names
(header.stamp.sec/nanosec, ...), so one set of converters serves every log format.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from rosbags.typesys import Stores, get_typestore

from mcl3d.core.geometry import se3_from_tq, tq_from_se3
from mcl3d.io.logs import livox, pointcloud2
from mcl3d.io.logs.messages import Imu, Odometry, PointCloud, PoseStamped, Transform

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
GT_TYPES = (POSE_STAMPED, ODOMETRY, POSE_COV_STAMPED)
POINT_TYPES = (POINTCLOUD2, *livox.CUSTOM_MSG_TYPES)  # what a scan topic may hold


def normalize_type(name: str) -> str:
    """'sensor_msgs/PointCloud2' (ROS 1) and 'sensor_msgs/msg/PointCloud2' -> the ROS 2 form."""
    parts = name.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name.strip()


def short_type(name: str) -> str:
    """'sensor_msgs/msg/PointCloud2' -> 'sensor_msgs/PointCloud2' (for messages to the user)."""
    return name.replace("/msg/", "/")


@cache
def ros2_typestore():
    """The ROS 2 Humble type store: the definitions our writer embeds and serializes with,
    and those used for bags that embed none (plus livox_ros_driver2's, for Livox bags)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(livox.ros2_types())
    return store


def stamp_ns(msg) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _quat(q) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=np.float64)


def _pose_matrix(pose) -> np.ndarray:
    return se3_from_tq(_vec(pose.position), _quat(pose.orientation))


def to_pointcloud(msg, where: str) -> PointCloud:
    fields = [pointcloud2.FieldSpec(f.name, int(f.offset), int(f.datatype), int(f.count))
              for f in msg.fields]
    body = pointcloud2.EncodedCloud(
        height=int(msg.height), width=int(msg.width), fields=fields,
        is_bigendian=bool(msg.is_bigendian), point_step=int(msg.point_step),
        row_step=int(msg.row_step), data=msg.data, is_dense=bool(msg.is_dense))
    return pointcloud2.decode(body, stamp_ns(msg), msg.header.frame_id, where)


def to_scan(msg, msgtype: str, where: str) -> PointCloud:
    """A scan from any of `POINT_TYPES` (Livox CustomMsg or PointCloud2)."""
    if msgtype in livox.CUSTOM_MSG_TYPES:
        return livox.to_pointcloud(msg)
    return to_pointcloud(msg, where)


def to_imu(msg) -> Imu:
    has_orientation = float(msg.orientation_covariance[0]) != -1.0
    return Imu(stamp_ns=stamp_ns(msg), frame_id=msg.header.frame_id,
               angular_velocity=_vec(msg.angular_velocity),
               linear_acceleration=_vec(msg.linear_acceleration),
               orientation_xyzw=_quat(msg.orientation) if has_orientation else None)


def to_odometry(msg) -> Odometry:
    twist = msg.twist.twist
    return Odometry(stamp_ns=stamp_ns(msg), frame_id=msg.header.frame_id,
                    child_frame_id=msg.child_frame_id,
                    T_frame_child=_pose_matrix(msg.pose.pose),
                    twist=np.concatenate([_vec(twist.linear), _vec(twist.angular)]),
                    pose_covariance=np.asarray(msg.pose.covariance, np.float64).reshape(6, 6))


def to_pose(msg, msgtype: str) -> PoseStamped:
    """A ground-truth pose from PoseStamped, PoseWithCovarianceStamped or Odometry."""
    pose = msg.pose.pose if msgtype in (ODOMETRY, POSE_COV_STAMPED) else msg.pose
    return PoseStamped(stamp_ns=stamp_ns(msg), frame_id=msg.header.frame_id,
                       T=_pose_matrix(pose))


def to_transforms(msg) -> list[Transform]:
    out = []
    for tf in msg.transforms:
        tr = tf.transform
        out.append(Transform(stamp_ns=stamp_ns(tf), parent_frame=tf.header.frame_id,
                             child_frame=tf.child_frame_id,
                             T_parent_child=se3_from_tq(_vec(tr.translation), _quat(tr.rotation))))
    return out


# ---- dataclasses -> ROS 2 message objects (for the writer) ----

def _header(store, stamp: int, frame_id: str):
    T = store.types
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec,
                                                                           nanosec=nanosec),
                                    frame_id=frame_id)


def _ros_vec(store, v, cls="geometry_msgs/msg/Vector3"):
    return store.types[cls](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _ros_quat(store, q):
    return store.types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]),
                                                       z=float(q[2]), w=float(q[3]))


def _ros_pose(store, T):
    t, q = tq_from_se3(np.asarray(T, dtype=np.float64))
    return store.types["geometry_msgs/msg/Pose"](
        position=_ros_vec(store, t, "geometry_msgs/msg/Point"), orientation=_ros_quat(store, q))


def from_pointcloud(store, cloud: PointCloud, where: str):
    body = pointcloud2.encode(cloud, where)
    Field = store.types["sensor_msgs/msg/PointField"]
    fields = [Field(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
              for f in body.fields]
    return store.types[POINTCLOUD2](
        header=_header(store, cloud.stamp_ns, cloud.frame_id), height=body.height,
        width=body.width, fields=fields, is_bigendian=False, point_step=body.point_step,
        row_step=body.row_step, data=body.data, is_dense=True)


def from_imu(store, imu: Imu):
    zeros = np.zeros(9, dtype=np.float64)
    if imu.orientation_xyzw is None:
        orientation, orientation_cov = (0.0, 0.0, 0.0, 1.0), zeros.copy()
        orientation_cov[0] = -1.0  # ROS: "no orientation estimate"
    else:
        orientation, orientation_cov = imu.orientation_xyzw, zeros.copy()
    return store.types[IMU](
        header=_header(store, imu.stamp_ns, imu.frame_id),
        orientation=_ros_quat(store, orientation), orientation_covariance=orientation_cov,
        angular_velocity=_ros_vec(store, imu.angular_velocity),
        angular_velocity_covariance=zeros.copy(),
        linear_acceleration=_ros_vec(store, imu.linear_acceleration),
        linear_acceleration_covariance=zeros.copy())


def from_odometry(store, odom: Odometry):
    T = store.types
    twist = np.asarray(odom.twist, dtype=np.float64)
    return T[ODOMETRY](
        header=_header(store, odom.stamp_ns, odom.frame_id), child_frame_id=odom.child_frame_id,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_ros_pose(store, odom.T_frame_child),
            covariance=np.asarray(odom.pose_covariance, np.float64).reshape(36).copy()),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=_ros_vec(store, twist[:3]),
                                               angular=_ros_vec(store, twist[3:])),
            covariance=np.zeros(36, dtype=np.float64)))


def from_pose(store, pose: PoseStamped):
    return store.types[POSE_STAMPED](header=_header(store, pose.stamp_ns, pose.frame_id),
                                     pose=_ros_pose(store, pose.T))


def from_transforms(store, transforms: list[Transform]):
    T = store.types
    stamped = []
    for tf in transforms:
        t, q = tq_from_se3(np.asarray(tf.T_parent_child, dtype=np.float64))
        stamped.append(T["geometry_msgs/msg/TransformStamped"](
            header=_header(store, tf.stamp_ns, tf.parent_frame), child_frame_id=tf.child_frame,
            transform=T["geometry_msgs/msg/Transform"](translation=_ros_vec(store, t),
                                                       rotation=_ros_quat(store, q))))
    return T[TF_MESSAGE](transforms=stamped)
