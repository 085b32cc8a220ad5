"""TSDF maps from point-cloud maps (what other SLAM systems export), fused in Taichi.

Normals and spacing on the device (maps/point_normals.py, the points then in Morton order),
oriented from the map itself or towards viewpoints (maps/normals.py); each point's band
along its normal (kernels/point_fusion.py) takes point-to-plane distances; then cells
clear of every point on the normals' side become FREE. Pools are sized from the cells the
bands reach, counted on the host, and grown and retried should they still overflow. A map
whose blocks exceed SLAB_BLOCKS is fused slab by slab along x (each slab with the runs of
points whose bands reach it, so every block gets the same sums as in one pass) into a
read-only map of distances and weights: memory while building is 8 bytes a voxel for the
map plus one slab's build sums (28 bytes a voxel), not 28 bytes a voxel for the whole city.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mcl3d.core.errors import MapError, PointCloudError
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.kernels import point_fusion
from mcl3d.maps.build import BuildConfig, grown_capacity, grown_tiles, new_map
from mcl3d.maps.normals import orient_consistently, orient_towards
from mcl3d.maps.point_normals import sorted_normals
from mcl3d.maps.sparse_cells import CellLookup, cell_keys, dilate_cells, tiles_of, unique_keys
from mcl3d.maps.tsdf import BLOCK, CHUNK_CELLS, MapGeometry, TsdfMap

NORMALS_STAGE = "estimate normals"
ORIENT_STAGE = "orient normals"
ALLOCATE_STAGE = "allocate blocks"
FUSE_POINTS_STAGE = "fuse points"
FREE_STAGE = "mark free space"
SLAB_BLOCKS = 1 << 15  # blocks of one slab (their build sums: ~0.45 GiB, plus the columns beside)
READ_ONLY_BLOCKS_PER_BUILD_BLOCK = 3  # a read-only block is 8 bytes a voxel, a building one 28
SLAB_POOL_MARGIN = 1.3  # a slab's pool: its blocks plus 30 % for the columns beside it
RUN_LENGTH = 32  # points (in Morton order) one fusion thread takes at a time
FOOTPRINT_GAPS = 2.0  # a band patch spans this many mean spacings: scan lines leave gaps
FREE_CHUNK_CELLS = 1 << 18  # candidate free cells tested at once (8 neighbours each)


def build_from_points(points: np.ndarray, config: BuildConfig, *,
                      viewpoints: np.ndarray | None = None,
                      on_progress: ProgressCallback | None = None) -> TsdfMap:
    """Signed distance from a point cloud (map frame).

    Normals and spacing come from each point's k nearest (maps/point_normals.py; points
    without a normal, on a line or nearly alone, are left out), oriented towards the
    viewpoints, else consistently over the map (maps/normals.py). Voxels of each point's
    band (kernels/point_fusion.py) get its point-to-plane distance, weighted by their
    distance to the point; blocks farther than the truncation from every point, on the
    normals' side, within free_margin_m, become FREE.
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < config.normal_neighbors:
        raise PointCloudError(f"the point cloud has {len(pts)} valid points; at least "
                              f"{config.normal_neighbors} are needed to estimate normals")
    report(on_progress, Progress(NORMALS_STAGE, 0, 1))
    order, nrm, spacing = sorted_normals(pts, config.normal_neighbors)
    keep = order[spacing > 0]
    pts, nrm, spacing = pts[keep], nrm[spacing > 0], spacing[spacing > 0]
    del order, keep
    report(on_progress, Progress(ORIENT_STAGE, 0, 1))
    if viewpoints is not None and len(viewpoints):
        nrm = orient_towards(pts, nrm, np.asarray(viewpoints, dtype=np.float64))
    else:
        nrm = orient_consistently(pts, nrm, config.orientation_cell_m)
    nrm = np.ascontiguousarray(nrm, dtype=np.float32)
    steps = np.minimum(FOOTPRINT_GAPS * spacing / np.float32(config.voxel_size_m),
                       max_footprint_steps(config)).astype(np.uint8)
    del spacing
    geometry = MapGeometry.around(pts.min(axis=0), pts.max(axis=0), config.voxel_size_m,
                                  config.trunc_m, margin_m=config.trunc_m + config.free_margin_m)
    report(on_progress, Progress(ALLOCATE_STAGE, 0, 1))
    fusion = _PointFusion(geometry, config, pts, nrm, steps, on_progress)
    tsdf = fusion.whole() if len(fusion.cells) <= SLAB_BLOCKS else fusion.by_slabs()
    del fusion
    report(on_progress, Progress(FREE_STAGE, 0, 1))
    _mark_free_around_points(tsdf, pts, nrm, config)
    report(on_progress, Progress(FREE_STAGE, 1, 1))
    return tsdf


