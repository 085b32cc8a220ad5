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
Speed on a shared machine: the methods run interleaved in one process, frame by frame (every
method steps frame i before any steps frame i + 1, in an order that rotates with the frame
and the repetition), each with `--threads` threads, over `--repeats` passes of every log.
A frame's time is its median over the passes; reported are the median over frames and the
10th-90th percentile spread, wall and process-cpu ms per frame (the whole step, preprocessing
included; the first two frames, which compile kernels, excluded), and per frame the ratio of
mcl3d's time to small_gicp's (median over frames). Accuracy (first pass): ATE RMSE and
end-point drift (% of distance) after aligning the first pose, RPE per metre. kiss-icp and
small_gicp are dev-only dependencies: `pip install -e '.[bench]'`.

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
        ("office", "mid360", "handheld", 15.0), ("forest", "vlp16", "loop", 20.0),
        ("office", "os1-64", "ground", 15.0), ("forest", "mid360", "handheld", 15.0)]
SKIP_FRAMES = 2  # kernel compilation


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def simulate(folder: Path, world, sensor, path, duration) -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    out = folder / f"{world}_{sensor}_{path}.mcap"
    run(SimulateRequest(world=world, sensor=sensor, trajectory=path, duration_s=duration,
                        seed=1, output=out, config_path=None, export_mesh=None,
                        export_map=None, force=True))
    return out


def read_log(path: Path):
    """Scans (stamp_s, points, times_s), IMU rows between scans, ground truth."""
    from mcl3d.io.logs.reader import LogReader

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


class Mcl3dRunner:
    """mcl3d odometry; the device fields are allocated once and reused for every pass."""

    def __init__(self, use_imu: bool):
        from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig

        self.use_imu = use_imu
        self.odo = LidarOdometry(OdometryConfig(use_imu=use_imu))

    def reset(self, T_lidar_imu):
        self.odo.reset(T_lidar_imu)

    def step(self, scan, imu):
        stamp_ns, pts, times = scan
        frame = self.odo.step(pts, times, stamp_ns, imu if self.use_imu else None)
        return stamp_ns * 1e-9, frame.T_world_lidar


class KissRunner:
    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        config = KISSConfig()
        config.mapping.voxel_size = config.data.max_range / 100.0  # what kiss_icp_pipeline sets
        config.registration.max_num_threads = self.threads
        self.odo = KissICP(config)

    def step(self, scan, imu):
        stamp_ns, pts, times = scan
        span = max(times.max(), 1e-6)
        self.odo.register_frame(pts, times / span)
        return stamp_ns * 1e-9 + span, self.odo.last_pose.copy()


class SmallGicpRunner:
    def __init__(self, threads: int):
        self.threads = threads

    def reset(self, T_lidar_imu):
        import small_gicp

        self.voxelmap = small_gicp.GaussianVoxelMap(1.0)
        self.voxelmap.set_lru(horizon=100, clear_cycle=10)
        self.T_world, self.T_last_current = np.eye(4), np.eye(4)

    def step(self, scan, imu):
        import small_gicp

        stamp_ns, pts, times = scan
        down, _ = small_gicp.preprocess_points(pts, 0.25, num_threads=self.threads)
        if self.voxelmap.size() == 0:
            self.voxelmap.insert(down)
        else:
            result = small_gicp.align(self.voxelmap, down, self.T_world @ self.T_last_current,
                                      num_threads=self.threads)
            self.T_last_current = np.linalg.inv(self.T_world) @ result.T_target_source
            self.T_world = result.T_target_source
            self.voxelmap.insert(down, self.T_world)
        return stamp_ns * 1e-9 + float(np.median(times)), self.T_world.copy()


