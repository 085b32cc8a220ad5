"""`mcl3d slam LOG -o out/`: Monte Carlo SLAM over a whole log, written as trajectories, a
map and a per-frame log.

Steps: check the outputs, open the log, run `MonteCarloSlam.step` on every scan with the IMU
samples since the previous one, then write the representative particle's trajectory (TUM,
KITTI; every scan placed by its keyframes, so loop corrections show), the representative of
each scan as it was chosen online, the odometry front-end's trajectory, the map (union of
keyframe clouds, PLY), the per-frame log (CSV), the effective config, a summary (ATE of
SLAM and of odometry alone against the log's ground truth, messages dropped for faults) and a
picture of the run (slam.png).
Optionally build a TSDF map from the result, so `slam` -> `localize` is one pipeline.
Ctrl-C keeps everything done so far. Every `CHECKPOINT_INTERVAL_S` of wall time the run
writes the trajectories that need no end-of-run work, the online one (slam_online.tum) and
the odometry one (odometry.tum), and a summary marked as a checkpoint, so a crash keeps them;
slam.tum is placed by the keyframes at the end and is written then. The contract:
`run(request, on_progress=None)`.
"""

from __future__ import annotations

import csv
import json
from dataclasses import astuple, dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core import config as config_io
from mcl3d.core.checkpoint import Checkpointer, write_checkpoint_summary
from mcl3d.core.errors import Mcl3dError, RunInterrupted
from mcl3d.core.geometry import rot_to_quat
from mcl3d.core.outputs import atomic_open, check_writable, output_folder
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.evaluation.run_plots import SLAM_PICTURE, slam_figure, write_png
from mcl3d.io.foxglove_results import open_results
from mcl3d.io.logs.plausibility import check_scans
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum
from mcl3d.mapping.pipeline import BuildMapRequest
from mcl3d.mapping.pipeline import run as build_map
from mcl3d.maps.build import BuildConfig
from mcl3d.odometry.scan_feed import LidarImuFeed
from mcl3d.registration.preprocess import voxel_downsample
from mcl3d.slam.frame_store import STAGES, SlamFrames
from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
from mcl3d.slam.result_view import SlamView
from mcl3d.slam.slam_config import SlamConfig
from mcl3d.slam.slam_summary import SlamSummary, summarize


@dataclass(frozen=True)
class SlamOutputs:
    """The files one run writes, in its output folder."""

    tum: Path
    kitti: Path
    online: Path
    odometry: Path
    map: Path
    frames: Path
    summary: Path
    config: Path
    picture: Path

    @classmethod
    def in_folder(cls, folder: Path) -> SlamOutputs:
        return cls(tum=folder / "slam.tum", kitti=folder / "slam_kitti.txt",
                   online=folder / "slam_online.tum", odometry=folder / "odometry.tum",
                   map=folder / "map.ply", frames=folder / "frames.csv",
                   summary=folder / "slam_summary.json", config=folder / "slam_config.yaml",
                   picture=folder / SLAM_PICTURE)

    def all(self) -> list[Path]:
        return list(astuple(self))


@dataclass
class SlamRequest:
    """One SLAM run: the log, the output folder and how to run it."""

    log: Path
    output_dir: Path
    config: SlamConfig = field(default_factory=SlamConfig)
    force: bool = False  # overwrite existing outputs
    points_topic: str | None = None  # default: the only one in the log
    imu_topic: str | None = None
    gt_topic: str | None = None
    max_scans: int | None = None  # stop after this many scans
    tsdf: Path | None = None  # also build a TSDF map here from the SLAM trajectory
    result_mcap: Path | None = None  # also write the Foxglove result log here
    live_port: int | None = None  # serve the same messages live on this port (None: off)


@dataclass(frozen=True)
class TsdfBuild:
    path: Path
    scans: int
    seconds: float


@dataclass
class SlamResult:
    frames: SlamFrames
    outputs: SlamOutputs
    summary: SlamSummary
    tsdf: TsdfBuild | None = None


