"""TSDF fusion end to end per scan vs Open3D end to end, and the memory of an office map.

1. The whole job a user waits for, scan by scan from a log, as `mcl3d build-map LOG` does it
   (mcl3d/mapping/pipeline.py, calling the same functions): decode the scan, interpolate its
   start and end poses from the trajectory (per-point times), estimate normals facing the
   sensor (default: from the scan's range image on the device, maps/scan_normals.py; before:
   Open3D's KNN on the host, maps/normals.py, timed side by side), fuse (`ScanFuser.fuse`:
   deskew inside the kernels, point-to-plane band, free-space carving). build-map decodes
   every scan in a first pass (the map's bounds) and keeps them for fusion while they fit
   its scan cache: that pass is timed per scan and added to mcl3d's total in place of the
   decode row. Also mcl3d's projective mode (`normals: none`, no normals needed).
   Open3D end to end on the same decoded scans and poses: the scan deskewed into its start
   pose on the host (mcl3d's deskew kernel, the same motion: Open3D has none), projected into
   4 pinhole depth images (90° each, Open3D's `project_to_depth_image`), then its tensor
   VoxelBlockGrid (5 cm, truncation 4 voxels, as ours) allocates blocks and integrates each
   image: blocks from every 4th pixel of every 4th row (Open3D's way, fast, it misses sparse
   and far surfaces), or from every point (its point-cloud overload, as our fusion does).
   Projective TSDF integration needs no normals, so Open3D's total has none.
   Inputs: a simulated 10 Hz log (default office world, OS1-64, handheld path with motion,
   seed 1, `mcl3d simulate`; --world, --sensor choose others) and the real Ouster OS1-128
   capture in ../shared/data (3 scans at 2.5 m/s, poses from the SDK's KITTI file, a 4th
   pose extrapolated so the last sweep deskews too). Each method builds one map over the
   whole log, scans interleaved between methods (a warm-up on the first scans, compile time
   excluded), `--repeats` passes; per stage the median ms per scan, wall and process cpu
   time (all threads).
   Quality of each finished map, its surface extracted the same way for both (Open3D's
   marching cubes): distance of the surface vertices to the world mesh (simulated log), to
   the nearest deskewed scan point, and the share of scan points within one voxel of the
   surface (completeness).
2. Memory: the office map built from its mesh: allocated and free blocks, bytes per
   block (f32 while building, f32 and f16 read-only), total, against a dense grid.

    python bench/bench_tsdf_fusion.py --backend cpu     # -> bench/results/bench_tsdf_fusion.json
    python bench/bench_tsdf_fusion.py --quick [--world forest --sensor vlp16]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VOXEL = 0.05
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OUSTER = DATA / "ouster_os1_128_lb_n3"
CAPACITY_BLOCKS = 100_000  # the OS1-128 capture takes 61k (14 KiB each while building)


def _timed(fn, sync=None):
    """(result, wall ms, cpu ms) of fn(), after sync() says the device is done."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    if sync is not None:
        sync()
    return out, (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3


# ------------------------------------------------------------------------- inputs
class LogScans:
    """A log's scans decoded once, with their poses, as build-map gets them; per-scan times
    of the stages every method shares (decode, poses) and of build-map's first pass."""

    def __init__(self, name, log, trajectory=None, sensor=None):
        from mcl3d.io.logs.reader import LogReader
        from mcl3d.io.trajectory import read_trajectory
        from mcl3d.mapping import pipeline
        from mcl3d.maps.build import BuildConfig
        from mcl3d.maps.tsdf import MapGeometry

        self.name, self.sensor = name, sensor
        self.config = BuildConfig(capacity_blocks=CAPACITY_BLOCKS)
        req = pipeline.BuildMapRequest(source=log, output=Path("unused.tsdf"),
                                       config=self.config, trajectory=trajectory)
        self.shared = {"decode": [], "poses": []}
        self.scans = []
        self.rings = []  # each scan's ring numbers (None without): range-image normals
        with LogReader(log) as reader:
            self.traj = (read_trajectory(trajectory) if trajectory
                         else pipeline._poses(req, reader)[0])
            bounds, wall, cpu = _timed(lambda: pipeline._scan_bounds(req, reader, self.traj))
            it = reader.scans()
            while True:
                cloud, w, c = _timed(lambda: next(it, None))
                if cloud is None:
                    break
                self.shared["decode"].append((w, c))
                pose, w, c = _timed(lambda cloud=cloud: pipeline._scan_pose(self.traj, cloud))
                self.shared["poses"].append((w, c))
                self.scans.append((cloud.points, *pose))
                self.rings.append(cloud.fields.get("ring"))
        n = len(self.scans)
        self.pass1 = [(wall / n, cpu / n)] * n
        self.decoded_once = bounds.cached is not None  # pass 2 fuses the scans pass 1 kept
        cfg = self.config
        lo = np.minimum(bounds.lo_m, self.traj.positions().min(axis=0))
        hi = np.maximum(bounds.hi_m, self.traj.positions().max(axis=0))
        self.geometry = MapGeometry.around(lo, hi, cfg.voxel_size_m, cfg.trunc_m,
                                           margin_m=cfg.trunc_m + cfg.voxel_size_m)
        self.points_w = np.concatenate([to_world(*s) for s in self.scans])


def deskewed(points, T_a, T_b, alpha):
    """The scan in its start pose's frame: p' = exp(α ξ) p with ξ = log(T_a⁻¹ T_b) (mcl3d's
    deskew kernel; the fusion kernels interpolate the same two poses per point)."""
    from mcl3d.core.geometry import se3_inverse, se3_log
    from mcl3d.registration.preprocess import deskew

    if alpha is None:
        return np.asarray(points, np.float32)
    xi = se3_log(se3_inverse(T_a) @ T_b)
    return deskew(points, alpha, xi).astype(np.float32)


def to_world(points, T_a, T_b, alpha):
    p = deskewed(points, T_a, T_b, alpha).astype(np.float64)
    return p @ T_a[:3, :3].T + T_a[:3, 3]


def simulated_log(folder: Path, duration_s: float, world: str, sensor: str
                  ) -> tuple[Path, Path]:
    """A 10 Hz log (handheld, seed 1) and the world's mesh."""
    log, mesh = folder / f"{world}.mcap", folder / f"{world}_mesh.ply"
    cmd = [sys.executable, "-m", "mcl3d", "simulate", world, "-o", str(log), "--sensor",
           sensor, "--trajectory", "handheld", "--duration", f"{duration_s:g}", "--seed", "1",
           "--export-mesh", str(mesh), "--force"]
    subprocess.run(cmd, check=True, capture_output=True)
    return log, mesh


def ouster_trajectory(folder: Path) -> Path | None:
    """TUM poses of the Ouster capture's frames: the SDK's KITTI poses at the scans' stamps,
    and one more a frame later at the last step's velocity (the last sweep's end)."""
    from mcl3d.core.geometry import se3_inverse
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import Trajectory, write_tum

    pcap = OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap"
    if not pcap.exists():
        return None
    kitti = np.loadtxt(OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3_poses_kitti.txt")
    poses = np.tile(np.eye(4), (len(kitti), 1, 1))
    poses[:, :3, :] = kitti.reshape(-1, 3, 4)
    with LogReader(pcap) as reader:
        stamps = np.array([cloud.stamp_ns for cloud in reader.scans()], np.int64)
    if len(stamps) != len(poses):
        raise SystemExit(f"{pcap}: {len(stamps)} scans for {len(poses)} poses")
    poses = np.concatenate([poses, [poses[-1] @ se3_inverse(poses[-2]) @ poses[-1]]])
    stamps = np.append(stamps, 2 * stamps[-1] - stamps[-2])
    path = folder / "ouster_poses.tum"
    write_tum(path, Trajectory.from_ns(stamps, poses))
    return path


# ------------------------------------------------------------------------ methods
class Ours:
    """`build-map`'s per-scan work: normals (auto: range image on the device; knn: host),
    then `ScanFuser.fuse`."""

    def __init__(self, scans: LogScans, normals: str):
        from mcl3d.maps.build import ScanFuser, new_map

        self.cfg = scans.config.model_copy(update={"normals": normals})
        self.tsdf = new_map(scans.geometry, self.cfg)
        self.fuser = ScanFuser(self.tsdf, self.cfg)
        self.scans = scans

    def sync(self):
        import taichi as ti

        ti.sync()

    def reset(self):
        from mcl3d.maps.build import ScanFuser

        self.tsdf.clear()
        self.tsdf.as_sums = True
        self.fuser = ScanFuser(self.tsdf, self.cfg)
        self.sync()

    def scan(self, i) -> dict:
        points, T_a, T_b, alpha = self.scans.scans[i]
        out, normals = {}, None
        if self.cfg.normals != "none":
            pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
            normals, *out["normals"] = _timed(
                lambda: self.fuser.normals(pts, self.scans.rings[i]), self.sync)
        _, *out["fuse (deskew in kernel)"] = _timed(
            lambda: self.fuser.fuse(points, T_a, T_b, alpha, normals_l=normals), self.sync)
        return out

    def surface(self) -> np.ndarray:
        from mcl3d.maps.export import level_set_mesh

        if self.tsdf.overflowed:
            raise SystemExit(f"the map overflowed {CAPACITY_BLOCKS} blocks")
        self.tsdf.finalize()
        mesh = level_set_mesh(self.tsdf.geometry, self.tsdf.blocks())
        return mesh.vertex.positions.numpy().astype(np.float64)

    @property
    def blocks(self):
        return self.tsdf.n_blocks


class Open3D:
    """Open3D's tensor VoxelBlockGrid integration of each scan as 4 depth images."""

    def __init__(self, scans: LogScans, every_point: bool, columns: int, beams: int):
        import open3d.core as o3c

        self.scans, self.every_point = scans, every_point
        self.max_range = scans.config.max_range_m
        self.min_range = scans.config.min_range_m
        width = columns // 4
        f = 0.5 * width  # 90° per image
        el = np.concatenate([np.abs(_elevations(s[0])) for s in scans.scans[:1]])
        half = float(np.percentile(el, 99.5))
        fy = f * (2 * np.pi / columns) / (2 * half / beams)  # a row per beam
        height = 2 * int(np.ceil(fy * np.tan(half) / np.cos(np.pi / 4))) + 2
        self.size = (width, height)
        self.K = o3c.Tensor(np.array([[f, 0, width / 2], [0, fy, height / 2], [0, 0, 1]]),
                            o3c.float64)
        self.cams = _camera_poses()
        self.grid = None

    def reset(self):
        import open3d as o3d
        import open3d.core as o3c

        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1,), (1,)), voxel_size=VOXEL, block_resolution=8,
            block_count=CAPACITY_BLOCKS)

    def scan(self, i) -> dict:
        import open3d as o3d
        import open3d.core as o3c

        points, T_a, T_b, alpha = self.scans.scans[i]
        out = {}

        def deskew():
            p = deskewed(points, T_a, T_b, alpha)
            r2 = (p * p).sum(axis=1)
            return p[(r2 >= self.min_range ** 2) & (r2 <= self.max_range ** 2)]

        pts, *out["deskew (host)"] = _timed(deskew)

        def project():
            cloud = o3d.t.geometry.PointCloud(o3c.Tensor(pts))
            return [cloud.project_to_depth_image(
                *self.size, self.K, o3c.Tensor(np.linalg.inv(T_lc)), depth_scale=1.0,
                depth_max=self.max_range) for T_lc in self.cams]

        images, *out["depth images"] = _timed(project)

        def integrate():
            sector = None
            if self.every_point:
                pts_w = (pts @ T_a[:3, :3].T + T_a[:3, 3]).astype(np.float32)
                sector = np.round(np.arctan2(pts[:, 1], pts[:, 0]) / (np.pi / 2)) % 4
            for k, (image, T_lc) in enumerate(zip(images, self.cams, strict=True)):
                extrinsic = o3c.Tensor(np.linalg.inv(T_a @ T_lc))
                if sector is None:
                    blocks = self.grid.compute_unique_block_coordinates(
                        image, self.K, extrinsic, depth_scale=1.0, depth_max=self.max_range,
                        trunc_voxel_multiplier=4.0)
                else:
                    blocks = self.grid.compute_unique_block_coordinates(
                        o3d.t.geometry.PointCloud(o3c.Tensor(pts_w[sector == k])),
                        trunc_voxel_multiplier=4.0)
                self.grid.integrate(blocks, image, self.K, extrinsic, depth_scale=1.0,
                                    depth_max=self.max_range, trunc_voxel_multiplier=4.0)
            self.grid.hashmap().size()  # waits for the last integration

        _, *out["integrate (blocks + TSDF)"] = _timed(integrate)
        return out

    def surface(self) -> np.ndarray:
        mesh = self.grid.extract_triangle_mesh(weight_threshold=1e-6)
        return mesh.vertex.positions.numpy().astype(np.float64)

    @property
    def blocks(self):
        return self.grid.hashmap().size()


