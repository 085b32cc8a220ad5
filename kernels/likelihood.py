"""The scan likelihood of every particle: one kernel over particles x points.

The per-point model (docs/sensor-model.md) depends on the voxel only through its signed
distance d, its weight and its block's state, so `build_codes` evaluates it once per voxel
of the (read-only) map into a code, and the hot loop does one two-level lookup per point
with no data-dependent branch:

- observed voxel with d < truncation: code k + TABLE_SIZE (|d| < match_dist), k the bin of
  d in the hit table (log(z_hit exp(-d^2 / (2 sigma^2)) + z_rand) over TABLE_SIZE bins of d in
  [-truncation, truncation), filled by mcl3d.localization.sensor_model.code_table);
- observed free space (d >= truncation, or a FREE block): CODE_FREE (log_free, a penalty);
- unknown or outside the map: CODE_UNKNOWN (log_unknown, a neutral constant).

Codes are 16 bits, two per i32 word along z (the pool is 1 KiB per block instead of 4 KiB
of f32 distance + weight: the lookups miss the cache less). `slot` maps each coarse cell to
its block, or to one of two extra constant blocks (all free / all unknown), so unallocated
cells need no branch either; dense over the bounds for maps up to DENSE_SLOT_BYTES, else laid
out as the map's sparse coarse index (one 8³ tile of slots per tile of the index, reached
through the index's top grid), see `slot_shape`.
Parallel over particles, visited in `order` (particles with
equal `locality_keys` next to each other: neighbouring threads and iterations then read the
same map blocks; each particle's result does not depend on the order). `cache_block`
(static) keeps the last coarse-cell lookup like the peer's CUDA kernel (measured slower on
the cpu backend).

log_w[i] += tempering * sum(log-likelihoods); match[i] = fraction of points within
match_dist of a surface; ll_mean[i] = the mean per-point log-likelihood of this scan.
"""

import numpy as np
import taichi as ti

from mcl3d.kernels.se3 import quat_to_mat
from mcl3d.kernels.tsdf_lookup import (
    BLOCK,
    FREE,
    TILE,
    TILE_SHIFT,
    tile_cell,
    tile_entry,
    tile_id,
)

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
TABLE_SIZE = 1024
MATCH_BIT = 10  # code bit set for hits within match_dist (TABLE_SIZE = 2^MATCH_BIT)
CODE_FREE = 2 * TABLE_SIZE
CODE_UNKNOWN = 2 * TABLE_SIZE + 1
N_CODES = 2 * TABLE_SIZE + 2
WORDS_Z = BLOCK // 2  # two 16-bit codes per i32 word
COARSE_BINS = 256  # coarse search model: distance bins, then far-free, then unknown
COARSE_UNKNOWN = COARSE_BINS + 1
DENSE_SLOT_BYTES = 64 << 20  # see slot_shape
KEY_BITS = 5  # per axis of locality_keys: 15-bit keys (numpy sorts them with a radix sort)


@ti.func
def voxel_code(d: ti.f32, w: ti.f32, b: ti.i32, trunc: ti.f32, match_dist_m: ti.f32) -> ti.i32:
    """The model's case for a voxel (d, w) of block state b (see the module docstring)."""
    code = CODE_UNKNOWN
    if b == FREE:
        code = CODE_FREE
    elif b >= 0 and w > 0.0:
        if d >= trunc * 0.999:
            code = CODE_FREE
        else:
            k = ti.cast((d + trunc) * (TABLE_SIZE * 0.5 / trunc), ti.i32)
            code = ti.math.clamp(k, 0, TABLE_SIZE - 1) + (
                ti.cast(ti.abs(d) < match_dist_m, ti.i32) << MATCH_BIT)
    return code


@ti.kernel
def build_codes(m: ti.template(), codes: ti.template(), n_blocks: ti.i32,
                match_dist_m: ti.f32):
    """Codes of the map's blocks [0, n_blocks) and of the two constant blocks after the pool
    (index capacity: all free, capacity + 1: all unknown)."""
    trunc = m.truncation_m
    for b in range(n_blocks + 2):
        for lx, ly, h in ti.ndrange(BLOCK, BLOCK, WORDS_Z):
            word = 0
            for s in ti.static(range(2)):
                code = CODE_UNKNOWN
                if b == n_blocks:
                    code = CODE_FREE
                elif b < n_blocks:
                    lz = 2 * h + s
                    d = ti.cast(m.sdf[b, lx, ly, lz], ti.f32)
                    w = 1.0  # never-observed voxels hold d = +trunc: only then is w needed
                    if d >= trunc * 0.999:
                        w = ti.cast(m.weight[b, lx, ly, lz], ti.f32)
                    code = voxel_code(d, w, b, trunc, match_dist_m)
                word |= code << (16 * s)
            codes[ti.select(b < n_blocks, b, m.capacity + b - n_blocks), lx, ly, h] = word


