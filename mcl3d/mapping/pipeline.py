"""The `mcl3d build-map` pipeline: source -> TSDF -> map file (+ optional mesh / points).

Sources: a log (MCAP / bag) with ground truth or a trajectory file, a point-cloud map
(PCD/PLY/KITTI .bin), a mesh (PLY/OBJ/STL/OFF/GLB), or a tsdf_localization HDF5 map. Every
output is checked before the work starts and written atomically at the end.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, MapError, PointCloudError, RunInterrupted, TrajectoryError
from mcl3d.core.outputs import check_writable

LOG_SUFFIXES = (".mcap", ".bag", ".db3")
MESH_ONLY_SUFFIXES = (".obj", ".stl", ".off", ".gltf", ".glb")
POINT_ONLY_SUFFIXES = (".pcd", ".bin")
HDF5_SUFFIXES = (".h5", ".hdf5")


@dataclass
class BuildMapResult:
    source: Path
    output: Path
    source_kind: str
    header: dict
    stats: dict
    seconds: float
    n_scans: int = 0
    n_points: int = 0
    exports: dict = field(default_factory=dict)

    @property
    def scans_per_s(self) -> float:
        return self.n_scans / self.seconds if self.seconds > 0 else 0.0


def _ply_has_faces(path: Path) -> bool:
    with open(path, "rb") as f:
        head = f.read(4096)
    end = head.find(b"end_header")
    text = head[:end if end >= 0 else len(head)].decode("ascii", "replace")
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[:2] == ["element", "face"]:
            return parts[2] != "0"
    return False


def source_kind(path: Path) -> str:
    """log | points | mesh | hdf5, from the file type (PLY: mesh when it has faces)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    suffix = path.suffix.lower()
    if path.is_dir() or suffix in LOG_SUFFIXES:
        return "log"
    if suffix in HDF5_SUFFIXES:
        return "hdf5"
    if suffix in MESH_ONLY_SUFFIXES:
        return "mesh"
    if suffix in POINT_ONLY_SUFFIXES:
        return "points"
    if suffix == ".ply":
        return "mesh" if _ply_has_faces(path) else "points"
    raise InputError(f"{path}: cannot tell what to build from; give a log "
                     f"({', '.join(LOG_SUFFIXES)}), a point cloud (.pcd/.ply/.bin), a mesh "
                     f"(.ply/.obj/.stl/.off/.glb) or a HATSDF map (.h5)")


