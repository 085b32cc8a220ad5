"""TSDF maps from point-cloud maps (what other SLAM systems export), fused in Taichi.

Each point's tangent plane writes point-to-plane distances into the voxels of a cube of the
truncation's radius around it; then cells clear of every point on the normals' side
become FREE. Pools are sized from the cells the points' cubes touch, counted on the host,
and grown and retried should they still overflow. A map whose blocks exceed SLAB_BLOCKS is
fused slab by slab along x (each slab with the points whose cubes reach it, so every block
gets the same sums as in one pass) into a read-only map of distances and weights: memory
while building is 8 bytes a voxel for the map plus one slab's build sums (28 bytes a voxel),
not 28 bytes a voxel for the whole city.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mcl3d.core.errors import MapError, PointCloudError
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.kernels import tsdf_fusion
from mcl3d.maps.build import BuildConfig, grown_capacity, grown_tiles, new_map
from mcl3d.maps.normals import oriented_normals
from mcl3d.maps.sparse_cells import CellLookup, cell_keys, dilate_cells, tiles_of, unique_keys
from mcl3d.maps.tsdf import BLOCK, CHUNK_CELLS, MapGeometry, TsdfMap

ALLOCATE_STAGE = "allocate blocks"
FUSE_POINTS_STAGE = "fuse points"
FREE_STAGE = "mark free space"
SLAB_BLOCKS = 1 << 17  # blocks fused at once (their build sums: ~1.8 GiB)


def build_from_points(points: np.ndarray, config: BuildConfig, *,
                      normals: np.ndarray | None = None,
                      viewpoints: np.ndarray | None = None,
                      on_progress: ProgressCallback | None = None) -> TsdfMap:
    """Signed distance from an oriented point cloud (map frame).

    Without `normals` they are estimated and oriented (maps/normals.py: towards the
    viewpoints, else consistently over the map). Voxels within the truncation in front of a
    point's plane and behind_m behind it get its point-to-plane distance, weighted by their
    distance to the point; blocks farther than the truncation from every point, on the
    normals' side, within free_margin_m, become FREE.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < config.normal_neighbors:
        raise PointCloudError(f"the point cloud has {len(pts)} valid points; at least "
                              f"{config.normal_neighbors} are needed to estimate normals")
    if normals is None:
        normals = oriented_normals(pts, config.normal_neighbors, viewpoints,
                                   config.orientation_cell_m,
                                   lambda name: report(on_progress, Progress(name, 0, 1)))
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(nrm) != len(pts):
        raise PointCloudError(f"{len(nrm)} normals for {len(pts)} points")
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    geometry = MapGeometry.around(pts.min(axis=0), pts.max(axis=0), config.voxel_size_m,
                                  config.trunc_m, margin_m=config.trunc_m + config.free_margin_m)
    report(on_progress, Progress(ALLOCATE_STAGE, 0, 1))
    fusion = _PointFusion(geometry, config, pts, nrm, on_progress)
    tsdf = fusion.whole() if len(fusion.cells) <= SLAB_BLOCKS else fusion.by_slabs()
    report(on_progress, Progress(FREE_STAGE, 0, 1))
    _mark_free_around_points(tsdf, pts, nrm, config)
    report(on_progress, Progress(FREE_STAGE, 1, 1))
    return tsdf


