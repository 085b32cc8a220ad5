"""`mcl3d odometry LOG -o out/`: odometry over a whole log, written as trajectories + summary.

Steps: read the config, check the outputs, open the log, find the lidar-IMU extrinsic, run
`Odometry.step` on every scan with the IMU samples since the previous one, write the
trajectory (TUM and KITTI), the per-frame relative motions with covariances, the effective
config, and a summary (ms per frame, keyframes, warnings, ATE/RPE and drift against the log's
ground truth when it has one). Ctrl-C keeps the frames done so far.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core import config as config_io
from mcl3d.core.errors import Mcl3dError, RunInterrupted, TopicError
from mcl3d.core.outputs import atomic_open, check_writable, output_folder
from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum
from mcl3d.odometry.lidar_odometry import Odometry, OdometryConfig, OdometryFrame

OUTPUT_NAMES = {"tum": "odometry.tum", "kitti": "odometry_kitti.txt",
                "motion": "relative_motion.npz", "summary": "odometry_summary.json",
                "config": "odometry_config.yaml"}


@dataclass
class OdometryRequest:
    log: Path
    output_dir: Path
    config_path: Path | None = None
    overrides: dict = field(default_factory=dict)
    force: bool = False
    points_topic: str | None = None
    imu_topic: str | None = None
    gt_topic: str | None = None
    max_scans: int | None = None


@dataclass
class OdometryResult:
    frames: list[OdometryFrame]
    outputs: dict[str, Path]
    summary: dict


def _imu_extrinsic(reader, lidar_frame: str, imu_frame: str) -> tuple[np.ndarray, str | None]:
    try:
        return reader.static_transform(lidar_frame, imu_frame), None
    except TopicError:
        return np.eye(4), (f"no static transform between '{lidar_frame}' and '{imu_frame}': "
                           "the IMU is taken to be aligned with the lidar")


def run(req: OdometryRequest, progress: bool = True) -> OdometryResult:
    """Run odometry over the log; the output folder is removed again if nothing was written."""
    with output_folder(req.output_dir):
        return _run(req, progress)


def _run(req: OdometryRequest, progress: bool) -> OdometryResult:
    from mcl3d.console import track
    from mcl3d.io.logs.reader import LogReader

    cfg = config_io.load(OdometryConfig, req.config_path, req.overrides)
    paths = {k: Path(req.output_dir) / name for k, name in OUTPUT_NAMES.items()}
    for path in paths.values():
        check_writable(path, req.force)
    frames: list[OdometryFrame] = []
    gt_stamps, gt_poses, notes = [], [], []
    with LogReader(req.log, points_topic=req.points_topic, imu_topic=req.imu_topic,
                   gt_topic=req.gt_topic) as reader:
        reader.require("points")
        odo: Odometry | None = None
        total = reader.count("points") or None
        if req.max_scans is not None and total is not None:
            total = min(total, req.max_scans)
        scans = lidar_imu_feed(reader, cfg.use_imu, gt_stamps, gt_poses, notes)
        if progress:
            scans = track(scans, total, "odometry", "scans")
        try:
            for cloud, imu_rows, T_lidar_imu in scans:
                if odo is None:
                    odo = Odometry(cfg)
                odo.T_lidar_imu = T_lidar_imu
                frames.append(odo.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu_rows))
                if req.max_scans is not None and len(frames) >= req.max_scans:
                    break
        except KeyboardInterrupt:
            _write(paths, frames, cfg, gt_stamps, gt_poses, notes, interrupted=True)
            raise RunInterrupted(f"interrupted after {len(frames)} scans; the trajectory so "
                                 f"far is in {paths['tum']}") from None
    if not frames:
        raise Mcl3dError(f"{req.log}: the point-cloud topic has no scans")
    summary = _write(paths, frames, cfg, gt_stamps, gt_poses, notes, interrupted=False)
    return OdometryResult(frames, paths, summary)


def lidar_imu_feed(reader, use_imu: bool, gt_stamps: list, gt_poses: list, notes: list[str]):
    """(cloud, IMU rows since the previous scan or None, T_lidar_imu) per scan, ground truth
    appended on the way. The IMU is used when asked and present, and dropped (with a note)
    when its stamps are not on the LiDAR's clock; its extrinsic is looked up once the first
    IMU message names its frame (identity, with a note, when the log has none)."""
    kinds = ["points"] + [k for k in ("imu", "gt") if reader.topics.get(k)]
    use_imu = use_imu and "imu" in kinds
    if not use_imu:
        notes.append("no IMU used: the motion is predicted with constant velocity")
    T_lidar_imu, extrinsic_known = np.eye(4), False
    for cloud, (imu_rows, imu_frame) in _scans_with_imu(reader, kinds, [], gt_stamps,
                                                         gt_poses):
        if use_imu and len(imu_rows) and not _same_clock(imu_rows, cloud.stamp_ns):
            use_imu = False
            notes.append(f"IMU stamps ({imu_rows[-1, 0]:.3f} s) are not on the LiDAR's clock "
                         f"({cloud.stamp_ns * 1e-9:.3f} s): IMU ignored, constant-velocity "
                         "prediction used")
        if use_imu and len(imu_rows) and not extrinsic_known:
            T_lidar_imu, note = _imu_extrinsic(reader, cloud.frame_id, imu_frame)
            extrinsic_known = True
            if note:
                notes.append(note)
        yield cloud, imu_rows if use_imu else None, T_lidar_imu


def _same_clock(imu_rows: np.ndarray, stamp_ns: int, tolerance_s: float = 1.0) -> bool:
    """Whether the IMU samples before a scan are stamped on the scan's clock (some drivers
    stamp IMU messages with sensor time since boot while clouds carry epoch time)."""
    return bool(abs(imu_rows[-1, 0] - stamp_ns * 1e-9) < tolerance_s)


def _scans_with_imu(reader, kinds, pending, gt_stamps, gt_poses):
    """(cloud, (imu rows since the previous scan, imu frame)) per scan, plus ground truth."""
    imu_frame = "imu"
    for kind, msg in reader.messages(tuple(kinds)):
        if kind == "imu":
            imu_frame = msg.frame_id or imu_frame
            pending.append((msg.stamp_ns * 1e-9, *msg.angular_velocity,
                            *msg.linear_acceleration))
        elif kind == "gt":
            gt_stamps.append(msg.stamp_ns * 1e-9)
            gt_poses.append(msg.T)
        else:
            rows = np.array(pending, dtype=np.float64).reshape(-1, 7)
            # keep the last sample: it holds until the next one, across the scan stamp
            del pending[:-1]
            yield msg, (rows, imu_frame)


def _write(paths, frames, cfg, gt_stamps, gt_poses, notes, interrupted: bool) -> dict:
    if not frames:
        return {}
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
    traj = Trajectory(stamps * 1e-9, np.stack([f.T_world_lidar for f in frames]))
    write_tum(paths["tum"], traj)
    write_kitti(paths["kitti"], traj)
    with atomic_open(paths["motion"], "wb") as f:
        np.savez(f, stamp_ns=stamps, T_prev_curr=np.stack([fr.T_prev_curr for fr in frames]),
                 covariance=np.stack([fr.covariance for fr in frames]),
                 num_inliers=np.array([fr.num_inliers for fr in frames]),
                 degenerate=np.array([fr.degenerate for fr in frames]),
                 keyframe=np.array([fr.keyframe for fr in frames]))
    config_io.save(cfg, paths["config"])
    ms = np.array([f.ms for f in frames[1:]] or [frames[0].ms])
    warnings = [f"scan {i} ({f.stamp_ns * 1e-9:.3f} s): {w}" for i, f in enumerate(frames)
                for w in f.warnings]
    summary = {
        "scans": len(frames), "interrupted": interrupted,
        "keyframes": int(sum(f.keyframe for f in frames)),
        "path_length_m": traj.path_length_m(),
        "ms_per_frame": {"mean": float(ms.mean()), "median": float(np.median(ms)),
                         "max": float(ms.max())},
        "degenerate_frames": int(sum(f.degenerate for f in frames)),
        "notes": notes, "warnings": warnings[:100], "num_warnings": len(warnings),
        "evaluation": _evaluate(traj, gt_stamps, gt_poses),
    }
    with atomic_open(paths["summary"], "w") as f:
        json.dump(summary, f, indent=2)
    return summary


def ground_truth(gt_stamps: list, gt_poses: list) -> Trajectory:
    """The log's ground-truth messages as a trajectory: sorted, one pose per stamp."""
    order = np.argsort(gt_stamps, kind="stable")
    stamps, keep = np.unique(np.asarray(gt_stamps)[order], return_index=True)
    return Trajectory(stamps, np.asarray(gt_poses)[order][keep])


def _evaluate(est: Trajectory, gt_stamps, gt_poses) -> dict | None:
    """ATE and RPE (per metre) after aligning the first poses, and the end-point drift as a
    percentage of the distance travelled."""
    from mcl3d.evaluation.metrics import evaluate

    if len(gt_stamps) < 2 or len(est) < 2:
        return None
    gt = ground_truth(gt_stamps, gt_poses)
    try:
        ev = evaluate(gt, est, alignment="origin", rpe_delta=1.0, rpe_unit="m")
    except Mcl3dError as exc:
        return {"error": str(exc)}
    ref, aligned = ev.association.ref_poses, ev.est_aligned_poses
    length = Trajectory(ev.association.est_stamps_s, ref).path_length_m()
    end_error = float(np.linalg.norm(ref[-1, :3, 3] - aligned[-1, :3, 3]))
    out = ev.as_dict()
    out["drift_percent"] = 100.0 * end_error / length if length > 0 else None
    out["gt_path_length_m"] = length
    return out