class BuildMapPipeline:
    """One map build; `run()` reads as the list of steps."""

    def __init__(self, source: Path, output: Path, config, *, trajectory: Path | None = None,
                 f16: bool = False, force: bool = False, export_mesh: Path | None = None,
                 export_points: Path | None = None, points_topic: str | None = None,
                 gt_topic: str | None = None, progress: bool = True):
        self.source = Path(source)
        self.output = Path(output)
        self.config = config
        self.trajectory_path = Path(trajectory) if trajectory else None
        self.f16 = f16
        self.force = force
        self.export_mesh = Path(export_mesh) if export_mesh else None
        self.export_points = Path(export_points) if export_points else None
        self.points_topic = points_topic
        self.gt_topic = gt_topic
        self.progress = progress
        self.n_scans = 0
        self.n_points = 0

    def run(self) -> BuildMapResult:
        self._check_outputs()
        kind = source_kind(self.source)
        start = time.perf_counter()
        try:
            tsdf, source_info = self._build(kind)
        except KeyboardInterrupt:
            raise RunInterrupted("interrupted while building the map; nothing was "
                                 "written") from None
        seconds = time.perf_counter() - start
        return self._write(tsdf, kind, source_info, seconds)

    # ------------------------------------------------------------------ steps
    def _check_outputs(self) -> None:
        outputs = [p for p in (self.output, self.export_mesh, self.export_points) if p]
        if len({p.resolve() for p in outputs}) != len(outputs):
            raise InputError("the map, mesh and points outputs must be different files")
        from mcl3d.maps.export import MESH_SUFFIXES, POINT_SUFFIXES

        if self.export_mesh and self.export_mesh.suffix.lower() not in MESH_SUFFIXES:
            raise InputError(f"{self.export_mesh}: unknown mesh type; use one of "
                             f"{', '.join(MESH_SUFFIXES)}")
        if self.export_points and self.export_points.suffix.lower() not in POINT_SUFFIXES:
            raise InputError(f"{self.export_points}: unknown point-cloud type; use one of "
                             f"{', '.join(POINT_SUFFIXES)}")
        for path in outputs:
            check_writable(path, self.force)

    def _build(self, kind: str):
        from mcl3d.maps import build

        if kind == "log":
            return self._build_from_log()
        if kind == "points":
            from mcl3d.io.logs.cloud_files import read_cloud_file

            cloud = read_cloud_file(self.source)
            if len(cloud.points) == 0:
                raise PointCloudError(f"{self.source}: the point cloud is empty")
            viewpoints = None
            if self.trajectory_path:
                viewpoints = self._trajectory().positions()
            self.n_points = len(cloud.points)
            tsdf = build.build_from_points(cloud.points, self.config, viewpoints=viewpoints)
            return tsdf, {"kind": "points", "path": str(self.source),
                          "points": len(cloud.points),
                          "normals_oriented_towards": "trajectory" if viewpoints is not None
                          else "consistent tangent planes, floors up"}
        if kind == "mesh":
            vertices, triangles = _read_mesh(self.source)
            tsdf = build.build_from_mesh(vertices, triangles, self.config)
            return tsdf, {"kind": "mesh", "path": str(self.source),
                          "triangles": len(triangles), "sign": self.config.mesh_sign}
        from mcl3d.maps.hatsdf import import_hatsdf

        tsdf = import_hatsdf(self.source, frame_id=self.config.frame_id)
        return tsdf, {"kind": "hdf5 (tsdf_localization/HATSDF)", "path": str(self.source)}

    def _trajectory(self):
        from mcl3d.io.trajectory import read_trajectory

        return read_trajectory(self.trajectory_path)

    def _poses(self, reader):
        from mcl3d.io.trajectory import Trajectory

        if self.trajectory_path:
            return self._trajectory(), str(self.trajectory_path)
        stamps_ns, poses = reader.ground_truth()
        order = np.argsort(stamps_ns, kind="stable")
        stamps_ns, poses = stamps_ns[order], poses[order]
        keep = np.concatenate([[True], np.diff(stamps_ns) > 0])
        return (Trajectory(stamps_ns[keep] * 1e-9, poses[keep]),
                f"{self.source} topic {reader.topics.gt}")

    def _build_from_log(self):
        from mcl3d.io.logs.reader import LogReader
        from mcl3d.maps import build

        cfg = self.config
        with LogReader(self.source, points_topic=self.points_topic,
                       gt_topic=self.gt_topic) as reader:
            traj, traj_source = self._poses(reader)
            lo, hi, n_scans, n_empty = self._scan_bounds(reader, traj)
            lo = np.minimum(lo, traj.positions().min(axis=0))
            hi = np.maximum(hi, traj.positions().max(axis=0))
            geometry = build.MapGeometry.around(lo, hi, cfg.voxel_size_m, cfg.trunc_m,
                                                margin_m=cfg.trunc_m + cfg.voxel_size_m)
            needed = 0
            while True:
                tsdf = build.new_map(geometry, cfg, needed)
                fuser = build.ScanFuser(tsdf, cfg)
                self._fuse_all(reader, traj, fuser, n_scans)
                if not tsdf.overflowed:
                    break
                needed = build.grown_capacity(tsdf, cfg)
                tsdf.destroy()
        tsdf.finalize()
        self.n_scans, self.n_points = fuser.n_scans, fuser.n_points
        return tsdf, {"kind": "log", "path": str(self.source), "points_topic":
                      reader.topics.points, "poses": traj_source, "scans": fuser.n_scans,
                      "empty_scans_skipped": n_empty, "deskewed": self._deskewed}

    def _scan_pose(self, traj, cloud):
        """(T_start, T_end, alpha) for a scan: its per-point times deskew it when present."""
        stamp_s = cloud.stamp_ns * 1e-9
        t0, t1 = traj.stamps_s[0], traj.stamps_s[-1]
        if not (t0 <= stamp_s <= t1):
            raise TrajectoryError(
                f"scan at {stamp_s:.9f} s is outside the trajectory ({t0:.9f}..{t1:.9f} s); "
                f"give a trajectory that covers the log (--trajectory) or trim the log")
        times = cloud.times_s
        if times is None or len(times) == 0 or not np.isfinite(times).all():
            T = traj.interpolate_poses([stamp_s])[0]
            return T, T, None
        a, b = float(times.min()), float(times.max())
        # the ends of a scan may lie just past the trajectory: deskew up to its ends
        qa, qb = np.clip(stamp_s + np.array([a, b]), t0, t1)
        T_a, T_b = traj.interpolate_poses([qa, qb])
        self._deskewed = True
        if b - a <= 0:
            return T_a, T_a, None
        return T_a, T_b, ((times - a) / (b - a)).astype(np.float32)

    def _scan_bounds(self, reader, traj):
        """Pass 1: check every scan has a pose and find the map's bounds."""
        cfg = self.config
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        n_scans = n_empty = 0
        self._deskewed = False
        for cloud in reader.scans():
            pts = np.asarray(cloud.points, dtype=np.float32).reshape(-1, 3)
            T, _, _ = self._scan_pose(traj, cloud)
            r2 = (pts * pts).sum(axis=1)  # f32 and squared: this pass reads every scan
            pts = pts[(r2 >= cfg.min_range_m**2) & (r2 <= cfg.max_range_m**2)]
            n_scans += 1
            if len(pts) == 0:
                n_empty += 1
                continue
            world = pts @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
            lo, hi = np.minimum(lo, world.min(axis=0)), np.maximum(hi, world.max(axis=0))
        if n_scans == n_empty:
            raise PointCloudError(
                f"{self.source}: none of its {n_scans} scans has points between "
                f"{cfg.min_range_m} and {cfg.max_range_m} m; nothing to build a map from")
        return lo, hi, n_scans, n_empty

    def _fuse_all(self, reader, traj, fuser, n_scans: int) -> None:
        from mcl3d.console import track

        scans = reader.scans()
        if self.progress:
            scans = track(scans, n_scans, "fusing scans", unit="scans")
        for cloud in scans:
            if len(cloud.points) == 0:
                continue
            T_a, T_b, alpha = self._scan_pose(traj, cloud)
            fuser.fuse(cloud.points, T_a, T_b, alpha)

    def _write(self, tsdf, kind: str, source_info: dict, seconds: float) -> BuildMapResult:
        from mcl3d.maps import export, io
        from mcl3d.maps.tsdf import VOXELS_PER_BLOCK, block_stats

        if tsdf.n_blocks == 0:
            raise MapError(f"{self.source}: the map has no surface blocks; nothing to write")
        build_info = {"config": self.config.model_dump(), "seconds": round(seconds, 3),
                      "f16": self.f16}
        header = io.save_map(self.output, tsdf, source=source_info, build=build_info,
                             f16=self.f16)
        data = tsdf.blocks()
        # memory as loaded for localization (read-only pool, f32 or f16)
        stats = block_stats(tsdf.geometry, data,
                            VOXELS_PER_BLOCK * (4 if self.f16 else 8) + 16)
        stats["file_bytes"] = self.output.stat().st_size
        exports = {}
        if self.export_mesh:
            exports["mesh_triangles"] = export.write_mesh(self.export_mesh, tsdf.geometry, data)
        if self.export_points:
            exports["surface_points"] = export.write_points(self.export_points, tsdf.geometry,
                                                            data)
        return BuildMapResult(self.source, self.output, kind, header, stats, seconds,
                              self.n_scans, self.n_points, exports)


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices)
    triangles = np.asarray(mesh.triangles)
    if len(triangles) == 0:
        raise PointCloudError(f"{path}: no triangles could be read (empty or unreadable mesh)")
    return vertices, triangles


