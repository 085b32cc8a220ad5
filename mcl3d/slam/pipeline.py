"""`mcl3d slam LOG -o out/`: Monte Carlo SLAM over a whole log, written as trajectories, a
map and a per-frame log.

Steps: read the config, check the outputs, open the log, run `MonteCarloSlam.step` on every
scan with the IMU samples since the previous one, then write the representative particle's
trajectory (TUM, KITTI; every scan placed by its keyframes, so loop corrections show), the
representative of each scan as it was chosen online, the odometry front-end's trajectory, the
map (union of keyframe clouds, PLY), the per-frame log (CSV), the effective config and a
summary (ATE of SLAM and of odometry alone against the log's ground truth). Optionally build
a TSDF map from the result (`--tsdf`), so `slam` -> `localize` is one pipeline. Ctrl-C
keeps everything done so far.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core import config as config_io
from mcl3d.core.errors import Mcl3dError, RunInterrupted
from mcl3d.core.outputs import atomic_open, check_writable, output_folder
from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum
from mcl3d.slam.monte_carlo_slam import STAGES, MonteCarloSlam, SlamConfig, SlamFrame

OUTPUT_NAMES = {"tum": "slam.tum", "kitti": "slam_kitti.txt", "online": "slam_online.tum",
                "odometry": "odometry.tum", "map": "map.ply", "frames": "frames.csv",
                "summary": "slam_summary.json", "config": "slam_config.yaml"}


@dataclass
class SlamRequest:
    log: Path
    output_dir: Path
    config_path: Path | None = None
    overrides: dict = field(default_factory=dict)
    force: bool = False
    points_topic: str | None = None
    imu_topic: str | None = None
    gt_topic: str | None = None
    max_scans: int | None = None
    tsdf: Path | None = None


@dataclass
class SlamResult:
    frames: list[SlamFrame]
    outputs: dict[str, Path]
    summary: dict


def run(req: SlamRequest, progress: bool = True) -> SlamResult:
    """Run SLAM over the log; the output folder is removed again if nothing was written."""
    cfg = config_io.load(SlamConfig, req.config_path, req.overrides)
    paths = {k: Path(req.output_dir) / name for k, name in OUTPUT_NAMES.items()}
    if req.tsdf:
        check_writable(req.tsdf, req.force)
    with output_folder(req.output_dir):
        for path in paths.values():
            check_writable(path, req.force)
        result = _run(req, cfg, paths, progress)
    if req.tsdf:
        result.summary["tsdf"] = _build_tsdf(req, paths["tum"])
    return result


def _run(req: SlamRequest, cfg: SlamConfig, paths: dict, progress: bool) -> SlamResult:
    from mcl3d.console import track
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.odometry.pipeline import lidar_imu_feed

    gt_stamps, gt_poses, notes = [], [], []
    slam: MonteCarloSlam | None = None
    with LogReader(req.log, points_topic=req.points_topic, imu_topic=req.imu_topic,
                   gt_topic=req.gt_topic) as reader:
        reader.require("points")
        total = reader.count("points") or None
        if req.max_scans is not None and total is not None:
            total = min(total, req.max_scans)
        scans = lidar_imu_feed(reader, cfg.odometry.use_imu, gt_stamps, gt_poses, notes)
        if progress:
            scans = track(scans, total, "slam", "scans")
        try:
            for cloud, imu_rows, T_lidar_imu in scans:
                if slam is None:
                    slam = MonteCarloSlam(cfg)
                slam.odometry.T_lidar_imu = T_lidar_imu
                slam.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu_rows)
                if req.max_scans is not None and len(slam.frames) >= req.max_scans:
                    break
        except KeyboardInterrupt:
            if slam is not None and slam.frames:
                _write(paths, slam, cfg, gt_stamps, gt_poses, notes, interrupted=True)
            raise RunInterrupted(f"interrupted after {len(slam.frames) if slam else 0} scans; "
                                 f"the results so far are in {req.output_dir}") from None
    if slam is None or not slam.frames:
        raise Mcl3dError(f"{req.log}: the point-cloud topic has no scans")
    summary = _write(paths, slam, cfg, gt_stamps, gt_poses, notes, interrupted=False)
    return SlamResult(slam.frames, paths, summary)


def _build_tsdf(req: SlamRequest, trajectory: Path) -> dict:
    """The TSDF map of the log's scans placed by the SLAM trajectory (build-map's defaults)."""
    from mcl3d.mapping.pipeline import BuildMapPipeline
    from mcl3d.maps.build import BuildConfig

    result = BuildMapPipeline(req.log, req.tsdf, BuildConfig(), trajectory=trajectory,
                              force=req.force, points_topic=req.points_topic,
                              progress=False).run()
    return {"path": str(req.tsdf), "scans": result.n_scans, "seconds": result.seconds}


def write_ply(path: Path, points: np.ndarray) -> None:
    """Binary little-endian PLY of xyz float32 points (any viewer opens it)."""
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\ncomment mcl3d slam map\n"
              f"element vertex {len(pts)}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(pts.tobytes())


def _write(paths, slam: MonteCarloSlam, cfg: SlamConfig, gt_stamps, gt_poses, notes,
           interrupted: bool) -> dict:
    from mcl3d.registration.preprocess import voxel_downsample

    frames = slam.frames
    stamps_ns, poses = slam.trajectory()
    stamps_s = stamps_ns * 1e-9
    traj = Trajectory(stamps_s, poses)
    online = Trajectory(stamps_s, np.stack([f.T_world_lidar for f in frames]))
    odometry = Trajectory(stamps_s, np.stack([f.T_odom_lidar for f in frames]))
    write_tum(paths["tum"], traj)
    write_kitti(paths["kitti"], traj)
    write_tum(paths["online"], online)
    write_tum(paths["odometry"], odometry)
    write_ply(paths["map"], voxel_downsample(slam.map_points(), cfg.scan_voxel_m))
    _write_frames(paths["frames"], frames)
    config_io.save(cfg, paths["config"])
    summary = _summary(slam, traj, online, odometry, gt_stamps, gt_poses, notes, interrupted)
    with atomic_open(paths["summary"], "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def _write_frames(path: Path, frames: list[SlamFrame]) -> None:
    with atomic_open(path, "w") as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(["stamp_s", "x", "y", "z", "representative", "ess", "max_weight",
                      "hypotheses", "loop_particles", "corrected", "pruned", "keyframe",
                      "keyframes", "elevator", "travel_m", *[f"{s}_ms" for s in STAGES]])
        for fr in frames:
            x, y, z = fr.T_world_lidar[:3, 3]
            out.writerow([f"{fr.stamp_ns * 1e-9:.9f}", f"{x:.4f}", f"{y:.4f}", f"{z:.4f}",
                          fr.representative, f"{fr.ess:.1f}", f"{fr.max_weight:.4g}",
                          fr.hypotheses, fr.looping, fr.corrected, fr.pruned, int(fr.keyframe),
                          fr.num_keyframes, int(fr.elevator), f"{fr.travel_m:.3f}",
                          *[f"{fr.timings_ms.get(s, 0.0):.2f}" for s in STAGES]])


def _summary(slam: MonteCarloSlam, traj, online, odometry, gt_stamps, gt_poses, notes,
             interrupted: bool) -> dict:
    frames = slam.frames
    steady = frames[3:] or frames  # the first scans include compiling each kernel
    ms = {s: float(np.mean([f.timings_ms.get(s, 0.0) for f in steady])) for s in STAGES}
    totals = np.array([sum(f.timings_ms.values()) for f in steady])
    warnings = [f"scan {i}: {w}" for i, f in enumerate(frames) for w in f.odometry_warnings]
    return {
        "scans": len(frames), "interrupted": interrupted,
        "particles": slam.cfg.particles, "keyframes": slam.particles.num_keyframes,
        "path_length_m": odometry.path_length_m(),
        "loop_frames": int(sum(f.looping > 0 for f in frames)),
        "corrected_frames": int(sum(f.corrected > 0 for f in frames)),
        "pruned_total": int(sum(f.pruned for f in frames)),
        "elevator_frames": int(sum(f.elevator for f in frames)),
        "final_hypotheses": frames[-1].hypotheses, "final_ess": frames[-1].ess,
        "ms_per_frame": {"mean": float(totals.mean()), "median": float(np.median(totals)),
                         "max": float(totals.max())},
        "ms_per_stage": ms,
        "particle_state_bytes": slam.particles.state_bytes(),
        "notes": notes, "odometry_warnings": warnings[:100],
        "num_odometry_warnings": len(warnings),
        "evaluation": _evaluate({"slam": traj, "online": online, "odometry": odometry},
                                gt_stamps, gt_poses),
    }


def _evaluate(trajectories: dict[str, Trajectory], gt_stamps, gt_poses) -> dict | None:
    """ATE (SE(3)-aligned, as `evo_ape -a`) of each trajectory against the ground truth."""
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.odometry.pipeline import ground_truth

    if len(gt_stamps) < 2:
        return None
    gt = ground_truth(gt_stamps, gt_poses)
    out = {}
    for name, est in trajectories.items():
        if len(est) < 3:
            return None
        try:
            ev = evaluate(gt, est, alignment="se3").as_dict()
        except Mcl3dError as exc:
            return {"error": str(exc)}
        out[name] = {"ate_m": ev["ate"]["translation_m"]["rmse"],
                     "ate_deg": ev["ate"]["rotation_deg"]["rmse"]}
    return out
