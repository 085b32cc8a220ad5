"""TSDF fusion speed vs Open3D, and the memory of an office-sized map vs a dense grid.

1. Fusion: one OS1-64-like scan (64 beams over ±16.6°, 1024 columns) ray cast in the
   simulated office (mcl3d.sim.worlds, 50 m x 20 m), fused into a 5 cm map with a
   truncation of 4 voxels. mcl3d (Taichi) is timed per scan (block allocation + band +
   free-space carving), in its two distance modes: point-to-plane with normals (the
   default; normal estimation is timed separately, it runs in Open3D on the host) and
   projective (no normals), with and without free-space carving (Open3D does none beyond
   its truncation band). The baseline, in the same run on the same threads, is
   Open3D's tensor VoxelBlockGrid integration of the same scan: the points are projected
   into 4 pinhole depth images (90° each) and each is integrated (block lookup +
   integrate), the way a projective TSDF takes a spinning lidar. Medians over repeats
   after a warm-up; compile time excluded. The map is cleared between repeats, so every
   repeat allocates its blocks afresh (as a scan of new ground does). Besides wall time,
   the CPU time of the process per scan (all threads) is reported: on a shared machine
   it depends far less on what else runs than wall time does.
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


def _ours(points_l, T, geometry, normals, mode, repeats, carve=True):
    """ms per scan (median, min, median CPU ms), fusing into one map that is cleared between
    repeats (the kernels are compiled once per map, so a fresh map per repeat would time
    the compiler)."""
    from mcl3d.maps.build import BuildConfig, ScanFuser, new_map

    cfg = BuildConfig(normals=mode, capacity_blocks=200000, carve_free_space=carve)
    tsdf = new_map(geometry, cfg)
    times, cpu = [], []
    for i in range(repeats + 1):
        tsdf.clear()
        tsdf.block_count.to_numpy()  # the clear is done
        t0, c0 = time.perf_counter(), time.process_time()
        ScanFuser(tsdf, cfg).fuse(points_l, T, normals_l=normals)
        tsdf.block_count.to_numpy()  # wait for the device
        if i > 0:  # the first run compiles
            times.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
    n_blocks = tsdf.n_blocks
    tsdf.destroy()
    return statistics.median(times), min(times), n_blocks, statistics.median(cpu)


def _depth_images(points_l, width=256):
    """The scan as 4 pinhole depth images (camera k looks along lidar yaw k·90°)."""
    f = 0.5 * width / np.tan(np.pi / 4)
    height = 2 * int(np.ceil(f * np.tan(np.deg2rad(VFOV_DEG)) / np.cos(np.pi / 4))) + 2
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    images = []
    for k in range(4):
        yaw = k * np.pi / 2
        R_lidar_cam = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                                [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
        pc = points_l @ R_lidar_cam  # points in the camera frame
        z = pc[:, 2]
        ok = z > 1e-3
        u = np.floor(K[0, 0] * pc[ok, 0] / z[ok] + K[0, 2]).astype(int)
        v = np.floor(K[1, 1] * pc[ok, 1] / z[ok] + K[1, 2]).astype(int)
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        depth = np.full((height, width), np.inf, np.float32)
        np.minimum.at(depth, (v[inside], u[inside]), z[ok][inside].astype(np.float32))
        depth[~np.isfinite(depth)] = 0
        T_lidar_cam = np.eye(4)
        T_lidar_cam[:3, :3] = R_lidar_cam
        images.append((depth, T_lidar_cam))
    return images, K


def _open3d(points_l, T, repeats):
    import open3d as o3d
    import open3d.core as o3c

    images, K = _depth_images(points_l)
    Kt = o3c.Tensor(K, o3c.float64)
    prepared = [(o3d.t.geometry.Image(o3c.Tensor(depth)),
                 o3c.Tensor(np.linalg.inv(T @ T_lc), o3c.float64)) for depth, T_lc in images]
    state = {}

    def run():
        grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1,), (1,)), voxel_size=VOXEL, block_resolution=8,
            block_count=200000)
        t0, c0 = time.perf_counter(), time.process_time()
        for image, extrinsic in prepared:
            blocks = grid.compute_unique_block_coordinates(
                image, Kt, extrinsic, depth_scale=1.0, depth_max=100.0,
                trunc_voxel_multiplier=4.0)
            grid.integrate(blocks, image, Kt, extrinsic, depth_scale=1.0, depth_max=100.0,
                           trunc_voxel_multiplier=4.0)
        grid.hashmap().size()  # wait for the last integration
        state["t"] = (time.perf_counter() - t0) * 1e3
        state["cpu"] = (time.process_time() - c0) * 1e3
        state["blocks"] = grid.hashmap().size()

    run()
    times, cpu = [], []
    for _ in range(repeats):
        run()
        times.append(state["t"])
        cpu.append(state["cpu"])
    return statistics.median(times), min(times), state["blocks"], statistics.median(cpu), sum(
        int((d > 0).sum()) for d, _ in images)


def _memory(vertices, triangles):
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.tsdf import VOXELS_PER_BLOCK

    t0 = time.perf_counter()
    tsdf = build_from_mesh(vertices, triangles, BuildConfig(capacity_blocks=200000))
    seconds = time.perf_counter() - t0
    data = tsdf.blocks()
    g = tsdf.geometry
    n, free = len(data.coords), len(data.free_coords)
    per = {"build_f32": VOXELS_PER_BLOCK * 12 + 16, "f32": VOXELS_PER_BLOCK * 8 + 16,
           "f16": VOXELS_PER_BLOCK * 4 + 16}
    coarse = g.n_cells * 4
    dense = g.n_cells * VOXELS_PER_BLOCK * 8
    extent = (np.asarray(g.coarse_dims) * g.block_size_m).round(2).tolist()
    return {"extent_m": extent, "cells": g.n_cells, "blocks": n, "free_blocks": free,
            "bytes_per_block": per, "coarse_bytes": coarse,
            "total_bytes": {k: coarse + n * v for k, v in per.items()},
            "dense_grid_bytes_f32": dense, "build_from_mesh_s": round(seconds, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from mcl3d import runtime
    from mcl3d.maps.build import BuildConfig, _mesh_scene, estimate_normals
    from mcl3d.maps.tsdf import MapGeometry

    info = runtime.init(args.backend)
    vertices, triangles, world = _office()
    scene = _mesh_scene(vertices, triangles)
    route = next(iter(world.routes.values()))
    T = np.eye(4)
    T[:3, 3] = [route[0][0], route[0][1], world.floor_z_m[0] + 0.8]
    points = _scan(scene, T)
    geometry = MapGeometry.around(vertices.min(0), vertices.max(0), VOXEL, 4 * VOXEL, 0.4)
    k = BuildConfig().normal_neighbors
    normals = estimate_normals(points, k, np.zeros((1, 3)))
    normals_ms = _median_ms(lambda: estimate_normals(points, k, np.zeros((1, 3))),
                            args.repeats)[0]
    plane = _ours(points, T, geometry, normals, "knn", args.repeats)
    proj = _ours(points, T, geometry, None, "none", args.repeats)
    band_only = _ours(points, T, geometry, None, "none", args.repeats, carve=False)
    o3d_ms = _open3d(points, T, args.repeats)
    memory = _memory(vertices, triangles)

    threads = os.environ.get("OMP_NUM_THREADS", str(os.cpu_count()))
    rows = [
        ("mcl3d point-to-plane (fuse)", plane[0], plane[1], plane[2], plane[3]),
        ("mcl3d point-to-plane + normals", plane[0] + normals_ms, None, plane[2], None),
        ("mcl3d projective", proj[0], proj[1], proj[2], proj[3]),
        ("mcl3d projective, no carving (as Open3D)", band_only[0], band_only[1], band_only[2],
         band_only[3]),
        ("Open3D VoxelBlockGrid (4 depth images)", o3d_ms[0], o3d_ms[1], o3d_ms[2], o3d_ms[3]),
    ]
    print(f"\nTSDF fusion of one {BEAMS}x{COLUMNS} scan ({len(points)} points; Open3D gets "
          f"{o3d_ms[4]} depth pixels), {VOXEL * 100:.0f} cm voxels, trunc 4 voxels; "
          f"{info.backend} on {info.device}, OMP_NUM_THREADS={threads}")
    print(f"{'method':42s} {'median ms':>10s} {'min ms':>8s} {'blocks':>8s} {'vs Open3D':>10s} "
          f"{'cpu ms':>8s} {'cpu vs O3D':>10s}")
    for name, med, best, blocks, cpu_ms in rows:
        ratio = o3d_ms[0] / med
        cpu_cols = (f"{cpu_ms:8.1f} {o3d_ms[3] / cpu_ms:9.2f}x" if cpu_ms
                    else f"{'':8s} {'':10s}")
        print(f"{name:42s} {med:10.1f} {best if best is None else round(best, 1)!s:>8s} "
              f"{blocks:8d} {ratio:9.2f}x {cpu_cols}")
    print(f"(normal estimation alone: {normals_ms:.1f} ms; ratio > 1 = faster than Open3D; "
          f"cpu ms: process CPU time per scan, all threads)")
    mb = 1 / 2**20
    print(f"\nOffice map {memory['extent_m']} m from its mesh: {memory['blocks']} blocks "
          f"allocated, {memory['free_blocks']} free, of {memory['cells']} cells")
    for key, per in memory["bytes_per_block"].items():
        print(f"  {key:10s} {per:6d} B/block  total {memory['total_bytes'][key] * mb:8.1f} MiB")
    print(f"  dense f32 grid (distance + weight): {memory['dense_grid_bytes_f32'] * mb:.1f} MiB")
    if args.json:
        result = {
            "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(),
                        "omp_threads": threads, "backend": info.backend,
                        "device": info.device},
            "scan": {"beams": BEAMS, "columns": COLUMNS, "points": len(points),
                     "o3d_depth_pixels": o3d_ms[4]},
            "fusion_ms": {"point_to_plane": plane[0], "point_to_plane_min": plane[1],
                          "normals": normals_ms, "projective": proj[0],
                          "projective_min": proj[1], "projective_no_carving": band_only[0],
                          "open3d": o3d_ms[0],
                          "open3d_min": o3d_ms[1]},
            "fusion_cpu_ms": {"point_to_plane": plane[3], "projective": proj[3],
                              "projective_no_carving": band_only[3], "open3d": o3d_ms[3]},
            "ratio_open3d_over_ours": {"point_to_plane": o3d_ms[0] / plane[0],
                                       "point_to_plane_with_normals":
                                           o3d_ms[0] / (plane[0] + normals_ms),
                                       "projective": o3d_ms[0] / proj[0],
                                       "projective_no_carving": o3d_ms[0] / band_only[0]},
            "blocks_allocated": {"point_to_plane": plane[2], "projective": proj[2],
                                 "open3d": o3d_ms[2]},
            "office_memory": memory,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
        print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
