"""Odometry accuracy and speed on simulated logs: mcl3d vs KISS-ICP vs small_gicp, same scans.

Logs are simulated in the run (`mcl3d simulate`-equivalent, fixed seeds): office and forest
worlds, VLP-16 / OS1-64 / MID-360, ground, loop and handheld paths. Each method gets the same
decoded scans in the same order:
  - mcl3d odometry, with IMU and without (constant velocity), default config;
  - KISS-ICP 1.3 (`KissICP.register_frame`, default config; its poses refer to the end of
    the sweep, so they are stamped at the last point time);
  - small_gicp 1.0 scan-to-model as in its `kitti_odometry.py` example (GaussianVoxelMap
    1.0 m with LRU, 0.25 m downsampling, no deskew; stamped at the median point time, which
    is where an undeskewed sweep registers).
Reported: ATE RMSE and end-point drift (% of distance) after aligning the first pose, RPE
per metre, and median wall and process-cpu ms per frame (the whole step, preprocessing
included; the first two frames, which compile kernels, excluded). kiss-icp and
small_gicp are dev-only dependencies: `pip install kiss-icp small_gicp`.

    python bench/bench_odometry.py --out bench/results/bench_odometry.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

LOGS = [("office", "vlp16", "loop", 20.0), ("forest", "os1-64", "ground", 20.0),
        ("office", "mid360", "handheld", 15.0), ("forest", "vlp16", "loop", 20.0)]


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def simulate(folder: Path, world, sensor, path, duration) -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    out = folder / f"{world}_{sensor}_{path}.mcap"
    run(SimulateRequest(world=world, sensor=sensor, trajectory=path, duration_s=duration,
                        seed=1, output=out, config_path=None, export_mesh=None,
                        export_map=None, force=True), progress=False)
    return out


def read_log(path: Path):
    """Scans (stamp_s, points, times_s), IMU rows between scans, ground truth."""
    from mcl3d.logs.reader import LogReader

    scans, imu_chunks, gt, pending = [], [], {}, []
    with LogReader(path) as reader:
        T_lidar_imu = reader.static_transform("lidar", "imu")
        for kind, msg in reader.messages(("points", "imu", "gt")):
            if kind == "imu":
                pending.append((msg.stamp_ns * 1e-9, *msg.angular_velocity,
                                *msg.linear_acceleration))
            elif kind == "gt":
                gt[msg.stamp_ns * 1e-9] = msg.T
            else:
                scans.append((msg.stamp_ns, msg.points.astype(np.float64),
                              msg.times_s.astype(np.float64)))
                imu_chunks.append(np.array(pending).reshape(-1, 7))
                del pending[:-1]
    return scans, imu_chunks, gt, T_lidar_imu


def run_mcl3d(scans, imu_chunks, T_lidar_imu, use_imu):
    from mcl3d.odometry import Odometry, OdometryConfig

    odo = Odometry(OdometryConfig(use_imu=use_imu), T_lidar_imu)
    stamps, poses, ms = [], [], []
    for (stamp_ns, pts, times), imu in zip(scans, imu_chunks, strict=True):
        t0, c0 = time.perf_counter(), cpu_s()
        frame = odo.step(pts, times, stamp_ns, imu if use_imu else None)
        ms.append(((time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3))
        stamps.append(stamp_ns * 1e-9)
        poses.append(frame.T_world_lidar)
    return np.array(stamps), np.stack(poses), ms


def run_kiss(scans):
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    config = KISSConfig()
    config.mapping.voxel_size = config.data.max_range / 100.0  # what kiss_icp_pipeline sets
    odo = KissICP(config)
    stamps, poses, ms = [], [], []
    for stamp_ns, pts, times in scans:
        t0, c0 = time.perf_counter(), cpu_s()
        span = max(times.max(), 1e-6)
        odo.register_frame(pts, times / span)
        ms.append(((time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3))
        stamps.append(stamp_ns * 1e-9 + span)
        poses.append(odo.last_pose.copy())
    return np.array(stamps), np.stack(poses), ms


def run_small_gicp(scans):
    import small_gicp

    voxelmap = small_gicp.GaussianVoxelMap(1.0)
    voxelmap.set_lru(horizon=100, clear_cycle=10)
    T_world, T_last_current = np.eye(4), np.eye(4)
    stamps, poses, ms = [], [], []
    for stamp_ns, pts, times in scans:
        t0, c0 = time.perf_counter(), cpu_s()
        down, _ = small_gicp.preprocess_points(pts, 0.25, num_threads=os.cpu_count() or 1)
        if voxelmap.size() == 0:
            voxelmap.insert(down)
        else:
            result = small_gicp.align(voxelmap, down, T_world @ T_last_current,
                                      num_threads=os.cpu_count() or 1)
            T_last_current = np.linalg.inv(T_world) @ result.T_target_source
            T_world = result.T_target_source
            voxelmap.insert(down, T_world)
        ms.append(((time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3))
        stamps.append(stamp_ns * 1e-9 + float(np.median(times)))
        poses.append(T_world.copy())
    return np.array(stamps), np.stack(poses), ms


def score(stamps, poses, ms, gt):
    from mcl3d.evaluation import evaluate
    from mcl3d.trajectory import Trajectory

    gt_stamps = np.array(sorted(gt))
    ref = Trajectory(gt_stamps, np.stack([gt[s] for s in gt_stamps]))
    inside = (stamps >= gt_stamps[0]) & (stamps <= gt_stamps[-1])
    # ground truth at the method's own stamps (KISS-ICP and small_gicp refer elsewhere)
    ref_at = Trajectory(stamps[inside], ref.interpolate_poses(stamps[inside]))
    est = Trajectory(stamps[inside], poses[inside])
    ev = evaluate(ref_at, est, alignment="origin", rpe_delta=1.0, rpe_unit="m")
    length = ref_at.path_length_m()
    end = np.linalg.norm(ev.association.ref_poses[-1, :3, 3] - ev.est_aligned_poses[-1, :3, 3])
    return {"ate_rmse_m": ev.ate.translation_m.rmse, "drift_percent": 100 * end / length,
            "rpe_m_per_m": ev.rpe.translation_m.mean, "rpe_deg_per_m": ev.rpe.rotation_deg.mean,
            "ms_per_frame": float(np.median([m[0] for m in ms[2:]])),
            "cpu_ms_per_frame": float(np.median([m[1] for m in ms[2:]])), "path_m": length}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--logs", type=int, default=len(LOGS), help="use the first N logs")
    parser.add_argument("--out", type=Path, default=Path("bench/results/bench_odometry.json"))
    args = parser.parse_args()

    from importlib.metadata import version

    from rich.table import Table

    from mcl3d import runtime
    from mcl3d.console import console

    info = runtime.init(args.backend)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for world, sensor, path, duration in LOGS[:args.logs]:
            log = simulate(Path(tmp), world, sensor, path, duration)
            scans, imu, gt, T_lidar_imu = read_log(log)
            name = f"{world}/{sensor}/{path}"
            methods = {"mcl3d (IMU)": (run_mcl3d, (scans, imu, T_lidar_imu, True)),
                       "mcl3d (no IMU)": (run_mcl3d, (scans, imu, T_lidar_imu, False)),
                       "KISS-ICP": (run_kiss, (scans,)),
                       "small_gicp scan-to-model": (run_small_gicp, (scans,))}
            for method, (fn, fn_args) in methods.items():
                stamps, poses, ms = fn(*fn_args)
                results.append({"log": name, "method": method, **score(stamps, poses, ms, gt)})
                console.print(f"{name:28s} {method:26s} drift "
                              f"{results[-1]['drift_percent']:.2f} %")

    table = Table(title=f"Odometry on simulated logs ({info.backend}: {info.device})")
    for col in ("log", "method", "path m", "ATE cm", "drift %", "RPE cm/m", "RPE deg/m",
                "ms/frame", "cpu-ms/frame"):
        table.add_column(col, justify="left" if col in ("log", "method") else "right")
    for r in results:
        table.add_row(r["log"], r["method"], f"{r['path_m']:.1f}", f"{100 * r['ate_rmse_m']:.1f}",
                      f"{r['drift_percent']:.2f}", f"{100 * r['rpe_m_per_m']:.2f}",
                      f"{r['rpe_deg_per_m']:.3f}", f"{r['ms_per_frame']:.1f}",
                      f"{r['cpu_ms_per_frame']:.1f}")
    console.print(table, width=150)
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average": os.getloadavg(),
                          "backend": info.backend, "device": info.device},
              "versions": {p: version(p) for p in ("kiss-icp", "small_gicp", "taichi")},
              "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
