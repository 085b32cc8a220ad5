"""The `mcl3d build-map` pipeline: source -> TSDF -> map file (+ optional mesh / points).

Sources: a log (MCAP / bag) with ground truth or a trajectory file, a point-cloud map
(PCD/PLY/KITTI .bin), a mesh (PLY/OBJ/STL/OFF/GLB), or a tsdf_localization HDF5 map. Every
output is checked before the work starts and written atomically at the end. The contract:
`run(request, on_progress=None) -> BuildMapResult`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, MapError, PointCloudError, RunInterrupted, TrajectoryError
from mcl3d.core.outputs import check_writable
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.io.logs.cloud_files import read_cloud_file
from mcl3d.io.logs.faults import LogFaults, format_stamp
from mcl3d.io.logs.plausibility import check_scans
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory, read_trajectory
from mcl3d.maps import build, export, map_file, point_build
from mcl3d.maps.hatsdf import import_hatsdf
from mcl3d.maps.tsdf import (
    MapGeometry,
    MapStats,
    TsdfMap,
    loaded_bytes_per_block,
    map_stats,
)

LOG_SUFFIXES = (".mcap", ".bag", ".db3", ".pcap")
MESH_ONLY_SUFFIXES = (".obj", ".stl", ".off", ".gltf", ".glb")
POINT_ONLY_SUFFIXES = (".pcd", ".bin")
HDF5_SUFFIXES = (".h5", ".hdf5")
FUSE_STAGE = "fusing scans"  # the progress stage of a log's scans
FUSED_FIELDS = ("ring",)  # what fusion reads of a scan besides its points and times
STAMP_TEXT_NS = 1_000  # a stamp written through float64 seconds (older files, other tools)
# is only good to ~0.24 us at epoch times: a scan this close past an end counts as at the end


@dataclass(frozen=True)
class BuildMapRequest:
    """One map build: the source, the map file to write, and how to build it."""

    source: Path  # a log, a point-cloud map, a mesh or a HATSDF map (see source_kind)
    output: Path  # the map file (.tsdf)
    config: build.BuildConfig = field(default_factory=build.BuildConfig)
    trajectory: Path | None = None  # poses T_map_lidar of a log's scans (default: its ground
    # truth); for a point cloud, viewpoints that orient its normals
    f16: bool = False  # store distances and weights in half precision (read-only maps)
    force: bool = False  # overwrite existing outputs
    export_mesh: Path | None = None  # also write the zero level set as a mesh
    export_points: Path | None = None  # also write the surface voxels as points
    points_topic: str | None = None  # a log's point-cloud topic (default: detected)
    gt_topic: str | None = None  # a log's ground-truth topic (default: detected)


@dataclass(frozen=True)
class MapExports:
    """What the optional exports hold (None: not asked for)."""

    mesh_triangles: int | None = None
    surface_points: int | None = None


@dataclass(frozen=True)
class BuildMapResult:
    source: Path
    output: Path
    source_kind: str  # log | points | mesh | hdf5
    header: dict  # the map file's header, as written
    geometry: MapGeometry
    stats: MapStats  # memory as loaded for localization (read-only pool, f32 or f16)
    seconds: float  # building, without writing
    n_scans: int = 0  # scans fused (log sources)
    n_points: int = 0  # points fused
    exports: MapExports = MapExports()
    faults: LogFaults = field(default_factory=LogFaults)  # a log's messages dropped for faults

    @property
    def scans_per_s(self) -> float:
        return self.n_scans / self.seconds if self.seconds > 0 else 0.0


@dataclass
class _Built:
    """A finished map before it is written, and where it came from."""

    tsdf: TsdfMap
    source_info: dict  # the map file header's "source" entry
    n_scans: int = 0
    n_points: int = 0
    faults: LogFaults = field(default_factory=LogFaults)


def run(request: BuildMapRequest, on_progress: ProgressCallback | None = None
        ) -> BuildMapResult:
    """Build the map and write it (and its exports); nothing is written when it fails or is
    interrupted. `on_progress` hears of every scan of a log source."""
    _check_outputs(request)
    kind = source_kind(request.source)
    start = time.perf_counter()
    try:
        built = _build(request, kind, on_progress)
    except KeyboardInterrupt:
        raise RunInterrupted("interrupted while building the map; nothing was "
                             "written") from None
    seconds = time.perf_counter() - start
    return _write(request, built, kind, seconds)


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


def _check_outputs(req: BuildMapRequest) -> None:
    outputs = [p for p in (req.output, req.export_mesh, req.export_points) if p]
    if len({p.resolve() for p in outputs}) != len(outputs):
        raise InputError("the map, mesh and points outputs must be different files")
    if req.export_mesh and req.export_mesh.suffix.lower() not in export.MESH_SUFFIXES:
        raise InputError(f"{req.export_mesh}: unknown mesh type; use one of "
                         f"{', '.join(export.MESH_SUFFIXES)}")
    if req.export_points and req.export_points.suffix.lower() not in export.POINT_SUFFIXES:
        raise InputError(f"{req.export_points}: unknown point-cloud type; use one of "
                         f"{', '.join(export.POINT_SUFFIXES)}")
    for path in outputs:
        check_writable(path, req.force)


# ------------------------------------------------------------------------ sources
def _build(req: BuildMapRequest, kind: str, on_progress: ProgressCallback | None) -> _Built:
    if kind == "log":
        return _build_from_log(req, on_progress)
    if kind == "points":
        return _build_from_points(req, on_progress)
    if kind == "mesh":
        vertices, triangles = _read_mesh(req.source)
        tsdf = build.build_from_mesh(vertices, triangles, req.config)
        return _Built(tsdf, {"kind": "mesh", "path": str(req.source),
                             "triangles": len(triangles), "sign": req.config.mesh_sign})
    tsdf = import_hatsdf(req.source, frame_id=req.config.frame_id)
    return _Built(tsdf, {"kind": "hdf5 (tsdf_localization/HATSDF)", "path": str(req.source)})


def _build_from_points(req: BuildMapRequest, on_progress: ProgressCallback | None) -> _Built:
    cloud = read_cloud_file(req.source)
    if len(cloud.points) == 0:
        raise PointCloudError(f"{req.source}: the point cloud is empty")
    viewpoints = None
    if req.trajectory:
        viewpoints = read_trajectory(req.trajectory).positions()
    tsdf = point_build.build_from_points(cloud.points, req.config, viewpoints=viewpoints,
                                         on_progress=on_progress)
    return _Built(tsdf, {"kind": "points", "path": str(req.source),
                         "points": len(cloud.points),
                         "normals_oriented_towards": "trajectory" if viewpoints is not None
                         else "the map itself (consistent tangent planes)"},
                  n_points=len(cloud.points))


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d  # here: 0.5 s of import that maps from logs do not need

    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(mesh.vertices)
    triangles = np.asarray(mesh.triangles)
    if len(triangles) == 0:
        raise PointCloudError(f"{path}: no triangles could be read (empty or unreadable mesh)")
    return vertices, triangles


# --------------------------------------------------------------------------- logs
@dataclass
class _LogScans:
    """What the first pass over a log's scans found."""

    lo_m: np.ndarray  # bounds of the in-range points in the map frame
    hi_m: np.ndarray
    n_scans: int
    n_empty: int  # scans without a point in range
    deskewed: bool  # some scans have per-point times
    cached: list | None  # every scan as pass 1 decoded it (what fusion reads), None when
    # they did not fit in BuildConfig.scan_cache_mb: pass 2 then decodes the log again


