"""A city-sized point-cloud map without poses: generated, built into a TSDF, localized in.

Issue #19's target: a 20 M-point map of 1.2 km x 1.2 km of streets, built at 10 cm voxels
in <= 10 minutes and <= 8 GiB peak memory on 2 cores, as `mcl3d build-map city.ply -o
city.tsdf --voxel-size 0.1` (no trajectory: normals oriented from the map itself).

The world is procedural: a grid of --streets streets each way over --extent-m (14 m wide,
a 15 cm kerb at 5 m from the centre line), lined with buildings 6 to 30 m tall with gaps,
poles every 25 m and trees every 15 m on both sides, on a ground plane. The point map is
what a mobile-mapping run would export: rays cast from a lidar 1.8 m above the street
every 2 m along every street (directions uniform over azimuth, elevation -30..+40 deg, hits
1.5-60 m away, 1 cm range noise) until --points points, written as an x y z PLY.

The build runs the build-map pipeline in this process (the same code the command runs) and
records per stage its wall time, process cpu time and peak RSS (sampled every 20 ms).
Then the map is loaded, its surface voxels (every 4th chunk of blocks) are compared with
the world mesh (distance), and MCL tracks a VLP-16-like lidar (bench_km_map.Scanner) over
--track-scans scans 1 m apart along one street, from the true first pose.

    python bench/bench_city_map.py [--quick] [--points 20000000] [--extent-m 1200]
"""

from __future__ import annotations

import argparse
import resource
import threading
import time
from pathlib import Path

import numpy as np
from results_io import Run

LIDAR_HEIGHT_M = 1.8
STREET_HALF_M = 7.0
KERB_M = 5.0
POSE_STEP_M = 2.0
MAX_RANGE_M = 60.0
RAYS_PER_CAST = 1 << 20
FREE_STAGE = "mark free space"  # mcl3d.maps.build.FREE_STAGE: the pipeline writes next
SURFACE_SAMPLE_EVERY = 4  # chunks of blocks whose surface is compared with the mesh


def street_positions(extent_m: float, n: int) -> np.ndarray:
    """Centre lines of n streets evenly inside [0, extent] (the same each way)."""
    return (np.arange(n) + 0.5) * extent_m / n


def _on_a_street(lo, hi, streets: np.ndarray, axis: int) -> bool:
    """Whether the box [lo, hi] (x, y) reaches into a street that runs across `axis`."""
    return bool(np.any((streets + STREET_HALF_M > lo[axis]) & (streets - STREET_HALF_M < hi[axis])))


def city_mesh(extent_m: float, n_streets: int, seed: int):
    """Ground, kerbs, buildings, poles and trees along a grid of streets."""
    from mcl3d.sim.mesh import MeshBuilder

    rng = np.random.default_rng(seed)
    b = MeshBuilder()
    lo, hi = -40.0, extent_m + 40.0
    b.add([[lo, lo, 0], [hi, lo, 0], [hi, hi, 0], [lo, hi, 0]], [[0, 1, 2], [0, 2, 3]], 0.3)
    streets = street_positions(extent_m, n_streets)
    for axis in (0, 1):  # axis 0: streets along x at y = c; axis 1: along y at x = c
        for c in streets:
            for sign in (-1.0, 1.0):
                _kerb(b, axis, c, sign, extent_m)
                _buildings(b, rng, axis, c, sign, extent_m, streets)
                _street_furniture(b, rng, axis, c, sign, extent_m, streets)
    return b.build()


def _box_along(b, axis: int, s0: float, s1: float, a0: float, a1: float, z0: float, z1: float,
               refl: float) -> None:
    """A box spanning s0..s1 along the street and a0..a1 across it."""
    if axis == 0:
        b.box([s0, a0, z0], [s1, a1, z1], refl)
    else:
        b.box([a0, s0, z0], [a1, s1, z1], refl)


