"""TSDF fusion speed vs Open3D, and the memory of an office-sized map vs a dense grid.

1. Fusion: one OS1-64-like scan (64 beams over ±16.6°, 1024 columns) ray cast in the
   simulated office (mcl3d.sim.worlds, 50 m x 20 m), fused into a 5 cm map with a
   truncation of 4 voxels. mcl3d (Taichi) is timed per scan (host preparation + block
   allocation + band + free-space carving), in its two distance modes: point-to-plane with
   normals (the default; normal estimation is timed separately, it runs in Open3D on the
   host) and projective (no normals), each with and without free-space carving (the fast
   configuration, `carve_free_space: false` in a build-map --config file: Open3D does
   none beyond its truncation band; the map then knows no free space outside the band).
   The point-to-plane fusion is also split into its stages: host preparation, allocation,
   band, carving (carving = the update with carving minus the update without). The
   baseline, in the same run on the same threads, is Open3D's tensor VoxelBlockGrid
   integration of the same scan: the points are projected into 4 pinhole depth images
   (90° each) and each is integrated (block lookup + integrate), the way a projective TSDF
   takes a spinning lidar. Open3D allocates blocks from every 4th pixel of every 4th row
   only, so it stores about a third of our blocks; a second Open3D run allocates them from
   every point instead (its point-cloud overload), as our fusion does. Each method's map is
   also scored: the share of the scan's points whose voxel (nearest sample) was observed.
   The methods take turns, one scan each per round (a warm-up round first; compile time
   excluded), so load from other work hits them alike; ratios are per round (Open3D's time
   over ours in the same round), reported as median and min..max over rounds. The map is
   cleared between rounds, so every round allocates its blocks afresh (as a scan of new
   ground does). Besides wall time, the CPU time of the process per scan (all threads) is
   reported: on a shared machine it depends far less on what else runs than wall time.
2. Memory: the office map built from its mesh: allocated and free blocks, bytes per
   block (f32 while building, f32 and f16 read-only), total, against a dense grid.

    OMP_NUM_THREADS=2 python bench/bench_tsdf_fusion.py --backend cpu \
        --json bench/results/bench_tsdf_fusion.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

VOXEL = 0.05
BEAMS, COLUMNS, VFOV_DEG = 64, 1024, 16.6
# Open3D's depth images: a row is 1/0.7 times a column's angle (the beams ~1 row apart).
# Of the vertical focal lengths tried (0.5 to 1.0 times the horizontal), this one let
# Open3D observe the most of the scan's voxels (82% with its own block allocation, against
# 63% with square pixels, where beams lie up to 1.7 rows apart and voxels that project
# between them get nothing).
DEPTH_FY_SCALE = 0.7


def _office():
    from mcl3d.sim.worlds import build_world

    world = build_world("office", seed=0)
    return world.static.vertices, world.static.triangles, world


def _scan(scene, T_world_lidar):
    import open3d as o3d

    az = np.linspace(-np.pi, np.pi, COLUMNS, endpoint=False)
    el = np.deg2rad(np.linspace(-VFOV_DEG, VFOV_DEG, BEAMS))
    A, E = np.meshgrid(az, el)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    d_w = d @ T_world_lidar[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_world_lidar[:3, 3], d_w.shape), d_w], 1)
    t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    ok = np.isfinite(t) & (t < 100)
    return (d[ok] * t[ok, None]).astype(np.float32)


def _median_ms(fn, repeats):
    fn()  # warm-up: compile / first call
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), min(times)


def _timed(fn, sync=None):
    """(wall ms, cpu ms) of fn(), after sync() says the device is done."""
    t0, c0 = time.perf_counter(), time.process_time()
    fn()
    if sync is not None:
        sync()
    return (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3


class _Ours:
    """One scan fused into a map that is cleared between rounds (the kernels are compiled
    once per map, so a fresh map per round would time the compiler)."""

    def __init__(self, points_l, T, geometry, normals, mode, carve=True):
        from mcl3d.maps.build import BuildConfig, ScanFuser, new_map

        self.cfg = BuildConfig(normals=mode, capacity_blocks=200000, carve_free_space=carve)
        self.tsdf = new_map(geometry, self.cfg)
        self.fuser = ScanFuser(self.tsdf, self.cfg)
        self.args = (points_l, T)
        self.normals = normals

    def sync(self):
        self.tsdf.block_count.to_numpy()

    def clear(self):
        self.tsdf.clear()
        self.tsdf.as_sums = True
        self.sync()

    def once(self):
        self.clear()
        return _timed(lambda: self.fuser.fuse(*self.args, normals_l=self.normals), self.sync)

    def stages(self):
        """(wall, cpu) ms of host preparation, allocation, band, carving."""
        self.clear()
        prep = {}

        def prepare():
            prep["scan"] = self.fuser.prepare(*self.args, normals_l=self.normals)

        out = {"prepare": _timed(prepare)}
        scan = prep["scan"]
        out["allocate"] = _timed(lambda: self.fuser.allocate(scan), self.sync)
        out["band"] = _timed(lambda: self.fuser.update(scan, False), self.sync)
        self.clear()
        self.fuser.allocate(scan)
        self.sync()
        both = _timed(lambda: self.fuser.update(scan, True), self.sync)
        out["carve"] = (both[0] - out["band"][0], both[1] - out["band"][1])
        return out

    @property
    def n_blocks(self):
        return self.tsdf.n_blocks

    def coverage(self, points_w):
        """Fraction of the scan's points whose voxel the last fusion observed (weight > 0)."""
        data = self.tsdf.blocks()
        g = self.tsdf.geometry
        observed = data.coords[:, None, None, None, :] * 8 + np.stack(
            np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1)
        keys = _voxel_keys(observed[data.weight > 0])
        at = np.floor((points_w - np.asarray(g.origin_m)) / g.voxel_size_m).astype(np.int64)
        return float(np.isin(_voxel_keys(at), keys).mean())