def _build_from_log(req: BuildMapRequest, on_progress: ProgressCallback | None) -> _Built:
    """Two passes over the scans: the map's bounds, then fusion; a pool that overflows is
    grown and the fusion pass run again."""
    cfg = req.config
    with LogReader(req.source, points_topic=req.points_topic, gt_topic=req.gt_topic) as reader:
        check_scans(reader, req.source, needs_3d=False)
        traj, traj_source, scans = _poses_and_scans(req, reader)
        lo = np.minimum(scans.lo_m, traj.positions().min(axis=0))
        hi = np.maximum(scans.hi_m, traj.positions().max(axis=0))
        geometry = MapGeometry.around(lo, hi, cfg.voxel_size_m, cfg.trunc_m,
                                      margin_m=cfg.trunc_m + cfg.voxel_size_m)
        needed = needed_tiles = 0
        while True:
            tsdf = build.new_map(geometry, cfg, needed, needed_tiles)
            fuser = build.ScanFuser(tsdf, cfg)
            _fuse_all(scans.cached if scans.cached is not None else reader.scans(), traj,
                      fuser, scans.n_scans, on_progress)
            if not tsdf.overflowed:
                break
            needed, needed_tiles = build.grown_capacity(tsdf, cfg), build.grown_tiles(tsdf)
            tsdf.destroy()
    tsdf.finalize()
    source = {"kind": "log", "path": str(req.source), "points_topic": reader.topics.points,
              "poses": traj_source, "scans": fuser.n_scans,
              "empty_scans_skipped": scans.n_empty, "deskewed": scans.deskewed}
    if reader.faults.found():
        source["faults"] = reader.faults.as_dict()
    return _Built(tsdf, source, fuser.n_scans, fuser.n_points, reader.faults)


