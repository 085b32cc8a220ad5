"""Monte Carlo SLAM back-end: ms per frame and memory versus particles N and keyframes K.

Keyframes are real simulated MID-360 forest scans (a short log is simulated once and cached
under bench/results/), placed along the log's path; every particle holds its own noisy copy
of every keyframe pose and sits at the last scan's pose, so all of them see a loop. One
frame = prediction, neighbour search, one gradient-guided correction with propagation to
the keyframes, the likelihood against 3 neighbours, and pruning, i.e. everything but the
odometry front-end, which is timed on the same scans in the same run as the baseline.

    python bench/bench_slam.py [--backend cpu|cuda|vulkan] [--particles 1000 10000 100000]
                               [--keyframes 10 100] [--repeats 5] [--out FILE.json]

Writes a table and bench/results/bench_slam.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def forest_log() -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    log = RESULTS / "bench_slam_forest.mcap"
    if not log.exists():
        RESULTS.mkdir(parents=True, exist_ok=True)
        run(SimulateRequest(world="forest", sensor="mid360", trajectory="ground",
                            duration_s=20.0, seed=1, output=log,
                            overrides={"world.forest_rows": 6,
                                       "world.forest_trees_per_row": 10}, force=True))
    return log


def read_scans(log: Path, count: int):
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_tum

    gt = read_tum(log.with_name(log.stem + "_gt.tum"))
    scans = []
    with LogReader(log) as reader:
        for _, cloud in reader.messages(("points",)):
            scans.append((cloud.points, cloud.times_s, cloud.stamp_ns))
            if len(scans) == count:
                break
    poses = gt.interpolate_poses([s[2] * 1e-9 for s in scans])
    return scans, np.linalg.inv(poses[0]) @ poses


def odometry_ms(scans) -> float:
    """The front-end's median ms per scan on the same scans (the baseline)."""
    from mcl3d.odometry.lidar_odometry import LidarOdometry

    odo = LidarOdometry()
    ms = []
    for points, times, stamp in scans:
        t0 = time.perf_counter()
        odo.step(points, times, stamp)
        ms.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ms[3:]))


def setup(n: int, K: int, scans, poses):
    """A SLAM back-end with K keyframes from the scans and N particles around the path."""
    import taichi as ti

    from mcl3d.core.geometry import se3_exp
    from mcl3d.registration.preprocess import estimate_covariances, voxel_downsample
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam, thin
    from mcl3d.slam.slam_config import KeyframeConfig, LoopClosureConfig, SlamConfig

    cfg = SlamConfig(particles=n, keyframes=KeyframeConfig(capacity=max(K + 1, 16)),
                     loop_closure=LoopClosureConfig(min_travel_m=0.1))
    slam = MonteCarloSlam(cfg)
    rng = np.random.default_rng(0)
    p = slam.particles
    clouds = []
    for k in range(K):
        points = scans[k % len(scans)][0]
        down = voxel_downsample(points, cfg.front_end.scan_voxel_m)
        covs = estimate_covariances(down, 10)
        clouds.append((down, covs))
        noisy = poses[k % len(poses)][None] @ se3_exp(rng.normal(0, 0.01, (n, 6)))
        p.q_cur.from_numpy(_quats(noisy))
        p.t_cur.from_numpy(noisy[:, :3, 3].astype(np.float32))
        pos = poses[k % len(poses)][:3, 3]
        p.add_keyframe(float(k), 1e-5 * np.r_[k, k * pos, k], pos)  # even drift, 1 m apart
        pts, cv = thin(down, covs, cfg.keyframes.max_points)
        slam.maps.clear(k, cfg.keyframes.voxel_m)
        slam.maps.insert(k, pts, cv)
    src, src_covs = thin(*clouds[0], cfg.correction.points)
    slam.gicp.set_source(src, src_covs)
    ti.sync()
    return slam, len(src)


def _quats(T):
    from mcl3d.core.geometry import rot_to_quat

    return rot_to_quat(T[:, :3, :3]).astype(np.float32)


def one_frame(slam, num_src: int, travel_m: float, step: int) -> dict[str, float]:
    import taichi as ti

    cfg = slam.cfg
    p = slam.particles
    times = {}
    t0 = time.perf_counter()
    p.predict(np.eye(4), np.diag([1e-8] * 3 + [1e-6] * 3), step)
    ti.sync()
    t1 = time.perf_counter()
    looping = p.select_neighbours(travel_m, cfg.loop_closure.min_travel_m)
    ti.sync()
    t2 = time.perf_counter()
    here = p.positions()[0]
    p.correct(travel_m, 1e-5 * np.r_[travel_m, travel_m * here, travel_m], here, num_src,
              cfg.correction)
    ti.sync()
    t3 = time.perf_counter()
    p.weigh(num_src, cfg.likelihood)
    ti.sync()
    t4 = time.perf_counter()
    slam._prune(step, True)
    ti.sync()
    t5 = time.perf_counter()
    times.update(predict=t1 - t0, neighbours=t2 - t1, correct=t3 - t2, weigh=t4 - t3,
                 prune=t5 - t4)
    times = {k: v * 1e3 for k, v in times.items()}
    times["total"] = sum(times.values())
    times["looping"] = looping
    return times


def main() -> None:
    from mcl3d.core import runtime
    from mcl3d.mapping.pipeline import format_bytes

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--particles", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--keyframes", type=int, nargs="+", default=[10, 100])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_slam.json")
    args = ap.parse_args()
    info = runtime.init(args.backend)
    scans, poses = read_scans(forest_log(), 40)
    base_ms = odometry_ms(scans)
    rows = []
    for K in args.keyframes:
        for n in args.particles:
            slam, num_src = setup(n, K, scans, poses)
            one_frame(slam, num_src, 100.0, 0)  # compile
            runs = [one_frame(slam, num_src, 100.0, r + 1) for r in range(args.repeats)]
            med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
            groups = slam.gicp.max_groups
            scratch = groups * 468  # BatchGicp per-row fields (see docs/slam.md)
            row = {"particles": n, "keyframes": K, "ms": med,
                   "ms_spread": [float(min(r["total"] for r in runs)),
                                 float(max(r["total"] for r in runs))],
                   "ratio_to_odometry": med["total"] / base_ms,
                   "particle_state_bytes": slam.particles.state_bytes(),
                   "gicp_scratch_bytes": scratch}
            rows.append(row)
            print(f"N={n:>7,} K={K:>3}: {med['total']:8.1f} ms/frame "
                  f"(predict {med['predict']:.1f}, neighbours {med['neighbours']:.1f}, "
                  f"correct {med['correct']:.1f}, weigh {med['weigh']:.1f}, "
                  f"prune {med['prune']:.1f}) = {row['ratio_to_odometry']:.1f}x odometry; "
                  f"particle state {format_bytes(row['particle_state_bytes'])}, "
                  f"GICP scratch {format_bytes(scratch)}", flush=True)
            del slam
    out = {"backend": info.backend, "device": info.device, "machine": platform.processor()
           or platform.machine(), "odometry_ms_per_scan": base_ms, "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(f"odometry front-end (baseline, same scans): {base_ms:.1f} ms/scan; "
          f"{info.backend} on {info.device}")


if __name__ == "__main__":
    main()
