"""The scans of a log with the IMU samples between them, as the odometry and SLAM pipelines
consume them: per scan the cloud, the IMU rows since the previous scan and the lidar-IMU
extrinsic; the log's ground truth is collected on the way."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from mcl3d.core.errors import TopicError
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory

SAME_CLOCK_TOLERANCE_S = 1.0  # IMU stamps further than this from the scan's: another clock


def scans_with_imu(reader: LogReader, kinds: tuple[str, ...], gt_stamps_ns: list[int],
                   gt_poses: list[np.ndarray]) -> Iterator[tuple]:
    """(cloud, IMU rows since the previous scan, IMU frame) per scan, ground truth appended
    to `gt_stamps_ns` / `gt_poses` on the way. IMU rows are (stamp_s, wx, wy, wz, ax, ay, az);
    the last sample before a scan is kept for the next one: it holds until the next sample,
    across the scan stamp."""
    imu_frame = "imu"
    pending: list[tuple] = []
    for kind, msg in reader.messages(kinds):
        if kind == "imu":
            imu_frame = msg.frame_id or imu_frame
            pending.append((msg.stamp_ns * 1e-9, *msg.angular_velocity,
                            *msg.linear_acceleration))
        elif kind == "gt":
            gt_stamps_ns.append(msg.stamp_ns)
            gt_poses.append(msg.T)
        else:
            rows = np.array(pending, dtype=np.float64).reshape(-1, 7)
            del pending[:-1]
            yield msg, rows, imu_frame


class LidarImuFeed:
    """Iterates (cloud, IMU rows since the previous scan or None, T_lidar_imu) per scan.

    The IMU is used when asked and present, and dropped (with a note) when its stamps are
    not on the LiDAR's clock; its extrinsic is looked up once the first IMU message names its
    frame (identity, with a note, when the log has none). `notes` and the ground truth fill
    as the scans are read."""

    def __init__(self, reader: LogReader, use_imu: bool) -> None:
        self.reader = reader
        self.use_imu = use_imu
        self.notes: list[str] = []
        self.gt_stamps_ns: list[int] = []
        self.gt_poses: list[np.ndarray] = []

    def __iter__(self) -> Iterator[tuple]:
        reader = self.reader
        kinds = ("points", *(k for k in ("imu", "gt") if reader.topics.get(k)))
        use_imu = self.use_imu and "imu" in kinds
        if not use_imu:
            self.notes.append("no IMU used: the motion is predicted with constant velocity")
        T_lidar_imu, extrinsic_known = np.eye(4), False
        for cloud, imu_rows, imu_frame in scans_with_imu(reader, kinds, self.gt_stamps_ns,
                                                         self.gt_poses):
            if use_imu and len(imu_rows) and not _same_clock(imu_rows, cloud.stamp_ns):
                use_imu = False
                self.notes.append(f"IMU stamps ({imu_rows[-1, 0]:.3f} s) are not on the "
                                  f"LiDAR's clock ({cloud.stamp_ns * 1e-9:.3f} s): IMU ignored, "
                                  "constant-velocity prediction used")
            if use_imu and len(imu_rows) and not extrinsic_known:
                T_lidar_imu = self._imu_extrinsic(cloud.frame_id, imu_frame)
                extrinsic_known = True
            yield cloud, imu_rows if use_imu else None, T_lidar_imu

    def _imu_extrinsic(self, lidar_frame: str, imu_frame: str) -> np.ndarray:
        try:
            return self.reader.static_transform(lidar_frame, imu_frame)
        except TopicError:
            self.notes.append(f"no static transform between '{lidar_frame}' and "
                              f"'{imu_frame}': the IMU is taken to be aligned with the lidar")
            return np.eye(4)

    def ground_truth(self) -> Trajectory | None:
        """The ground truth read so far, sorted, one pose per stamp; None under two poses."""
        if len(self.gt_stamps_ns) < 2:
            return None
        order = np.argsort(self.gt_stamps_ns, kind="stable")
        stamps, keep = np.unique(np.asarray(self.gt_stamps_ns, np.int64)[order],
                                 return_index=True)
        return Trajectory.from_ns(stamps, np.asarray(self.gt_poses)[order][keep])


def _same_clock(imu_rows: np.ndarray, stamp_ns: int) -> bool:
    """Whether the IMU samples before a scan are stamped on the scan's clock (some drivers
    stamp IMU messages with sensor time since boot while clouds carry epoch time)."""
    return bool(abs(imu_rows[-1, 0] - stamp_ns * 1e-9) < SAME_CLOCK_TOLERANCE_S)