def _poses_and_scans(req: BuildMapRequest, reader: LogReader
                     ) -> tuple[Trajectory, str, _LogScans]:
    """The scans' poses, where they come from, and pass 1 over the scans. With the log's
    ground truth as poses and scans that fit the cache, one read of the log gives both
    (every chunk holding ground truth holds scans too: reading it alone decompressed the
    whole log once more, 1.4 s of a 20 s OS1-64 build); else the poses first, then pass 1."""
    if not req.trajectory and _fits_one_read(req, reader):
        stamps, poses, clouds = [], [], []
        for kind, msg in reader.messages(("points", "gt")):
            if kind == "gt":
                stamps.append(msg.stamp_ns)
                poses.append(msg.T)
            else:
                clouds.append(_fused_fields(msg))  # as the cache keeps them
        if stamps:
            traj, source = _truth(req, reader, np.asarray(stamps, np.int64), np.stack(poses))
            return traj, source, _scan_bounds(req, reader, traj, clouds)
    traj, source = _poses(req, reader)
    return traj, source, _scan_bounds(req, reader, traj)


def _fits_one_read(req: BuildMapRequest, reader: LogReader) -> bool:
    """Whether the log's summary says it has ground truth and the scans' decoded size (their
    count times the first one's size, decoded by a reader of its own: its faults are not
    this run's) fits `scan_cache_mb`."""
    info = {kind: reader.all_topics.get(reader.topics.get(kind)) for kind in ("points", "gt")}
    if any(i is None or not i.count for i in info.values()):
        return False
    with LogReader(req.source, points_topic=reader.topics.points,
                   gt_topic=reader.topics.gt) as probe:
        scans = probe.scans()
        first = next(scans, None)
        scans.close()
    return first is not None and (
        info["points"].count * _cloud_bytes(_fused_fields(first))
        <= req.config.scan_cache_mb * 2**20)


def _poses(req: BuildMapRequest, reader: LogReader) -> tuple[Trajectory, str]:
    """The scans' poses and where they come from: the trajectory file, else the log's
    ground truth (sorted, repeated stamps dropped)."""
    if req.trajectory:
        return read_trajectory(req.trajectory), str(req.trajectory)
    return _truth(req, reader, *reader.ground_truth())


def _truth(req: BuildMapRequest, reader: LogReader, stamps_ns: np.ndarray, poses: np.ndarray
           ) -> tuple[Trajectory, str]:
    """The log's ground truth as the scans' poses (sorted, repeated stamps dropped)."""
    order = np.argsort(stamps_ns, kind="stable")
    stamps_ns, poses = stamps_ns[order], poses[order]
    keep = np.concatenate([[True], np.diff(stamps_ns) > 0])
    return (Trajectory.from_ns(stamps_ns[keep], poses[keep]),
            f"{req.source} topic {reader.topics.gt}")


def _point_times(cloud) -> np.ndarray | None:
    """The scan's per-point times (s from its stamp), None when it has no usable ones."""
    times = cloud.times_s
    if times is None or len(times) == 0 or not np.isfinite(times).all():
        return None
    return times