def slot_shape(m) -> tuple[int, ...]:
    """Shape of the `slot` field for map m: dense over the map's bounds (one coarse cell per
    entry) while that costs at most DENSE_SLOT_BYTES, which saves the hot loop the top-grid
    read (measured: ~25 % of the kernel's time on cpu); else tiled like the map's sparse
    index: slot[t + 1] for tile t, slot[0] for cells without a tile (all unknown)."""
    if 4 * int(np.prod(m.coarse_dims)) <= DENSE_SLOT_BYTES:
        return tuple(m.coarse_dims)
    return (m.tile_capacity + 1, TILE, TILE, TILE)


@ti.func
def cell_slot(m: ti.template(), t: ti.i32, c: ivec3) -> ti.i32:
    """The code block of coarse cell c of tile t (t < 0: no tile): its pool block, else the
    all-free (capacity) or all-unknown (capacity + 1) block."""
    s = m.capacity + 1
    if t >= 0:
        b = tile_cell(m, t, c)
        if b >= 0:
            s = b
        elif b == FREE:
            s = m.capacity
    return s


@ti.kernel
def build_slots(m: ti.template(), slot: ti.template()):
    """Coarse cell -> code block for every entry of `slot` (shape from slot_shape)."""
    if ti.static(len(slot.shape) == 3):
        for cx, cy, cz in slot:
            c = ivec3(cx, cy, cz)
            slot[cx, cy, cz] = cell_slot(m, tile_id(m, c), c)
    else:
        for t, i, j, h in slot:
            slot[t, i, j, h] = cell_slot(m, t - 1, ivec3(i, j, h))


@ti.func
def slot_of(m: ti.template(), slot: ti.template(), c: ivec3) -> ti.i32:
    """The code block of coarse cell c (capacity + 1 outside the bounds), read at a clamped
    index whatever the cell, so that the hot loops need no branch: one read of a dense
    `slot`, or the top grid then the tile's slots."""
    cu = ti.cast(c, ti.u32)
    dims = ti.math.uvec3(m.coarse_dims[0], m.coarse_dims[1], m.coarse_dims[2])
    inside = (cu[0] < dims[0]) & (cu[1] < dims[1]) & (cu[2] < dims[2])
    cc = ti.select(inside, c, 0)
    s = 0
    if ti.static(len(slot.shape) == 3):
        s = slot[cc[0], cc[1], cc[2]]
    else:
        ts = ti.max(tile_entry(m, cc), 0)
        s = slot[ts, cc[0] & (TILE - 1), cc[1] & (TILE - 1), cc[2] & (TILE - 1)]
    return ti.select(inside, s, m.capacity + 1)


@ti.kernel
def locality_keys(pos: ti.template(), quat: ti.template(), n: ti.i32, cell_m: ti.f32,
                  cell_rad: ti.f32, keys: ti.template()):
    """Morton code of (x, y, yaw) cells, each axis wrapped to KEY_BITS bits: particles with
    equal keys see every scan point in nearly the same voxel."""
    for i in range(n):
        q = quat[i]
        yaw = ti.atan2(2.0 * (q[3] * q[2] + q[0] * q[1]), 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2]))
        c = ti.cast(ti.floor(ti.math.vec3(pos[i][0] / cell_m, pos[i][1] / cell_m,
                                          yaw / cell_rad)), ti.i32)
        key = 0
        for bit in ti.static(range(KEY_BITS)):
            for axis in ti.static(range(3)):
                key |= ((c[axis] >> bit) & 1) << (3 * bit + axis)
        keys[i] = key


@ti.kernel
def scan_log_likelihood(m: ti.template(), codes: ti.template(), slot: ti.template(),
                        order: ti.template(), pos: ti.template(), quat: ti.template(), n: ti.i32,
                        pts: ti.template(), n_pts: ti.i32, table: ti.template(),
                        tempering: ti.f32, log_w: ti.template(), match: ti.template(),
                        ll_mean: ti.template(), cache_block: ti.template()):
    o = vec3(m.origin_m[0], m.origin_m[1], m.origin_m[2])
    inv_vox = 1.0 / m.voxel_size_m
    unknown = m.capacity + 1
    ti.loop_config(block_dim=64)  # cpu: 64 neighbouring particles per task (~8% faster than 32)
    for k in range(n):
        i = order[k]
        R = quat_to_mat(quat[i])
        t = (pos[i] - o) * inv_vox
        Rs = R * inv_vox
        total = 0.0
        hits = 0
        last_c = ivec3(-(1 << 30))
        s = unknown
        for j in range(n_pts):
            g = ti.cast(ti.floor(Rs @ pts[j] + t), ti.i32)
            c = g >> 3
            if ti.static(cache_block):
                if (c != last_c).any():
                    last_c = c
                    s = slot_of(m, slot, c)
            else:
                s = slot_of(m, slot, c)
            word = codes[s, g[0] & (BLOCK - 1), g[1] & (BLOCK - 1), (g[2] & (BLOCK - 1)) >> 1]
            code = (word >> ((g[2] & 1) << 4)) & 0xFFFF
            total += table[code]
            hits += (code >> MATCH_BIT) & 1
        inv_m = 1.0 / ti.max(n_pts, 1)
        log_w[i] += tempering * total
        match[i] = hits * inv_m
        ll_mean[i] = total * inv_m


