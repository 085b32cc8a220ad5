"""A kilometre-scale map: built from simulated scans, saved, described, loaded and tracked in.

The world is a synthetic city: an L-shaped street (two legs of --side-m, 14 m wide) lined on
both sides by buildings 6 to 45 m tall with gaps between them, on a ground plane; the map's
bounds span side x side x 50 m. A VLP-16-like lidar (16 rings, 900 columns, 60 m) 1.8 m
above the street takes a scan every --step-m along the route; the scans are fused (normals
from the scan, free-space carving) into a map of --voxel-m (default 20 cm: a 2 km street at
10 cm holds ~330k blocks, 4.5 GiB while building, more than a shared 2-core box should
give a benchmark; memory grows with the street, not with the bounds), which is saved, read back by
`map-info` (coarse index, blocks and file bytes) and loaded again for localization: MCL
tracking from the true pose over --track-scans scans 1 m apart (a 10 Hz lidar at 10 m/s,
between the build's scans) 85 % along the route, with odometry that is the true motion plus
noise. Global initialization's candidate cells are generated in the loaded map, from its
known blocks (the dense grid over the bounds they came from before took cells of 8 voxels
here, 1.6 m at 20 cm, and refused these bounds at 5 cm voxels).

A global start follows (default settings: the coarse search phase on its sparse distance
field, then the accurate model) over --global-scans scans 1 m apart from 30 % along the route,
with --global-particles particles (default: two per candidate cell of the initialization,
at most a million).

Reported: peak RSS of the process (the build dominates), the coarse index's memory (top
grid + tiles), the blocks' and the file's, against the dense coarse grid the version-1
layout needed over the same bounds (and at 5 cm voxels), build and tracking times, and the
tracking error; for the global start, the coarse search field's cell and device bytes
against the former dense field over the bounds, its initialization time, whether and when it
converged, and its update times. There is no other implementation to compare with in the
same run: the baseline is the former dense layouts' memory, computed for the same bounds.

    python bench/bench_km_map.py [--quick] [--backend cpu] [--voxel-m 0.1] [--side-m 1000]
                                 [--global-particles N] [--global-scans 40]
"""

from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from results_io import Run

STREET_HALF_M = 7.0
LIDAR_HEIGHT_M = 1.8
MAX_RANGE_M = 60.0
TRACK_STEP_M = 1.0
BLOCKS_PER_M_AT_10CM = 200  # blocks per metre of street (measured: ~165), sizes the pool
HEIGHT_M = 50.0
GLOBAL_TOL_M = 0.5  # a global start converged: the filter says so, this close to the truth
MAX_GLOBAL_PARTICLES = 1_000_000


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def city_mesh(side_m: float, seed: int):
    """Ground plus buildings along both sides of both legs of the L route."""
    from mcl3d.sim.mesh import MeshBuilder

    rng = np.random.default_rng(seed)
    b = MeshBuilder()
    lo, hi = -40.0, side_m + 40.0
    b.add([[lo, lo, 0], [hi, lo, 0], [hi, hi, 0], [lo, hi, 0]], [[0, 1, 2], [0, 2, 3]], 0.3)
    for leg in (0, 1):
        s = -20.0
        while s < side_m + 20.0:
            length, gap = rng.uniform(25, 50), rng.uniform(6, 12)
            for sign in (-1.0, 1.0):
                height = rng.choice([rng.uniform(6, 15), rng.uniform(15, 45)], p=[0.8, 0.2])
                near = sign * STREET_HALF_M
                far = sign * (STREET_HALF_M + rng.uniform(10, 20))
                across = sorted((near, far))
                if leg == 0:  # along x at y = 0; the corner (side, 0) stays open
                    if s + length > side_m - STREET_HALF_M and sign > 0:
                        continue
                    b.box([s, across[0], 0], [min(s + length, side_m + 30), across[1], height],
                          0.5)
                else:  # along y at x = side
                    if s < STREET_HALF_M and sign < 0:
                        continue
                    b.box([side_m + across[0], max(s, STREET_HALF_M + 1), 0],
                          [side_m + across[1], s + length, height], 0.5)
            s += length + gap
    return b.build()


def route(side_m: float, step_m: float) -> np.ndarray:
    """Lidar poses T_map_lidar every step_m along the L: east along y = 0, then north."""
    poses = []
    for leg, (start, heading) in enumerate((((0.0, 0.0), 0.0), ((side_m, 0.0), np.pi / 2))):
        for s in np.arange(0.0, side_m, step_m):
            T = np.eye(4)
            c, si = np.cos(heading), np.sin(heading)
            T[:3, :3] = [[c, -si, 0], [si, c, 0], [0, 0, 1]]
            T[:3, 3] = [start[0] + s * (leg == 0), start[1] + s * (leg == 1), LIDAR_HEIGHT_M]
            poses.append(T)
    return np.asarray(poses)