def _elevations(points):
    p = np.asarray(points, np.float64)
    return np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))


def _camera_poses():
    """T_lidar_cam of the 4 cameras: camera k looks along lidar yaw k·90° (z forward,
    x right, y down)."""
    out = []
    for k in range(4):
        yaw = k * np.pi / 2
        T = np.eye(4)
        T[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0],
                              [0, 0, 1]]) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
        out.append(T)
    return out


# ------------------------------------------------------------------- measurement
def run_log(scans: LogScans, methods: dict, repeats: int) -> dict:
    """{method: {stage: [(wall, cpu) per scan and pass]}}: every method builds its own map over
    the log, scans interleaved between methods; a warm-up on the first scans first."""
    times = {name: {} for name in methods}
    n = len(scans.scans)
    for rnd in range(repeats + 1):  # pass 0: warm-up (compilation) on two scans
        for method in methods.values():
            method.reset()
        for i in range(n if rnd else min(n, 2)):
            for name, method in methods.items():
                for stage, wc in method.scan(i).items():
                    if rnd:
                        times[name].setdefault(stage, []).append(wc)
    return times


def stage_rows(scans: LogScans, methods: dict, times: dict, repeats: int):
    """Per method, a row per stage (median ms per scan) and a total per scan: its own stages
    plus the shared decode and poses (and build-map's first pass for mcl3d)."""
    rows = []
    shared = {"decode (shared)": scans.shared["decode"] * repeats,
              "poses + point times (shared)": scans.shared["poses"] * repeats}
    totals = {}
    for name, method in methods.items():
        stages = dict(shared)
        if isinstance(method, Ours):
            if scans.decoded_once:  # build-map decodes each scan once, in pass 1
                del stages["decode (shared)"]
            stages["pass 1: decode + bounds"] = scans.pass1 * repeats
        stages.update(times[name])
        per_scan = np.sum([np.asarray(v) for v in stages.values()], axis=0)  # (scans, 2)
        totals[name] = per_scan
        for stage, v in stages.items():
            v = np.asarray(v)
            rows.append({"input": scans.name, "method": name, "stage": stage,
                         "wall ms": round(float(np.median(v[:, 0])), 1),
                         "cpu ms": round(float(np.median(v[:, 1])), 1)})
        rows.append({"input": scans.name, "method": name, "stage": "total per scan",
                     "wall ms": round(float(np.median(per_scan[:, 0])), 1),
                     "cpu ms": round(float(np.median(per_scan[:, 1])), 1)})
    return rows, totals


