"""Point-cloud maps without poses: build time, peak memory, orientation and localization,
side by side with the same map built with its poses.

A user brings a map exported by another SLAM system (FAST-LIO, LIO-SAM, GLIM: points, no
poses). The bench simulates a world's log and merges its scans, placed by their true poses,
into such a map (voxel-downsampled to about `--points`), then runs the whole commands:

- `mcl3d build-map MAP.ply --trajectory GT.tum` (normals face the trajectory: with poses) and
  `mcl3d build-map MAP.ply` (normals oriented from the map itself, maps/normals.py), each
  timed as a child process (wall s, peak RSS);
- the agreement of the normals oriented from the map alone with those oriented towards the
  trajectory (right for surfaces a sensor saw), on the points within `--near` m of it;
- `mcl3d localize` in each map: global (no initial guess) and tracking (from the first
  ground-truth pose), scored by the run's own ground-truth figures.

    python bench/bench_point_maps.py --world warehouse --points 2600000 --duration 100
    python bench/bench_point_maps.py --world office --points 1000000 --duration 60
    python bench/bench_point_maps.py --quick   # 100,000 points from a 5 s log, no localize

Writes bench/results/bench_point_maps.json through results_io (`--json` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from results_io import Run


def mcl3d(*args) -> dict:
    """Run one whole command as a child process: wall seconds and the child's peak RSS."""
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-m", "mcl3d", *map(str, args)],
                             stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(child.pid, 0)
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        raise subprocess.CalledProcessError(child.returncode, child.args)
    return {"wall_s": time.perf_counter() - start, "peak_rss_gib": usage.ru_maxrss / 2**20}


def simulate(work: Path, world: str, points: int, duration_s: float, seed: int
             ) -> tuple[Path, Path, Path]:
    """The log, its ground truth and its point map of about `points` points (cached)."""
    log, gt, cloud = work / f"{world}.mcap", work / f"{world}_gt.tum", work / f"{world}_map.ply"
    if not log.exists():
        mcl3d("simulate", world, "-o", log, "--duration", duration_s, "--seed", seed,
              "--force")
    if not cloud.exists():
        export_point_map(log, points, cloud)
    return log, gt, cloud


def export_point_map(log: Path, points: int, path: Path) -> None:
    """What a SLAM system exports: every scan placed by its (true) pose, deskewed, merged and
    voxel-downsampled, the voxel chosen by bisection so that about `points` remain. Only
    surfaces a sensor saw are in it, with their real density and noise."""
    import open3d as o3d

    from mcl3d.io.logs.cloud_files import write_ply
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import Trajectory

    chunks = []
    with LogReader(log) as reader:
        stamps_ns, poses = reader.ground_truth()
        traj = Trajectory.from_ns(stamps_ns, poses)
        t0, t1 = traj.stamps_s[0], traj.stamps_s[-1]
        for scan in reader.scans():
            times = scan.stamp_ns * 1e-9 + (0.0 if scan.times_s is None
                                             else scan.times_s.astype(np.float64))
            T = traj.interpolate_poses(np.clip(np.broadcast_to(times, len(scan.points)),
                                               t0, t1))
            chunks.append(np.einsum("nij,nj->ni", T[:, :3, :3], scan.points) + T[:, :3, 3])
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack(chunks)))
    lo, hi = 0.005, 1.0
    for _ in range(12):
        voxel = np.sqrt(lo * hi)
        n = len(cloud.voxel_down_sample(voxel).points)
        lo, hi = (voxel, hi) if n > points else (lo, voxel)
    write_ply(path, np.asarray(cloud.voxel_down_sample(hi).points, dtype=np.float32))


def orientation_agreement(cloud: Path, gt: Path, near_m: float, k: int, cell_m: float
                          ) -> dict:
    """Share of the points near the trajectory whose map-oriented normal agrees with the
    trajectory-oriented one."""
    from scipy.spatial import cKDTree

    from mcl3d.io.logs.cloud_files import read_cloud_file
    from mcl3d.io.trajectory import read_trajectory
    from mcl3d.maps import normals

    points = read_cloud_file(cloud).points.astype(np.float64)
    viewpoints = read_trajectory(gt).positions()
    raw = normals.estimate_normals(points, k)
    start = time.perf_counter()
    by_map = normals.orient_consistently(points, raw, cell_m)
    orient_s = time.perf_counter() - start
    by_poses = normals.orient_towards(points, raw, viewpoints)
    dist, _ = cKDTree(viewpoints).query(points, k=1, workers=-1)
    near = dist < near_m
    agree = np.einsum("ij,ij->i", by_map, by_poses) > 0
    return {"points": len(points), "points_near": int(near.sum()),
            "agreement_near": float(agree[near].mean()), "agreement_all": float(agree.mean()),
            "orient_s": orient_s}