def _kerb(b, axis: int, c: float, sign: float, extent_m: float) -> None:
    across = sorted((c + sign * KERB_M, c + sign * STREET_HALF_M))
    _box_along(b, axis, -20.0, extent_m + 20.0, *across, 0.0, 0.15, 0.4)


def _buildings(b, rng, axis: int, c: float, sign: float, extent_m: float, streets) -> None:
    s = -20.0
    while s < extent_m + 20.0:
        length, gap = rng.uniform(15, 45), rng.uniform(4, 12)
        near = c + sign * STREET_HALF_M
        far = c + sign * (STREET_HALF_M + rng.uniform(8, 20))
        a0, a1 = sorted((near, far))
        lo = [s, a0] if axis == 0 else [a0, s]
        hi = [s + length, a1] if axis == 0 else [a1, s + length]
        if not _on_a_street(lo, hi, streets, 1 - axis) and not _on_a_street(lo, hi, streets,
                                                                             axis):
            height = rng.choice([rng.uniform(6, 15), rng.uniform(15, 30)], p=[0.75, 0.25])
            _box_along(b, axis, s, s + length, a0, a1, 0.0, height, 0.5)
        s += length + gap


def _street_furniture(b, rng, axis: int, c: float, sign: float, extent_m: float,
                      streets) -> None:
    """Poles every 25 m at 5.5 m from the centre line, trees every 15 m at 6.2 m."""
    for s in np.arange(5.0, extent_m, 25.0):
        if np.min(np.abs(streets - s)) > STREET_HALF_M + 2:
            xy = (s, c + sign * 5.5) if axis == 0 else (c + sign * 5.5, s)
            b.cylinder(xy, 0.1, 0.0, 6.0, 0.6, sides=8)
    for s in np.arange(12.0, extent_m, 15.0):
        if np.min(np.abs(streets - s)) > STREET_HALF_M + 4 and rng.random() < 0.7:
            xy = (s, c + sign * 6.2) if axis == 0 else (c + sign * 6.2, s)
            b.cylinder(xy, 0.15, 0.0, 2.5, 0.4, sides=8)
            b.cone(xy, rng.uniform(1.2, 2.2), 2.0, rng.uniform(5.0, 8.0), 0.3)


def route_positions(extent_m: float, n_streets: int, step_m: float) -> np.ndarray:
    """Lidar positions every step_m along every street."""
    s = np.arange(0.0, extent_m, step_m)
    out = []
    for c in street_positions(extent_m, n_streets):
        out.append(np.column_stack([s, np.full_like(s, c), np.full_like(s, LIDAR_HEIGHT_M)]))
        out.append(np.column_stack([np.full_like(s, c), s, np.full_like(s, LIDAR_HEIGHT_M)]))
    return np.concatenate(out)