def ratio_rows(scans: LogScans, totals: dict) -> list[dict]:
    """Open3D's total over mcl3d's, per scan (same scan, same pass), median and range."""
    rows = []
    for ours in (k for k in totals if k.startswith("mcl3d")):
        for other in (k for k in totals if k.startswith("Open3D")):
            r = totals[other] / totals[ours]
            rows.append({"input": scans.name, "mcl3d": ours, "Open3D": other,
                         "wall: Open3D / mcl3d": f"{np.median(r[:, 0]):.2f} "
                                                 f"({r[:, 0].min():.2f}..{r[:, 0].max():.2f})",
                         "cpu: Open3D / mcl3d": f"{np.median(r[:, 1]):.2f}"})
    return rows


def quality_rows(scans: LogScans, methods: dict, mesh_path: Path | None) -> list[dict]:
    """Each finished map's surface (marching cubes) against the world mesh and the scans."""
    from scipy.spatial import cKDTree

    scene = None
    if mesh_path is not None:
        import open3d as o3d

        mesh = o3d.t.io.read_triangle_mesh(str(mesh_path))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(mesh)
    scan_tree = cKDTree(scans.points_w)
    rows = []
    for name, method in methods.items():
        surface = method.surface()
        row = {"input": scans.name, "method": name, "blocks": method.blocks,
               "surface vertices": len(surface)}
        row["to mesh: median / p90 (mm)"] = "no mesh (real scans)"
        if scene is not None:
            import open3d.core as o3c

            d = np.abs(scene.compute_distance(o3c.Tensor(surface.astype(np.float32))).numpy())
            row["to mesh: median / p90 (mm)"] = \
                f"{1e3 * np.median(d):.1f} / {1e3 * np.percentile(d, 90):.1f}"
        d_scan = scan_tree.query(surface, workers=-1)[0]
        row["to scans: median / p90 (mm)"] = \
            f"{1e3 * np.median(d_scan):.1f} / {1e3 * np.percentile(d_scan, 90):.1f}"
        near = cKDTree(surface).query(scans.points_w, distance_upper_bound=VOXEL,
                                      workers=-1)[0]
        row["scan points within 5 cm"] = f"{np.isfinite(near).mean():.1%}"
        rows.append(row)
    return rows