@ti.func
def coarse_code(f: ti.template(), g: ivec3) -> ti.i32:
    """The code of field cell g of the coarse search field `f` (mcl3d.localization.weighing.
    DeviceCoarseField), the unknown code outside the bounds: one read of a dense grid of
    codes (layout `codes`), or its block's slot (a dense grid of slots, or a top grid of
    tiles of 8^3 slots) then the cell in that slot's brick (slot 0, the unknown brick,
    outside the bounds). Reads at clamped indices whatever the cell: no branch."""
    code = 0
    if ti.static(f.layout == "codes"):
        gu = ti.cast(g, ti.u32)
        inside = (gu[0] < f.codes.shape[0]) & (gu[1] < f.codes.shape[1]) & (
            gu[2] < f.codes.shape[2])
        gc = ti.select(inside, g, 0)
        code = ti.select(inside, f.codes[gc[0], gc[1], gc[2]], COARSE_UNKNOWN)
    else:
        c = g >> f.block_shift
        cu = ti.cast(c, ti.u32)
        dims = ti.math.uvec3(f.coarse_dims[0], f.coarse_dims[1], f.coarse_dims[2])
        inside = (cu[0] < dims[0]) & (cu[1] < dims[1]) & (cu[2] < dims[2])
        cc = ti.select(inside, c, 0)
        s = 0
        if ti.static(f.layout == "slots"):
            s = f.slots[cc[0], cc[1], cc[2]]
        else:
            t = f.top[cc[0] >> TILE_SHIFT, cc[1] >> TILE_SHIFT, cc[2] >> TILE_SHIFT]
            s = f.tiles[t, cc[0] & (TILE - 1), cc[1] & (TILE - 1), cc[2] & (TILE - 1)]
        s = ti.select(inside, s, 0)
        mask = (1 << f.block_shift) - 1
        code = f.bricks[s, g[0] & mask, g[1] & mask, g[2] & mask]
    return code


@ti.kernel
def write_coarse_tiles(f: ti.template(), tiles: ti.types.ndarray(dtype=ivec3, ndim=1),
                       n: ti.i32):
    """Top grid of a tiled field: tile i of `tiles` (coordinates of 8^3 blocks) gets id i + 1
    (id 0, never written, holds only unknown slots)."""
    for i in range(n):
        t = tiles[i]
        f.top[t[0], t[1], t[2]] = i + 1


@ti.kernel
def write_coarse_slots(f: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                       slots: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32):
    """The slots of the listed blocks (their tiles already in the top grid when tiled)."""
    for i in range(n):
        c = coords[i]
        if ti.static(f.layout == "slots"):
            f.slots[c[0], c[1], c[2]] = slots[i]
        else:
            t = f.top[c[0] >> TILE_SHIFT, c[1] >> TILE_SHIFT, c[2] >> TILE_SHIFT]
            f.tiles[t, c[0] & (TILE - 1), c[1] & (TILE - 1), c[2] & (TILE - 1)] = slots[i]


@ti.kernel
def write_coarse_bricks(f: ti.template(), start: ti.i32,
                        codes: ti.types.ndarray(dtype=ti.i32, ndim=4), n: ti.i32):
    """Bricks [start, start + n) of the field from `codes` (n, k, k, k)."""
    for i, a, b, c in ti.ndrange(n, codes.shape[1], codes.shape[2], codes.shape[3]):
        f.bricks[start + i, a, b, c] = codes[i, a, b, c]


@ti.kernel
def coarse_scan_log_likelihood(field: ti.template(), origin: vec3, inv_cell: ti.f32,
                               order: ti.template(), pos: ti.template(), quat: ti.template(),
                               n: ti.i32, pts: ti.template(), n_pts: ti.i32,
                               table: ti.template(), match_codes: ti.i32, tempering: ti.f32,
                               log_w: ti.template(), match: ti.template(),
                               ll_mean: ti.template()):
    """The coarse search model (mcl3d.localization.coarse_field): one lookup per point in
    the sparse field of distance codes (`coarse_code`), the same outputs as
    scan_log_likelihood."""
    ti.loop_config(block_dim=64)
    for k in range(n):
        i = order[k]
        R = quat_to_mat(quat[i])
        t = (pos[i] - origin) * inv_cell
        Rs = R * inv_cell
        total = 0.0
        hits = 0
        for j in range(n_pts):
            code = coarse_code(field, ti.cast(ti.floor(Rs @ pts[j] + t), ti.i32))
            total += table[code]
            hits += ti.cast(code < match_codes, ti.i32)
        inv_m = 1.0 / ti.max(n_pts, 1)
        log_w[i] += tempering * total
        match[i] = hits * inv_m
        ll_mean[i] = total * inv_m