class Scanner:
    """Ray casts a VLP-16-like scan (every other column) with 1.5 cm range noise."""

    def __init__(self, mesh, seed: int):
        import open3d as o3d

        from mcl3d.sim.lidars import make_lidar

        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                                 o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        self.dirs = make_lidar("vlp16").firing(0, 0.1, 2).directions
        self.rng = np.random.default_rng(seed)
        self.o3d = o3d

    def scan(self, T: np.ndarray) -> np.ndarray:
        """Points in the lidar frame."""
        d_map = self.dirs @ T[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T[:3, 3], d_map.shape), d_map], axis=1)
        t = self.scene.cast_rays(self.o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        ok = np.isfinite(t) & (t < MAX_RANGE_M) & (t > 1.0)
        r = t[ok] + self.rng.normal(0, 0.015, ok.sum())
        return (self.dirs[ok] * r[:, None]).astype(np.float32)


def build(scanner: Scanner, poses: np.ndarray, geometry, voxel_m: float, route_m: float):
    """Fuse every scan; a pool that overflows is grown and the fusion run again (as
    build-map does). Returns the map, the build config and the number of retries."""
    from mcl3d.maps.build import BuildConfig, ScanFuser, grown_capacity, grown_tiles, new_map

    cfg = BuildConfig(voxel_size_m=voxel_m, max_range_m=MAX_RANGE_M,
                      capacity_blocks=int(route_m * BLOCKS_PER_M_AT_10CM * (0.1 / voxel_m) ** 2),
                      max_capacity_blocks=1 << 23)
    needed = needed_tiles = retries = 0
    while True:
        tsdf = new_map(geometry, cfg, needed, needed_tiles)
        fuser = ScanFuser(tsdf, cfg)
        for T in poses:
            fuser.fuse(scanner.scan(T), T)
        if not tsdf.overflowed:
            return tsdf, cfg, retries
        needed, needed_tiles = grown_capacity(tsdf, cfg), grown_tiles(tsdf)
        tsdf.destroy()
        retries += 1


def track(tsdf, scanner: Scanner, poses: np.ndarray, particles: int, seed: int) -> dict:
    """MCL tracking from the true first pose; odometry = true motion + noise (5 cm along
    x and y, 1 cm in height, per scan)."""
    from mcl3d.core.geometry import se3_inverse
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    cfg = LocalizerConfig.model_validate({"particles": particles, "seed": seed,
                                          "sensor": {"points": 256}})
    loc = Localizer(tsdf, cfg)
    loc.init_pose(poses[0], [0.3, 0.3, 0.05, 0.02, 0.02, 0.1])
    rng = np.random.default_rng(seed)
    errors, ms = [], []
    for k, T in enumerate(poses):
        dT = np.eye(4) if k == 0 else se3_inverse(poses[k - 1]) @ T
        dT[:3, 3] += rng.normal(0, [0.05, 0.05, 0.01]) * (k > 0)
        t0 = time.perf_counter()
        r = loc.step(scanner.scan(T), dT, 0.1 * k)
        ms.append(1e3 * (time.perf_counter() - t0))
        errors.append(float(np.linalg.norm(r.T_map_lidar[:3, 3] - T[:3, 3])))
    return {"scans": len(poses), "particles": particles,
            "position_error_m": {"mean": float(np.mean(errors)), "max": float(np.max(errors)),
                                 "last": errors[-1]},
            "step_ms_median": statistics.median(ms[1:] if len(ms) > 1 else ms)}


def global_start(tsdf, scanner: Scanner, poses: np.ndarray, particles: int, seed: int) -> dict:
    """A global start with the default settings (the coarse search phase on its sparse field,
    then the accurate model), roll and pitch from gravity, odometry = true motion + noise as
    in `track`: the filter's state and position error after each scan, update times (the
    coarse phase's and the rest), the coarse field's cell and device bytes, and the time
    and peak host allocation (tracemalloc) of the initialization (candidates + field)."""
    import tracemalloc

    from mcl3d.core.geometry import se3_inverse
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    cfg = LocalizerConfig.model_validate({"particles": particles, "seed": seed})
    loc = Localizer(tsdf, cfg, imu_roll_pitch=(0.0, 0.0))
    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    loc.init_global()
    init = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
            "peak_alloc_mib": tracemalloc.get_traced_memory()[1] / 2**20}
    tracemalloc.stop()
    rng = np.random.default_rng(seed + 1)
    errors, states, wall_ms, cpu_ms = [], [], [], []
    for k, T in enumerate(poses):
        dT = None if k == 0 else se3_inverse(poses[k - 1]) @ T
        if dT is not None:
            dT[:3, 3] += rng.normal(0, [0.05, 0.05, 0.01])
        points = scanner.scan(T)
        t0, c0 = time.perf_counter(), time.process_time()
        r = loc.step(points, dT, 0.1 * k)
        wall_ms.append(1e3 * (time.perf_counter() - t0))
        cpu_ms.append(1e3 * (time.process_time() - c0))
        errors.append(float(np.linalg.norm(r.T_map_lidar[:3, 3] - T[:3, 3])))
        states.append(r.state.value)
    coarse = cfg.sensor.coarse_scans
    said = [k for k, st in enumerate(states) if st == "converged"]
    off = np.flatnonzero(np.asarray(errors) >= GLOBAL_TOL_M)
    within = int(off[-1]) + 1 if len(off) else 0
    return {"particles": particles, "scans": len(poses), "init": init,
            "field": loc.weigher.coarse_summary,
            "converged": states[-1] == "converged" and errors[-1] < GLOBAL_TOL_M,
            "converged_at_scan": said[0] if said else None, "final_state": states[-1],
            "within_tol_from_scan": within if within < len(errors) else None,
            "final_error_m": errors[-1], "errors_m": errors, "states": states,
            "coarse_update_ms": {"wall": statistics.median(wall_ms[1:coarse]),
                                 "cpu": statistics.median(cpu_ms[1:coarse])},
            "later_update_ms": {"wall": statistics.median(wall_ms[coarse:]),
                                "cpu": statistics.median(cpu_ms[coarse:])}}