def fusion(scans: LogScans, repeats: int, columns: int, beams: int, mesh=None):
    methods = {"mcl3d point-to-plane, device normals (default)": Ours(scans, "auto"),
               "mcl3d point-to-plane, host KNN normals": Ours(scans, "knn"),
               "mcl3d projective (normals: none)": Ours(scans, "none")}
    if beams:  # Open3D integrates a spinning lidar's depth image: a Livox gives none
        methods.update({"Open3D (its block allocation)": Open3D(scans, False, columns, beams),
                        "Open3D (blocks from every point)": Open3D(scans, True, columns,
                                                                   beams)})
    times = run_log(scans, methods, repeats)
    stages, totals = stage_rows(scans, methods, times, repeats)
    quality = quality_rows(scans, methods, mesh)
    for method in methods.values():
        if isinstance(method, Ours):
            method.tsdf.destroy()  # the next input's maps need the memory
    return stages, ratio_rows(scans, totals), quality


# -------------------------------------------------------------------------- memory
def _memory():
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.tsdf import VOXELS_PER_BLOCK
    from mcl3d.sim.worlds import build_world

    world = build_world("office", seed=0)
    t0 = time.perf_counter()
    tsdf = build_from_mesh(world.static.vertices, world.static.triangles,
                           BuildConfig(capacity_blocks=200000))
    seconds = time.perf_counter() - t0
    data = tsdf.blocks()
    g = tsdf.geometry
    n, free = len(data.coords), len(data.free_coords)
    # while building: f32 distance, weight and free hits, i64 fixed-point sums (not on Vulkan)
    per = {"build_f32": VOXELS_PER_BLOCK * 28 + 16, "f32": VOXELS_PER_BLOCK * 8 + 16,
           "f16": VOXELS_PER_BLOCK * 4 + 16}
    coarse = g.n_cells * 4
    mib = 1 / 2**20
    extent = " x ".join(f"{v:g}" for v in (np.asarray(g.coarse_dims) * g.block_size_m).round(1))
    rows = [{"map": f"office from its mesh ({extent} m)", "storage": key,
             "bytes per block": b, "blocks": n, "free blocks": free,
             "MiB": round((coarse + n * b) * mib, 1)} for key, b in per.items()]
    rows.append({"map": "dense grid of the same extent", "storage": "f32 distance + weight",
                 "bytes per block": VOXELS_PER_BLOCK * 8, "blocks": g.n_cells, "free blocks": 0,
                 "MiB": round(g.n_cells * VOXELS_PER_BLOCK * 8 * mib, 1)})
    return rows, round(seconds, 1)


