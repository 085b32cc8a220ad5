"""Building TSDF maps from scans with poses, from point-cloud maps and from meshes.

Defaults: 5 cm voxels and a truncation of 4 voxels (0.20 m). The localization sensor model
is a Gaussian on the signed distance with sigma about one voxel (5 cm, the accuracy the
TSDF-MCL paper reaches); 0.20 m keeps the whole Gaussian up to 4 sigma (likelihood 3e-4 of
its peak) inside the band, where distances are real rather than clamped, and leaves at
least 3 voxels each side of a surface for trilinear values and gradients. Wider bands cost
memory and blur thin structures (walls thinner than the band lose their back side).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import taichi as ti
from pydantic import Field, model_validator

from mcl3d.core import runtime
from mcl3d.core.config import Section
from mcl3d.core.errors import MapError, PointCloudError
from mcl3d.core.geometry import rot_to_quat
from mcl3d.kernels import tsdf_fusion
from mcl3d.maps.normals import oriented_normals
from mcl3d.maps.scan_normals import RangeImageNormals, layout
from mcl3d.maps.sparse_cells import cell_keys, tiles_of
from mcl3d.maps.tsdf import BLOCK, CHUNK_CELLS, MIN_BUILD_TILES, MapGeometry, TsdfMap
from mcl3d.maps.voxel_normals import fits, voxel_normals_of

TRUNCATION_VOXELS = 4
CPU_RUN_LENGTH = 64
GPU_RUN_LENGTH = 4
PERCENTILE_SAMPLES = 8192
SENSOR_ORIGIN = np.zeros((1, 3))  # a scan's normals face the sensor
SHARE_NORMAL_VOXELS = 0.5  # range-image neighbours this close (in voxels) share a normal:
# at voxel scale their windows, a column apart, give the same plane (maps/scan_normals)


class BuildConfig(Section):
    """Parameters of `mcl3d build-map` (units in the names)."""

    voxel_size_m: float = Field(0.05, gt=0.0, le=10.0, description="voxel edge length")
    truncation_m: float | None = Field(
        None, gt=0.0, description="truncation distance; default 4 voxels (0.20 m at 5 cm)")
    capacity_blocks: int = Field(
        65536, ge=1, description="initial pool size in 8^3 blocks (14 KiB each while building)")
    max_capacity_blocks: int = Field(
        1 << 20, ge=1, description="the pool grows up to this many blocks, then fails")
    min_range_m: float = Field(0.3, ge=0.0, description="scan points closer are ignored")
    max_range_m: float = Field(120.0, gt=0.0, description="scan points farther are ignored")
    normals: str = Field("auto", pattern="^(auto|knn|none)$",
                         description="point-to-plane distances from normals estimated on the "
                                     "device (auto: from the range image for scans with "
                                     "rings, else from the k nearest in a voxel "
                                     "neighbourhood), or on the host from the k nearest "
                                     "neighbours (knn); none: projective distance along rays")
    normal_neighbors: int = Field(12, ge=4, le=64, description="neighbours for normals")
    scan_cache_mb: int = Field(
        512, ge=0, description="a log's decoded scans kept in memory between the pass that "
                               "finds the map's bounds and the fusion pass, so the log is "
                               "decoded once; a larger log is decoded twice")
    orientation_cell_m: float = Field(
        0.3, gt=0.0, description="point-cloud maps without viewpoints: one representative "
                                 "per cell of this edge carries the orientation (maps/normals)")
    ray_spacing_deg: float | None = Field(
        None, gt=0.0, description="angle between neighbouring rays, sets how wide a patch of "
                                  "surface each point fills; default: estimated per scan")
    behind_m: float = Field(
        0.1, gt=0.0, description="how deep behind a measured surface the band "
                                 "reaches (solids thinner than twice this are not seen "
                                 "from their far side)")
    sigma_weight_m: float | None = Field(
        None, gt=0.0, description="band weights fall off with distance to the measured "
                                  "point (Gaussian sigma); default: one "
                                  "voxel")
    carve_free_space: bool = Field(True, description="mark space between sensor and band free")
    free_margin_m: float = Field(
        2.0, ge=0.0, description="point-cloud maps: mark free blocks up to this far from the "
                                 "points (on the normals' side; mesh maps mark all of the "
                                 "free side)")
    mesh_sign: str = Field("normals", pattern="^(normals|parity)$",
                           description="inside/outside of a mesh: from triangle normals (they "
                                       "face free space) or ray parity (closed solids)")
    frame_id: str = Field("map", min_length=1)

    @model_validator(mode="after")
    def _check(self) -> BuildConfig:
        if self.truncation_m is not None and self.truncation_m < self.voxel_size_m:
            raise ValueError(f"truncation_m ({self.truncation_m}) must be at least one voxel "
                             f"({self.voxel_size_m})")
        if self.max_range_m <= self.min_range_m:
            raise ValueError("max_range_m must be larger than min_range_m")
        return self

    @property
    def trunc_m(self) -> float:
        return self.truncation_m or TRUNCATION_VOXELS * self.voxel_size_m

    @property
    def sigma_w_m(self) -> float:
        return self.sigma_weight_m or self.voxel_size_m


def new_map(geometry: MapGeometry, config: BuildConfig, needed: int = 0,
            needed_tiles: int = 0) -> TsdfMap:
    """A writable map sized min(all cells, capacity) or to `needed` blocks when known; its
    coarse index to `needed_tiles` tiles when known (else TsdfMap's default)."""
    capacity = min(geometry.n_cells, max(config.capacity_blocks, needed))
    if capacity > config.max_capacity_blocks:
        raise MapError(
            f"the map needs {needed or capacity} blocks, more than max_capacity_blocks "
            f"{config.max_capacity_blocks}; raise it or use a larger voxel size",
            setting="max_capacity_blocks")
    tiles = max(capacity // 2, MIN_BUILD_TILES, needed_tiles)
    tsdf = TsdfMap(geometry, capacity, frame_id=config.frame_id, capacity_tiles=tiles)
    tsdf.as_sums = True
    return tsdf


def grown_capacity(tsdf: TsdfMap, config: BuildConfig) -> int:
    """Capacity for a retry after an overflow, or MapError when past the maximum."""
    needed = tsdf.requested_blocks
    if needed > config.max_capacity_blocks:
        raise MapError(
            f"the map needs {needed} blocks but max_capacity_blocks is "
            f"{config.max_capacity_blocks}; raise it to at least {needed} or use a larger "
            f"voxel size", setting="max_capacity_blocks")
    return min(int(needed * 1.25) + 16, config.max_capacity_blocks)


def grown_tiles(tsdf: TsdfMap) -> int:
    """Tiles of the coarse index for a retry after an overflow (at most one per top-grid
    cell, so tiles never fail a retry)."""
    return min(int(tsdf.requested_tiles * 1.25) + 16, tsdf.geometry.n_top_cells)


# ------------------------------------------------------------------------- scans
@dataclass
class PreparedScan:
    """A scan ready for the fusion kernels: f32 arrays plus the launch's scalar arguments."""

    points_l: np.ndarray  # (n, 3) f32, lidar frame
    normals_l: np.ndarray  # (n, 3) f32 (zeros when fusing without normals)
    alpha: np.ndarray  # (n,) f32 in [0, 1]: where between the two poses each point was taken
    args: tuple  # poses, ranges, ray spacing, behind_m, use_normals (see tsdf_fusion)

    def chunks(self):
        """Slices of at most CHUNK_CELLS points, one kernel launch each."""
        n = len(self.points_l)
        for s in range(0, n, CHUNK_CELLS):
            e = min(n, s + CHUNK_CELLS)
            yield PreparedScan(self.points_l[s:e], self.normals_l[s:e], self.alpha[s:e],
                               self.args)


class ScanFuser:
    """Fuses scans into a TSDF: truncation band per ray plus free-space carving.

    Each scan runs two kernels: allocation of the band's blocks (`allocate`), then band
    update and carving (`update`), which reads the block ids allocated by the first launch
    and the rays it set up (kept in two device arrays that grow with the largest scan).
    """

    def __init__(self, tsdf: TsdfMap, config: BuildConfig):
        self.tsdf = tsdf
        self.config = config
        self.n_scans = 0
        self.n_points = 0
        self._rays = None  # (ray_p, ray_n): vec4 per point, see tsdf_fusion.scan_allocate
        self._range_normals = RangeImageNormals()

    def _ray_buffers(self, n: int):
        """Device arrays for the rays of n points: allocated once, regrown (to a power of
        two) only by a larger scan."""
        if self._rays is None or self._rays[0].shape[0] < n:
            size = min(max(1 << max(n - 1, 1).bit_length(), 1024), CHUNK_CELLS)
            self._rays = (ti.ndarray(ti.math.vec4, shape=size),
                          ti.ndarray(ti.math.vec4, shape=size))
        return self._rays

    def fuse(self, points_l: np.ndarray, T_start: np.ndarray, T_end: np.ndarray | None = None,
             alpha: np.ndarray | None = None, normals_l: np.ndarray | None = None,
             rings: np.ndarray | None = None) -> None:
        """Fuse one scan given in the lidar frame.

        `alpha` in [0, 1] per point places it between the poses T_start and T_end
        (deskewing); without it every point uses T_start. `rings` (each point's laser) let
        the normals come from the scan's range image on the device.
        """
        scan = self.prepare(points_l, T_start, T_end, alpha, normals_l, rings)
        if scan is None:
            return
        for part in scan.chunks():
            self.allocate(part)
            self.update(part, self.config.carve_free_space)
        self.n_scans += 1
        self.n_points += len(scan.points_l)

    def prepare(self, points_l: np.ndarray, T_start: np.ndarray,
                T_end: np.ndarray | None = None, alpha: np.ndarray | None = None,
                normals_l: np.ndarray | None = None, rings: np.ndarray | None = None
                ) -> PreparedScan | None:
        """The scan as the kernels take it (None for an empty scan); arguments as `fuse`."""
        pts = np.ascontiguousarray(points_l, dtype=np.float32).reshape(-1, 3)
        n = len(pts)
        if n == 0:
            return None
        cfg = self.config
        use_normals = cfg.normals != "none"
        if use_normals and normals_l is None:
            normals_l = self.normals(pts, rings)
        nrm = (np.ascontiguousarray(normals_l, dtype=np.float32) if use_normals
               else np.zeros_like(pts))
        T_end = T_start if T_end is None else T_end
        a = (np.zeros(n, np.float32) if alpha is None
             else np.ascontiguousarray(alpha, dtype=np.float32))
        q0, q1 = rot_to_quat(T_start[:3, :3]), rot_to_quat(T_end[:3, :3])
        if np.dot(q0, q1) < 0:
            q1 = -q1
        spacing = (np.deg2rad(cfg.ray_spacing_deg) if cfg.ray_spacing_deg
                   else ray_spacing_rad(pts))
        args = (ti.math.vec4(*q0), ti.math.vec3(*T_start[:3, 3]),
                ti.math.vec4(*q1), ti.math.vec3(*T_end[:3, 3]),
                cfg.min_range_m, cfg.max_range_m, spacing, min(cfg.behind_m, cfg.trunc_m),
                use_normals)
        return PreparedScan(pts, nrm, a, args)

    def normals(self, points_l: np.ndarray, rings: np.ndarray | None) -> np.ndarray:
        """Unit normals facing the sensor (zeros: none found, that point fuses
        projectively): with normals auto on the device, from the range image when the scan
        has one (pixels within SHARE_NORMAL_VOXELS of the middle one of their three columns
        take its normal), else from the k nearest in a voxel neighbourhood; with knn (or k
        beyond the device search) from the k nearest neighbours on the host."""
        k = self.config.normal_neighbors
        if self.config.normals == "auto":
            shape = layout(points_l, rings)
            if shape is not None:
                return self._range_normals(points_l, rings, shape,
                                           SHARE_NORMAL_VOXELS * self.config.voxel_size_m)
            if fits(points_l, k):
                return voxel_normals_of(points_l, k)
        return oriented_normals(points_l, k, SENSOR_ORIGIN, self.config.orientation_cell_m)

    def allocate(self, scan: PreparedScan) -> None:
        """Pass 1: allocate (and initialize) the blocks the scan's bands reach, and claim the
        tiles of the coarse index that pass 2 carves in."""
        m = self.tsdf
        n = len(scan.points_l)
        before = m.requested_blocks
        threads = runtime.loop_threads()
        # runs only serve to spread points over cpu threads; a GPU thread takes one point
        # (runs of several lost points on Mesa's lavapipe)
        runs = run_length() if threads > 1 else 1
        m.relaunch_until_placed(lambda: tsdf_fusion.scan_allocate(
            m, scan.points_l, scan.normals_l, scan.alpha, n, *scan.args, *self._ray_buffers(n),
            runs, threads, self.config.carve_free_space))
        m.init_new_blocks(before, m.requested_blocks)

    def update(self, scan: PreparedScan, carve: bool) -> None:
        """Pass 2: the truncation bands, and free-space carving when `carve`; the scan must
        be the one `allocate` took last (its rays are reused)."""
        _q0, t0, _q1, t1, _lo, _hi, spacing, behind, _normals = scan.args
        tsdf_fusion.scan_fuse(self.tsdf, *self._rays, scan.alpha, len(scan.points_l), t0, t1,
                              spacing, behind, carve, self.config.sigma_w_m, run_length(),
                              runtime.loop_threads())


def run_length() -> int:
    """Consecutive points one thread fuses (tsdf_fusion.scan_fuse): long runs on cpu, whose
    few threads gain most from merged voxel updates, short ones on GPUs, which need
    thousands of threads."""
    info = runtime.current()
    return CPU_RUN_LENGTH if info is None or info.backend == "cpu" else GPU_RUN_LENGTH


def ray_spacing_rad(points_l: np.ndarray) -> float:
    """Mean angle between neighbouring rays of a scan: sqrt(solid angle / rays).

    The solid angle is that of the elevation band the scan covers (a spinning lidar's
    vertical field of view), from the 1st to the 99th percentile of its elevations.
    """
    x, y, z = points_l[:, 0], points_l[:, 1], points_l[:, 2]
    r2 = x * x + y * y + z * z  # (einsum "ij,ij->i" takes 5x longer on f32)
    ok = r2 > 0
    n_ok = int(np.count_nonzero(ok))
    if n_ok < 2:
        return 0.0
    # sin(elevation) = z / r: percentiles of it are those of the elevations (arcsin is
    # monotonic; only the interpolation between neighbouring samples differs). Every k-th
    # point is plenty for the 1st and 99th percentiles and keeps this off the fusion's time.
    step = max(1, len(points_l) // PERCENTILE_SAMPLES)
    sub_ok = ok[::step]
    if np.count_nonzero(sub_ok) < 2:
        sub_ok, step = ok, 1
    sin_el = np.clip(points_l[::step, 2][sub_ok] / np.sqrt(r2[::step][sub_ok]), -1, 1)
    lo, hi = np.percentile(sin_el, [1, 99])
    solid_angle = 2 * np.pi * max(hi - lo, 1e-3)
    return float(np.sqrt(solid_angle / n_ok))


# -------------------------------------------------------------------------- meshes
def _mesh_scene(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d  # here: 0.5 s of import that maps from logs do not need

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


class MeshDistance:
    """Exact signed distance to a triangle mesh, with a sign that is right at edges.

    The sign of a query comes from the surface normal at its closest point. When that point
    is on an edge or a vertex (outside a room's corner, say), one adjacent triangle's normal
    can give the wrong side; the angle-weighted pseudo-normals of Baerentzen and Aanaes
    (2005) give the right one for any closed, consistently oriented mesh. `parity` uses
    Open3D's ray-parity sign instead (watertight meshes, either orientation).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.triangles = np.asarray(triangles, dtype=np.int64)
        self.scene = _mesh_scene(self.vertices, self.triangles)
        corners = self.vertices[self.triangles]  # (T, 3 corners, 3)
        face_n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        face_n /= np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-300)
        self.face_normals = face_n
        vertex_n = np.zeros_like(self.vertices)
        for k in range(3):
            a = corners[:, (k + 1) % 3] - corners[:, k]
            b = corners[:, (k + 2) % 3] - corners[:, k]
            cos = np.einsum("ij,ij->i", a, b) / np.maximum(
                np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
            np.add.at(vertex_n, self.triangles[:, k],
                      face_n * np.arccos(np.clip(cos, -1.0, 1.0))[:, None])
        self.vertex_normals = vertex_n
        edges = np.sort(np.stack([self.triangles[:, [0, 1]], self.triangles[:, [1, 2]],
                                  self.triangles[:, [2, 0]]], axis=1), axis=2)  # (T, 3, 2)
        keys, self._edge_of = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
        self._edge_of = self._edge_of.reshape(-1, 3)  # edge k of a triangle is opposite corner k+2
        edge_n = np.zeros((len(keys), 3))
        np.add.at(edge_n, self._edge_of.ravel(), np.repeat(face_n, 3, axis=0))
        self.edge_normals = edge_n

    def signed_distance(self, query: np.ndarray, sign: str = "normals") -> np.ndarray:
        import open3d as o3d

        out = np.empty(len(query), np.float32)
        step = 1 << 20
        for s in range(0, len(query), step):
            q = np.ascontiguousarray(query[s:s + step], dtype=np.float32)
            if sign == "parity":
                out[s:s + len(q)] = self.scene.compute_signed_distance(
                    o3d.core.Tensor(q)).numpy()
                continue
            res = self.scene.compute_closest_points(o3d.core.Tensor(q))
            closest = res["points"].numpy().astype(np.float64)
            tri = res["primitive_ids"].numpy().astype(np.int64)
            diff = q - closest
            normal = self._pseudo_normals(closest, tri)
            dist = np.linalg.norm(diff, axis=1)
            out[s:s + len(q)] = np.where(np.einsum("ij,ij->i", diff, normal) >= 0, dist, -dist)
        return out

    def _pseudo_normals(self, closest: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """Face, edge or vertex pseudo-normal at each closest point (by its barycentrics)."""
        corners = self.vertices[self.triangles[tri]]
        bary = _barycentric(closest, corners)
        on = bary < 1e-4  # f32 closest points: within ~1e-4 of an edge counts as on it
        n_zero = on.sum(axis=1)
        normal = self.face_normals[tri].copy()
        edge = n_zero == 1  # on the edge opposite the zero barycentric corner
        if edge.any():
            opposite = np.argmax(on[edge], axis=1)
            normal[edge] = self.edge_normals[self._edge_of[tri[edge], (opposite + 1) % 3]]
        vertex = n_zero >= 2  # at the corner whose barycentric is not zero
        if vertex.any():
            corner = np.argmin(on[vertex], axis=1)
            normal[vertex] = self.vertex_normals[self.triangles[tri[vertex], corner]]
        return normal


def _barycentric(p: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of points p in triangles `corners` (N, 3, 3)."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    denom = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    return np.stack([1.0 - v - w, v, w], axis=1)


def _mesh_cells(mesh: MeshDistance, geometry: MapGeometry, config: BuildConfig
                ) -> tuple[np.ndarray, np.ndarray]:
    """Coarse cells near the mesh (|d| at the centre < truncation + half a block diagonal)
    and free cells (d at the centre beyond that), each (n, 3) int32 in (x, y, z) order.

    An octree descent from a node covering the bounds: a node whose centre is farther from
    the mesh than the threshold plus the reach of its cells' centres holds no near cell
    (distance is 1-Lipschitz) and takes its centre's sign whole; the others split into
    eight. Only nodes near the surface are visited; the cells of size 1 get the same test
    at their centres as every cell had. A whole node's sign is exact where the sign does
    not change away from the surface: closed, consistently oriented meshes, or parity
    (whose isolated errors where a ray grazes coplanar faces a far node does not repeat)."""
    dims = np.asarray(geometry.coarse_dims, np.int64)
    block = geometry.block_size_m
    origin = np.asarray(geometry.origin_m)
    half_diag = 0.5 * np.sqrt(3) * block
    near_m = config.trunc_m + half_diag + 1e-6
    size = 1 << int(np.ceil(np.log2(dims.max())))
    nodes = np.zeros((1, 3), np.int64)
    free_nodes = []
    while True:
        sd = mesh.signed_distance(origin + (nodes + 0.5 * size) * block, config.mesh_sign)
        if size == 1:
            near_cells = nodes[np.abs(sd) < near_m]
            free_nodes.append((nodes[sd >= config.trunc_m + half_diag], 1))
            break
        reach = 0.5 * np.sqrt(3) * (size - 1) * block + 1e-3  # + f32 distances' error
        far = np.abs(sd) >= near_m + reach
        free_nodes.append((nodes[far & (sd > 0)], size))
        size //= 2
        corners = np.stack(np.meshgrid(*[[0, size]] * 3, indexing="ij"), -1).reshape(-1, 3)
        nodes = (nodes[~far][:, None, :] + corners).reshape(-1, 3)
        nodes = nodes[np.all(nodes < dims, axis=1)]
    free_cells = np.concatenate([_node_cells(n, s, dims) for n, s in free_nodes])
    return _lexicographic(near_cells), _lexicographic(free_cells)


def _node_cells(nodes: np.ndarray, size: int, dims: np.ndarray) -> np.ndarray:
    """The cells (n, 3) of cubic nodes of `size` cells (lower corners `nodes`) inside dims:
    small nodes all at once, large ones (few, and often mostly outside) one by one."""
    if size <= 8:
        local = np.stack(np.meshgrid(*[np.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3)
        cells = (nodes[:, None, :] + local).reshape(-1, 3)
        return cells[np.all(cells < dims, axis=1)]
    parts = [np.zeros((0, 3), np.int64)]
    for lo in nodes:
        axes = [np.arange(a, b) for a, b in zip(lo, np.minimum(lo + size, dims), strict=True)]
        parts.append(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3))
    return np.concatenate(parts)


def _lexicographic(cells: np.ndarray) -> np.ndarray:
    """Cells (n, 3) as int32 in (x, y, z) order, the order a dense grid's cells come in."""
    cells = cells.reshape(-1, 3)
    order = np.argsort(cell_keys(cells, cells.max(axis=0, initial=0) + 1), kind="stable")
    return cells[order].astype(np.int32)


def build_from_mesh(vertices: np.ndarray, triangles: np.ndarray, config: BuildConfig
                    ) -> TsdfMap:
    """Exact signed distance to a triangle mesh in the blocks near its surface.

    Blocks whose centre is farther than truncation + half a block diagonal from the mesh
    hold no band voxel: they become FREE on the free side, however far from the surface (a
    mesh's sign holds far from it, and a drone in a large hall flies more than a few metres
    from every wall: global localization only places particles in free space), and stay
    unknown inside solids. Blocks near the surface get the exact distance at every voxel
    centre. Which blocks are near is found by descending an octree of cells from the
    bounds (`_mesh_cells`): the host's work grows with the surface, not with the bounds.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if len(triangles) == 0 or len(vertices) < 3:
        raise PointCloudError("the mesh has no triangles")
    if not np.isfinite(vertices).all():
        raise PointCloudError("the mesh has NaN or inf vertices")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise PointCloudError("the mesh has triangle indices outside its vertex list")
    trunc = config.trunc_m
    geometry = MapGeometry.around(vertices.min(axis=0), vertices.max(axis=0),
                                  config.voxel_size_m, trunc, margin_m=trunc)
    mesh = MeshDistance(vertices, triangles)
    near_cells, free_cells = _mesh_cells(mesh, geometry, config)
    origin = np.asarray(geometry.origin_m)
    tsdf = new_map(geometry, config, len(near_cells),
                   len(tiles_of(np.concatenate([near_cells, free_cells]))))
    tsdf.as_sums = False
    tsdf.mark_free(free_cells)
    tsdf.allocate(near_cells)
    local = np.stack(np.meshgrid(*[np.arange(BLOCK)] * 3, indexing="ij"), axis=-1)
    per = 4096
    for s in range(0, len(near_cells), per):
        c = near_cells[s:s + per]
        vox = (c[:, None, None, None, :] * BLOCK + local[None]).reshape(-1, 3)
        d = mesh.signed_distance(origin + (vox + 0.5) * config.voxel_size_m, config.mesh_sign)
        d = np.clip(d, -trunc, trunc).reshape(len(c), BLOCK, BLOCK, BLOCK)
        tsdf.write_blocks(c, d, np.ones_like(d))
    return tsdf

