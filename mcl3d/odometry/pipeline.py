"""`mcl3d odometry LOG -o out/`: odometry over a whole log, written as trajectories + summary.

Steps: check the outputs, open the log, find the lidar-IMU extrinsic, run `LidarOdometry.step` on
every scan with the IMU samples since the previous one, write the trajectory (TUM and KITTI),
the per-frame relative motions with covariances, the effective config, and a summary (ms per
frame, keyframes, warnings, ATE/RPE and drift against the log's ground truth when it has
one, the messages dropped for faults). Ctrl-C keeps the frames done so far; every
`CHECKPOINT_INTERVAL_S` of wall time the trajectory so far (TUM, KITTI) and a summary marked
as a checkpoint are written, so a crash keeps them too. The contract:
`run(request, on_progress=None)`.
"""

from __future__ import annotations

import json
from dataclasses import astuple, dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core import config as config_io
from mcl3d.core.checkpoint import Checkpointer, write_checkpoint_summary
from mcl3d.core.errors import Mcl3dError, RunInterrupted
from mcl3d.core.outputs import atomic_open, check_writable, output_folder
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.io.foxglove_results import open_results
from mcl3d.io.logs.plausibility import check_scans
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum
from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig, OdometryFrame
from mcl3d.odometry.odometry_summary import (
    FrameTimesMs,
    OdometrySummary,
    evaluate_odometry,
    run_warnings,
)
from mcl3d.odometry.result_view import OdometryView
from mcl3d.odometry.scan_feed import LidarImuFeed

MAX_LISTED_WARNINGS = 100  # the summary lists this many, and counts them all


@dataclass(frozen=True)
class OdometryOutputs:
    """The files one run writes, in its output folder."""

    tum: Path
    kitti: Path
    motion: Path
    summary: Path
    config: Path

    @classmethod
    def in_folder(cls, folder: Path) -> OdometryOutputs:
        return cls(tum=folder / "odometry.tum", kitti=folder / "odometry_kitti.txt",
                   motion=folder / "relative_motion.npz",
                   summary=folder / "odometry_summary.json",
                   config=folder / "odometry_config.yaml")

    def all(self) -> list[Path]:
        return list(astuple(self))


@dataclass
class OdometryRequest:
    """One odometry run: the log, the output folder and how to run it."""

    log: Path
    output_dir: Path
    config: OdometryConfig = field(default_factory=OdometryConfig)
    force: bool = False  # overwrite existing outputs
    points_topic: str | None = None  # default: the only one in the log
    imu_topic: str | None = None
    gt_topic: str | None = None
    max_scans: int | None = None  # stop after this many scans
    result_mcap: Path | None = None  # also write the Foxglove result log here
    live_port: int | None = None  # serve the same messages live on this port (None: off)


@dataclass
class OdometryResult:
    frames: list[OdometryFrame]
    outputs: OdometryOutputs
    summary: OdometrySummary


def run(request: OdometryRequest, on_progress: ProgressCallback | None = None
        ) -> OdometryResult:
    """Run odometry over the log; the output folder is removed again if nothing was written."""
    with output_folder(request.output_dir):
        return _run(request, on_progress)


