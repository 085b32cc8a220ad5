"""What a `slam` run shows in Foxglove (result MCAP, live view): per scan the representative's
pose and the scan placed by it, the particle cloud's covariance ellipsoid, the particles by
weight, the other hypotheses, the ground truth (tied to the run's frame at the first scan)
and the error, the filter's numbers and its events; on keyframes and loops the keyframe
poses, the accepted loops as lines and each hypothesis' trajectory; at the end the map."""

from __future__ import annotations

import numpy as np

from mcl3d.evaluation.consistency import weighted_pose_mean
from mcl3d.io.foxglove_results import ResultPublisher, StartAligned, nearest_pose
from mcl3d.slam.monte_carlo_slam import HYPOTHESIS_MIN_SHARE, MonteCarloSlam, SlamFrame

MAX_HYPOTHESES = 8  # hypotheses drawn (heaviest first)
TRAJECTORY_EVERY = 10  # scans between trajectory updates without a keyframe or loop
GT_TAIL = 64  # ground-truth poses looked at per scan (the latest read)


def hypotheses(poses: np.ndarray, weights: np.ndarray, cell_m: float
               ) -> list[tuple[np.ndarray, np.ndarray, float, int]]:
    """(T_mean, 6x6 covariance, weight share, heaviest particle) of every grid cell of
    `cell_m` holding at least `HYPOTHESIS_MIN_SHARE` of the weight (as the filter counts
    hypotheses), heaviest first, at most `MAX_HYPOTHESES`."""
    w = weights / weights.sum()
    cells = np.floor(poses[:, :3, 3] / cell_m).astype(np.int64)
    _, label = np.unique(cells, axis=0, return_inverse=True)
    label = label.ravel()
    mass = np.bincount(label, weights=w)
    out = []
    for cell in np.argsort(-mass)[:MAX_HYPOTHESES]:
        if mass[cell] < HYPOTHESIS_MIN_SHARE:
            break
        members = np.flatnonzero(label == cell)
        T_mean, cov = weighted_pose_mean(poses[members], w[members])
        out.append((T_mean, cov, float(mass[cell]), int(members[np.argmax(w[members])])))
    return out


class SlamView:
    """Publishes each scan of one run; `finish(map_points)` publishes the map."""

    def __init__(self, publisher: ResultPublisher) -> None:
        self.pub = publisher
        self.align = StartAligned()
        self.loop_scans = 0  # scans whose loops were published
        self.several = False  # whether more than one hypothesis was shown last
        self.elevator = False
        self.last_ns = 0

    def update(self, slam: MonteCarloSlam, frame: SlamFrame, scan_points: np.ndarray,
               gt_stamps_ns: list[int], gt_poses: list[np.ndarray]) -> None:
        pub, stamp = self.pub, frame.stamp_ns
        self.last_ns = stamp
        pub.publish_estimate(stamp, frame.T_world_lidar, None, scan_points)
        pub.publish_covariance(stamp, frame.T_mean, frame.covariance)
        poses = slam.particles.current_poses()
        log_w = slam.particles.log_w.to_numpy().astype(np.float64)
        weights = np.exp(log_w - log_w.max())
        pub.publish_particles(stamp, poses[:, :3, 3], weights)
        hyps = hypotheses(poses, weights, slam.cfg.pruning.hypothesis_cell_m)
        pub.publish_hypotheses(stamp, [(T, cov, share) for T, cov, share, best in hyps
                                       if best != frame.representative])
        self.publish_loops(frame)
        if frame.keyframe or frame.loop_keyframes or len(slam.frames) % TRAJECTORY_EVERY == 1:
            pub.publish_keyframes(stamp, slam.representative_keyframes())
            pub.publish_trajectories(stamp, [self._path(slam, best) for *_, best in hyps])
        pub.publish_stats(stamp, {
            "ess": frame.ess, "hypotheses": frame.hypotheses, "looping": frame.looping,
            "corrected": frame.corrected, "pruned": frame.pruned,
            "keyframes": frame.num_keyframes, "error_m": self._error(frame, gt_stamps_ns,
                                                                     gt_poses),
            "ms": sum(frame.timings_ms.values())})
        self._log_changes(frame, len(hyps) > 1)

    def publish_loops(self, frame: SlamFrame) -> None:
        """The scan's accepted loops as lines from its pose to each loop keyframe, added to
        those drawn before (each loop is published once)."""
        if not frame.loop_keyframes:
            return
        segments = []
        for k, T_keyframe_lidar in zip(frame.loop_keyframes, frame.loop_relative, strict=True):
            T_world_keyframe = frame.T_world_lidar @ np.linalg.inv(T_keyframe_lidar)
            segments.append(np.stack([frame.T_world_lidar[:3, 3], T_world_keyframe[:3, 3]]))
            self.pub.log(frame.stamp_ns, "info", f"loop closed toward keyframe {k}")
        self.pub.publish_loops(frame.stamp_ns, np.stack(segments), f"loop {self.loop_scans}")
        self.loop_scans += 1

    @staticmethod
    def _path(slam: MonteCarloSlam, particle: int) -> np.ndarray:
        """A particle's trajectory through its own kept keyframes, ending at its pose now."""
        p = slam.particles
        keyframes = p.keyframe_poses(particle)[p.slots_in_order(), :3, 3]
        return np.vstack([keyframes, slam.particles.positions()[particle]])

    def _error(self, frame: SlamFrame, gt_stamps_ns: list[int], gt_poses: list[np.ndarray]
               ) -> float | None:
        T_gt = nearest_pose(np.asarray(gt_stamps_ns[-GT_TAIL:], np.int64),
                            gt_poses[-GT_TAIL:], frame.stamp_ns)
        if T_gt is None:
            return None
        T_gt = self.align(frame.T_world_lidar, T_gt)
        self.pub.publish_ground_truth(frame.stamp_ns, T_gt)
        return float(np.linalg.norm(T_gt[:3, 3] - frame.T_world_lidar[:3, 3]))

    def _log_changes(self, frame: SlamFrame, several: bool) -> None:
        stamp = frame.stamp_ns
        if several != self.several:
            self.pub.log(stamp, "info", f"{frame.hypotheses} hypotheses" if several
                         else "one hypothesis left")
            self.several = several
        if frame.elevator != self.elevator:
            self.pub.log(stamp, "info", "elevator ride" + ("" if frame.elevator else " ended"))
            self.elevator = frame.elevator
        for text in frame.odometry_warnings:
            self.pub.log(stamp, "warning", text)

    def finish(self, map_points: np.ndarray) -> None:
        self.pub.publish_map(self.last_ns, map_points)
