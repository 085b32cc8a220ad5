"""The coarse search field of a global start, sparse: its memory grows with the map's surface.

A global search first scores particles on the distance from each scan point to the nearest
surface (docs/sensor-model.md, "a coarse model first"). The field holds, per cell of
`cell_m`, a code: the bin of that distance below `coarse_max_dist_m`, else "observed, far
from surfaces" or "unknown". Only cells within `coarse_max_dist_m` of a surface, or in
blocks the map holds voxels for, differ from one constant per map block, so the field is
stored like the map (docs/sparse-maps.md): one **brick** of k³ codes (k cells per block
along an axis) per map block that needs one, and one slot per map block naming its brick
or one of two constant bricks (unknown, observed-far). Blocks that have no slot read the
unknown brick. A dense grid over the bounds (the field before) cannot be allocated for a
kilometre of street at 5 cm voxels.

The distances are exact (scipy's Euclidean distance transform between cell centres), computed
window by window over the blocks that need a brick, each window with a halo of
`coarse_max_dist_m`: host memory grows with the surface too. NumPy and scipy only; the device
copy lives in mcl3d.localization.weighing and is read by
mcl3d.kernels.likelihood.coarse_scan_log_likelihood.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.ndimage import distance_transform_edt

from mcl3d.core.geometry import quat_to_rot
from mcl3d.localization.sensor_model import BLOCK, FREE, SensorModelConfig
from mcl3d.maps.sparse_cells import CellLookup, cell_keys, dilate_cells, unique_keys

COARSE_BINS = 256  # mcl3d.kernels.likelihood.COARSE_BINS: then far-free, then unknown
COARSE_FAR_FREE = COARSE_BINS
COARSE_UNKNOWN = COARSE_BINS + 1
UNKNOWN_BRICK = 0  # brick 0: every cell unknown (blocks without a slot read it)
FAR_FREE_BRICK = 1  # brick 1: every cell observed and far from surfaces
MAX_COARSE_CELLS = 16_000_000  # cells of the bounds before the cell grows (see coarse_field)
WINDOW_CELLS = 64  # a distance-transform window's interior, cells along an axis


@dataclass
class CoarseField:
    """The field on the host: codes per cell (COARSE_BINS distance bins over
    [0, max_dist_m), COARSE_FAR_FREE for observed cells farther, COARSE_UNKNOWN for unknown
    cells farther and outside the bounds); cell (i, j, l) lies in map block (i, j, l) // k."""

    origin_m: np.ndarray  # (3,) the map's origin: cell i covers origin + [i, i+1) cells
    cell_m: float
    max_dist_m: float
    cells_per_block: int  # k
    coarse_dims: np.ndarray  # (3,) the map's bounds, in blocks
    block_coords: np.ndarray  # (n, 3) int32 the blocks with a slot
    block_slots: np.ndarray  # (n,) int32 their brick: FAR_FREE_BRICK or >= 2
    bricks: np.ndarray  # (n_bricks, k, k, k) int32 codes; bricks 0 and 1 are constant

    @cached_property
    def _slots(self) -> CellLookup:
        return CellLookup(self.block_coords, self.block_slots, self.coarse_dims)

    def codes_at(self, cells: np.ndarray) -> np.ndarray:
        """Codes of the cells (..., 3) (any integer coordinates)."""
        g = np.asarray(cells, dtype=np.int64)
        k = self.cells_per_block
        slot = np.maximum(self._slots(g // k), UNKNOWN_BRICK)  # no slot (-1): unknown
        local = g % k
        return self.bricks[slot, local[..., 0], local[..., 1], local[..., 2]]


@dataclass
class _BlockMasks:
    """The map's allocated blocks at the field's cells, sorted by cell key."""

    coords: np.ndarray  # (n, 3) int32
    keys: np.ndarray  # (n,) int64 sorted
    observed: np.ndarray  # (n, k, k, k) bool: a voxel of the cell was observed
    surface: np.ndarray  # (n, k, k, k) bool: a surface crosses the cell


def _block_masks(tsdf, f: int) -> _BlockMasks:
    """A cell of f³ voxels is observed when one of its voxels is (weight > 0, or a distance
    below the truncation: never-observed voxels hold +truncation), a surface cell when an
    observed voxel holds |d| at most half a voxel diagonal. Reads the blocks a chunk at a time."""
    k = BLOCK // f
    trunc = np.float32(tsdf.truncation_m)
    half_diag = np.float32(0.5 * np.sqrt(3) * tsdf.voxel_size_m)
    coords, observed, surface = [np.zeros((0, 3), np.int32)], [], []
    for c, d, w in tsdf.block_chunks():
        shape = (len(c), k, f, k, f, k, f)
        obs = (w > 0) | (d < trunc * np.float32(0.999))
        surf = obs & (np.abs(d) <= half_diag)
        coords.append(c)
        observed.append(obs.reshape(shape).any(axis=(2, 4, 6)))
        surface.append(surf.reshape(shape).any(axis=(2, 4, 6)))
    empty = np.zeros((0, k, k, k), bool)
    coords = np.concatenate(coords)
    keys = cell_keys(coords, tsdf.coarse_dims)
    order = np.argsort(keys, kind="stable")
    return _BlockMasks(coords[order], keys[order], np.concatenate([empty, *observed])[order],
                       np.concatenate([empty, *surface])[order])


def finest_factor(voxel_size_m: float, cfg: SensorModelConfig) -> int:
    """Voxels per field cell along an axis from coarse_cell_m (a power of two, at most 8)."""
    f = 1
    while f < BLOCK and voxel_size_m * f * 2 <= cfg.coarse_cell_m + 1e-9:
        f *= 2
    return f


def reach_cells(cfg: SensorModelConfig, cell_m: float) -> int:
    """Cells along an axis within which a surface cell can be nearer than max_dist (one
    spare cell against rounding)."""
    return int(np.floor(cfg.coarse_max_dist_m / cell_m)) + 1


def _near_blocks(blocks: _BlockMasks, dims, reach_blocks: int) -> np.ndarray:
    """Sorted keys of the blocks that may need a brick: the allocated ones and those within
    `reach_blocks` (a cube) of a block holding a surface cell."""
    surface_blocks = blocks.coords[blocks.surface.any(axis=(1, 2, 3))]
    near = dilate_cells(surface_blocks, reach_blocks, dims)
    return unique_keys(np.concatenate([blocks.keys, cell_keys(near, dims)]))


def coarse_field(tsdf, cfg: SensorModelConfig) -> CoarseField:
    """The map's coarse distance field. Distances are Euclidean between cell centres to the
    nearest surface cell; unknown cells near surfaces (just behind a wall) keep their
    distance, so a pose slightly off still scores by how far off it is. Cells are
    coarse_cell_m (a power of two of voxels), coarsened while the bounds hold more than
    MAX_COARSE_CELLS of them (at most to one cell per block): the rule of the dense field this
    one replaced, so the codes are the same wherever that one could be built (finer cells
    within the same memory measured up to 2.5x slower lookups on a street map)."""
    dims = np.asarray(tsdf.coarse_dims, np.int64)
    f = finest_factor(tsdf.voxel_size_m, cfg)
    while f < BLOCK and tsdf.geometry.n_cells * (BLOCK // f) ** 3 > MAX_COARSE_CELLS:
        f *= 2
    k = BLOCK // f
    reach = reach_cells(cfg, tsdf.voxel_size_m * f)
    blocks = _block_masks(tsdf, f)
    near = _near_blocks(blocks, dims, -(-reach // k))
    cells, values = tsdf.coarse_cells()
    free_keys = unique_keys(cell_keys(cells[values == FREE], dims))
    cell_m = float(tsdf.voxel_size_m * f)
    coords, slots, bricks = _bricks(blocks, free_keys, near, dims, cell_m, reach, cfg)
    far_free = free_keys[~_find(near, free_keys)[0]]
    coords = np.concatenate([coords, _coords_of(far_free, dims)])
    slots = np.concatenate([slots, np.full(len(far_free), FAR_FREE_BRICK, np.int32)])
    return CoarseField(np.asarray(tsdf.origin_m, np.float64), cell_m, cfg.coarse_max_dist_m, k,
                       dims, coords.astype(np.int32), slots, bricks)


def _coords_of(keys: np.ndarray, dims) -> np.ndarray:
    """Block coordinates (n, 3) int32 of cell_keys."""
    return np.stack([keys // (dims[1] * dims[2]), (keys // dims[2]) % dims[1], keys % dims[2]],
                    axis=1).astype(np.int32).reshape(-1, 3)


class _SurfaceByWindow:
    """The allocated blocks holding surface cells, grouped by window of `size` blocks: the
    rows whose surface cells a window's distance transform sees (window plus halo)."""

    STEPS = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)

    def __init__(self, blocks: _BlockMasks, size: int, wdims: np.ndarray):
        rows = np.flatnonzero(blocks.surface.any(axis=(1, 2, 3)))
        wkeys = cell_keys(blocks.coords[rows] // size, wdims)
        order = np.argsort(wkeys, kind="stable")
        self.rows, self.wkeys = rows[order], wkeys[order]
        self.wdims, self.coords = wdims, blocks.coords

    def rows_in(self, window: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Rows of the blocks in [lo, hi) (at most one window beyond `window` each way)."""
        neighbours = window + self.STEPS
        ok = np.all((neighbours >= 0) & (neighbours < self.wdims), axis=1)
        keys = cell_keys(neighbours[ok], self.wdims)
        starts = np.searchsorted(self.wkeys, keys, "left")
        ends = np.searchsorted(self.wkeys, keys, "right")
        rows = np.concatenate([self.rows[a:b] for a, b in zip(starts, ends, strict=True)])
        return rows[np.all((self.coords[rows] >= lo) & (self.coords[rows] < hi), axis=1)]


def _bricks(blocks: _BlockMasks, free_keys, near_keys, dims, cell_m: float, reach: int,
            cfg: SensorModelConfig):
    """(coords (n, 3), slots (n,), bricks) of the near blocks whose codes are not all
    unknown; blocks whose codes are all observed-far get FAR_FREE_BRICK. Windows of
    WINDOW_CELLS cells (at least the halo) along an axis, in key order."""
    k = blocks.observed.shape[1]
    halo = -(-reach // k)
    size = max(-(-WINDOW_CELLS // k), halo)  # blocks along a window's side: halo <= size
    wdims = -(-dims // size)
    surface = _SurfaceByWindow(blocks, size, wdims)
    near = _coords_of(near_keys, dims)
    near_wkeys = cell_keys(near // size, wdims)
    order = np.argsort(near_wkeys, kind="stable")
    changes = np.r_[True, near_wkeys[order][1:] != near_wkeys[order][:-1]]
    starts = np.flatnonzero(changes)[:len(order)]  # none when no block is near
    out_coords, out_slots = [np.zeros((0, 3), np.int32)], [np.zeros(0, np.int32)]
    bricks = [np.full((1, k, k, k), COARSE_UNKNOWN, np.int32),
              np.full((1, k, k, k), COARSE_FAR_FREE, np.int32)]
    n_bricks = 2
    for s, e in itertools.pairwise([*starts, len(order)]):
        rows = order[s:e]
        window = near[rows[0]] // size
        lo = np.maximum(window * size - halo, 0)
        hi = np.minimum((window + 1) * size + halo, dims)
        dist = _window_distances(blocks, surface.rows_in(window, lo, hi), lo, hi, cell_m)
        codes = _codes(blocks, free_keys, near[rows], near_keys[rows], dist, lo, cfg)
        unknown = np.all(codes == COARSE_UNKNOWN, axis=(1, 2, 3))
        far_free = np.all(codes == COARSE_FAR_FREE, axis=(1, 2, 3))
        own = ~unknown & ~far_free
        slots = np.where(far_free, FAR_FREE_BRICK, 0).astype(np.int32)
        slots[own] = n_bricks + np.arange(own.sum(), dtype=np.int32)
        n_bricks += int(own.sum())
        bricks.append(codes[own])
        out_coords.append(near[rows][~unknown])
        out_slots.append(slots[~unknown])
    return np.concatenate(out_coords), np.concatenate(out_slots), np.concatenate(bricks)


def _local_cells(k: int) -> np.ndarray:
    """The k³ cell offsets (k³, 3) of a block, C order."""
    return np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)


def _window_distances(blocks: _BlockMasks, src: np.ndarray, lo, hi, cell_m: float):
    """Distances (float32, m) from each cell of blocks [lo, hi) to the nearest surface cell
    of the blocks `src` (rows), or None when they hold none."""
    if not blocks.surface[src].any():
        return None
    k = blocks.surface.shape[1]
    surface = np.zeros((hi - lo) * k, bool)
    at = ((blocks.coords[src] - lo) * k)[:, None, :] + _local_cells(k)[None]
    surface[at[..., 0], at[..., 1], at[..., 2]] = blocks.surface[src].reshape(len(src), -1)
    return distance_transform_edt(~surface, sampling=cell_m).astype(np.float32)


def _find(sorted_keys: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(found, row) of each key in sorted, distinct keys (row valid where found)."""
    if len(sorted_keys) == 0:
        return np.zeros(len(keys), bool), np.zeros(len(keys), np.int64)
    row = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[row] == keys, row


def _codes(blocks: _BlockMasks, free_keys, coords, keys, dist, lo, cfg: SensorModelConfig
           ) -> np.ndarray:
    """The codes (n, k, k, k) of the blocks `coords` (keys) of a window starting at `lo`."""
    k = blocks.observed.shape[1]
    allocated, row = _find(blocks.keys, keys)
    observed = np.zeros((len(coords), k, k, k), bool)
    observed[allocated] = blocks.observed[row[allocated]]
    observed[_find(free_keys, keys)[0]] = True
    if dist is None:
        d = np.full((len(coords), k, k, k), np.inf, np.float32)
    else:
        at = ((coords - lo) * k)[:, None, :] + _local_cells(k)[None]
        d = dist[at[..., 0], at[..., 1], at[..., 2]].reshape(len(coords), k, k, k)
    near = d < cfg.coarse_max_dist_m
    codes = np.where(near, np.minimum(d * (COARSE_BINS / cfg.coarse_max_dist_m),
                                      COARSE_BINS - 1), 0).astype(np.int32)
    codes[~near & observed] = COARSE_FAR_FREE
    codes[~near & ~observed] = COARSE_UNKNOWN
    return codes


def coarse_table(cfg: SensorModelConfig, sigma_m: float) -> np.ndarray:
    """Log-likelihood per coarse code: the hit term at the bin centres, then observed free
    far from surfaces (log p_free), then unknown (log p_unknown)."""
    d = (np.arange(COARSE_BINS) + 0.5) * (cfg.coarse_max_dist_m / COARSE_BINS)
    hit = np.log(cfg.z_hit * np.exp(-0.5 * (d / sigma_m) ** 2) + cfg.z_rand)
    return np.concatenate([hit, [cfg.log_free, cfg.log_unknown]]).astype(np.float32)


def coarse_match_codes(cfg: SensorModelConfig) -> int:
    """Codes below this count as a surface match (distance under match_dist_m)."""
    return int(np.ceil(cfg.match_dist_m * COARSE_BINS / cfg.coarse_max_dist_m))


def coarse_log_likelihood_numpy(field: CoarseField, positions: np.ndarray,
                                quats_xyzw: np.ndarray, points: np.ndarray,
                                table: np.ndarray, match_codes: int, tempering: float
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy twin of mcl3d.kernels.likelihood.coarse_scan_log_likelihood: (tempered
    increment, match ratio, mean per-point ll) per particle."""
    R = quat_to_rot(quats_xyzw.astype(np.float64)).astype(np.float32)
    p = np.einsum("nij,mj->nmi", R, points.astype(np.float32)) + positions[:, None, :]
    g = np.floor((p - field.origin_m.astype(np.float32)) / np.float32(field.cell_m)
                 ).astype(np.int64)
    code = field.codes_at(g)
    ll = table[code].astype(np.float64)
    m = max(len(points), 1)
    return tempering * ll.sum(axis=1), (code < match_codes).mean(axis=1), ll.sum(axis=1) / m