def localize(work: Path, log: Path, tsdf: Path, name: str, init: str, particles: int,
             seed: int, backend: str) -> dict:
    out = work / f"loc_{name}_{init}"
    timing = mcl3d("localize", log, "--map", tsdf, "-o", out, "--init", init, "--particles",
                   particles, "--seed", seed, "--backend", backend, "--force")
    s = json.loads((out / "summary.json").read_text())
    after = s.get("ate_after_convergence") or {}
    return {"converged_after_s": s["converged_after_s"], "final_state": s["final_state"],
            "converged_fraction": s["converged_fraction"],
            "ate_after_convergence_m": after.get("translation_rmse_m"),
            "rotation_after_convergence_deg": after.get("rotation_rmse_deg"),
            "wall_s": timing["wall_s"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--points", type=int, default=None, help="default 1,000,000")
    parser.add_argument("--duration", type=float, default=None, help="log seconds (60)")
    parser.add_argument("--quick", action="store_true",
                        help="100,000 points from a 5 s log, no localization")
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=50_000, help="global localization")
    parser.add_argument("--near", type=float, default=10.0, help="m from the trajectory")
    parser.add_argument("--no-localize", action="store_true", help="build and orient only")
    parser.add_argument("--work", type=Path, default=Path("/tmp/mcl3d_point_maps"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    args.points = args.points or (100_000 if args.quick else 1_000_000)
    args.duration = args.duration or (5.0 if args.quick else 60.0)
    args.no_localize = args.no_localize or args.quick
    bench_run = Run("bench_point_maps", baselines=("open3d", "scipy"))

    from mcl3d.maps.build import BuildConfig

    work = args.work / f"{args.world}_{args.points}_{args.seed}"
    work.mkdir(parents=True, exist_ok=True)
    log, gt, cloud = simulate(work, args.world, args.points, args.duration, args.seed)
    result: dict = {"world": args.world, "seed": args.seed, "builds": {}, "localize": {}}
    maps = {"with_poses": work / "with_poses.tsdf", "without_poses": work / "without_poses.tsdf"}
    for name, tsdf in maps.items():
        extra = ("--trajectory", gt) if name == "with_poses" else ()
        result["builds"][name] = mcl3d("build-map", cloud, "-o", tsdf, *extra, "--backend",
                                       args.backend, "--force")
        print(name, result["builds"][name], flush=True)
    cfg = BuildConfig()
    result["orientation"] = orientation_agreement(cloud, gt, args.near, cfg.normal_neighbors,
                                                  cfg.orientation_cell_m)
    print(result["orientation"], flush=True)
    if not args.no_localize:
        for name, tsdf in maps.items():
            for init, particles in (("global", args.particles), ("gt", 5000)):
                row = localize(work, log, tsdf, name, init, particles, args.seed,
                               args.backend)
                result["localize"][f"{name}/{init}"] = row
                print(name, init, row, flush=True)
    path = bench_run.write({**tables(result, args), **result}, args.json)
    print(f"wrote {path}")


def tables(result: dict, args) -> dict:
    """The rendered part of the JSON: builds, orientation, localization."""
    builds = [{"map": name.replace("_", " "), "build-map s": round(b["wall_s"], 1),
               "peak RSS GiB": round(b["peak_rss_gib"], 2)}
              for name, b in result["builds"].items()]
    o = result["orientation"]
    orient = [{"points": f"{o['points']:,}", f"within {args.near:g} m of the trajectory":
               f"{o['points_near']:,}", "agree there": f"{100 * o['agreement_near']:.1f} %",
               "agree, all points": f"{100 * o['agreement_all']:.1f} %",
               "orienting s": round(o["orient_s"], 1)}]
    out = {f"Whole build-map commands, {args.world}, {o['points']:,} points": builds,
           "Normals oriented from the map alone against oriented towards the trajectory":
               orient}
    if result["localize"]:
        out["Whole localize commands in each map"] = [
            {"map / init": key.replace("_", " "),
             "converged after s": r["converged_after_s"], "final state": r["final_state"],
             "ATE after convergence cm": None if r["ate_after_convergence_m"] is None
             else round(100 * r["ate_after_convergence_m"], 2), "wall s": round(r["wall_s"], 1)}
            for key, r in result["localize"].items()]
    notes = [f"{args.world} log of {args.duration:g} s, seed {args.seed}; the point map is its "
             "scans placed by the true poses and voxel-downsampled; global localization with "
             f"{args.particles:,} particles, tracking with 5,000; backend {args.backend}."]
    return {"tables": out, "notes": notes}


if __name__ == "__main__":
    main()
