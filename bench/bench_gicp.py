"""GICP speed and accuracy: pairwise registration vs small_gicp, and batched GICP for many poses.

1. Pairwise, on the real HDL-32E pair (../shared/data/hdl32_pair): mcl3d `align` (VGICP on
   device voxel maps, coarse to fine) against small_gicp (VGICP and kd-tree GICP) on the
   same points, same downsampling and k, same run. Times are medians over repeats after a
   warm-up (compilation excluded), registration only (both sides get preprocessed clouds)
   and end to end (raw points in); wall and process cpu time (cpu time is what a shared
   machine cannot inflate). Errors are against T_target_source.txt.
2. Batched: `--poses` poses (default 10,000) x `--points` source points (512) of the source
   scan around the reference pose (1° and 10 cm per axis, seed 0), one Gauss-Newton iteration
   of every pose (linearize, solve, update), against voxel maps (1 m) of the target in two
   layouts: one map shared by every pose, and one map per pose (map k: a random 80% of the
   target's points, seed 0, so that no two maps hold the same numbers; 2,048 buckets each;
   `--maps M`: M such maps, pose k using map k mod M).
   Baselines doing the same arithmetic in the same run (bench/gicp_baselines.py): Numba
   (compiled, parallel over poses on every thread, a hash table per map) and vectorized
   NumPy, both float32, one voxel per point, the same centred sums, Jacobi-scaled Cholesky and
   SE(3) retraction. Before timing, each baseline's H, b, error, inliers and updated pose are
   compared with mcl3d's at the same poses (the bench stops if they disagree). Rounds take
   turns (mcl3d block, Numba block, NumPy iterations), medians over every timed iteration of
   wall and process cpu time. small_gicp's `align(max_iterations=1)` called pose by pose
   from Python (Levenberg-Marquardt, float64) is kept as a reference row: not the same
   arithmetic, and it pays the binding per pose.

small_gicp and numba are dev-only dependencies: `pip install -e '.[bench]'`.

    python bench/bench_gicp.py --backend cpu          # full run -> bench/results/bench_gicp.json
    python bench/bench_gicp.py --quick                # seconds to a minute
    python bench/bench_gicp.py --skip-pairwise        # the batched part only
"""

from __future__ import annotations

import argparse
import os
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


class Layout:
    """One batched problem, set up for mcl3d and for the baselines: poses, source points and
    maps (`num_maps` 1: shared; else map k serves poses k, k + num_maps, ...)."""

    def __init__(self, args, target, pts, covs, poses, num_maps, rng):
        import gicp_baselines as gb

        from mcl3d.registration.batch_gicp import BatchGicp, plane_form
        from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

        P = len(poses)
        buckets = 1 << 15 if num_maps == 1 else MAP_BUCKETS
        self.name = ("one shared map" if num_maps == 1 else f"one map per pose ({num_maps})"
                     if num_maps == P else f"{num_maps} maps, {P // num_maps} poses each")
        self.maps = GaussianVoxelMaps(max_maps=num_maps, buckets_per_map=buckets,
                                      max_points=len(target.points))
        self.base = gb.VoxelMaps(args.batch_resolution, buckets, num_maps)
        t0 = time.perf_counter()
        for k in range(num_maps):
            keep = (np.ones(len(target.points), bool) if num_maps == 1
                    else rng.random(len(target.points)) < MAP_SUBSET)
            self.maps.clear(k, args.batch_resolution)
            ours = self.maps.insert(k, target.points[keep], target.covs[keep])
            self.base.insert(k, target.points[keep], target.covs[keep])
            if ours != self.base.num_voxels[k]:
                raise SystemExit(f"map {k}: {ours} voxels in mcl3d, {self.base.num_voxels[k]} "
                                 "in the baseline's map")
        self.base.finish()
        self.build_s = time.perf_counter() - t0
        self.voxels = int(self.base.num_voxels.sum())
        self.map_of = np.arange(P, dtype=np.int64) % num_maps
        self.poses = poses
        self.gicp = BatchGicp(self.maps, max_groups=P, max_source_points=len(pts))
        self.gicp.set_source(pts, covs)
        rows = plane_form(covs)
        if rows is None:
            raise SystemExit("source covariances are not plane-regularized")
        self.pts32 = pts.astype(np.float32)
        self.plane32 = rows[:, :5].astype(np.float32)

    def ours_reset(self, n=None):
        n = len(self.poses) if n is None else n
        self.gicp.set_problem(self.poses[:n], row_group=np.arange(n), row_map=self.map_of[:n])

    def ours_iterate(self):
        import taichi as ti

        self.gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
        ti.sync()

    def start(self, poses):
        """float32 R, t the baselines move in place."""
        return (np.ascontiguousarray(poses[:, :3, :3], np.float32),
                np.ascontiguousarray(poses[:, :3, 3], np.float32))

    def numba_iterate(self, R, t):
        import gicp_baselines as gb

        G = len(R)
        out = (np.empty((G, 6, 6), np.float32), np.empty((G, 6), np.float32),
               np.empty(G, np.float32), np.empty(G, np.int64))
        b = self.base
        gb.numba_iterate(R, t, self.pts32, self.plane32, self.map_of[:G], b.res, b.table_keys,
                         b.table_vox, b.means, b.cov_rows, b.buckets, *out)
        return out

    def numpy_iterate(self, R, t):
        import gicp_baselines as gb

        return gb.numpy_iterate(R, t, self.pts32, self.plane32, self.map_of[:len(R)], self.base)


