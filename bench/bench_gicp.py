"""GICP speed and accuracy: pairwise registration vs small_gicp, and batched GICP for many poses.

1. Pairwise, on the real HDL-32E pair (../shared/data/hdl32_pair): mcl3d `align` (VGICP on
   device voxel maps, coarse to fine) against small_gicp 1.0.1 (VGICP and kd-tree GICP) on the
   same points, same downsampling and k, same run. Times are medians over repeats after a
   warm-up (compilation excluded), registration only (both sides get preprocessed clouds)
   and end to end (raw points in); wall and process cpu time (cpu time is what a shared
   machine cannot inflate). Errors are against T_target_source.txt.
2. Batched: `--poses` poses (default 10,000) x `--points` source points (512) against one
   voxel map of the same target, ms per Gauss-Newton iteration (linearize + solve + update
   for every pose), wall and cpu time, median over `--batch-repeats` blocks of `--iterations`
   iterations and the best block (other processes on a shared machine inflate some).
   Baseline: small_gicp's single-iteration VGICP `align`, one thread, called pose by pose on
   a subset, cpu time scaled to all poses.

small_gicp is a dev-only dependency: `pip install small_gicp`.

    python bench/bench_gicp.py --backend cpu --out bench/results/bench_gicp.json
    python bench/bench_gicp.py --skip-pairwise --out /tmp/bench_gicp_batched.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdl32_pair"


def errors(T, reference):
    from mcl3d.core.geometry import rotation_angle, se3_inverse

    D = se3_inverse(reference) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def cpu_s() -> float:
    """CPU seconds used by this process (all threads): robust to other processes' load."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def median_time(fn, repeats):
    """(median wall ms, median cpu ms, last result) after a warm-up call."""
    fn()  # warm-up: compilation, caches
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), cpu_s()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(cpu_s() - c0)
    return statistics.median(walls) * 1e3, statistics.median(cpus) * 1e3, out


def pairwise(args, target_raw, source_raw, reference):
    import small_gicp

    from mcl3d.registration.align import align, preprocess

    ds, k, rows = args.downsample, args.k_neighbors, []
    target, source = preprocess(target_raw, ds, k), preprocess(source_raw, ds, k)
    sg_target, sg_tree = small_gicp.preprocess_points(target_raw, ds, k, args.threads)
    sg_source, _ = small_gicp.preprocess_points(source_raw, ds, k, args.threads)

    def ours(levels):
        return lambda: align(target, source, voxel_resolution_m=levels).T_target_source

    def sg_vgicp(levels, threads):
        def run():
            T = np.eye(4)
            for res in levels:
                vmap = small_gicp.GaussianVoxelMap(res)
                vmap.insert(sg_target)
                T = small_gicp.align(vmap, sg_source, T, num_threads=threads,
                                     max_iterations=30).T_target_source
            return T
        return run

    def sg_gicp():
        return small_gicp.align(sg_target, sg_source, sg_tree, num_threads=args.threads,
                                max_iterations=30).T_target_source

    cases = [
        ("mcl3d VGICP 1.0+0.25 m (default)", ours((1.0, 0.25))),
        (f"small_gicp VGICP 1.0+0.25 m, {args.threads} threads",
         sg_vgicp((1.0, 0.25), args.threads)),
        ("small_gicp VGICP 1.0+0.25 m, 1 thread", sg_vgicp((1.0, 0.25), 1)),
        ("mcl3d VGICP 1.0 m", ours((1.0,))),
        (f"small_gicp VGICP 1.0 m, {args.threads} threads", sg_vgicp((1.0,), args.threads)),
        ("small_gicp GICP (kd-tree)", sg_gicp),
        ("mcl3d end to end (preprocess + align)",
         lambda: align(preprocess(target_raw, ds, k), preprocess(source_raw, ds, k))
         .T_target_source),
        ("small_gicp end to end (align from raw)",
         lambda: small_gicp.align(target_raw, source_raw, registration_type="VGICP",
                                  downsampling_resolution=ds, num_threads=args.threads,
                                  max_iterations=30).T_target_source),
    ]
    for name, fn in cases:
        ms, cpu_ms, T = median_time(fn, args.repeats)
        t_err, r_err = errors(T, reference)
        rows.append({"case": name, "ms": ms, "cpu_ms": cpu_ms, "trans_err_m": t_err,
                     "rot_err_deg": r_err})
    return rows, target, source


