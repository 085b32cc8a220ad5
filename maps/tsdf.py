"""The two-level TSDF container: a sparse coarse index of block ids + a pool of 8³ blocks.

The container owns the Taichi fields (allocated once, from the capacities given) and the
map's geometry; the kernels that read and write them live in mcl3d.kernels.tsdf_* and take
the container as a template argument, so lookups compile to plain field reads on every
backend. Geometry (voxel size, truncation, origin, bounds) is fixed at construction. The
origin and bounds are held in 0-d fields that kernels read at run time, and a writable
map's fields come in power-of-two sizes (`field_slots`): Taichi's offline cache keys a
kernel on its IR and the shapes of the fields it touches, so a build of a map of another
size or origin (same voxel size and truncation, compile-time constants) reuses the fusion
kernels compiled by an earlier one (~25 s on 2 cores) instead of compiling them again.

The coarse index (one cell per 8³-voxel block: its pool id, or unknown / free) is sparse,
made of dense fields only, since Vulkan rejects Taichi's pointer and dynamic SNodes: a top
grid of tile ids over the map's bounds, one per 8³ coarse cells, and a pool of tiles, each a
dense 8³ index of cells, claimed on demand by an atomic flag and counter as blocks are. We
chose tiles over a hashed index because a lookup stays two dependent reads with no probing
(the likelihood does one per point per particle) and allocation keeps the blocks' one-winner
scheme; the price is the top grid, 8 bytes per (3.2 m)³ of bounds at 5 cm voxels (12 MiB
for 1 km x 1 km x 50 m, where the dense index took 6 GiB). Memory then grows with observed
space: a tile (4 KiB) exists where a block was allocated or a cell observed free, so it grows
with the surface plus the free space carved around it (within a tile of the rays), not with
the bounds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import taichi as ti

from mcl3d.core import runtime
from mcl3d.core.errors import ConfigError, MapError
from mcl3d.kernels import tsdf_blocks, tsdf_fusion
from mcl3d.kernels.tsdf_band import max_band_samples
from mcl3d.kernels.tsdf_lookup import BLOCK, FREE, TILE, UNKNOWN
from mcl3d.maps.sparse_cells import tiles_of

VOXELS_PER_BLOCK = BLOCK**3
CELLS_PER_TILE = TILE**3
CHUNK_BLOCKS = 8192  # blocks per launch: 8192 * 512 = 4M iterations, under Vulkan's 8M limit
CHUNK_CELLS = 4 << 20  # coarse cells per launch and points per launch
TOP_CELL_BYTES = 8  # tile id + claim flag
TILE_BYTES = CELLS_PER_TILE * 8 + 12  # cells + claim flags, and the tile's coordinate
DENSE_CELL_BYTES = 8  # the former dense coarse grid: block id + allocation flag per cell
MIN_BUILD_TILES = 1024
# the smallest field sizes of a writable map (slots of blocks, tiles, top-grid cells): under
# them maps share one size (a few MiB at most), above them sizes go in powers of two
MIN_POOL_SLOTS = 1024
MIN_TILE_SLOTS = MIN_BUILD_TILES
MIN_TOP_SLOTS = 4096


def field_slots(n: int, floor: int, writable: bool) -> int:
    """Slots a field holds for n entries: a writable map's sizes are rounded up to a power
    of two (at least `floor`) so that the kernels compiled for one map serve maps of other
    sizes (Taichi compiles per field shape); a read-only map's are exact (no memory spent:
    its kernels, the likelihood's, compile per map anyway)."""
    n = max(int(n), 1)
    return max(1 << (n - 1).bit_length(), floor) if writable else n