MAP_BUCKETS = 2048  # per map of the per-pose layout: ~1,100 voxels of 1 m each
MAP_SUBSET = 0.8  # of the target's points in each per-pose map


def validate(layout: Layout, n: int) -> list[dict]:
    """Each baseline's H, b, error, inliers and one-step pose against mcl3d's, at the first n
    poses as mcl3d holds them (f32 quaternions); a point within ~1e-6 m of a voxel face may
    land in the neighbouring voxel on one side, so poses whose inlier counts differ are
    counted, and the others compared."""
    layout.ours_reset(n)
    layout.gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
    r0 = layout.gicp.result()
    layout.gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
    r1 = layout.gicp.result()
    rows = []
    for name, fn in (("Numba", layout.numba_iterate), ("NumPy", layout.numpy_iterate)):
        R, t = layout.start(r0.T)
        H, b, e, inl = fn(R, t)
        same = inl == r0.num_inliers
        rel_H = np.abs(H - r0.H).max((1, 2)) / np.abs(r0.H).max((1, 2))
        rel_b = np.abs(b - r0.b).max(1) / np.abs(r0.b).max(1)
        rel_e = np.abs(e - r0.error) / np.abs(r0.error)
        step_t = np.linalg.norm(t - r1.T[:, :3, 3], axis=1)
        step_R = np.abs(R - r1.T[:, :3, :3]).max((1, 2))
        row = {"maps": layout.name, "baseline": name, "poses": n,
               "same inliers": f"{same.mean():.1%}",
               "max rel. H diff": f"{rel_H[same].max():.1e}",
               "max rel. b diff": f"{rel_b[same].max():.1e}",
               "max rel. error diff": f"{rel_e[same].max():.1e}",
               "max step diff (µm)": f"{1e6 * step_t[same].max():.1f}",
               "max step R diff": f"{step_R[same].max():.1e}"}
        rows.append(row)
        if same.mean() < 0.9 or rel_H[same].max() > 1e-3 or 1e6 * step_t[same].max() > 100:
            raise SystemExit(f"{name} does not compute what mcl3d computes: {row}")
    return rows


def time_layout(layout: Layout, args) -> dict:
    """ms per iteration (wall, cpu) of each implementation, rounds taking turns."""
    layout.ours_reset()
    layout.ours_iterate()  # compile
    R, t = layout.start(layout.poses[:64])
    layout.numba_iterate(R, t)  # compile (cached after the first run)
    times = {"mcl3d": [], "Numba": [], "NumPy": []}
    for _ in range(args.batch_repeats):
        layout.ours_reset()
        for _ in range(args.iterations):
            times["mcl3d"].append(_wall_cpu(layout.ours_iterate))
        R, t = layout.start(layout.poses)
        for _ in range(args.iterations):
            times["Numba"].append(_wall_cpu(lambda R=R, t=t: layout.numba_iterate(R, t)))
        R, t = layout.start(layout.poses)
        for _ in range(args.numpy_iterations):
            times["NumPy"].append(_wall_cpu(lambda R=R, t=t: layout.numpy_iterate(R, t)))
    return {name: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v),
                   len(v)) for name, v in times.items()}