class _PointFusion:
    """The points (f32), their cubes' cells and the tiles the map will need."""

    def __init__(self, geometry: MapGeometry, config: BuildConfig, pts: np.ndarray,
                 nrm: np.ndarray, on_progress: ProgressCallback | None):
        self.geometry, self.config, self.on_progress = geometry, config, on_progress
        self.radius = int(np.ceil(config.trunc_m / config.voxel_size_m))
        self.pts32 = np.ascontiguousarray(pts, dtype=np.float32)
        self.nrm32 = np.ascontiguousarray(nrm, dtype=np.float32)
        self.cells = _cube_cells(geometry, pts, self.radius)
        reach = int(np.ceil(config.free_margin_m / geometry.block_size_m))
        self.tiles = len(tiles_of(dilate_cells(self.cells, reach, geometry.coarse_dims)))
        self.fused = 0

    def whole(self) -> TsdfMap:
        """One pass over all points into one writable map."""
        tsdf = _points_map(self.geometry, self.config, self.pts32, self.radius,
                           len(self.cells), self.tiles)
        self._fuse(tsdf, self.pts32, self.nrm32)
        tsdf.finalize()
        return tsdf

    def by_slabs(self) -> TsdfMap:
        """Slab by slab along x into a read-only map (see the module docstring)."""
        if len(self.cells) > self.config.max_capacity_blocks:
            raise MapError(
                f"the map needs {len(self.cells)} blocks, more than max_capacity_blocks "
                f"{self.config.max_capacity_blocks}; raise it or use a larger voxel size",
                setting="max_capacity_blocks")
        out = TsdfMap(self.geometry, len(self.cells), writable=False,
                      frame_id=self.config.frame_id, capacity_tiles=self.tiles)
        g = self.geometry
        gx = np.floor((self.pts32[:, 0] - np.float32(g.origin_m[0]))
                      / np.float32(g.voxel_size_m)).astype(np.int64)
        margin = self.radius + 1  # + 1: the kernels' f32 voxel of a point may differ by one

        def points_of(x0, x1):
            return np.flatnonzero((gx >= x0 * BLOCK - margin) & (gx < x1 * BLOCK + margin))

        slabs = _slabs(self.cells[:, 0], SLAB_BLOCKS)
        needed = max(len(_cube_cells(g, self.pts32[points_of(*x)], self.radius)) for x in slabs)
        slab = None  # one map for every slab, cleared between them: its kernels compile once
        for x0, x1 in slabs:
            sel = points_of(x0, x1)
            pts, nrm = self.pts32[sel], self.nrm32[sel]
            slab = _points_map(g, self.config, pts, self.radius, needed, self.tiles, slab)
            self._fuse(slab, pts, nrm)
            slab.finalize()
            data = slab.blocks()
            keep = (data.coords[:, 0] >= x0) & (data.coords[:, 0] < x1)
            out.allocate(data.coords[keep])
            out.write_blocks(data.coords[keep], data.sdf[keep], data.weight[keep])
            del data
        slab.destroy()
        return out

    def _fuse(self, tsdf: TsdfMap, pts32: np.ndarray, nrm32: np.ndarray) -> None:
        cfg, r = self.config, self.radius
        per_launch = max(1, (4 << 20) // (2 * r + 1) ** 3)
        for s in range(0, len(pts32), per_launch):
            e = min(len(pts32), s + per_launch)
            tsdf_fusion.points_fuse(tsdf, pts32[s:e], nrm32[s:e], e - s, r, cfg.sigma_w_m,
                                    min(cfg.behind_m, cfg.trunc_m))
            self.fused += e - s
            report(self.on_progress, Progress(FUSE_POINTS_STAGE, self.fused, len(self.pts32)))


def _slabs(block_x: np.ndarray, max_blocks: int) -> list[tuple[int, int]]:
    """Ranges [x0, x1) of block x holding at most max_blocks of the cells (a single x
    holding more is a slab of its own)."""
    counts = np.bincount(block_x)
    slabs, start, held = [], 0, 0
    for x, c in enumerate(counts):
        if held and held + c > max_blocks:
            slabs.append((start, x))
            start, held = x, 0
        held += c
    slabs.append((start, len(counts)))
    return slabs


def _cube_cells(geometry: MapGeometry, pts: np.ndarray, radius_vox: int) -> np.ndarray:
    """The coarse cells (n, 3) that the cubes of radius_vox voxels around the points touch,
    in (x, y, z) order.

    Samples at most a block apart across each cube name every block it touches: listed on
    the host so that the pools are sized once (one int64 key per point and offset, made
    unique per chunk of points, so memory stays a few bytes a point)."""
    dims = np.asarray(geometry.coarse_dims, np.int64)
    steps = np.unique(np.round(np.linspace(-radius_vox, radius_vox,
                                           int(np.ceil(2 * radius_vox / BLOCK)) + 1)))
    origin, voxel = np.asarray(geometry.origin_m), geometry.voxel_size_m
    keys = [np.zeros(0, np.int64)]
    for s in range(0, len(pts), CHUNK_CELLS):
        g = np.floor((pts[s:s + CHUNK_CELLS] - origin) / voxel).astype(np.int64)
        for dx in steps:
            for dy in steps:
                for dz in steps:
                    c = np.clip((g + np.array([dx, dy, dz], dtype=np.int64)) >> 3, 0, dims - 1)
                    keys.append(unique_keys(cell_keys(c, dims)))
        keys = [unique_keys(np.concatenate(keys))]
    k = keys[0]
    return np.stack([k // (dims[1] * dims[2]), (k // dims[2]) % dims[1], k % dims[2]], axis=1)


def _points_map(geometry: MapGeometry, config: BuildConfig, pts32: np.ndarray, radius: int,
                needed: int, tiles: int, reuse: TsdfMap | None = None) -> TsdfMap:
    """A writable map with the points' blocks allocated, its pools sized to `needed` blocks
    and `tiles` tiles (or `reuse`, cleared, when given); should a pool still overflow, it is
    grown and the allocation run again (three tries, then the capacity error names what is
    needed)."""
    for attempt in range(3):
        if attempt == 0 and reuse is not None:
            tsdf = reuse
            tsdf.clear()
            tsdf.as_sums = True
        else:
            tsdf = new_map(geometry, config, needed, tiles)

        def allocate(m=tsdf):
            for s in range(0, len(pts32), CHUNK_CELLS):
                e = min(len(pts32), s + CHUNK_CELLS)
                tsdf_fusion.points_allocate(m, pts32[s:e], e - s, radius)

        tsdf.relaunch_until_placed(allocate)
        if not tsdf.overflowed or attempt == 2:
            break
        needed, tiles = grown_capacity(tsdf, config), max(int(tiles * 1.25), grown_tiles(tsdf))
        tsdf.destroy()
    tsdf.check_capacity()  # after the last try: names the pool and the size it needs
    tsdf.init_new_blocks(0, tsdf.n_blocks)
    return tsdf


def _candidate_cells(tsdf: TsdfMap, margin_m: float) -> np.ndarray:
    """Unallocated cells within margin of an allocated block, as (k, 3) coordinates (a
    sparse dilation: never a grid over the bounds)."""
    cells, values = tsdf.coarse_cells()
    r = int(np.ceil(margin_m / tsdf.geometry.block_size_m))
    near = dilate_cells(cells[values >= 0], r, tsdf.coarse_dims)
    return near[CellLookup(cells, values, tsdf.coarse_dims)(near) < 0]


def _mark_free_around_points(tsdf: TsdfMap, pts: np.ndarray, nrm: np.ndarray,
                             config: BuildConfig) -> None:
    """Unallocated cells within free_margin_m of the blocks, clear of every point by the
    truncation plus half a block diagonal and on the normals' side of most of their 8
    nearest points, become FREE."""
    cells = _candidate_cells(tsdf, config.free_margin_m)
    if not len(cells):
        return
    g = tsdf.geometry
    centers = np.asarray(g.origin_m) + (cells + 0.5) * g.block_size_m
    dist, idx = cKDTree(pts).query(centers, k=8, workers=-1)
    side = np.einsum("ckj,ckj->ck", centers[:, None, :] - pts[idx], nrm[idx])
    clear = dist[:, 0] >= config.trunc_m + 0.5 * np.sqrt(3) * g.block_size_m
    outside = (side > 0).sum(axis=1) >= 6
    tsdf.mark_free(cells[clear & outside])