def run(request: SlamRequest, on_progress: ProgressCallback | None = None) -> SlamResult:
    """Run SLAM over the log; the output folder is removed again if nothing was written."""
    outputs = SlamOutputs.in_folder(Path(request.output_dir))
    if request.tsdf:
        check_writable(request.tsdf, request.force)
    with output_folder(request.output_dir):
        for path in outputs.all():
            check_writable(path, request.force)
        result = _run(request, outputs, on_progress)
    if request.tsdf:
        result.tsdf = _build_tsdf(request, outputs.tum)
    return result


def _run(req: SlamRequest, outputs: SlamOutputs, on_progress: ProgressCallback | None
         ) -> SlamResult:
    cfg = req.config
    slam: MonteCarloSlam | None = None
    with LogReader(req.log, points_topic=req.points_topic, imu_topic=req.imu_topic,
                   gt_topic=req.gt_topic) as reader, open_results(
            req.result_mcap, req.live_port, req.force, "slam") as pub:
        view = None if pub is None else SlamView(pub)
        reader.require("points")
        check_scans(reader, req.log, needs_3d=True)
        total = reader.count("points") or None
        if req.max_scans is not None and total is not None:
            total = min(total, req.max_scans)
        feed = LidarImuFeed(reader, cfg.odometry.use_imu)
        checkpoint = Checkpointer(lambda: _write_checkpoint(outputs, slam, feed))
        try:
            for cloud, imu_rows, T_lidar_imu in feed:
                if slam is None:
                    slam = MonteCarloSlam(cfg, scans=total)
                slam.odometry.T_lidar_imu = T_lidar_imu
                frame = slam.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu_rows)
                if view is not None:
                    view.update(slam, frame, cloud.points, feed.gt_stamps_ns, feed.gt_poses)
                report(on_progress, Progress("slam", len(slam.frames), total))
                checkpoint.tick()
                if req.max_scans is not None and len(slam.frames) >= req.max_scans:
                    break
        except KeyboardInterrupt:
            if slam is not None and slam.frames:
                _write(outputs, slam, feed, interrupted=True)
            raise RunInterrupted(f"interrupted after {len(slam.frames) if slam else 0} scans; "
                                 f"the results so far are in {req.output_dir}") from None
        if view is not None and slam is not None:
            view.finish(voxel_downsample(slam.map_points(), slam.cfg.front_end.scan_voxel_m))
    if slam is None or not slam.frames:
        raise Mcl3dError(f"{req.log}: the point-cloud topic has no scans")
    summary = _write(outputs, slam, feed, interrupted=False)
    return SlamResult(slam.frames, outputs, summary)


def _build_tsdf(req: SlamRequest, trajectory: Path) -> TsdfBuild:
    """The TSDF map of the log's scans placed by the SLAM trajectory (build-map's defaults)."""
    result = build_map(BuildMapRequest(req.log, req.tsdf, BuildConfig(), trajectory=trajectory,
                                       force=req.force, points_topic=req.points_topic))
    return TsdfBuild(req.tsdf, result.n_scans, result.seconds)


def write_ply(path: Path, points: np.ndarray) -> None:
    """Binary little-endian PLY of xyz float32 points (any viewer opens it)."""
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\ncomment mcl3d slam map\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(pts.tobytes())


def _write_checkpoint(outputs: SlamOutputs, slam: MonteCarloSlam, feed: LidarImuFeed) -> None:
    """The online and odometry trajectories so far and the cheap part of the summary."""
    frames = slam.frames
    online = Trajectory.from_ns(frames.stamp_ns, frames.poses("T_world_lidar"))
    write_tum(outputs.online, online)
    write_tum(outputs.odometry, Trajectory.from_ns(frames.stamp_ns, frames.poses("T_odom_lidar")))
    write_checkpoint_summary(outputs.summary, {
        "scans": len(frames), "particles": slam.cfg.particles,
        "keyframes": int(frames.num_keyframes[-1]), "path_length_m": online.path_length_m(),
        "final_hypotheses": int(frames.hypotheses[-1]), "final_ess": float(frames.ess[-1]),
        "faults": feed.reader.faults.as_dict()})