def _wall_cpu(fn):
    """(wall ms, cpu ms) of fn()."""
    t0, c0 = time.perf_counter(), cpu_s()
    fn()
    return (time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3


def converge(layout: Layout, reference) -> dict:
    """Every pose optimized to small_gicp's thresholds (0.1°, 1 mm; on the piecewise voxel
    cost poses can circle small limit cycles): the share that converged, the spread of the
    translations and their mean's offset from the full-scan reference (with 512 points on a
    1 m map the minimum sits a few cm from it)."""
    layout.ours_reset()
    out = layout.gicp.optimize(max_iterations=10, rotation_eps_rad=np.radians(0.1),
                               translation_eps_m=1e-3)
    t = out.T[:, :3, 3]
    return {"maps": layout.name, "converged in 10 iterations": f"{out.converged.mean():.1%}",
            "spread (cm)": round(100 * float(np.linalg.norm(t.std(axis=0))), 1),
            "mean vs reference (cm)": round(
                100 * float(np.linalg.norm(t.mean(axis=0) - reference[:3, 3])), 1)}


def small_gicp_pose_by_pose(args, target, pts, poses):
    """cpu ms of small_gicp's align(max_iterations=1), one thread, pose by pose on a subset,
    scaled to all poses (one thread: cpu time = busy time)."""
    import small_gicp

    sg_source = small_gicp.PointCloud(pts)
    small_gicp.estimate_covariances(sg_source, num_neighbors=args.k_neighbors)
    sg_target = small_gicp.PointCloud(target.points)
    small_gicp.estimate_covariances(sg_target, num_neighbors=args.k_neighbors)
    vmap = small_gicp.GaussianVoxelMap(args.batch_resolution)
    vmap.insert(sg_target)
    subset = min(len(poses), 500)
    c0 = cpu_s()
    for T in poses[:subset]:
        small_gicp.align(vmap, sg_source, T, max_iterations=1, num_threads=1)
    return (cpu_s() - c0) / subset * len(poses) * 1e3, subset


def batched(args, target, source, reference) -> dict:
    from mcl3d.core.geometry import se3, so3_exp

    rng = np.random.default_rng(0)
    pick = rng.choice(len(source.points), args.points, replace=False)
    pts, covs = source.points[pick], source.covs[pick]
    poses = np.stack([reference @ se3(so3_exp(np.radians(1.0) * rng.normal(size=3)),
                                      0.1 * rng.normal(size=3)) for _ in range(args.poses)])
    speed, checks, accuracy, setup = [], [], [], {}
    for num_maps in (1, args.maps or args.poses):
        layout = Layout(args, target, pts, covs, poses, num_maps, rng)
        setup[layout.name] = {"voxels": layout.voxels, "build_s": round(layout.build_s, 1)}
        checks += validate(layout, min(args.poses, 256))
        timed = time_layout(layout, args)
        ours_wall, ours_cpu, _ = timed["mcl3d"]
        for name, (wall, cpu, count) in timed.items():
            label = {"mcl3d": "mcl3d (Taichi)", "Numba": "Numba, same arithmetic",
                     "NumPy": "NumPy, same arithmetic"}[name]
            speed.append({"maps": layout.name, "implementation": label,
                          "wall ms": round(wall, 1), "cpu ms": round(cpu, 1),
                          "wall / mcl3d": round(wall / ours_wall, 2),
                          "cpu / mcl3d": round(cpu / ours_cpu, 2), "iterations timed": count})
        if num_maps == 1:
            sg_ms, subset = small_gicp_pose_by_pose(args, target, pts, poses)
            speed.append({"maps": layout.name,
                          "implementation": f"small_gicp align(max_iterations=1) pose by pose,"
                                            f" 1 thread (LM, float64; {subset} poses, scaled)",
                          "wall ms": round(sg_ms, 1), "cpu ms": round(sg_ms, 1),
                          "wall / mcl3d": round(sg_ms / ours_wall, 2),
                          "cpu / mcl3d": round(sg_ms / ours_cpu, 2),
                          "iterations timed": subset})
        accuracy.append(converge(layout, reference))
        del layout
    return {"speed": speed, "checks": checks, "accuracy": accuracy, "setup": setup}


def pairwise_rows(rows):
    return [{"case": r["case"], "wall ms": round(r["ms"], 1), "cpu ms": round(r["cpu_ms"], 1),
             "trans err (cm)": round(100 * r["trans_err_m"], 2),
             "rot err (deg)": round(r["rot_err_deg"], 3)} for r in rows]


def print_table(caption, rows):
    from rich.console import Console
    from rich.table import Table

    table = Table(title=caption)
    for col in rows[0]:
        table.add_column(col, justify="left" if col in ("case", "maps", "implementation",
                                                         "baseline") else "right")
    for r in rows:
        table.add_row(*(str(v) for v in r.values()))
    Console(width=200).print(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes, one repeat: seconds to a minute")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--downsample", type=float, default=0.1)
    parser.add_argument("--k-neighbors", type=int, default=10)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                        help="small_gicp threads (Taichi and Numba use every core)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--poses", type=int, default=10000)
    parser.add_argument("--points", type=int, default=512)
    parser.add_argument("--maps", type=int, default=None,
                        help="maps of the second layout, poses sharing them in turn (default: "
                             "one per pose; each map is built and checked on the host, ~20 ms)")
    parser.add_argument("--iterations", type=int, default=10,
                        help="GN iterations timed per block (batched case)")
    parser.add_argument("--batch-repeats", type=int, default=5,
                        help="rounds of timed iterations (batched case)")
    parser.add_argument("--numpy-iterations", type=int, default=1,
                        help="NumPy iterations timed per round (it is slow)")
    parser.add_argument("--skip-pairwise", action="store_true",
                        help="only the batched case (no pairwise table)")
    parser.add_argument("--batch-resolution", type=float, default=1.0)
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON path (default bench/results/bench_gicp.json)")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.poses, args.iterations, args.batch_repeats = 2, 300, 3, 2
    # small_gicp's OpenMP threads sleep while they wait instead of spinning (GOMP's default
    # spin burns a shared machine's cores and inflates its times); must precede its import
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from results_io import Run

    run = Run("bench_gicp", baselines=("small_gicp", "numba"))

    from mcl3d.console import console
    from mcl3d.core import runtime
    from mcl3d.io.logs.cloud_files import read_cloud_file
    from mcl3d.registration.align import preprocess

    info = runtime.init(args.backend)
    target_raw = read_cloud_file(args.data / "251370668.pcd").points.astype(np.float64)
    source_raw = read_cloud_file(args.data / "251371071.pcd").points.astype(np.float64)
    reference = np.loadtxt(args.data / "T_target_source.txt")

    if args.skip_pairwise:
        rows = []
        target = preprocess(target_raw, args.downsample, args.k_neighbors)
        source = preprocess(source_raw, args.downsample, args.k_neighbors)
    else:
        rows, target, source = pairwise(args, target_raw, source_raw, reference)
    batch = batched(args, target, source, reference)

    import numba

    tables = {}
    device = f"{info.backend}: {info.device}"
    if rows:
        tables[f"Pairwise registration, HDL-32E pair ({device})"] = pairwise_rows(rows)
    tables[f"Batched GICP, {args.poses} poses x {args.points} points: one Gauss-Newton "
           f"iteration of every pose ({device}; median ms)"] = batch["speed"]
    tables["Batched GICP: the baselines against mcl3d at the same poses (H, b, error, "
           "inliers at the pose, the pose after one step)"] = batch["checks"]
    tables["Batched GICP: every pose optimized (10 iterations at most)"] = batch["accuracy"]
    for caption, table_rows in tables.items():
        print_table(caption, table_rows)
    load = os.getloadavg()[0]
    notes = [
        f"{os.cpu_count()} cpus, load average {run.load_before:.1f} at the start and "
        f"{load:.1f} at the end; Taichi and Numba ({numba.config.NUMBA_NUM_THREADS} threads) "
        "on every core, NumPy mostly on one; cpu ms = process cpu time, all threads.",
        "Poses: the reference pose perturbed by 1° and 10 cm per axis (seed 0); maps of 1 m "
        "voxels; per-pose maps: a random 80% of the target's points each (seed 0); "
        + ", ".join(f"{k}: {v['voxels']} voxels, built in {v['build_s']} s"
                    for k, v in batch["setup"].items()) + ".",
        "Inlier counts differ where a point lies within float32 rounding of a voxel face "
        "(mcl3d builds R from an f32 quaternion); the other poses agree to the digits shown.",
    ]
    if rows:
        notes.append(f"Pairwise: mcl3d / small_gicp wall time, same VGICP schedule: "
                     f"{rows[0]['ms'] / rows[1]['ms']:.2f}x.")
    path = run.write({"tables": tables, "notes": notes, "backend": info.backend,
                      "device": info.device, "settings": {
                          **{k: str(v) if isinstance(v, Path) else v
                             for k, v in vars(args).items()},
                          "OMP_WAIT_POLICY": os.environ["OMP_WAIT_POLICY"]},
                      "pairwise": rows, "batched": batch}, args.out)
    console.print(f"wrote {path}")


if __name__ == "__main__":
    main()
