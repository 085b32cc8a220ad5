"""The peers of `bench/study_slam.py`, fed the scans `mcl3d slam` gets: kiss-icp (LiDAR
odometry), kiss-slam (kiss-icp + local maps + loop closures + pose graph) and rko-lio
(LiDAR-inertial odometry). Scans come from the log through mcl3d.io.logs, cropped to the
same field of view as the SLAM run; every trajectory is stamped at the scans' header stamps
so it is scored against the ground truth exactly as mcl3d's are.

Install with `pip install -e .[bench]` (kiss-icp, kiss-slam, rko-lio).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MID_POSE = 0.5  # kiss-icp's deskew puts the pose at the middle of the [0, 1] point times
MIN_RANGE_M = 0.5  # mcl3d's odometry default
MAX_RANGE_M = 100.0
THREADS = 0  # worker threads of each peer (0: all cores, their default)


@dataclass
class PeerRun:
    """One peer's trajectory over a log, and what it closed (kiss-slam)."""

    name: str
    stamps_ns: np.ndarray
    poses: np.ndarray  # T_world_lidar at each stamp, the first scan's frame as world
    seconds: float
    closures: list[tuple[int, int, np.ndarray]] = field(default_factory=list)
    # (scan of the matched local map's key pose, scan of the query's, T_query_matched)


def scans(log: Path, fov_deg: float):
    """(stamp_ns, points, per-point times relative to the stamp, IMU rows, T_lidar_imu) per
    scan, cropped as the SLAM run crops; the ground truth is read on the way (returned by
    the generator at its end)."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.odometry.scan_feed import LidarImuFeed
    from mcl3d.slam.monte_carlo_slam import crop_fov

    with LogReader(log) as reader:
        feed = LidarImuFeed(reader, use_imu=True)
        for cloud, imu_rows, T_lidar_imu in feed:
            times = cloud.times_s if cloud.times_s is not None else np.zeros(len(cloud.points))
            points, times = crop_fov(np.asarray(cloud.points, np.float64),
                                     np.asarray(times, np.float64), fov_deg)
            keep = np.linalg.norm(points, axis=1)
            keep = (keep >= MIN_RANGE_M) & (keep <= MAX_RANGE_M)
            yield cloud.stamp_ns, points[keep], times[keep], imu_rows, T_lidar_imu


def _unit_times(times: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-point times mapped to [0, 1], and where the stamp (time 0) falls on that scale."""
    lo, hi = float(times.min()), float(times.max())
    if hi <= lo:
        return np.full(times.shape, MID_POSE), MID_POSE
    return (times - lo) / (hi - lo), -lo / (hi - lo)


def _at_stamp(T_mid: np.ndarray, delta: np.ndarray, stamp_unit: float) -> np.ndarray:
    """kiss-icp's mid-scan pose moved to the header stamp along the scan's own motion."""
    from mcl3d.core.geometry import se3_exp, se3_log

    return T_mid @ se3_exp((stamp_unit - MID_POSE) * se3_log(delta))


def _kiss_icp_config(max_range_m: float, voxel_m: float | None):
    from kiss_icp.config import KISSConfig

    cfg = KISSConfig()
    cfg.data.deskew = True
    cfg.data.max_range = max_range_m
    cfg.data.min_range = MIN_RANGE_M
    cfg.mapping.voxel_size = voxel_m or max_range_m / 100.0
    cfg.registration.max_num_threads = THREADS
    return cfg


def run_kiss_icp(log: Path, fov_deg: float, max_range_m: float,
                 voxel_m: float | None = None) -> PeerRun:
    from kiss_icp.kiss_icp import KissICP

    odo = KissICP(_kiss_icp_config(max_range_m, voxel_m))
    stamps, poses = [], []
    t0 = time.perf_counter()
    for stamp_ns, points, times, _, _ in scans(log, fov_deg):
        unit, stamp_unit = _unit_times(times)
        odo.register_frame(points, unit)
        stamps.append(stamp_ns)
        poses.append(_at_stamp(odo.last_pose, odo.last_delta, stamp_unit))
    return PeerRun("kiss-icp", np.array(stamps), np.array(poses), time.perf_counter() - t0)