def max_footprint_steps(config: BuildConfig) -> int:
    """The widest patch, in half voxels of half-width: the truncation either side (the
    reach of the cube the bands replace), so sparse surfaces stay closed."""
    return int(np.ceil(2 * config.trunc_m / config.voxel_size_m))


class _PointFusion:
    """The points in Morton order (f32), their normals and band footprints, the blocks and
    tiles the map will need."""

    def __init__(self, geometry: MapGeometry, config: BuildConfig, pts: np.ndarray,
                 nrm: np.ndarray, steps: np.ndarray, on_progress: ProgressCallback | None):
        self.geometry, self.config, self.on_progress = geometry, config, on_progress
        self.behind_m = min(config.behind_m, config.trunc_m)
        self.pts32, self.nrm32, self.steps = pts, nrm, steps
        self.cells = band_cells(geometry, pts, nrm, steps, self.behind_m)
        reach = int(np.ceil(config.free_margin_m / geometry.block_size_m))
        self.tiles = len(tiles_of(dilate_cells(self.cells, reach, geometry.coarse_dims)))
        self.fused = 0

    def whole(self) -> TsdfMap:
        """One pass over all points into one writable map."""
        tsdf = self._map(self.pts32, self.nrm32, self.steps, len(self.cells))
        self._fuse(tsdf, self.pts32, self.nrm32, self.steps)
        tsdf.finalize()
        return tsdf

    def by_slabs(self) -> TsdfMap:
        """Slab by slab along x into a read-only map (see the module docstring)."""
        if len(self.cells) > READ_ONLY_BLOCKS_PER_BUILD_BLOCK * self.config.max_capacity_blocks:
            raise MapError(
                f"the map needs {len(self.cells)} blocks, more than "
                f"{READ_ONLY_BLOCKS_PER_BUILD_BLOCK} x max_capacity_blocks "
                f"{self.config.max_capacity_blocks}; raise it or use a larger voxel size",
                setting="max_capacity_blocks")
        # the host's band cells may miss a block a diagonal band crosses: a margin
        capacity = len(self.cells) + len(self.cells) // 32 + 1024
        out = TsdfMap(self.geometry, capacity, writable=False,
                      frame_id=self.config.frame_id, capacity_tiles=self.tiles)
        g = self.geometry
        gx = np.floor((self.pts32[:, 0] - np.float32(g.origin_m[0]))
                      / np.float32(g.voxel_size_m)).astype(np.int32)
        # a band reaches the truncation along its normal and half a patch across it
        # (+ 1: the kernels' f32 voxel of a point may differ by one)
        margin = (int(np.ceil(self.config.trunc_m / g.voxel_size_m))
                  + (max_footprint_steps(self.config) + 1) // 2 + 1)

        def points_of(x0, x1):
            """Whole runs of points (the runs of one pass) with a point near the slab."""
            near = (gx >= x0 * BLOCK - margin) & (gx < x1 * BLOCK + margin)
            runs = np.flatnonzero(np.add.reduceat(near, np.arange(0, len(near), RUN_LENGTH)))
            idx = (runs[:, None] * RUN_LENGTH + np.arange(RUN_LENGTH)).ravel()
            return idx[idx < len(near)]

        slabs = _slabs(self.cells[:, 0], SLAB_BLOCKS)
        # a slab's bands also reach the block columns beside it; how far into them (often
        # a whole street's facade) the host does not count: the pool grows when short
        inside = max(int(np.sum((self.cells[:, 0] >= x0) & (self.cells[:, 0] < x1)))
                     for x0, x1 in slabs)
        needed = int(inside * SLAB_POOL_MARGIN) + 1024
        slab = None  # one map for every slab, cleared between them: its kernels compile once
        for x0, x1 in slabs:
            sel = points_of(x0, x1)
            pts, nrm, steps = self.pts32[sel], self.nrm32[sel], self.steps[sel]
            slab = self._map(pts, nrm, steps, needed, slab)
            self._fuse(slab, pts, nrm, steps)
            slab.finalize()
            for coords, sdf, weight in slab.block_chunks():
                keep = (coords[:, 0] >= x0) & (coords[:, 0] < x1)
                out.allocate(coords[keep])
                out.write_blocks(coords[keep], sdf[keep], weight[keep])
        slab.destroy()
        return out

    def _map(self, pts32, nrm32, steps, needed: int, reuse: TsdfMap | None = None) -> TsdfMap:
        def allocate(m):
            for s in range(0, len(pts32), CHUNK_CELLS):
                e = min(len(pts32), s + CHUNK_CELLS)
                point_fusion.points_allocate_band(m, pts32[s:e], nrm32[s:e],
                                                  steps[s:e].astype(np.int32), e - s,
                                                  self.behind_m)

        return _points_map(self.geometry, self.config, allocate, needed, self.tiles, reuse)

    def _fuse(self, tsdf: TsdfMap, pts32: np.ndarray, nrm32: np.ndarray,
              steps: np.ndarray) -> None:
        for s in range(0, len(pts32), CHUNK_CELLS):
            e = min(len(pts32), s + CHUNK_CELLS)
            point_fusion.points_fuse_band(tsdf, pts32[s:e], nrm32[s:e],
                                          steps[s:e].astype(np.int32), e - s,
                                          self.config.sigma_w_m, self.behind_m, RUN_LENGTH)
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


def band_cells(geometry: MapGeometry, pts: np.ndarray, nrm: np.ndarray, steps: np.ndarray,
               behind_m: float) -> np.ndarray:
    """The coarse cells (n, 3) that the points' bands reach, in (x, y, z) order, for sizing
    the pools: the blocks of each patch's corner columns at their ends and middle (a band
    shorter than a block crosses at most the blocks between those; a rare miss is caught by
    the pools' overflow and retry). One int64 key per sample, made unique per chunk, so
    memory stays a few bytes a point."""
    dims = np.asarray(geometry.coarse_dims, np.int64)
    origin = np.asarray(geometry.origin_m, np.float32)
    inv = np.float32(1.0 / geometry.voxel_size_m)
    depths = np.float32([-behind_m, 0.5 * (geometry.truncation_m - behind_m),
                         geometry.truncation_m])
    keys = [np.zeros(0, np.int64)]
    for s in range(0, len(pts), CHUNK_CELLS):
        p, n = (pts[s:s + CHUNK_CELLS] - origin) * inv, nrm[s:s + CHUNK_CELLS]
        half = 0.5 * steps[s:s + CHUNK_CELLS].astype(np.float32)[:, None]
        e1, e2 = _tangents(n)
        for a, b in ((0, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)):
            base = p + half * (a * e1 + b * e2) if a else p
            for d in depths:
                g = np.floor(base + (d * inv) * n).astype(np.int64) >> 3
                keys.append(unique_keys(cell_keys(np.clip(g, 0, dims - 1), dims)))
        keys = [unique_keys(np.concatenate(keys))]
    k = keys[0]
    return np.stack([k // (dims[1] * dims[2]), (k // dims[2]) % dims[1], k % dims[2]], axis=1)


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """tsdf_band.tangent_basis for (n, 3) unit normals."""
    a = np.zeros_like(n)
    use_y = np.abs(n[:, 0]) > 0.9
    a[~use_y, 0], a[use_y, 1] = 1.0, 1.0
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _points_map(geometry: MapGeometry, config: BuildConfig, allocate, needed: int, tiles: int,
                reuse: TsdfMap | None = None) -> TsdfMap:
    """A writable map with the points' blocks allocated (`allocate(map)`), its pools sized
    to `needed` blocks and `tiles` tiles (or `reuse`, cleared, when given); should a pool
    still overflow, it is grown and the allocation run again (three tries, then the
    capacity error names what is needed)."""
    for attempt in range(3):
        if attempt == 0 and reuse is not None:
            tsdf = reuse
            tsdf.clear()
            tsdf.as_sums = True
        else:
            tsdf = new_map(geometry, config, needed, tiles)
        tsdf.relaunch_until_placed(lambda m=tsdf: allocate(m))
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
    tree = cKDTree(pts)
    free = np.zeros(len(cells), bool)
    for s in range(0, len(cells), FREE_CHUNK_CELLS):  # a city's temporaries: chunk by chunk
        centers = np.asarray(g.origin_m) + (cells[s:s + FREE_CHUNK_CELLS] + 0.5) * g.block_size_m
        dist, idx = tree.query(centers, k=8, workers=-1)
        side = np.einsum("ckj,ckj->ck", centers[:, None, :] - pts[idx], nrm[idx])
        clear = dist[:, 0] >= config.trunc_m + 0.5 * np.sqrt(3) * g.block_size_m
        free[s:s + FREE_CHUNK_CELLS] = clear & ((side > 0).sum(axis=1) >= 6)
    tsdf.mark_free(cells[free])