def _voxel_keys(ijk):
    """One int64 per integer voxel coordinate (|i| < 2^20)."""
    ijk = np.asarray(ijk, np.int64) + (1 << 20)
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def _camera_rotations():
    """R_lidar_cam of the 4 cameras: camera k looks along lidar yaw k·90°."""
    out = []
    for k in range(4):
        yaw = k * np.pi / 2
        out.append(np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                             [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]))
    return out


def _pixels(points_l, R_lidar_cam, K, shape):
    """Pixel (u, v), depth and in-image mask of each point in one camera."""
    pc = points_l @ R_lidar_cam  # points in the camera frame
    z = pc[:, 2]
    ok = z > 1e-3
    zs = np.where(ok, z, 1.0)
    u = np.floor(K[0, 0] * pc[:, 0] / zs + K[0, 2]).astype(int)
    v = np.floor(K[1, 1] * pc[:, 1] / zs + K[1, 2]).astype(int)
    inside = ok & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
    return u, v, z, inside


def _in_images(points_l, images, K):
    """Per camera, the mask of the points that land in its image."""
    return [_pixels(points_l, T_lc[:3, :3], K, depth.shape)[3] for depth, T_lc in images]


def _depth_images(points_l, width=256, fy_scale=DEPTH_FY_SCALE):
    """The scan as 4 pinhole depth images (camera k looks along lidar yaw k·90°), 256
    columns per 90° (the scan has 1024 per 360°); rows fy_scale times as far apart in
    angle as columns."""
    f = 0.5 * width / np.tan(np.pi / 4)
    fy = f * fy_scale
    height = 2 * int(np.ceil(fy * np.tan(np.deg2rad(VFOV_DEG)) / np.cos(np.pi / 4))) + 2
    K = np.array([[f, 0, width / 2], [0, fy, height / 2], [0, 0, 1]])
    images = []
    for R_lidar_cam in _camera_rotations():
        u, v, z, inside = _pixels(points_l, R_lidar_cam, K, (height, width))
        depth = np.full((height, width), np.inf, np.float32)
        np.minimum.at(depth, (v[inside], u[inside]), z[inside].astype(np.float32))
        depth[~np.isfinite(depth)] = 0
        T_lidar_cam = np.eye(4)
        T_lidar_cam[:3, :3] = R_lidar_cam
        images.append((depth, T_lidar_cam))
    return images, K