def dense_field_bytes(geometry, voxel_m: float) -> dict:
    """What the former dense coarse field over the bounds took with the default settings:
    its cell (coarsened until the bounds held 16 M cells, at most one cell per block) and 4
    bytes a cell."""
    from mcl3d.localization.sensor_model import SensorModelConfig

    cfg = SensorModelConfig()
    f = 1
    while f < 8 and voxel_m * f * 2 <= cfg.coarse_cell_m + 1e-9:
        f *= 2
    while f < 8 and geometry.n_cells * (8 // f) ** 3 > 16_000_000:
        f *= 2
    return {"cell_m": voxel_m * f, "bytes": 4 * geometry.n_cells * (8 // f) ** 3}


def global_candidates(tsdf) -> dict:
    """Global initialization's candidate cells (the default band and covered rule): wall and
    cpu time, and the peak of memory allocated meanwhile (tracemalloc sees NumPy's arrays)."""
    import tracemalloc

    from mcl3d.localization.initialization import InitConfig, free_cells

    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    cells = free_cells(tsdf, InitConfig())
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - c0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"candidates": len(cells.corners_m), "cell_m": cells.cell_m, "wall_s": wall_s,
            "cpu_s": cpu_s, "peak_alloc_mib": peak / 2**20,
            "dense_grid": dense_grid_rule(tsdf.geometry, InitConfig().cell_m)}


def dense_grid_rule(geometry, cell_m: float) -> dict:
    """What the former dense candidate grid over the bounds did with this map: its cell
    (coarsened until the bounds held 20 M cells, at most 8 voxels) or a refusal (over 160 M
    cells at 8 voxels)."""
    f = 1
    while f < 8 and geometry.voxel_size_m * f * 2 <= cell_m + 1e-9:
        f *= 2
    while f < 8 and geometry.n_cells * (8 // f) ** 3 > 20_000_000:
        f *= 2
    return {"cell_m": geometry.voxel_size_m * f,
            "refused": geometry.n_cells * (8 // f) ** 3 > 160_000_000}


def global_rows(started: dict, dense: dict) -> list[dict]:
    """Table rows of the global start and its coarse search field."""
    field, mib = started["field"], 1 / 2**20
    at, within = started["converged_at_scan"], started["within_tol_from_scan"]
    return [
        {"quantity": "coarse search field: cell m, blocks with a slot, bricks",
         "value": f"{field['cell_m']:.2f}, {field['blocks']}, {field['bricks']}"},
        {"quantity": "coarse search field, MiB (slot index + bricks)",
         "value": f"{(field['index_bytes'] + field['brick_bytes']) * mib:.1f} "
                  f"({field['index_bytes'] * mib:.1f} + {field['brick_bytes'] * mib:.1f})"},
        {"quantity": "former dense field over the bounds (cell m), MiB: same / 5 cm voxels",
         "value": f"{dense['same_bounds']['bytes'] * mib:.0f} "
                  f"({dense['same_bounds']['cell_m']:.1f}) / "
                  f"{dense['at_5cm']['bytes'] * mib:.0f} ({dense['at_5cm']['cell_m']:.1f})"},
        {"quantity": "global start: init s wall / cpu, peak alloc MiB",
         "value": f"{started['init']['wall_s']:.1f} / {started['init']['cpu_s']:.1f}, "
                  f"{started['init']['peak_alloc_mib']:.0f}"},
        {"quantity": f"global start, {started['particles']} particles: converged (scan), "
                     f"final state, error m",
         "value": f"{'yes' if started['converged'] else 'no'} "
                  f"({at if at is not None else '-'} of {started['scans']}), "
                  f"{started['final_state']}, {started['final_error_m']:.2f}"},
        {"quantity": f"global start: estimate within {GLOBAL_TOL_M} m from scan",
         "value": "-" if within is None else f"{within} of {started['scans']}"},
        {"quantity": "global start ms per update, wall / cpu: coarse phase, after",
         "value": f"{started['coarse_update_ms']['wall']:.0f} / "
                  f"{started['coarse_update_ms']['cpu']:.0f}, "
                  f"{started['later_update_ms']['wall']:.0f} / "
                  f"{started['later_update_ms']['cpu']:.0f}"},
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 150 m L, 5 tracked scans")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--voxel-m", type=float, default=0.2)
    ap.add_argument("--side-m", type=float, help="length of each leg (default 1000)")
    ap.add_argument("--step-m", type=float, default=4.0, help="scan spacing along the route")
    ap.add_argument("--track-scans", type=int, help="tracked scans (default 15)")
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--global-particles", type=int,
                    help="particles of the global start (default: two per candidate cell, at "
                         "most 1000000)")
    ap.add_argument("--global-scans", type=int, help="scans of the global start (default 40, "
                                                     "quick 30)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work-dir", type=Path, help="where the map file goes (default: a temp dir)")
    args = ap.parse_args()
    side = args.side_m or (150.0 if args.quick else 1000.0)
    step = args.step_m
    n_track = args.track_scans or (5 if args.quick else 15)
    global_scans = args.global_scans or (30 if args.quick else 40)
    run = Run("bench_km_map", baselines=())

    from mcl3d.core import runtime

    runtime.init(args.backend)
    from mcl3d.mapping.map_info import map_info
    from mcl3d.maps.map_file import load_map, save_map
    from mcl3d.maps.tsdf import MapGeometry

    mesh = city_mesh(side, args.seed)
    scanner = Scanner(mesh, args.seed)
    poses = route(side, step)
    lo, hi = (-30.0, -30.0, -1.0), (side + 30.0, side + 30.0, HEIGHT_M)
    trunc = 4 * args.voxel_m
    geometry = MapGeometry.around(lo, hi, args.voxel_m, trunc)
    rss_start = rss_mib()
    t0, c0 = time.perf_counter(), time.process_time()
    tsdf, cfg, retries = build(scanner, poses, geometry, args.voxel_m, 2 * side)
    tsdf.finalize()
    build_s, build_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    rss_built = rss_mib()
    with tempfile.TemporaryDirectory() as tmp:
        path = (args.work_dir or Path(tmp)) / "km_city.tsdf"
        path.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        save_map(path, tsdf, source={"kind": "bench_km_map", "side_m": side, "step_m": step},
                 build=cfg.model_dump())
        save_s = time.perf_counter() - t0
        tsdf.destroy()
        info = map_info(path)
        t0 = time.perf_counter()
        loaded = load_map(path)
        load_s = time.perf_counter() - t0
        rss_loaded = rss_mib()
        candidates = global_candidates(loaded)
        tracked = route(side, TRACK_STEP_M)
        far = int(len(tracked) * 0.85)
        tracking = track(loaded, scanner, tracked[far:far + n_track], args.particles, args.seed)
        start = int(len(tracked) * 0.3)
        n_global = args.global_particles or min(MAX_GLOBAL_PARTICLES,
                                                2 * candidates["candidates"])
        started = global_start(loaded, scanner, tracked[start:start + global_scans], n_global,
                               args.seed)
    st = info.stats
    dense_5cm = MapGeometry.around(lo, hi, 0.05, 0.2).n_cells * 8
    mib = 1 / 2**20
    figures = {
        "side_m": side, "step_m": step, "voxel_m": args.voxel_m, "scans": len(poses),
        "bounds_m": [list(lo), list(hi)], "coarse_dims": list(geometry.coarse_dims),
        "top_dims": list(geometry.top_dims), "build_retries": retries,
        "build_s": build_s, "build_cpu_s": build_cpu_s, "save_s": save_s, "load_s": load_s,
        "rss_mib": {"start": rss_start, "built": rss_built, "loaded": rss_loaded,
                    "peak": peak_rss_mib()},
        "memory": st.as_dict()["memory"], "blocks": st.as_dict()["blocks"],
        "dense_index_bytes_at_5cm": dense_5cm, "tracking": tracking,
        "global_candidates": candidates, "global_start": started,
        "dense_field": {"same_bounds": dense_field_bytes(geometry, args.voxel_m),
                        "at_5cm": dense_field_bytes(MapGeometry.around(lo, hi, 0.05, 0.2), 0.05)},
    }
    caption = (f"Kilometre-scale map: {side:.0f} m x {side:.0f} m x {HEIGHT_M:.0f} m bounds, "
               f"{args.voxel_m * 100:.0f} cm voxels, {len(poses)} scans")
    figures["tables"] = {caption: [
        {"quantity": "coarse index (top grid + tiles), MiB",
         "value": f"{st.coarse_bytes * mib:.1f} ({st.coarse_top_bytes * mib:.1f} + "
                  f"{st.tiles} tiles {st.coarse_tile_bytes * mib:.1f})"},
        {"quantity": "dense coarse grid of format 1 (same bounds / at 5 cm), MiB",
         "value": f"{st.dense_index_bytes * mib:.0f} / {dense_5cm * mib:.0f}"},
        {"quantity": "blocks (loaded, f32), MiB",
         "value": f"{st.pool_bytes * mib:.0f} ({st.blocks} blocks, {st.free_blocks} free)"},
        {"quantity": "file, MiB", "value": f"{st.file_bytes * mib:.1f}"},
        {"quantity": "peak RSS (build), MiB", "value": f"{peak_rss_mib():.0f}"},
        {"quantity": "RSS after load, MiB", "value": f"{rss_loaded:.0f}"},
        {"quantity": "build s (wall / cpu)", "value": f"{build_s:.0f} / {build_cpu_s:.0f}"},
        {"quantity": "save / load s", "value": f"{save_s:.1f} / {load_s:.1f}"},
        {"quantity": "tracking error m (mean / max)",
         "value": f"{tracking['position_error_m']['mean']:.3f} / "
                  f"{tracking['position_error_m']['max']:.3f}"},
        {"quantity": "tracking ms per scan (median)", "value": f"{tracking['step_ms_median']:.0f}"},
        {"quantity": "global candidates: cells (cell m), s wall / cpu, peak alloc MiB",
         "value": f"{candidates['candidates']} ({candidates['cell_m']:.2f}), "
                  f"{candidates['wall_s']:.1f} / {candidates['cpu_s']:.1f}, "
                  f"{candidates['peak_alloc_mib']:.0f}"},
        {"quantity": "former dense candidate grid over the bounds: cell m",
         "value": "refused" if candidates["dense_grid"]["refused"]
                  else f"{candidates['dense_grid']['cell_m']:.2f}"},
        *global_rows(started, figures["dense_field"]),
    ]}
    figures["notes"] = [
        f"synthetic L-shaped street, seed {args.seed}, VLP-16-like scans every {step} m; "
        f"{tracking['scans']} tracked scans {TRACK_STEP_M:.0f} m apart ({args.particles} "
        f"particles, 256 points) {0.85 * 2 * side:.0f} m along the route; backend "
        f"{args.backend}; the dense grid of format 1 is computed for the same bounds",
        f"global start: default settings (coarse search phase on its sparse field), "
        f"{n_global} particles, roll/pitch from gravity, {global_scans} scans "
        f"{TRACK_STEP_M:.0f} m apart from {0.3 * 2 * side:.0f} m along the route, odometry "
        f"= true motion + noise; converged = the filter says so within {GLOBAL_TOL_M} m at "
        f"the last scan (it says `ambiguous` while a rival place holds >= 1 % of the "
        f"weight); update times: medians over the coarse phase's scans after the "
        f"first and over the later scans"]
    for row in next(iter(figures["tables"].values())):
        print(f"{row['quantity']:<60} {row['value']}")
    print("wrote", run.write(figures))


if __name__ == "__main__":
    main()