def run_interleaved(runners: dict, scans, imu_chunks, T_lidar_imu, repeats: int):
    """Every runner over the log `repeats` times, stepping frame by frame in turn. Returns per
    runner the first pass's (stamps, poses) and (repeats, frames, 2) wall/cpu ms."""
    names = list(runners)
    ms = {name: np.zeros((repeats, len(scans), 2)) for name in names}
    traj = {name: ([], []) for name in names}
    for rep in range(repeats):
        for runner in runners.values():
            runner.reset(T_lidar_imu)
        for i, (scan, imu) in enumerate(zip(scans, imu_chunks, strict=True)):
            shift = (i + rep) % len(names)
            for name in names[shift:] + names[:shift]:
                t0, c0 = time.perf_counter(), cpu_s()
                stamp, pose = runners[name].step(scan, imu)
                ms[name][rep, i] = (time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3
                if rep == 0:
                    traj[name][0].append(stamp)
                    traj[name][1].append(pose)
    return {name: (np.array(traj[name][0]), np.stack(traj[name][1]), ms[name])
            for name in names}


def timing(ms: np.ndarray) -> dict:
    """Median over frames of each frame's median over passes, and the 10-90% spread."""
    per_frame = np.median(ms[:, SKIP_FRAMES:], axis=0)  # (frames, wall/cpu)
    wall, cpu = per_frame[:, 0], per_frame[:, 1]
    return {"ms_per_frame": float(np.median(wall)),
            "ms_p10": float(np.percentile(wall, 10)), "ms_p90": float(np.percentile(wall, 90)),
            "cpu_ms_per_frame": float(np.median(cpu)),
            "pass_medians_ms": [float(np.median(p[SKIP_FRAMES:, 0])) for p in ms]}


def score(stamps, poses, gt):
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.trajectory import Trajectory

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
            "path_m": length}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--logs", type=int, default=len(LOGS), help="use the first N logs")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes over every log")
    parser.add_argument("--threads", type=int, default=2,
                        help="threads of every method (Taichi's cpu backend, small_gicp, kiss-icp)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/bench_odometry.json"))
    args = parser.parse_args()

    # same thread count everywhere; small_gicp's OpenMP threads sleep instead of spinning
    # while they wait (GOMP's default spin burns a shared machine's cores and inflates times)
    os.environ["TI_CPU_MAX_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

    from importlib.metadata import version

    from rich.console import Console
    from rich.table import Table

    from mcl3d.console import console
    from mcl3d.core import runtime

    info = runtime.init(args.backend)
    runners = {"mcl3d (IMU)": Mcl3dRunner(True), "mcl3d (no IMU)": Mcl3dRunner(False),
               "KISS-ICP": KissRunner(args.threads),
               "small_gicp scan-to-model": SmallGicpRunner(args.threads)}
    results, ratios = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for world, sensor, path, duration in LOGS[:args.logs]:
            log = simulate(Path(tmp), world, sensor, path, duration)
            scans, imu, gt, T_lidar_imu = read_log(log)
            name = f"{world}/{sensor}/{path}"
            out = run_interleaved(runners, scans, imu, T_lidar_imu, args.repeats)
            sg_ms = np.median(out["small_gicp scan-to-model"][2][:, SKIP_FRAMES:, 0], axis=0)
            for method, (stamps, poses, ms) in out.items():
                row = {"log": name, "method": method, "frames": len(scans),
                       **score(stamps, poses, gt), **timing(ms)}
                if method.startswith("mcl3d"):
                    own = np.median(ms[:, SKIP_FRAMES:, 0], axis=0)
                    row["ratio_vs_small_gicp"] = float(np.median(own / sg_ms))
                    ratios.append((name, method, row["ratio_vs_small_gicp"]))
                results.append(row)
                console.print(f"{name:24s} {method:26s} drift {row['drift_percent']:.2f} %  "
                              f"{row['ms_per_frame']:.1f} ms/frame")

    table = Table(title=f"Odometry on simulated logs ({info.backend}: {info.device}, "
                        f"{args.threads} threads, median of {args.repeats} interleaved passes)")
    for col in ("log", "method", "path m", "ATE cm", "drift %", "RPE cm/m", "RPE deg/m",
                "ms/frame (p10-p90)", "cpu-ms", "x small_gicp"):
        table.add_column(col, justify="left" if col in ("log", "method") else "right")
    for r in results:
        ratio = f"{r['ratio_vs_small_gicp']:.2f}" if "ratio_vs_small_gicp" in r else ""
        table.add_row(r["log"], r["method"], f"{r['path_m']:.1f}", f"{100 * r['ate_rmse_m']:.1f}",
                      f"{r['drift_percent']:.2f}", f"{100 * r['rpe_m_per_m']:.2f}",
                      f"{r['rpe_deg_per_m']:.3f}",
                      f"{r['ms_per_frame']:.1f} ({r['ms_p10']:.0f}-{r['ms_p90']:.0f})",
                      f"{r['cpu_ms_per_frame']:.1f}", ratio)
    Console(width=170).print(table)
    console.print("x small_gicp: median over frames of mcl3d's wall time / small_gicp's on the "
                  "same frame (target <= 1.5)")
    report = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                          "load_average": os.getloadavg(),
                          "backend": info.backend, "device": info.device},
              "versions": {p: version(p) for p in ("kiss-icp", "small_gicp", "taichi")},
              "settings": {"repeats": args.repeats, "threads": args.threads,
                           "skip_frames": SKIP_FRAMES,
                           "OMP_WAIT_POLICY": os.environ["OMP_WAIT_POLICY"]},
              "results": results}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