def _write(outputs: SlamOutputs, slam: MonteCarloSlam, feed: LidarImuFeed,
           interrupted: bool) -> SlamSummary:
    frames = slam.frames
    stamps_ns, poses = slam.trajectory()
    trajectories = {
        "slam": Trajectory.from_ns(stamps_ns, poses),
        "online": Trajectory.from_ns(stamps_ns, frames.poses("T_world_lidar")),
        "odometry": Trajectory.from_ns(stamps_ns, frames.poses("T_odom_lidar"))}
    write_tum(outputs.tum, trajectories["slam"])
    write_kitti(outputs.kitti, trajectories["slam"])
    write_tum(outputs.online, trajectories["online"])
    write_tum(outputs.odometry, trajectories["odometry"])
    map_points = voxel_downsample(slam.map_points(), slam.cfg.front_end.scan_voxel_m)
    write_ply(outputs.map, map_points)
    _write_frames(outputs.frames, frames)
    config_io.save(slam.cfg, outputs.config)
    gt = feed.ground_truth()
    summary = summarize(slam, trajectories, gt, feed.notes, interrupted, feed.reader.faults)
    with atomic_open(outputs.summary, "w") as f:
        json.dump(summary.as_dict(), f, indent=2)
    write_png(outputs.picture, slam_figure(frames, trajectories, map_points, gt,
                                           slam.cfg.particles, slam.cfg.front_end.scan_voxel_m))
    return summary


TANGENT = ("rx", "ry", "rz", "x", "y", "z")  # the covariance's axes, rotation first
COV_UPPER = np.triu_indices(6)
COV_COLUMNS = [f"cov_{TANGENT[i]}_{TANGENT[j]}" for i, j in zip(*COV_UPPER, strict=True)]


def _write_frames(path: Path, frames: SlamFrames) -> None:
    """One row per scan: the representative's position, the filter's state, the cloud's
    weighted mean pose and covariance (upper triangle, rad and m), stage times."""
    loops = {i: keyframes for i, keyframes, _ in frames.loops()}
    columns = [frames.stamp_ns, frames.poses("T_world_lidar"), frames.representative,
               frames.ess, frames.max_weight, frames.hypotheses, frames.looping,
               frames.corrected, frames.pruned, frames.keyframe, frames.num_keyframes,
               frames.elevator, frames.travel_m, frames.timings_ms, frames.poses("T_mean"),
               frames.covariance]
    with atomic_open(path, "w") as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(["stamp_s", "x", "y", "z", "representative", "ess", "max_weight",
                      "hypotheses", "loop_particles", "corrected", "pruned", "keyframe",
                      "keyframes", "elevator", "travel_m", *[f"{s}_ms" for s in STAGES],
                      "mean_x", "mean_y", "mean_z", "mean_qx", "mean_qy", "mean_qz",
                      "mean_qw", *COV_COLUMNS, "loop_keyframes"])
        for i, (stamp_ns, T, rep, ess, max_w, hyp, looping, corrected, pruned, keyframe,
                num_kf, elevator, travel_m, ms, T_mean, cov) in enumerate(
                zip(*columns, strict=True)):
            x, y, z = T[:3, 3]
            out.writerow([f"{int(stamp_ns) * 1e-9:.9f}", f"{x:.4f}", f"{y:.4f}", f"{z:.4f}",
                          rep, f"{ess:.1f}", f"{max_w:.4g}", hyp, looping, corrected, pruned,
                          int(keyframe), num_kf, int(elevator), f"{travel_m:.3f}",
                          *[f"{v:.2f}" for v in ms],
                          *[f"{v:.5f}" for v in T_mean[:3, 3]],
                          *[f"{v:.8f}" for v in rot_to_quat(T_mean[:3, :3])],
                          *[f"{v:.6g}" for v in cov[COV_UPPER]],
                          " ".join(str(k) for k in loops.get(i, ()))])
