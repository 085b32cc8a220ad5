"""Relative lidar motion between two scan stamps, from the best source the log has.

1. odometry (nav_msgs/Odometry, T_odom_base interpolated at both stamps, moved into the lidar
   frame with the base->lidar extrinsic from /tf_static);
2. IMU: rotation from integrating the gyro between the stamps, translation at the constant
   velocity of the last two confident estimates (or zero with extra noise);
3. constant velocity of the last two confident estimates (or zero with extra noise).

Sources 2-3 are guesses, so they come with extra noise (`MotionSourceConfig`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from mcl3d.core import geometry
from mcl3d.core.config import Section

KINDS = ("auto", "odom", "imu", "constant_velocity")


class MotionSourceConfig(Section):
    source: str = Field("auto", description="auto | odom | imu | constant_velocity")
    guess_trans_std_m_per_s: float = Field(
        0.3, ge=0.0, description="extra translation noise when translation is a guess")
    guess_rot_std_deg_per_s: float = Field(
        17.188733853924695, ge=0.0, description="extra rotation noise when rotation is a "
                                                "guess, deg/s")
    unknown_speed_m_per_s: float = Field(
        1.0, ge=0.0, description="extra translation noise per s when no velocity is known")
    unknown_turn_deg_per_s: float = Field(
        28.64788975654116, ge=0.0, description="extra rotation noise per s when no rate is "
                                               "known, deg/s")

    @property
    def guess_rot_std_rad_per_s(self) -> float:
        return math.radians(self.guess_rot_std_deg_per_s)

    @property
    def unknown_turn_rad_per_s(self) -> float:
        return math.radians(self.unknown_turn_deg_per_s)


@dataclass
class Motion:
    T_prev_curr: np.ndarray  # (4, 4) lidar motion from the previous scan to this one
    kind: str  # odom | imu | constant_velocity | none
    extra_std: tuple[float, float]  # (rad, m) added to the motion noise


class MotionSource:
    """Feed it odometry/IMU messages in log order; ask for the motion between scans."""

    def __init__(self, kind: str, cfg: MotionSourceConfig, T_base_lidar: np.ndarray | None = None,
                 R_lidar_imu: np.ndarray | None = None):
        self.kind = kind
        self.cfg = cfg
        self.T_base_lidar = np.eye(4) if T_base_lidar is None else T_base_lidar
        self.T_lidar_base = geometry.se3_inverse(self.T_base_lidar)
        self.R_lidar_imu = np.eye(3) if R_lidar_imu is None else R_lidar_imu
        self._odom: deque[tuple[int, np.ndarray]] = deque(maxlen=4096)
        self._imu: deque[tuple[int, np.ndarray]] = deque(maxlen=65536)
        self._estimates: deque[tuple[int, np.ndarray]] = deque(maxlen=2)

    # ---------------------------------------------------------------------- feeding
    def add_odometry(self, stamp_ns: int, T_odom_base: np.ndarray) -> None:
        if not self._odom or stamp_ns > self._odom[-1][0]:
            self._odom.append((int(stamp_ns), np.asarray(T_odom_base, dtype=np.float64)))

    def add_imu(self, stamp_ns: int, gyro_rad_s: np.ndarray) -> None:
        if not self._imu or stamp_ns > self._imu[-1][0]:
            self._imu.append((int(stamp_ns), np.asarray(gyro_rad_s, dtype=np.float64)))

    def add_estimate(self, stamp_ns: int, T_map_lidar: np.ndarray, confident: bool) -> None:
        """Estimates feed the constant-velocity guess; unconfident ones reset it."""
        if confident:
            self._estimates.append((int(stamp_ns), T_map_lidar))
        else:
            self._estimates.clear()

    def covers(self, stamp_ns: int) -> bool:
        """Whether the data needed for a scan at `stamp_ns` has arrived."""
        if self.kind == "odom":
            return bool(self._odom) and self._odom[-1][0] >= stamp_ns
        if self.kind == "imu":
            return bool(self._imu) and self._imu[-1][0] >= stamp_ns
        return True

    # ---------------------------------------------------------------------- motion
    def motion(self, t0_ns: int, t1_ns: int) -> Motion:
        dt = max((t1_ns - t0_ns) * 1e-9, 0.0)
        if self.kind == "odom" and len(self._odom) >= 1:
            T = self.T_lidar_base @ geometry.relative_se3(
                self._odom_at(t0_ns), self._odom_at(t1_ns)) @ self.T_base_lidar
            return Motion(T, "odom", (0.0, 0.0))
        T_cv, known = self._constant_velocity(t0_ns, t1_ns)
        c = self.cfg
        trans_extra = (c.guess_trans_std_m_per_s if known else c.unknown_speed_m_per_s) * dt
        if self.kind == "imu" and len(self._imu) >= 1:
            T = T_cv.copy()
            T[:3, :3] = self.R_lidar_imu @ self._gyro_rotation(t0_ns, t1_ns) @ self.R_lidar_imu.T
            while len(self._imu) > 1 and self._imu[1][0] <= t1_ns:
                self._imu.popleft()  # keep the sample in force at t1 and everything later
            return Motion(T, "imu", (0.0, trans_extra))
        rot_extra = (c.guess_rot_std_rad_per_s if known else c.unknown_turn_rad_per_s) * dt
        return Motion(T_cv, "constant_velocity", (rot_extra, trans_extra))

    def _odom_at(self, t_ns: int) -> np.ndarray:
        stamps = np.fromiter((s for s, _ in self._odom), dtype=np.int64)
        k = int(np.searchsorted(stamps, t_ns))
        if k <= 0:
            return self._odom[0][1]
        if k >= len(stamps):
            return self._odom[-1][1]
        (s0, T0), (s1, T1) = self._odom[k - 1], self._odom[k]
        return geometry.interpolate_se3(T0, T1, (t_ns - s0) / max(s1 - s0, 1))

    def _gyro_rotation(self, t0_ns: int, t1_ns: int) -> np.ndarray:
        """Integrated rotation (IMU frame) over [t0, t1], piecewise-constant rates."""
        R = np.eye(3)
        samples = list(self._imu)
        for k, (s, w) in enumerate(samples):
            s_next = samples[k + 1][0] if k + 1 < len(samples) else max(s, t1_ns)
            a, b = max(s, t0_ns), min(s_next, t1_ns)
            if k == 0 and t0_ns < s:
                a = t0_ns
            if b > a:
                R = R @ geometry.so3_exp(w * ((b - a) * 1e-9))
        return R

    def _constant_velocity(self, t0_ns: int, t1_ns: int) -> tuple[np.ndarray, bool]:
        if len(self._estimates) < 2:
            return np.eye(4), False
        (sa, Ta), (sb, Tb) = self._estimates
        if sb <= sa:
            return np.eye(4), False
        xi = geometry.se3_log(geometry.relative_se3(Ta, Tb)) * ((t1_ns - t0_ns) / (sb - sa))
        return geometry.se3_exp(xi), True