def point_map(mesh, positions: np.ndarray, n_points: int, seed: int) -> np.ndarray:
    """(n_points, 3) float32: hits of rays cast from the positions (see the docstring)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    rng = np.random.default_rng(seed)
    out = np.empty((n_points, 3), np.float32)
    filled = 0
    while filled < n_points:
        origin = positions[rng.integers(len(positions), size=RAYS_PER_CAST)]
        az = rng.uniform(0, 2 * np.pi, RAYS_PER_CAST)
        sin_el = rng.uniform(np.sin(np.radians(-30)), np.sin(np.radians(40)), RAYS_PER_CAST)
        cos_el = np.sqrt(1 - sin_el**2)
        d = np.column_stack([cos_el * np.cos(az), cos_el * np.sin(az), sin_el])
        rays = np.hstack([origin, d]).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        ok = np.isfinite(t) & (t > 1.5) & (t < MAX_RANGE_M)
        r = t[ok] + rng.normal(0, 0.01, ok.sum())
        pts = origin[ok] + d[ok] * r[:, None]
        take = min(len(pts), n_points - filled)
        out[filled:filled + take] = pts[:take]
        filled += take
    return out


def write_xyz_ply(points: np.ndarray, path: Path) -> None:
    header = ("ply\nformat binary_little_endian 1.0\ncomment mcl3d bench_city_map\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(points.astype("<f4").tobytes())


class StageClock:
    """Wall, process cpu and peak RSS of each stage a pipeline reports (RSS sampled by a
    thread every 20 ms; the process's ru_maxrss caps the last stage)."""

    def __init__(self):
        self.stages: dict[str, dict] = {}
        self.current = "read point map"
        self._t, self._c = time.perf_counter(), time.process_time()
        self._peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self):
        while not self._stop.wait(0.02):
            self._peak = max(self._peak, _rss_mib())

    def __call__(self, progress) -> None:
        if progress.stage != self.current:
            self.switch(progress.stage)
        if progress.stage == FREE_STAGE and progress.done == progress.total:
            self.switch("write map, stats")

    def switch(self, stage: str) -> None:
        t, c = time.perf_counter(), time.process_time()
        self._peak = max(self._peak, _rss_mib())
        row = self.stages.setdefault(self.current, {"wall_s": 0.0, "cpu_s": 0.0,
                                                    "peak_rss_mib": 0.0})
        row["wall_s"] += t - self._t
        row["cpu_s"] += c - self._c
        row["peak_rss_mib"] = max(row["peak_rss_mib"], self._peak)
        self.current, self._t, self._c, self._peak = stage, t, c, _rss_mib()

    def stop(self) -> None:
        self.switch("done")
        self._stop.set()
        self._thread.join()


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def build_map(ply: Path, out: Path, voxel_m: float) -> tuple[dict, dict]:
    """The build-map pipeline on the point map, timed stage by stage."""
    from mcl3d.mapping.pipeline import BuildMapRequest, run
    from mcl3d.maps.build import BuildConfig

    clock = StageClock()
    t0, c0 = time.perf_counter(), time.process_time()
    result = run(BuildMapRequest(ply, out, BuildConfig(voxel_size_m=voxel_m), force=True),
                 clock)
    clock.stop()
    total = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
             "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
             "blocks": result.stats.blocks, "free_blocks": result.stats.free_blocks,
             "tiles": result.stats.tiles, "file_mib": result.stats.file_bytes / 2**20}
    return clock.stages, total


def tracking_route(extent_m: float, n_streets: int, n: int) -> np.ndarray:
    """n lidar poses 1 m apart heading +x along the first street, from a third of the way."""
    c = street_positions(extent_m, n_streets)[0]
    x0 = extent_m / 3
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, :3, 3] = np.column_stack([x0 + np.arange(n), np.full(n, c),
                                       np.full(n, LIDAR_HEIGHT_M)])
    return poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="200 m, 1 M points, 5 scans")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--points", type=int, help="points of the map (default 20,000,000)")
    ap.add_argument("--extent-m", type=float, help="side of the city (default 1200)")
    ap.add_argument("--streets", type=int, default=2, help="streets each way")
    ap.add_argument("--voxel-m", type=float, default=0.1)
    ap.add_argument("--track-scans", type=int, help="tracked scans (default 15)")
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work-dir", type=Path, default=Path("/tmp/mcl3d_city_map"))
    args = ap.parse_args()
    extent = args.extent_m or (200.0 if args.quick else 1200.0)
    n_points = args.points or (1_000_000 if args.quick else 20_000_000)
    n_track = args.track_scans or (5 if args.quick else 15)
    run = Run("bench_city_map", baselines=())
    args.work_dir.mkdir(parents=True, exist_ok=True)
    ply, tsdf_path = args.work_dir / "city.ply", args.work_dir / "city.tsdf"

    from mcl3d.core import runtime

    runtime.init(args.backend)
    t0 = time.perf_counter()
    mesh = city_mesh(extent, args.streets, args.seed)
    positions = route_positions(extent, args.streets, POSE_STEP_M)
    write_xyz_ply(point_map(mesh, positions, n_points, args.seed), ply)
    generate_s = time.perf_counter() - t0
    stages, total = build_map(ply, tsdf_path, args.voxel_m)
    tracking, surface = track_in(tsdf_path, mesh,
                                 tracking_route(extent, args.streets, n_track), args)
    figures = {"extent_m": extent, "streets_each_way": args.streets, "points": n_points,
               "street_km": 2 * args.streets * extent / 1000, "voxel_m": args.voxel_m,
               "generate_s": generate_s, "stages": stages, "total": total,
               "tracking": tracking, "surface_error": surface}
    figures["tables"] = tables(figures)
    figures["notes"] = [
        f"procedural city, seed {args.seed}: {args.streets} streets each way over "
        f"{extent:.0f} m ({figures['street_km']:.1f} km of street), {n_points:,} points; "
        f"build-map pipeline in-process at {args.voxel_m} m voxels, no trajectory; backend "
        f"{args.backend}; tracking {tracking['scans']} scans 1 m apart, {args.particles} "
        "particles, from the true first pose"]
    for caption, rows in figures["tables"].items():
        print(caption)
        for row in rows:
            print("  ", row)
    print("wrote", run.write(figures))