def batched(args, target, source, reference):
    import taichi as ti

    from mcl3d.core.geometry import se3, so3_exp
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    rng = np.random.default_rng(0)
    maps = GaussianVoxelMaps(max_maps=1, buckets_per_map=1 << 15, max_points=len(target))
    maps.clear(0, args.batch_resolution)
    maps.insert(0, target.points, target.covs)
    pick = rng.choice(len(source), args.points, replace=False)
    pts, covs = source.points[pick], source.covs[pick]
    poses = np.stack([reference @ se3(so3_exp(np.radians(1.0) * rng.normal(size=3)),
                                      0.1 * rng.normal(size=3)) for _ in range(args.poses)])
    gicp = BatchGicp(maps, max_groups=args.poses, max_source_points=args.points)
    gicp.set_source(pts, covs)
    result, repeats = {}, {}
    for n in sorted({1, args.poses}):
        gicp.set_problem(poses[:n], row_group=np.arange(n), row_map=np.zeros(n))
        gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)  # compile
        times, cpus, blocks = [], [], []
        for _ in range(args.batch_repeats):  # medians of blocks: load from others comes and goes
            gicp.set_problem(poses[:n], row_group=np.arange(n), row_map=np.zeros(n))
            block_t, block_c = [], []
            for _ in range(args.iterations):
                ti.sync()
                t0, c0 = time.perf_counter(), cpu_s()
                gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
                ti.sync()
                block_t.append(time.perf_counter() - t0)
                block_c.append(cpu_s() - c0)
            blocks.append((statistics.median(block_t) * 1e3, statistics.median(block_c) * 1e3))
            times += block_t
            cpus += block_c
        result[n] = (statistics.median(times) * 1e3, statistics.median(cpus) * 1e3)
        repeats[n] = blocks
    gicp.set_problem(poses, row_group=np.arange(args.poses), row_map=np.zeros(args.poses))
    # small_gicp's thresholds, where align() and the odometry stop too: on the piecewise voxel
    # cost (points change voxels) poses can circle small limit cycles
    out = gicp.optimize(max_iterations=10, rotation_eps_rad=np.radians(0.1),
                        translation_eps_m=1e-3)
    # every pose should reach the same minimum of this 512-point cost (which, with so few
    # points on a 1 m map, sits a few cm from the full-scan reference)
    t = out.T[:, :3, 3]
    spread_m = float(np.linalg.norm(t.std(axis=0)))
    offset_m = float(np.linalg.norm(t.mean(axis=0) - reference[:3, 3]))

    import small_gicp

    sg_source = small_gicp.PointCloud(pts)
    small_gicp.estimate_covariances(sg_source, num_neighbors=args.k_neighbors)
    sg_target = small_gicp.PointCloud(target.points)
    small_gicp.estimate_covariances(sg_target, num_neighbors=args.k_neighbors)
    vmap = small_gicp.GaussianVoxelMap(args.batch_resolution)
    vmap.insert(sg_target)
    subset = min(args.poses, 500)
    c0 = cpu_s()
    for T in poses[:subset]:
        small_gicp.align(vmap, sg_source, T, max_iterations=1, num_threads=1)
    sg_ms = (cpu_s() - c0) / subset * args.poses * 1e3  # one thread: cpu time = busy time
    return {"ms_per_iteration": result[args.poses][0],
            "cpu_ms_per_iteration": result[args.poses][1],
            "min_block_ms_per_iteration": min(w for w, _ in repeats[args.poses]),
            "min_block_cpu_ms_per_iteration": min(c for _, c in repeats[args.poses]),
            "blocks_ms_cpu_ms": repeats[args.poses],
            "cpu_ms_per_iteration_one_pose": result[1][1],
            "ms_per_iteration_one_pose": result[1][0],
            "small_gicp_ms_per_iteration_scaled": sg_ms, "small_gicp_poses_timed": subset,
            "final_translation_spread_m": spread_m, "final_mean_offset_from_reference_m": offset_m,
            "converged_fraction": float(out.converged.mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--downsample", type=float, default=0.1)
    parser.add_argument("--k-neighbors", type=int, default=10)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="small_gicp threads (Taichi uses every core)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--poses", type=int, default=10000)
    parser.add_argument("--points", type=int, default=512)
    parser.add_argument("--iterations", type=int, default=10,
                        help="GN iterations timed per block (batched case)")
    parser.add_argument("--batch-repeats", type=int, default=5,
                        help="blocks of --iterations timed iterations (batched case)")
    parser.add_argument("--skip-pairwise", action="store_true",
                        help="only the batched case (no pairwise table)")
    parser.add_argument("--batch-resolution", type=float, default=1.0)
    parser.add_argument("--out", type=Path, default=Path("bench/results/bench_gicp.json"))
    args = parser.parse_args()
    # small_gicp's OpenMP threads sleep while they wait instead of spinning (GOMP's default
    # spin burns a shared machine's cores and inflates its times); must precede its import
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

    from rich.table import Table

    from mcl3d.console import console
    from mcl3d.core import runtime
    from mcl3d.io.logs.cloud_files import read_cloud_file

    info = runtime.init(args.backend)
    target_raw = read_cloud_file(args.data / "251370668.pcd").points.astype(np.float64)
    source_raw = read_cloud_file(args.data / "251371071.pcd").points.astype(np.float64)
    reference = np.loadtxt(args.data / "T_target_source.txt")

    if args.skip_pairwise:
        from mcl3d.registration.align import preprocess

        rows = []
        target = preprocess(target_raw, args.downsample, args.k_neighbors)
        source = preprocess(source_raw, args.downsample, args.k_neighbors)
    else:
        rows, target, source = pairwise(args, target_raw, source_raw, reference)
    batch = batched(args, target, source, reference)

    table = Table(title=f"Pairwise registration, HDL-32E pair ({info.backend}: {info.device})")
    for col in ("case", "wall ms", "cpu ms", "trans err (cm)", "rot err (deg)"):
        table.add_column(col, justify="left" if col == "case" else "right")
    for r in rows:
        table.add_row(r["case"], f"{r['ms']:.1f}", f"{r['cpu_ms']:.1f}",
                      f"{100 * r['trans_err_m']:.2f}", f"{r['rot_err_deg']:.3f}")
    ratio = None
    if rows:
        console.print(table, width=150)
        ratio = rows[0]["ms"] / rows[1]["ms"]
        console.print(f"mcl3d / small_gicp wall time, same VGICP schedule: {ratio:.2f}x "
                      f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cpus: other "
                      "processes inflate wall times; cpu ms are robust to that)")
    batch_table = Table(title=f"Batched GICP, {args.poses} poses x {args.points} points")
    batch_table.add_column("what")
    batch_table.add_column("value", justify="right")
    batch_table.add_row("mcl3d ms per GN iteration (all poses)", f"{batch['ms_per_iteration']:.1f}")
    batch_table.add_row("mcl3d cpu-ms per GN iteration (all threads)",
                        f"{batch['cpu_ms_per_iteration']:.1f}")
    batch_table.add_row(f"best of {args.batch_repeats} blocks: ms / cpu-ms per GN iteration",
                        f"{batch['min_block_ms_per_iteration']:.1f} / "
                        f"{batch['min_block_cpu_ms_per_iteration']:.1f}")
    batch_table.add_row("mcl3d ms / cpu-ms per GN iteration (1 pose)",
                        f"{batch['ms_per_iteration_one_pose']:.2f} / "
                        f"{batch['cpu_ms_per_iteration_one_pose']:.2f}")
    batch_table.add_row("small_gicp pose by pose, 1 thread, cpu-ms (scaled)",
                        f"{batch['small_gicp_ms_per_iteration_scaled']:.0f}")
    speedup = batch["small_gicp_ms_per_iteration_scaled"] / batch["cpu_ms_per_iteration"]
    batch_table.add_row("cpu-time ratio small_gicp / mcl3d", f"{speedup:.1f}x")
    batch_table.add_row("converged within 10 iterations (0.1°, 1 mm)",
                        f"{100 * batch['converged_fraction']:.1f}%")
    batch_table.add_row("spread of the converged poses (std)",
                        f"{100 * batch['final_translation_spread_m']:.1f} cm")
    batch_table.add_row("their mean vs the full-scan reference",
                        f"{100 * batch['final_mean_offset_from_reference_m']:.1f} cm")
    console.print(batch_table)

    from importlib.metadata import version

    import small_gicp  # noqa: F401  (version below)

    report = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "load_average": os.getloadavg(),
                    "backend": info.backend, "device": info.device},
        "versions": {"small_gicp": version("small_gicp"), "taichi": version("taichi")},
        "settings": {**{k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
                     "OMP_WAIT_POLICY": os.environ["OMP_WAIT_POLICY"]},
        "pairwise": rows, "pairwise_time_ratio_vs_small_gicp": ratio, "batched": batch,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