def _scan_pose(traj: Trajectory, cloud):
    """(T_start, T_end, alpha) for a scan: its per-point times deskew it when present. The
    scan is inside the trajectory by its integer-ns stamp; its float seconds may round past an
    end that has the same stamp, so they are clipped to the ends."""
    first_ns, last_ns = traj.range_ns()
    if not first_ns - STAMP_TEXT_NS <= cloud.stamp_ns <= last_ns + STAMP_TEXT_NS:
        raise TrajectoryError(
            f"scan at {format_stamp(cloud.stamp_ns)} s is outside the trajectory "
            f"({format_stamp(first_ns)}..{format_stamp(last_ns)} s); give a trajectory that "
            f"covers the log or trim the log", setting="trajectory")
    t0, t1 = traj.stamps_s[0], traj.stamps_s[-1]
    stamp_s = min(max(cloud.stamp_ns * 1e-9, t0), t1)
    times = _point_times(cloud)
    if times is None:
        T = traj.interpolate_poses([stamp_s])[0]
        return T, T, None
    a, b = float(times.min()), float(times.max())
    # the ends of a scan may lie just past the trajectory: deskew up to its ends
    qa, qb = np.clip(stamp_s + np.array([a, b]), t0, t1)
    T_a, T_b = traj.interpolate_poses([qa, qb])
    if b - a <= 0:
        return T_a, T_a, None
    return T_a, T_b, ((times - a) / (b - a)).astype(np.float32)


def _scan_bounds(req: BuildMapRequest, reader: LogReader, traj: Trajectory,
                 clouds: list | None = None) -> _LogScans:
    """Pass 1: check every scan has a pose and find the map's bounds; keep the decoded scans
    for pass 2 while they fit in the cache. `clouds`: the scans when already read."""
    cfg = req.config
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    n_scans = n_empty = 0
    deskewed = False
    cached, cache_left = [], cfg.scan_cache_mb * 2**20
    for cloud in reader.scans() if clouds is None else clouds:
        if cached is not None:
            cloud = _fused_fields(cloud)
            cache_left -= _cloud_bytes(cloud)
            if cache_left >= 0:
                cached.append(cloud)
            else:
                cached = None
        T, _, _ = _scan_pose(traj, cloud)
        deskewed = deskewed or _point_times(cloud) is not None
        n_scans += 1
        bounds = world_bounds(cloud.points, T, cfg.min_range_m, cfg.max_range_m)
        if bounds is None:
            n_empty += 1
            continue
        lo, hi = np.minimum(lo, bounds[0]), np.maximum(hi, bounds[1])
    if n_scans == n_empty:
        n_scans += reader.faults.count("scan_empty")
        raise PointCloudError(
            f"{req.source}: none of its {n_scans} scans has points between "
            f"{cfg.min_range_m} and {cfg.max_range_m} m; nothing to build a map from")
    return _LogScans(lo, hi, n_scans, n_empty, deskewed, cached)


def world_bounds(points: np.ndarray, T_map_lidar: np.ndarray, min_range_m: float,
                 max_range_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) in the map frame of a scan's points within range, None when there are none.

    Column by column in f32: this pass reads every scan, and on an (n, 3) array a matrix
    product and axis-0 reductions take ~10x longer (11 against 1 ms for 65k points)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    r2 = x * x + y * y + z * z
    ok = (r2 >= np.float32(min_range_m**2)) & (r2 <= np.float32(max_range_m**2))
    if not ok.any():
        return None
    R, t = T_map_lidar[:3, :3].astype(np.float32), T_map_lidar[:3, 3].astype(np.float32)
    lo, hi = np.empty(3), np.empty(3)
    for a in range(3):
        w = R[a, 0] * x + R[a, 1] * y + R[a, 2] * z + t[a]
        lo[a] = w.min(where=ok, initial=np.inf)
        hi[a] = w.max(where=ok, initial=-np.inf)
    return lo, hi


def _fused_fields(cloud):
    """The cloud with only the fields fusion reads (FUSED_FIELDS), for the scan cache."""
    return dataclasses.replace(cloud, fields={k: v for k, v in cloud.fields.items()
                                              if k in FUSED_FIELDS})


def _cloud_bytes(cloud) -> int:
    return cloud.points.nbytes + sum(v.nbytes for v in cloud.fields.values()) + (
        cloud.times_s.nbytes if cloud.times_s is not None else 0)