def track_in(tsdf_path: Path, mesh, poses: np.ndarray, args) -> tuple[dict, dict]:
    """Tracking in the map file, and its surface's distance to the world mesh."""
    from bench_km_map import Scanner, track

    from mcl3d.maps.map_file import load_map

    loaded = load_map(tsdf_path)
    return (track(loaded, Scanner(mesh, args.seed), poses, args.particles, args.seed),
            surface_error(loaded, mesh))


def surface_error(tsdf, mesh, every: int = SURFACE_SAMPLE_EVERY) -> dict:
    """Distance from the map's surface voxels (|sdf| under half a voxel diagonal) to the
    world mesh, over every `every`-th chunk of blocks (the map is never copied whole)."""
    import open3d as o3d

    from mcl3d.maps.tsdf import BlockData, surface_points

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    no_free = np.zeros((0, 3), np.int32)
    dist = []
    for k, (c, d, w) in enumerate(tsdf.block_chunks()):
        if k % every == 0:
            pts = surface_points(tsdf.geometry, BlockData(c, d, w, no_free))
            query = o3d.core.Tensor(pts.astype(np.float32))
            dist.append(scene.compute_distance(query).numpy())
    dist = np.concatenate(dist)
    return {"surface_voxels_sampled": len(dist), "mean_m": float(dist.mean()),
            "median_m": float(np.median(dist)), "p95_m": float(np.percentile(dist, 95)),
            "within_voxel": float(np.mean(dist <= tsdf.geometry.voxel_size_m))}


def tables(f: dict) -> dict:
    caption = (f"City point map without poses: {f['points']:,} points, {f['street_km']:.1f} km "
               f"of street over {f['extent_m']:.0f} m x {f['extent_m']:.0f} m, "
               f"{f['voxel_m'] * 100:.0f} cm voxels")
    rows = [{"stage": name, "wall s": round(s["wall_s"], 1), "cpu s": round(s["cpu_s"], 1),
             "peak RSS MiB": round(s["peak_rss_mib"])} for name, s in f["stages"].items()]
    t = f["total"]
    rows.append({"stage": "total", "wall s": round(t["wall_s"], 1),
                 "cpu s": round(t["cpu_s"], 1), "peak RSS MiB": round(t["peak_rss_mib"])})
    err, surf = f["tracking"]["position_error_m"], f["surface_error"]
    return {caption: rows, f"Map and tracking ({f['voxel_m'] * 100:.0f} cm)": [
        {"blocks": t["blocks"], "free blocks": t["free_blocks"], "tiles": t["tiles"],
         "file MiB": round(t["file_mib"], 1),
         "surface to mesh median / p95 m": f"{surf['median_m']:.3f} / {surf['p95_m']:.3f}",
         "tracking mean / max m": f"{err['mean']:.3f} / {err['max']:.3f}"}]}


if __name__ == "__main__":
    main()