def run_kiss_slam(log: Path, fov_deg: float, max_range_m: float,
                  voxel_m: float | None = None) -> PeerRun:
    """kiss-slam as its own pipeline drives it; the closures it accepted are kept with the
    scans of their local maps' key poses, so they can be checked against the truth."""
    from kiss_slam.config.config import load_config
    from kiss_slam.slam import KissSLAM

    cfg = load_config(None)
    cfg.odometry.preprocessing.max_range = max_range_m
    cfg.odometry.preprocessing.min_range = MIN_RANGE_M
    cfg.odometry.preprocessing.deskew = True
    cfg.odometry.mapping.voxel_size = voxel_m or max_range_m / 100.0
    cfg.odometry.registration.max_num_threads = THREADS
    slam = KissSLAM(cfg)
    key_scan = [0]  # scan of each local map's key pose (node 0 starts at the first scan)
    closures: list[tuple[int, int, np.ndarray]] = []
    count = [0]
    new_node, compute = slam.generate_new_node, slam.closer.compute

    def generate_new_node():
        key_scan.append(count[0] - 1)  # the new local map starts at the last scan
        new_node()

    def closer_compute(query_id, points, graph):
        good, ref_id, target_id, T = compute(query_id, points, graph)
        if good:
            closures.append((key_scan[ref_id], key_scan[target_id], np.array(T)))
        return good, ref_id, target_id, T

    slam.generate_new_node, slam.closer.compute = generate_new_node, closer_compute
    stamps, fix = [], []
    t0 = time.perf_counter()
    for stamp_ns, points, times, _, _ in scans(log, fov_deg):
        unit, stamp_unit = _unit_times(times)
        count[0] += 1
        slam.process_scan(points, unit)
        stamps.append(stamp_ns)
        fix.append(_at_stamp(np.eye(4), slam.odometry.last_delta, stamp_unit))
    slam.generate_new_node()
    slam.local_map_graph.erase_last_local_map()
    poses, _ = slam.fine_grained_optimization()
    poses = np.array(poses)[-len(stamps):] @ np.array(fix)
    return PeerRun("kiss-slam", np.array(stamps), poses, time.perf_counter() - t0, closures)


def _xyzw_xyz(T: np.ndarray) -> list[float]:
    from mcl3d.core.geometry import rot_to_quat

    return [*map(float, rot_to_quat(T[:3, :3])), *map(float, T[:3, 3])]


def run_rko_lio(log: Path, fov_deg: float, max_range_m: float) -> PeerRun:
    """rko-lio with the lidar as its base frame and the log's IMU extrinsic."""
    from rko_lio.lio_pipeline import LIOPipeline, PipelineConfig

    pipe, stamps = None, []
    t0 = time.perf_counter()
    for stamp_ns, points, times, imu_rows, T_lidar_imu in scans(log, fov_deg):
        if pipe is None:
            pipe = LIOPipeline(PipelineConfig.from_dict({
                "lio": {"max_range": max_range_m, "min_range": MIN_RANGE_M, "deskew": True,
                        "max_num_threads": THREADS},
                "extrinsic_imu2base_quat_xyzw_xyz": _xyzw_xyz(T_lidar_imu),
                "extrinsic_lidar2base_quat_xyzw_xyz": _xyzw_xyz(np.eye(4))}))
        for row in imu_rows if imu_rows is not None else ():
            pipe.add_imu(round(row[0] * 1e9), np.asarray(row[4:7]), np.asarray(row[1:4]))
        abs_ns = stamp_ns + np.rint(times * 1e9).astype(np.int64)
        pipe.register_scan(int(abs_ns.min()), int(abs_ns.max()), points, abs_ns)
        stamps.append(stamp_ns)
    seconds = time.perf_counter() - t0
    return _resampled("rko-lio", pipe.lio.poses_with_timestamps(), np.array(stamps), seconds)


def _resampled(name: str, stamped, stamps_ns: np.ndarray, seconds: float) -> PeerRun:
    """A peer's own (stamp, pose) list interpolated at the scans' stamps it covers, in the
    frame of its first pose."""
    from mcl3d.core.geometry import se3_from_tq
    from mcl3d.io.trajectory import Trajectory

    own_ns, own = stamped  # rko-lio's rows are x, y, z, qx, qy, qz, qw
    own = np.asarray(own, np.float64).reshape(-1, 7)
    traj = Trajectory.from_ns(np.asarray(own_ns, np.int64), se3_from_tq(own[:, :3], own[:, 3:]))
    inside = (stamps_ns >= traj.stamps_ns[0]) & (stamps_ns <= traj.stamps_ns[-1])
    poses = traj.interpolate_poses(stamps_ns[inside] * 1e-9)
    return PeerRun(name, stamps_ns[inside], np.linalg.inv(poses[0]) @ poses, seconds)


def closure_errors_m(run: PeerRun, gt_poses: np.ndarray) -> list[float]:
    """How far each accepted closure's relative pose is from the truth (m): a closure is
    wrong when it places the query's local map metres from where it is."""
    out = []
    for matched, query, T_query_matched in run.closures:
        true_rel = np.linalg.inv(gt_poses[query]) @ gt_poses[matched]
        out.append(float(np.linalg.norm((np.linalg.inv(true_rel) @ T_query_matched)[:3, 3])))
    return out