# ---------------------------------------------------------------------------- main
def print_table(caption, rows):
    from rich.console import Console
    from rich.table import Table

    table = Table(title=caption)
    for col in rows[0]:
        table.add_column(col, justify="right" if "ms" in col or col in (
            "blocks", "MiB", "bytes per block") else "left")
    for r in rows:
        table.add_row(*(str(v) for v in r.values()))
    Console(width=220).print(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--quick", action="store_true",
                        help="a 0.5 s simulated log only, one pass, no memory")
    parser.add_argument("--repeats", type=int, default=3, help="passes over each log")
    parser.add_argument("--duration", type=float, default=5.0,
                        help="seconds of the simulated 10 Hz log")
    parser.add_argument("--world", default="office", help="simulated world (mcl3d simulate)")
    parser.add_argument("--sensor", default="os1-64", help="simulated lidar (mcl3d simulate)")
    parser.add_argument("--skip-memory", action="store_true", help="fusion timings only")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON path (default bench/results/bench_tsdf_fusion.json)")
    args = parser.parse_args()
    if args.quick:
        args.repeats, args.duration, args.skip_memory = 1, 0.5, True
    # Open3D's OpenMP threads sleep while they wait instead of spinning (spinning counts as
    # cpu time and takes a shared machine's cores); must precede its import
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from results_io import Run

    run = Run("bench_tsdf_fusion", baselines=("open3d",))
    from mcl3d.core import runtime

    info = runtime.init(args.backend)
    tables, notes, stage_all, ratio_all, quality_all = {}, [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        log, mesh = simulated_log(folder, args.duration, args.world, args.sensor)
        columns, beams = {"vlp16": (1800, 16), "mid360": (0, 0)}.get(args.sensor, (1024, 64))
        inputs = [(LogScans(f"simulated {args.world}, {args.sensor}, {args.duration:g} s at "
                            "10 Hz", log), columns, beams, mesh)]
        traj = None if args.quick else ouster_trajectory(folder)
        if traj is not None:
            inputs.append((LogScans("Ouster OS1-128 capture (real, 3 scans)",
                                    OUSTER / "OS-1-128_v2.3.0_1024x10_lb_n3.pcap", traj),
                           1024, 128, None))
        else:
            notes.append("--quick: no real scans measured." if args.quick else
                         f"{OUSTER} is absent: no real scans measured.")
        for scans, columns, beams, mesh_path in inputs:
            print(f"{scans.name}: {len(scans.scans)} scans, "
                  f"{np.mean([len(s[0]) for s in scans.scans]):.0f} points each", flush=True)
            stages, ratios, quality = fusion(scans, args.repeats, columns, beams, mesh_path)
            stage_all += stages
            ratio_all += ratios
            quality_all += quality
    device = f"{info.backend}: {info.device}"
    tables[f"TSDF fusion end to end, ms per scan ({device}; medians)"] = stage_all
    tables["TSDF fusion end to end: Open3D's total over mcl3d's per scan (>1: mcl3d faster)"] \
        = ratio_all
    tables["TSDF fusion: the finished maps"] = quality_all
    memory_s = None
    if not args.skip_memory:
        rows, memory_s = _memory()
        tables["Memory of the office map built from its mesh (5 cm)"] = rows
    for caption, rows in tables.items():
        print_table(caption, rows)
    notes += [
        f"{os.cpu_count()} cpus, load average {run.load_before:.1f} at the start and "
        f"{os.getloadavg()[0]:.1f} at the end; {args.repeats} passes over each log after a "
        "warm-up; Taichi and Open3D on every core (OMP_WAIT_POLICY=PASSIVE).",
        "mcl3d deskews inside its fusion kernels (each point at its time between the scan's "
        "start and end poses); Open3D takes one pose per depth image, so its scan is deskewed "
        "on the host first (mcl3d's kernel, counted in Open3D's total).",
        "The normals stage: by default from the scan's range image on the device (ring x "
        "azimuth, PCA over the neighbouring pixels; a point within half a voxel of the "
        "middle one of its three columns takes that one's normal); before: Open3D's KNN "
        "normal estimation (k = 12) on the host; both face the sensor. Open3D's projective "
        "integration needs none.",
        "mcl3d's fusion bundles consecutive rays of a scan line that end in one voxel (one "
        "column band each, normals within 18 degrees): each bundle fuses once at its mean "
        "point with its count as weight and carves once (voxblox's merged integration).",
        "pass 1 is build-map's first read of the log (decoding every scan, the map's bounds), "
        "per scan (a mean: the median decode hides the MCAP chunks' decompression); it keeps "
        "the decoded scans for the fusion pass while they fit in scan_cache_mb, so then "
        "mcl3d's total has no second decode; Open3D's hash map needs no bounds.",
    ]
    path = run.write({"tables": tables, "notes": notes, "backend": info.backend,
                      "device": info.device, "memory_build_from_mesh_s": memory_s,
                      "settings": {"repeats": args.repeats, "duration_s": args.duration,
                                   "voxel_m": VOXEL, "quick": args.quick}}, args.out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
