"""Log messages as plain dataclasses of numpy arrays, independent of ROS 1/ROS 2 encodings.

Poses are 4x4 float64 `T_parent_child` matrices; quaternions elsewhere are (x, y, z, w).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PointCloud:
    """One scan: valid points in the sensor frame plus per-point time and other fields."""

    stamp_ns: int
    frame_id: str
    points: np.ndarray  # (N, 3) float32; NaN/inf/all-zero points already dropped
    times_s: np.ndarray | None  # (N,) float32 seconds relative to stamp_ns, or None
    fields: dict[str, np.ndarray] = field(default_factory=dict)  # aligned with points
    n_dropped: int = 0  # invalid points removed while decoding
    height: int = 1  # layout of the original message (organized clouds: rows)
    width: int = 0

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class Imu:
    stamp_ns: int
    frame_id: str
    angular_velocity: np.ndarray  # (3,) rad/s
    linear_acceleration: np.ndarray  # (3,) m/s^2
    orientation_xyzw: np.ndarray | None = None  # None when the IMU gives no orientation


@dataclass
class Odometry:
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    T_frame_child: np.ndarray  # (4, 4) float64
    twist: np.ndarray  # (6,) [vx vy vz wx wy wz] in the child frame
    pose_covariance: np.ndarray  # (6, 6) ROS order (x y z rotx roty rotz)


@dataclass
class PoseStamped:
    stamp_ns: int
    frame_id: str
    T: np.ndarray  # (4, 4) float64, pose of the tracked body in frame_id


@dataclass
class Transform:
    stamp_ns: int
    parent_frame: str
    child_frame: str
    T_parent_child: np.ndarray  # (4, 4) float64
