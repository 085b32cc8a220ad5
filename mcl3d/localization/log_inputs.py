"""What the log gives the filter before the first scan: the first messages, the motion
source (odometry, IMU or constant velocity) with its extrinsics, the gravity's roll/pitch
and the initial pose."""

from __future__ import annotations

import numpy as np

from mcl3d.core import geometry
from mcl3d.core.errors import TopicError
from mcl3d.localization.initialization import gravity_roll_pitch
from mcl3d.localization.localization_config import LocalizerConfig
from mcl3d.localization.motion_source import MotionSource, MotionSourceConfig


def first_messages(reader, kinds: tuple[str, ...], imu_samples: int) -> dict:
    """The first scan / odometry message and the first `imu_samples` IMU messages."""
    firsts: dict = {"imu": []}
    wanted = {k for k in kinds if reader.topics.get(k)}
    for kind, msg in reader.messages(tuple(wanted)):
        if kind == "imu":
            if len(firsts["imu"]) < imu_samples:
                firsts["imu"].append(msg)
        else:
            firsts.setdefault(kind, msg)
        if all((k == "imu" and len(firsts["imu"]) >= imu_samples) or (k != "imu" and k in firsts)
               for k in wanted):
            break
    return firsts


def _extrinsic(reader, parent: str, child: str, what: str, warnings: list[str]) -> np.ndarray:
    if parent == child:
        return np.eye(4)
    try:
        return reader.static_transform(parent, child)
    except TopicError:
        warnings.append(f"no static transform {parent} -> {child} in the log; assuming the "
                        f"{what} frame equals the lidar frame")
        return np.eye(4)


def make_motion_source(reader, cfg: MotionSourceConfig, firsts: dict, lidar_frame: str,
                       warnings: list[str]) -> MotionSource:
    """The motion source asked for, or with `auto` the best one the log has."""
    kind = cfg.source
    has_odom = "odom" in firsts
    has_imu = bool(firsts["imu"])
    if kind == "auto":
        kind = "odom" if has_odom else "imu" if has_imu else "constant_velocity"
        if kind == "constant_velocity":
            warnings.append("the log has no odometry and no IMU: using a constant-velocity "
                            "motion model with extra noise (name the odometry or IMU topic "
                            "if the log has them under other types)")
    elif kind == "odom" and not has_odom:
        raise TopicError(f"{reader.path}: the motion source is odometry but the log has no "
                         f"odometry messages", setting="motion")
    elif kind == "imu" and not has_imu:
        raise TopicError(f"{reader.path}: the motion source is the IMU but the log has no IMU "
                         f"messages", setting="motion")
    T_base_lidar = R_lidar_imu = None
    if kind == "odom":
        T_base_lidar = _extrinsic(reader, firsts["odom"].child_frame_id, lidar_frame, "odometry",
                                  warnings)
    if kind == "imu":
        R_lidar_imu = _extrinsic(reader, lidar_frame, firsts["imu"][0].frame_id, "IMU",
                                 warnings)[:3, :3]
    return MotionSource(kind, cfg, T_base_lidar, R_lidar_imu)


def gravity_in_lidar(reader, firsts: dict, lidar_frame: str, warnings: list[str]):
    """Roll/pitch of the lidar from the first IMU samples, or None without an IMU."""
    if not firsts["imu"]:
        return None
    R = _extrinsic(reader, lidar_frame, firsts["imu"][0].frame_id, "IMU", warnings)[:3, :3]
    acc = np.stack([m.linear_acceleration for m in firsts["imu"]]) @ R.T
    return gravity_roll_pitch(acc)


def initial_pose(cfg: LocalizerConfig, gt) -> np.ndarray | None:
    """T_map_lidar to start around (a given pose, or the first ground truth), None for a
    global initialization."""
    init = cfg.init
    if init.mode == "pose":
        x, y, z, roll, pitch, yaw = init.pose_m_rad
        return geometry.se3(geometry.rpy_to_rot(roll, pitch, yaw), [x, y, z])
    if init.mode == "gt":
        if gt is None:
            raise TopicError("starting at the ground truth needs a ground-truth topic in the "
                             "log (ground_truth, groundtruth or gt): name the topic, or give "
                             "an initial pose", setting="gt_topic")
        return gt[1][0]
    return None
