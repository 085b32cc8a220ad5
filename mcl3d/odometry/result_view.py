"""What an `odometry` run shows in Foxglove (result MCAP, live view): per scan the pose and
the scan placed by it, the keyframe poses, the ground truth (tied to the run's frame at the
first scan) and the drift from it, the registration's numbers and its warnings; at the end
the keyframe scans as the map."""

from __future__ import annotations

import numpy as np

from mcl3d.core.geometry import transform_points
from mcl3d.io.foxglove_results import ResultPublisher, StartAligned, nearest_pose
from mcl3d.odometry.lidar_odometry import OdometryFrame
from mcl3d.registration.preprocess import voxel_downsample

MAP_VOXEL_M = 0.2  # the keyframe map's voxel size
GT_TAIL = 64  # ground-truth poses looked at per scan (the latest read)


class OdometryView:
    """Publishes each frame of one run; `finish` publishes the keyframe map."""

    def __init__(self, publisher: ResultPublisher) -> None:
        self.pub = publisher
        self.keyframe_poses: list[np.ndarray] = []
        self.keyframe_clouds: list[np.ndarray] = []  # map frame, MAP_VOXEL_M apart
        self.align = StartAligned()
        self.degenerate = False
        self.last_ns = 0

    def update(self, frame: OdometryFrame, scan_points: np.ndarray, gt_stamps_ns: list[int],
               gt_poses: list[np.ndarray]) -> None:
        pub, stamp = self.pub, frame.stamp_ns
        self.last_ns = stamp
        pub.publish_estimate(stamp, frame.T_world_lidar, None, scan_points)
        if frame.keyframe:
            self.keyframe_poses.append(frame.T_world_lidar)
            self.keyframe_clouds.append(voxel_downsample(
                transform_points(frame.T_world_lidar, np.asarray(scan_points, np.float64)),
                MAP_VOXEL_M))
            pub.publish_keyframes(stamp, np.stack(self.keyframe_poses))
        T_gt = nearest_pose(np.asarray(gt_stamps_ns[-GT_TAIL:], np.int64),
                            gt_poses[-GT_TAIL:], stamp)
        error_m = None
        if T_gt is not None:
            T_gt = self.align(frame.T_world_lidar, T_gt)
            pub.publish_ground_truth(stamp, T_gt)
            error_m = float(np.linalg.norm(T_gt[:3, 3] - frame.T_world_lidar[:3, 3]))
        pub.publish_stats(stamp, {"inliers": frame.num_inliers, "overlap": frame.overlap,
                                  "iterations": frame.iterations, "error_m": error_m,
                                  "ms": frame.wall_ms})
        self._log_changes(frame)

    def _log_changes(self, frame: OdometryFrame) -> None:
        """Warnings, a degenerate stretch once at its start and once at its end."""
        if frame.degenerate and not self.degenerate:
            self.pub.log(frame.stamp_ns, "warning", "; ".join(frame.warnings) or "degenerate")
        elif self.degenerate and not frame.degenerate:
            self.pub.log(frame.stamp_ns, "info", "registration constrained again")
        elif not frame.degenerate:
            for text in frame.warnings:
                self.pub.log(frame.stamp_ns, "warning", text)
        self.degenerate = frame.degenerate

    def finish(self) -> None:
        if self.keyframe_clouds:
            self.pub.publish_map(self.last_ns, voxel_downsample(
                np.concatenate(self.keyframe_clouds), MAP_VOXEL_M))