@dataclass(frozen=True)
class MapGeometry:
    """Where the map is: voxel i covers origin + [i, i+1) voxels along each axis."""

    voxel_size_m: float
    truncation_m: float
    origin_m: tuple[float, float, float]
    coarse_dims: tuple[int, int, int]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.voxel_size_m) and self.voxel_size_m > 0):
            raise ConfigError(f"voxel size must be > 0 m, got {self.voxel_size_m}")
        if not (np.isfinite(self.truncation_m) and self.truncation_m >= self.voxel_size_m):
            raise ConfigError(
                f"truncation ({self.truncation_m} m) must be at least one voxel "
                f"({self.voxel_size_m} m)")
        if len(self.coarse_dims) != 3 or min(self.coarse_dims) < 1:
            raise ConfigError(f"coarse grid dims must be 3 positive ints, got {self.coarse_dims}")
        if not np.all(np.isfinite(self.origin_m)):
            raise ConfigError(f"map origin must be finite, got {self.origin_m}")

    @property
    def block_size_m(self) -> float:
        return self.voxel_size_m * BLOCK

    @property
    def n_cells(self) -> int:
        """Coarse cells within the bounds (most of them unknown)."""
        return int(np.prod(self.coarse_dims))

    @property
    def top_dims(self) -> tuple[int, int, int]:
        """The top grid of the coarse index: one tile per TILE³ coarse cells."""
        return tuple(-(-int(d) // TILE) for d in self.coarse_dims)

    @property
    def n_top_cells(self) -> int:
        return int(np.prod(self.top_dims))

    @property
    def extent_m(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.asarray(self.origin_m, dtype=np.float64)
        return lo, lo + np.asarray(self.coarse_dims) * self.block_size_m

    @staticmethod
    def around(lo_m, hi_m, voxel_size_m: float, truncation_m: float,
               margin_m: float = 0.0) -> MapGeometry:
        """The block-aligned geometry covering the box [lo, hi] plus a margin."""
        lo = np.asarray(lo_m, dtype=np.float64) - margin_m
        hi = np.asarray(hi_m, dtype=np.float64) + margin_m
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
            raise ConfigError(f"cannot build a map over the bounds {lo} .. {hi}")
        block = voxel_size_m * BLOCK
        origin = np.round(np.floor(lo / block) * block, 9)
        dims = np.maximum(np.ceil((hi - origin) / block).astype(np.int64), 1)
        if np.prod(-(-dims // TILE)) > 2**28 or np.any(dims * BLOCK >= 2**30):
            raise ConfigError(
                f"the map bounds {lo.round(1)} .. {hi.round(1)} m need {dims.tolist()} blocks of "
                f"{block} m: too large; use a larger voxel size or crop the input")
        return MapGeometry(float(voxel_size_m), float(truncation_m),
                           tuple(float(x) for x in origin), tuple(int(x) for x in dims))


def _require_runtime() -> None:
    if runtime.current() is None:
        raise MapError("the Taichi runtime is not started; "
                       "call mcl3d.core.runtime.init(backend) first")


@dataclass
class BlockData:
    """Allocated blocks on the host: coordinates, distances, weights, plus FREE blocks."""

    coords: np.ndarray  # (n, 3) int32 block coordinates
    sdf: np.ndarray  # (n, 8, 8, 8) float32 (or float16) signed distances in m
    weight: np.ndarray  # (n, 8, 8, 8) float32 observation weights (0 = unknown)
    free_coords: np.ndarray  # (k, 3) int32 blocks observed free of surfaces

    def sorted(self) -> BlockData:
        """Blocks in lexicographic coordinate order (deterministic files)."""
        order = np.lexsort(self.coords.T[::-1]) if len(self.coords) else np.arange(0)
        forder = (np.lexsort(self.free_coords.T[::-1]) if len(self.free_coords)
                  else np.arange(0))
        return dataclasses.replace(self, coords=self.coords[order], sdf=self.sdf[order],
                                   weight=self.weight[order],
                                   free_coords=self.free_coords[forder])


def _data_oriented(cls):
    """ti.data_oriented without its `__getattribute__` wrapper, which serves kernels defined
    as methods (this class has none) and costs a Python call on every attribute read.

    Taichi keys template-kernel instances of data-oriented objects by weak reference, so a
    map's instances die with it; a new map's come from Taichi's kernel cache when its fields
    have the shapes of an earlier map's (field_slots) and compile otherwise.
    """
    cls._data_oriented = True
    return cls


@_data_oriented
class TsdfMap:
    """A TSDF on the device; build with mcl3d.maps.build, load with mcl3d.maps.map_file.

    `f16` stores distances (and weights) in half precision: half the memory for read-only
    localization maps. A `writable` map (one being built) also holds its free-space hits
    and (but on Vulkan) the fixed-point sums of fusion: 28 bytes a voxel instead of 8 (f32)
    or 4 (f16). `capacity_tiles` sizes the coarse index's tile pool (default: a tile per
    block of capacity, at least MIN_BUILD_TILES; never more than one per top-grid cell).
    """

    def __init__(self, geometry: MapGeometry, capacity_blocks: int, *, f16: bool = False,
                 writable: bool = True, frame_id: str = "map",
                 capacity_tiles: int | None = None):
        _require_runtime()
        if capacity_blocks < 1:
            raise ConfigError(f"map capacity must be >= 1 block, got {capacity_blocks}")
        if capacity_tiles is None:
            capacity_tiles = max(capacity_blocks, MIN_BUILD_TILES)
        self.geometry = geometry
        self.frame_id = frame_id
        self.voxel_size_m = float(geometry.voxel_size_m)
        self.truncation_m = float(geometry.truncation_m)
        self.origin_m = tuple(float(x) for x in geometry.origin_m)
        self.coarse_dims = tuple(int(x) for x in geometry.coarse_dims)
        self.top_dims = geometry.top_dims
        self.capacity = int(capacity_blocks)
        self.tile_capacity = max(1, min(int(capacity_tiles), geometry.n_top_cells))
        self.f16 = bool(f16)
        if f16 and writable:
            raise ConfigError("an f16 map is read-only: build in f32, store with f16 "
                              "distances")
        self.writable = bool(writable)
        # field sizes (>= the capacities, which kernels read at run time)
        self.pool_slots = field_slots(self.capacity, MIN_POOL_SLOTS, self.writable)
        self.tile_slots = field_slots(self.tile_capacity, MIN_TILE_SLOTS, self.writable)
        self.top_slots = field_slots(geometry.n_top_cells, MIN_TOP_SLOTS, self.writable)
        # band samples a point may have (ti.static in tsdf_band): the truncation in voxels
        self.band_slots = max_band_samples(self.truncation_m, self.voxel_size_m)
        self.header: dict | None = None  # the file header when loaded from a file
        self.as_sums = False  # True while being built: the pool holds sums, not distances
        dtype = ti.f16 if f16 else ti.f32
        builder = ti.FieldsBuilder()
        self._place_coarse_index(builder)
        self._place_geometry(builder)
        self.block_count = ti.field(ti.i32)
        builder.place(self.block_count)
        self.block_coord = ti.Vector.field(3, ti.i32)
        self.block_free = ti.field(ti.i32)
        builder.dense(ti.i, self.pool_slots).place(self.block_coord, self.block_free)
        self.sdf = ti.field(dtype)
        self.weight = ti.field(dtype)
        pool = builder.dense(ti.i, self.pool_slots).dense(ti.jkl, BLOCK)
        pool.place(self.sdf)
        pool.place(self.weight)
        # fixed-point build sums (kernels.tsdf_lookup), except on Vulkan: Mesa's lavapipe
        # loses integer atomic adds in the band's patch loop (float ones arrive), so there the
        # pool sums floats as before, in whatever order the threads add
        self.exact_sums = writable and runtime.current().backend != "vulkan"
        self._trees = [self._place_sums()] if self.exact_sums else []
        if writable:  # its own array: the band's distance and weight stay packed
            self.free_hits = ti.field(ti.f32)
            builder.dense(ti.i, self.pool_slots).dense(ti.jkl, BLOCK).place(self.free_hits)
        self._trees.append(builder.finalize())
        self._used_slots = 0  # pool slots [used, capacity) still hold zeros (never written)
        tsdf_blocks.set_geometry(self, self.origin_m, self.coarse_dims, self.top_dims,
                                 self.capacity, self.tile_capacity)
        self.clear()

    def _place_coarse_index(self, builder) -> None:
        """The top grid (flat, tsdf_lookup.top_index) and the tile pool (tsdf_lookup); ids
        and claim flags in separate arrays, so that lookups read only ids."""
        self.tile_of, self.tile_flag = ti.field(ti.i32), ti.field(ti.i32)
        builder.dense(ti.i, self.top_slots).place(self.tile_of)
        builder.dense(ti.i, self.top_slots).place(self.tile_flag)
        self.cells, self.cell_flag = ti.field(ti.i32), ti.field(ti.i32)
        builder.dense(ti.i, self.tile_slots).dense(ti.jkl, TILE).place(self.cells)
        builder.dense(ti.i, self.tile_slots).dense(ti.jkl, TILE).place(self.cell_flag)
        self.tile_coord = ti.Vector.field(3, ti.i32)
        builder.dense(ti.i, self.tile_slots).place(self.tile_coord)
        self.tile_count, self.tile_misses = ti.field(ti.i32), ti.field(ti.i32)
        builder.place(self.tile_count, self.tile_misses)

    def _place_geometry(self, builder) -> None:
        """The geometry, read by the kernels at run time (tsdf_lookup; set_geometry)."""
        self.geo_origin = ti.Vector.field(3, ti.f32)
        self.geo_dims, self.geo_top = ti.Vector.field(3, ti.i32), ti.Vector.field(3, ti.i32)
        self.geo_caps = ti.Vector.field(2, ti.i32)
        builder.place(self.geo_origin, self.geo_dims, self.geo_top, self.geo_caps)

    def _place_sums(self):
        """The i64 build sums in a tree of their own, so that they start at byte 0 (8-byte
        atomics need 8-byte alignment; the main tree's i32 fields come first)."""
        builder = ti.FieldsBuilder()
        self.sum_w, self.sum_wd = ti.field(ti.i64), ti.field(ti.i64)
        builder.dense(ti.i, self.pool_slots).dense(ti.jkl, BLOCK).place(self.sum_w, self.sum_wd)
        return builder.finalize()

    # ------------------------------------------------------------------ bookkeeping
    def clear(self) -> None:
        """Every cell unknown, no tile claimed, no block allocated, every pool slot zero
        again (tiles and slots ever used; the others never held anything else)."""
        n = self.geometry.n_top_cells
        for start in range(0, n, CHUNK_CELLS):
            tsdf_blocks.zero_top(self, start, min(CHUNK_CELLS, n - start))
        tiles = self.n_tiles
        for start in range(0, tiles, CHUNK_BLOCKS):
            tsdf_blocks.zero_tiles(self, start, min(CHUNK_BLOCKS, tiles - start))
        used = max(self._used_slots, self.n_blocks)
        for start in range(0, used, CHUNK_BLOCKS):
            tsdf_blocks.zero_blocks(self, start, min(CHUNK_BLOCKS, used - start))
        self._used_slots = 0
        tsdf_blocks.reset_count(self)

    def destroy(self) -> None:
        """Free the device memory now (the object is unusable afterwards)."""
        for tree in self._trees:
            tree.destroy()
        self._trees = []

    @property
    def requested_blocks(self) -> int:
        """Blocks asked for so far, including those that did not fit."""
        return int(self.block_count[None])

    @property
    def n_blocks(self) -> int:
        return min(self.requested_blocks, self.capacity)

    @property
    def requested_tiles(self) -> int:
        """Tiles of the coarse index claimed so far, including those that did not fit."""
        return int(self.tile_count[None])

    @property
    def n_tiles(self) -> int:
        return min(self.requested_tiles, self.tile_capacity)

    @property
    def overflowed(self) -> bool:
        """Blocks or tiles did not fit: the map is incomplete."""
        return (self.requested_blocks > self.capacity
                or self.requested_tiles > self.tile_capacity)

    def check_capacity(self) -> None:
        if self.requested_tiles > self.tile_capacity:
            raise MapError(
                f"the map's coarse index needs {self.requested_tiles} tiles but its capacity "
                f"is {self.tile_capacity}; allow at least "
                f"{int(self.requested_tiles * 1.1) + 1} tiles or use a larger voxel size",
                setting="capacity_tiles")
        if self.requested_blocks > self.capacity:
            raise MapError(
                f"the map needs {self.requested_blocks} blocks but its capacity is "
                f"{self.capacity}; allow at least {int(self.requested_blocks * 1.1) + 1} "
                f"blocks or use a larger voxel size", setting="max_capacity_blocks")

    def relaunch_until_placed(self, launch) -> None:
        """Run `launch()` (idempotent kernel launches that claim tiles) again while a thread
        found its tile claimed by another thread of the same launch (tsdf_blocks)."""
        tsdf_blocks.take_misses(self)
        for _ in range(64):
            launch()
            if tsdf_blocks.take_misses(self) == 0:
                return
        raise MapError("tiles of the coarse index were still contended after 64 launches; "
                       "this is a bug, please report it")

    def init_new_blocks(self, start: int, end: int) -> None:
        """Initialize pool slots [start, end) after an allocation launch.

        While building (sums) a never written slot already holds its initial state, zeros
        (Taichi zero-fills fields; a FREE block's mark is set by allocate_block), so only
        reused slots (after `clear`) need the init pass.
        """
        end = min(end, self.capacity)
        stop = min(end, self._used_slots) if self.as_sums else end
        for s in range(start, stop, CHUNK_BLOCKS):
            tsdf_blocks.init_blocks(self, s, min(CHUNK_BLOCKS, stop - s), int(self.as_sums))
        self._used_slots = max(self._used_slots, end)

    def finalize(self) -> None:
        """Turn build-time sums into distances; the map is then ready for queries."""
        if not self.as_sums:
            return
        n = self.n_blocks
        for kernel in (tsdf_fusion.finalize_blocks, tsdf_fusion.refine_free_voxels,
                       tsdf_fusion.unmark_free_voxels):
            for s in range(0, n, CHUNK_BLOCKS):
                kernel(self, s, min(CHUNK_BLOCKS, n - s))
        self.as_sums = False

    # ---------------------------------------------------------------- host transfer
    def allocate(self, coords: np.ndarray) -> None:
        """Allocate the given block coordinates (n, 3) and initialize the new blocks."""
        self._each_chunk(tsdf_blocks.allocate_coords, coords)

    def mark_free(self, coords: np.ndarray) -> None:
        """Cells (n, 3) observed free of surfaces: unknown ones become FREE."""
        self._each_chunk(tsdf_blocks.mark_free_coords, coords)

    def _each_chunk(self, kernel, coords: np.ndarray) -> None:
        """`kernel(self, part, n)` over chunks of coords until every cell found its tile;
        new blocks initialized, capacity checked."""
        coords = np.ascontiguousarray(coords, dtype=np.int32).reshape(-1, 3)
        before = self.requested_blocks

        def launch():
            for s in range(0, len(coords), CHUNK_CELLS):
                part = coords[s:s + CHUNK_CELLS]
                kernel(self, part, len(part))

        self.relaunch_until_placed(launch)
        self.init_new_blocks(before, self.requested_blocks)
        self.check_capacity()

    def write_blocks(self, coords: np.ndarray, sdf: np.ndarray, weight: np.ndarray) -> None:
        """Set values of allocated blocks (coords (n,3), sdf/weight (n,8,8,8))."""
        coords = np.ascontiguousarray(coords, dtype=np.int32).reshape(-1, 3)
        for s in range(0, len(coords), CHUNK_BLOCKS):
            e = min(s + CHUNK_BLOCKS, len(coords))
            tsdf_blocks.write_blocks(self, coords[s:e],
                           np.ascontiguousarray(sdf[s:e], dtype=np.float32),
                           np.ascontiguousarray(weight[s:e], dtype=np.float32), e - s)

    def coarse_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """The known coarse cells, sparse: (coords (n, 3) int32, values (n,) int32: block
        id, FREE or OVERFLOW); every other cell is UNKNOWN."""
        coords, values = [], []
        n = self.n_tiles
        local = np.stack(np.meshgrid(*[np.arange(TILE)] * 3, indexing="ij"), axis=-1)
        for s in range(0, n, CHUNK_BLOCKS):
            e = min(s + CHUNK_BLOCKS, n)
            tc = np.zeros((e - s, 3), np.int32)
            cells = np.zeros((e - s, TILE, TILE, TILE), np.int32)
            tsdf_blocks.read_tiles(self, s, e - s, tc, cells)
            known = cells != UNKNOWN
            coords.append((tc.astype(np.int64)[:, None, None, None, :] * TILE + local)[known])
            values.append(cells[known])
        if not coords:
            return np.zeros((0, 3), np.int32), np.zeros(0, np.int32)
        return (np.concatenate(coords).astype(np.int32), np.concatenate(values))

    def block_chunks(self):
        """The allocated blocks in pool order, CHUNK_BLOCKS at a time, as (coords (n, 3)
        int32, sdf, weight (n, 8, 8, 8) float32): host users that reduce each block (global
        candidates) never hold every block's voxels at once."""
        n = self.n_blocks
        for s in range(0, n, CHUNK_BLOCKS):
            e = min(s + CHUNK_BLOCKS, n)
            c = np.zeros((e - s, 3), np.int32)
            d = np.zeros((e - s, BLOCK, BLOCK, BLOCK), np.float32)
            w = np.zeros_like(d)
            tsdf_blocks.read_blocks(self, s, e - s, c, d, w, int(self.as_sums))
            yield c, d, w

    def blocks(self) -> BlockData:
        """Copy the allocated blocks and the FREE block list to the host."""
        n = self.n_blocks
        coords = np.zeros((n, 3), np.int32)
        sdf = np.zeros((n, BLOCK, BLOCK, BLOCK), np.float32)
        weight = np.zeros((n, BLOCK, BLOCK, BLOCK), np.float32)
        s = 0
        for c, d, w in self.block_chunks():
            coords[s:s + len(c)], sdf[s:s + len(c)], weight[s:s + len(c)] = c, d, w
            s += len(c)
        cells, values = self.coarse_cells()
        return BlockData(coords, sdf, weight, cells[values == FREE])


@dataclass(frozen=True)
class MapStats:
    """Counts and memory of a map, for summaries (voxel counts include those of FREE
    blocks)."""

    blocks: int  # allocated
    free_blocks: int
    unknown_cells: int  # coarse cells neither allocated nor free
    observed_voxels: int
    free_voxels: int  # observed, at least a truncation from every surface
    surface_voxels: int  # within half a voxel diagonal of the surface
    bytes_per_block: int
    pool_bytes: int
    coarse_bytes: int  # the sparse coarse index: top grid + tiles
    coarse_top_bytes: int
    tiles: int
    coarse_tile_bytes: int
    dense_index_bytes: int  # the former dense coarse grid (block id + flag per cell)
    dense_grid_bytes: int  # a dense voxel grid of the same extent
    extent_lo_m: list[float]
    extent_hi_m: list[float]
    file_bytes: int | None = None  # the map file, when there is one

    def as_dict(self) -> dict:
        """Counts and bytes as plain numbers (`mcl3d map-info --json`)."""
        return {"blocks": {"allocated": self.blocks, "free": self.free_blocks,
                           "unknown_cells": self.unknown_cells},
                "voxels": {"surface": self.surface_voxels, "observed": self.observed_voxels,
                           "free": self.free_voxels},
                "memory": {"bytes_per_block": self.bytes_per_block,
                           "pool_bytes": self.pool_bytes, "coarse_bytes": self.coarse_bytes,
                           "coarse_top_bytes": self.coarse_top_bytes, "tiles": self.tiles,
                           "coarse_tile_bytes": self.coarse_tile_bytes,
                           "loaded_bytes": self.pool_bytes + self.coarse_bytes,
                           "dense_index_bytes": self.dense_index_bytes,
                           "dense_grid_bytes": self.dense_grid_bytes,
                           "file_bytes": self.file_bytes}}


def loaded_bytes_per_block(f16: bool) -> int:
    """Device memory per block of a map loaded for localization (read-only): distances and
    weights, plus the block's coordinate and free flag."""
    return VOXELS_PER_BLOCK * (4 if f16 else 8) + 16


def block_stats(geometry: MapGeometry, data: BlockData, bytes_per_block: int) -> MapStats:
    """Blocks, observed / free / surface voxels, and memory against a dense grid."""
    trunc = geometry.truncation_m
    observed = data.weight > 0
    free_vox = observed & (data.sdf >= trunc * 0.999)
    surface = observed & (np.abs(data.sdf) < 0.5 * geometry.voxel_size_m * np.sqrt(3))
    n_blocks, n_free = len(data.coords), len(data.free_coords)
    bytes_per_voxel = data.sdf.dtype.itemsize + data.weight.dtype.itemsize
    n_tiles = len(tiles_of(np.concatenate([data.coords, data.free_coords])))
    top_bytes = geometry.n_top_cells * TOP_CELL_BYTES
    lo, hi = geometry.extent_m
    return MapStats(
        blocks=n_blocks,
        free_blocks=n_free,
        unknown_cells=geometry.n_cells - n_blocks - n_free,
        observed_voxels=int(observed.sum()) + n_free * VOXELS_PER_BLOCK,
        free_voxels=int(free_vox.sum()) + n_free * VOXELS_PER_BLOCK,
        surface_voxels=int(surface.sum()),
        bytes_per_block=bytes_per_block,
        pool_bytes=n_blocks * bytes_per_block,
        coarse_bytes=top_bytes + n_tiles * TILE_BYTES,
        coarse_top_bytes=top_bytes,
        tiles=n_tiles,
        coarse_tile_bytes=n_tiles * TILE_BYTES,
        dense_index_bytes=geometry.n_cells * DENSE_CELL_BYTES,
        dense_grid_bytes=geometry.n_cells * VOXELS_PER_BLOCK * bytes_per_voxel,
        extent_lo_m=[round(float(x), 3) for x in lo],
        extent_hi_m=[round(float(x), 3) for x in hi],
    )


def map_stats(tsdf: TsdfMap, bytes_per_block: int) -> MapStats:
    """block_stats of a map on the device, its voxels read CHUNK_BLOCKS blocks at a time
    (a city's voxels are never copied to the host whole)."""
    coords, voxels = [np.zeros((0, 3), np.int32)], np.zeros(3, np.int64)
    no_free = np.zeros((0, 3), np.int32)
    for c, d, w in tsdf.block_chunks():
        part = block_stats(tsdf.geometry, BlockData(c, d, w, no_free), bytes_per_block)
        coords.append(c)
        voxels += (part.observed_voxels, part.free_voxels, part.surface_voxels)
    cells, values = tsdf.coarse_cells()
    empty = np.zeros((0, BLOCK, BLOCK, BLOCK), np.float32)
    whole = block_stats(tsdf.geometry, BlockData(np.concatenate(coords), empty, empty,
                                                 cells[values == FREE]), bytes_per_block)
    return dataclasses.replace(whole, observed_voxels=whole.observed_voxels + int(voxels[0]),
                               free_voxels=whole.free_voxels + int(voxels[1]),
                               surface_voxels=int(voxels[2]))


def surface_points(geometry: MapGeometry, data: BlockData, min_weight: float = 1e-6
                   ) -> np.ndarray:
    """Centres of observed voxels within half a voxel diagonal of the zero level set."""
    near = (data.weight > min_weight) & (np.abs(data.sdf) <= 0.5 * np.sqrt(3)
                                         * geometry.voxel_size_m)
    b, i, j, k = np.nonzero(near)
    vox = data.coords[b].astype(np.int64) * BLOCK + np.stack([i, j, k], axis=1)
    return np.asarray(geometry.origin_m) + (vox + 0.5) * geometry.voxel_size_m