def _run(req: OdometryRequest, on_progress: ProgressCallback | None) -> OdometryResult:
    cfg = req.config
    outputs = OdometryOutputs.in_folder(Path(req.output_dir))
    for path in outputs.all():
        check_writable(path, req.force)
    frames: list[OdometryFrame] = []
    with LogReader(req.log, points_topic=req.points_topic, imu_topic=req.imu_topic,
                   gt_topic=req.gt_topic) as reader, open_results(
            req.result_mcap, req.live_port, req.force, "odometry") as pub:
        view = None if pub is None else OdometryView(pub)
        reader.require("points")
        check_scans(reader, req.log, needs_3d=True)
        odo: LidarOdometry | None = None
        total = reader.count("points") or None
        if req.max_scans is not None and total is not None:
            total = min(total, req.max_scans)
        feed = LidarImuFeed(reader, cfg.use_imu)
        checkpoint = Checkpointer(lambda: _write_checkpoint(outputs, frames, feed))
        try:
            for cloud, imu_rows, T_lidar_imu in feed:
                if odo is None:
                    odo = LidarOdometry(cfg)
                odo.T_lidar_imu = T_lidar_imu
                frames.append(odo.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu_rows))
                if view is not None:
                    view.update(frames[-1], cloud.points, feed.gt_stamps_ns, feed.gt_poses)
                report(on_progress, Progress("odometry", len(frames), total))
                checkpoint.tick()
                if req.max_scans is not None and len(frames) >= req.max_scans:
                    break
        except KeyboardInterrupt:
            if frames:
                _write(outputs, frames, cfg, feed, interrupted=True)
            raise RunInterrupted(f"interrupted after {len(frames)} scans; the trajectory so "
                                 f"far is in {outputs.tum}") from None
        if view is not None:
            view.finish()
    if not frames:
        raise Mcl3dError(f"{req.log}: the point-cloud topic has no scans")
    summary = _write(outputs, frames, cfg, feed, interrupted=False)
    return OdometryResult(frames, outputs, summary)


def _trajectory(frames: list[OdometryFrame]) -> Trajectory:
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
    return Trajectory.from_ns(stamps, np.stack([f.T_world_lidar for f in frames]))


def _write_checkpoint(outputs: OdometryOutputs, frames: list[OdometryFrame],
                      feed: LidarImuFeed) -> None:
    """The trajectory so far and the cheap part of the summary (no accuracy, no motions)."""
    traj = _trajectory(frames)
    write_tum(outputs.tum, traj)
    write_kitti(outputs.kitti, traj)
    write_checkpoint_summary(outputs.summary, {
        "scans": len(frames), "keyframes": int(sum(f.keyframe for f in frames)),
        "path_length_m": traj.path_length_m(),
        "degenerate_frames": int(sum(f.degenerate for f in frames)),
        "faults": feed.reader.faults.as_dict()})


def _write(outputs: OdometryOutputs, frames: list[OdometryFrame], cfg: OdometryConfig,
           feed: LidarImuFeed, interrupted: bool) -> OdometrySummary:
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
    traj = _trajectory(frames)
    write_tum(outputs.tum, traj)
    write_kitti(outputs.kitti, traj)
    with atomic_open(outputs.motion, "wb") as f:
        np.savez(f, stamp_ns=stamps, T_prev_curr=np.stack([fr.T_prev_curr for fr in frames]),
                 covariance=np.stack([fr.covariance for fr in frames]),
                 num_inliers=np.array([fr.num_inliers for fr in frames]),
                 degenerate=np.array([fr.degenerate for fr in frames]),
                 keyframe=np.array([fr.keyframe for fr in frames]),
                 redeskewed=np.array([fr.redeskewed for fr in frames]))
    config_io.save(cfg, outputs.config)
    ms = np.array([f.wall_ms for f in frames[1:]] or [frames[0].wall_ms])
    warnings, stretches = run_warnings(frames)
    accuracy, accuracy_error = evaluate_odometry(traj, feed.ground_truth())
    summary = OdometrySummary(
        scans=len(frames), interrupted=interrupted,
        keyframes=int(sum(f.keyframe for f in frames)), path_length_m=traj.path_length_m(),
        ms_per_frame=FrameTimesMs.of(ms),
        degenerate_frames=int(sum(f.degenerate for f in frames)), notes=feed.notes,
        warnings=warnings[:MAX_LISTED_WARNINGS], num_warnings=len(warnings),
        accuracy=accuracy, accuracy_error=accuracy_error, faults=feed.reader.faults,
        degenerate_stretches=stretches,
        redeskewed_frames=int(sum(f.redeskewed for f in frames)))
    with atomic_open(outputs.summary, "w") as f:
        json.dump(summary.as_dict(), f, indent=2)
    return summary