def _fuse_all(clouds, traj: Trajectory, fuser: build.ScanFuser, n_scans: int,
              on_progress: ProgressCallback | None) -> None:
    """Pass 2: fuse every scan, reporting each (empty ones included)."""
    for done, cloud in enumerate(clouds, start=1):
        if len(cloud.points):
            T_a, T_b, alpha = _scan_pose(traj, cloud)
            fuser.fuse(cloud.points, T_a, T_b, alpha, rings=cloud.fields.get("ring"))
        report(on_progress, Progress(FUSE_STAGE, done, n_scans))


# ------------------------------------------------------------------------- output
def _write(req: BuildMapRequest, built: _Built, kind: str, seconds: float) -> BuildMapResult:
    tsdf = built.tsdf
    if tsdf.n_blocks == 0:
        raise MapError(f"{req.source}: the map has no surface blocks; nothing to write")
    build_info = {"config": req.config.model_dump(), "f16": req.f16}  # inputs, no clock
    header = map_file.save_map(req.output, tsdf, source=built.source_info, build=build_info,
                               f16=req.f16)
    stats = map_stats(tsdf, loaded_bytes_per_block(req.f16))
    stats = dataclasses.replace(stats, file_bytes=req.output.stat().st_size)
    data = tsdf.blocks() if req.export_mesh or req.export_points else None
    exports = MapExports(
        mesh_triangles=(export.write_mesh(req.export_mesh, tsdf.geometry, data)
                        if req.export_mesh else None),
        surface_points=(export.write_points(req.export_points, tsdf.geometry, data)
                        if req.export_points else None))
    return BuildMapResult(req.source, req.output, kind, header, tsdf.geometry,
                          stats, seconds, built.n_scans, built.n_points, exports, built.faults)


# ------------------------------------------------------------------ summary rows
def format_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def map_rows(geometry: MapGeometry, stats: MapStats) -> list[tuple[str, str]]:
    """Summary-table rows describing a map: geometry, blocks, voxels, memory."""
    lo, hi = stats.extent_lo_m, stats.extent_hi_m
    size = [round(h - v, 2) for v, h in zip(lo, hi, strict=True)]
    return [
        ("voxel / truncation", f"{geometry.voxel_size_m} m / {geometry.truncation_m} m"),
        ("extent", f"{lo} .. {hi} m ({size[0]} x {size[1]} x {size[2]} m)"),
        ("coarse grid", " x ".join(str(d) for d in geometry.coarse_dims) + " blocks of 8³"),
        ("coarse index", f"{format_bytes(stats.coarse_bytes)}: top grid "
                         f"{format_bytes(stats.coarse_top_bytes)} + {stats.tiles} tiles "
                         f"{format_bytes(stats.coarse_tile_bytes)} (dense: "
                         f"{format_bytes(stats.dense_index_bytes)})"),
        ("blocks", f"{stats.blocks} allocated, {stats.free_blocks} free, "
                   f"{stats.unknown_cells} unknown"),
        ("voxels", f"{stats.surface_voxels} on the surface, {stats.observed_voxels} "
                   f"observed, {stats.free_voxels} free"),
        ("memory (loaded)", f"{format_bytes(stats.pool_bytes + stats.coarse_bytes)}: blocks "
                            f"{format_bytes(stats.pool_bytes)} ({stats.bytes_per_block} "
                            f"B/block) + coarse index, vs dense grid "
                            f"{format_bytes(stats.dense_grid_bytes)}"),
        *([("file", format_bytes(stats.file_bytes))] if stats.file_bytes is not None else []),
    ]


def summary_rows(result: BuildMapResult, backend: str) -> list[tuple[str, str]]:
    """Rows of the end-of-build summary table."""
    rows = [("source", f"{result.source} ({result.source_kind})"),
            *map_rows(result.geometry, result.stats),
            ("time", f"{result.seconds:.2f} s on {backend}")]
    if result.n_scans:
        rows.append(("scans", f"{result.n_scans} ({result.scans_per_s:.3g} scans/s, "
                              f"{result.n_points} points)"))
    rows.append(("written", str(result.output)))
    if result.exports.mesh_triangles is not None:
        rows.append(("mesh triangles", str(result.exports.mesh_triangles)))
    if result.exports.surface_points is not None:
        rows.append(("surface points", str(result.exports.surface_points)))
    return rows