def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def map_rows(header: dict, stats: dict) -> list[tuple[str, str]]:
    """Summary-table rows describing a map: geometry, blocks, voxels, memory."""
    lo, hi = stats["extent_lo_m"], stats["extent_hi_m"]
    size = [round(h - v, 2) for v, h in zip(lo, hi, strict=True)]
    return [
        ("voxel / truncation", f"{header['voxel_size_m']} m / {header['truncation_m']} m"),
        ("extent", f"{lo} .. {hi} m ({size[0]} x {size[1]} x {size[2]} m)"),
        ("coarse grid", " x ".join(str(d) for d in header["coarse_dims"]) + " blocks of 8³"),
        ("blocks", f"{stats['blocks']} allocated, {stats['free_blocks']} free, "
                   f"{stats['unknown_cells']} unknown"),
        ("voxels", f"{stats['surface_voxels']} on the surface, {stats['observed_voxels']} "
                   f"observed, {stats['free_voxels']} free"),
        ("memory (loaded)", f"{format_bytes(stats['pool_bytes'] + stats['coarse_bytes'])} "
                            f"({stats['bytes_per_block']} B/block) vs dense grid "
                            f"{format_bytes(stats['dense_grid_bytes'])}"),
        *([("file", format_bytes(stats["file_bytes"]))] if "file_bytes" in stats else []),
    ]


def summary_rows(result: BuildMapResult, backend: str) -> list[tuple[str, str]]:
    """Rows of the end-of-build summary table."""
    rows = [("source", f"{result.source} ({result.source_kind})"),
            *map_rows(result.header, result.stats),
            ("time", f"{result.seconds:.2f} s on {backend}")]
    if result.n_scans:
        rows.append(("scans", f"{result.n_scans} ({result.scans_per_s:.1f} scans/s, "
                              f"{result.n_points} points)"))
    rows.append(("written", str(result.output)))
    for key, value in result.exports.items():
        rows.append((key.replace("_", " "), str(value)))
    return rows