class _Open3D:
    """Open3D's VoxelBlockGrid integration of the scan as 4 depth images, fresh grid per
    round (created outside the timing, as our map is cleared outside it).

    Blocks come from each depth image (`compute_unique_block_coordinates(depth, ...)`,
    which reads every 4th pixel of every 4th row: Open3D's way, fast, but it misses the
    blocks of sparse and far surfaces), or with `every_point` from all the points that
    fall in the image (the point-cloud overload: every point's surface gets its blocks,
    as in our fusion)."""

    def __init__(self, points_l, T, every_point=False):
        import open3d as o3d
        import open3d.core as o3c

        images, K = _depth_images(points_l)
        self.K = o3c.Tensor(K, o3c.float64)
        self.prepared = [(o3d.t.geometry.Image(o3c.Tensor(depth)),
                          o3c.Tensor(np.linalg.inv(T @ T_lc), o3c.float64))
                         for depth, T_lc in images]
        self.clouds = None
        if every_point:
            points_w = (points_l @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
            self.clouds = [o3d.t.geometry.PointCloud(o3c.Tensor(points_w[inside]))
                           for inside in _in_images(points_l, images, K)]
        self.pixels = sum(int((d > 0).sum()) for d, _ in images)
        self.n_blocks = 0
        self.grid = None

    def coverage(self, points_w):
        """As _Ours.coverage: Open3D's samples lie on the voxel corners (i * voxel)."""
        ijk, flat = self.grid.voxel_coordinates_and_flattened_indices()
        weight = self.grid.attribute("weight").reshape((-1,)).numpy()[flat.numpy()]
        keys = _voxel_keys(np.round(ijk.numpy()[weight > 0] / VOXEL))
        return float(np.isin(_voxel_keys(np.round(points_w / VOXEL)), keys).mean())

    def once(self):
        import open3d as o3d
        import open3d.core as o3c

        grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1,), (1,)), voxel_size=VOXEL, block_resolution=8,
            block_count=200000)

        def integrate():
            for i, (image, extrinsic) in enumerate(self.prepared):
                if self.clouds is None:
                    blocks = grid.compute_unique_block_coordinates(
                        image, self.K, extrinsic, depth_scale=1.0, depth_max=100.0,
                        trunc_voxel_multiplier=4.0)
                else:
                    blocks = grid.compute_unique_block_coordinates(
                        self.clouds[i], trunc_voxel_multiplier=4.0)
                grid.integrate(blocks, image, self.K, extrinsic, depth_scale=1.0,
                               depth_max=100.0, trunc_voxel_multiplier=4.0)
            grid.hashmap().size()  # wait for the last integration

        out = _timed(integrate)
        self.n_blocks = grid.hashmap().size()
        self.grid = grid
        return out


def _memory(vertices, triangles):
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.tsdf import VOXELS_PER_BLOCK

    t0 = time.perf_counter()
    tsdf = build_from_mesh(vertices, triangles, BuildConfig(capacity_blocks=200000))
    seconds = time.perf_counter() - t0
    data = tsdf.blocks()
    g = tsdf.geometry
    n, free = len(data.coords), len(data.free_coords)
    # while building: f32 distance, weight and free hits, i64 fixed-point sums (not on Vulkan)
    per = {"build_f32": VOXELS_PER_BLOCK * 28 + 16, "f32": VOXELS_PER_BLOCK * 8 + 16,
           "f16": VOXELS_PER_BLOCK * 4 + 16}
    coarse = g.n_cells * 4
    dense = g.n_cells * VOXELS_PER_BLOCK * 8
    extent = (np.asarray(g.coarse_dims) * g.block_size_m).round(2).tolist()
    return {"extent_m": extent, "cells": g.n_cells, "blocks": n, "free_blocks": free,
            "bytes_per_block": per, "coarse_bytes": coarse,
            "total_bytes": {k: coarse + n * v for k, v in per.items()},
            "dense_grid_bytes_f32": dense, "build_from_mesh_s": round(seconds, 2)}


def _summary(values):
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--repeats", type=int, default=9, help="timed rounds")
    parser.add_argument("--skip-memory", action="store_true", help="fusion timings only")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from mcl3d.core import runtime
    from mcl3d.maps.build import SENSOR_ORIGIN, BuildConfig, _mesh_scene
    from mcl3d.maps.normals import oriented_normals
    from mcl3d.maps.tsdf import MapGeometry

    info = runtime.init(args.backend)
    vertices, triangles, world = _office()
    scene = _mesh_scene(vertices, triangles)
    route = next(iter(world.routes.values()))
    T = np.eye(4)
    T[:3, 3] = [route[0][0], route[0][1], world.floor_z_m[0] + 0.8]
    points = _scan(scene, T)
    geometry = MapGeometry.around(vertices.min(0), vertices.max(0), VOXEL, 4 * VOXEL, 0.4)
    build = BuildConfig()

    def scan_normals():
        return oriented_normals(points, build.normal_neighbors, SENSOR_ORIGIN,
                                build.orientation_cell_m)

    normals = scan_normals()
    normals_ms = _median_ms(scan_normals, args.repeats)[0]
    methods = {
        "point_to_plane": _Ours(points, T, geometry, normals, "knn"),
        "projective": _Ours(points, T, geometry, None, "none"),
        "projective_no_carving": _Ours(points, T, geometry, None, "none", carve=False),
        "point_to_plane_no_carving": _Ours(points, T, geometry, normals, "knn", carve=False),
        "open3d": _Open3D(points, T),
        "open3d_every_point": _Open3D(points, T, every_point=True),
    }
    stages_of = methods["point_to_plane"]
    wall = {name: [] for name in methods}
    cpu = {name: [] for name in methods}
    stages = {}
    for rnd in range(args.repeats + 1):  # round 0 compiles and warms up
        for name, method in methods.items():
            w, c = method.once()
            if rnd:
                wall[name].append(w)
                cpu[name].append(c)
        split = stages_of.stages()
        if rnd:
            for stage, (w, c) in split.items():
                stages.setdefault(stage, {"wall": [], "cpu": []})
                stages[stage]["wall"].append(w)
                stages[stage]["cpu"].append(c)
    o3d_wall, o3d_cpu = wall["open3d"], cpu["open3d"]
    ratio = {name: [o / t for o, t in zip(o3d_wall, wall[name], strict=True)]
             for name in methods}
    ratio_cpu = {name: [o / t for o, t in zip(o3d_cpu, cpu[name], strict=True)]
                 for name in methods}
    ratio_every = {name: [o / t for o, t in zip(wall["open3d_every_point"], wall[name],
                                                 strict=True)] for name in methods}
    points_w = points @ T[:3, :3].T + T[:3, 3]
    for method in methods.values():  # the last round's maps
        if isinstance(method, _Ours):
            method.once()
    coverage = {name: method.coverage(points_w) for name, method in methods.items()}
    memory = None if args.skip_memory else _memory(vertices, triangles)

    threads = os.environ.get("OMP_NUM_THREADS", str(os.cpu_count()))
    labels = {"point_to_plane": "mcl3d point-to-plane (fuse)",
              "projective": "mcl3d projective",
              "projective_no_carving": "mcl3d projective, no carving (as Open3D)",
              "point_to_plane_no_carving": "mcl3d point-to-plane, no carving",
              "open3d": "Open3D VoxelBlockGrid (4 depth images)",
              "open3d_every_point": "Open3D, blocks from every point"}
    print(f"\nTSDF fusion of one {BEAMS}x{COLUMNS} scan ({len(points)} points; Open3D gets "
          f"{methods['open3d'].pixels} depth pixels), {VOXEL * 100:.0f} cm voxels, trunc 4 "
          f"voxels; {info.backend} on {info.device}, OMP_NUM_THREADS={threads}, "
          f"{args.repeats} rounds")
    print(f"{'method':42s} {'median ms':>9s} {'min ms':>7s} {'blocks':>7s} "
          f"{'vs Open3D (min..max)':>21s} {'cpu ms':>7s} {'cpu vs O3D':>10s} "
          f"{'vs every pt':>11s} {'covered':>7s}")
    for name, method in methods.items():
        r = _summary(ratio[name])
        print(f"{labels[name]:42s} {statistics.median(wall[name]):9.1f} "
              f"{min(wall[name]):7.1f} {method.n_blocks:7d} "
              f"{r['median']:6.2f}x ({r['min']:.2f}..{r['max']:.2f}) "
              f"{statistics.median(cpu[name]):7.1f} "
              f"{statistics.median(ratio_cpu[name]):9.2f}x "
              f"{statistics.median(ratio_every[name]):10.2f}x {coverage[name]:7.1%}")
    plane_ms = statistics.median(wall["point_to_plane"])
    print(f"{'mcl3d point-to-plane + normals':42s} {plane_ms + normals_ms:9.1f}")
    print("point-to-plane stages (median ms, wall / cpu): " + ", ".join(
        f"{stage} {statistics.median(v['wall']):.1f} / {statistics.median(v['cpu']):.1f}"
        for stage, v in stages.items()))
    print(f"(normal estimation alone: {normals_ms:.1f} ms; ratio > 1 = faster than Open3D, "
          f"per round; cpu ms: process CPU time per scan, all threads; covered: scan points "
          f"whose voxel got an observation)")
    if memory is not None:
        mb = 1 / 2**20
        print(f"\nOffice map {memory['extent_m']} m from its mesh: {memory['blocks']} blocks "
              f"allocated, {memory['free_blocks']} free, of {memory['cells']} cells")
        for key, per in memory["bytes_per_block"].items():
            print(f"  {key:10s} {per:6d} B/block  total "
                  f"{memory['total_bytes'][key] * mb:8.1f} MiB")
        print(f"  dense f32 grid (distance + weight): "
              f"{memory['dense_grid_bytes_f32'] * mb:.1f} MiB")
    if args.json:
        result = {
            "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                        "omp_threads": threads, "backend": info.backend,
                        "device": info.device},
            "scan": {"beams": BEAMS, "columns": COLUMNS, "points": len(points),
                     "o3d_depth_pixels": methods["open3d"].pixels},
            "rounds": args.repeats,
            "fusion_ms": {name: _summary(v) for name, v in wall.items()},
            "fusion_cpu_ms": {name: _summary(v) for name, v in cpu.items()},
            "normals_ms": normals_ms,
            "point_to_plane_stages_ms": {
                stage: {"wall": _summary(v["wall"]), "cpu": _summary(v["cpu"])}
                for stage, v in stages.items()},
            "ratio_open3d_over_ours": {name: _summary(v) for name, v in ratio.items()
                                       if name != "open3d"},
            "ratio_open3d_over_ours_cpu": {name: _summary(v) for name, v in ratio_cpu.items()
                                           if name != "open3d"},
            "ratio_open3d_every_point_over_ours": {
                name: _summary(v) for name, v in ratio_every.items()
                if not name.startswith("open3d")},
            "blocks_allocated": {name: m.n_blocks for name, m in methods.items()},
            "points_covered": coverage,
            "office_memory": memory,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
