"""The TSDF's coarse index and block pool: claiming tiles and allocating blocks (one thread
wins each), resetting and initializing pool slots, and copying blocks and coarse cells
between the host and the device. The map container is described in `tsdf_lookup`.

A launch that needs a tile that does not exist yet claims it; a thread that loses the claim
to another thread of the same launch cannot use the tile before the next launch, so it
counts a miss in `tile_misses` and the host relaunches the (idempotent) allocation until no
thread misses (mcl3d.maps.tsdf.TsdfMap.relaunch_until_placed).
"""

import taichi as ti

from mcl3d.kernels.tsdf_lookup import (
    BLOCK,
    FREE,
    FREE_WEIGHT,
    OVERFLOW,
    TILE,
    TILE_OVERFLOW,
    TILE_SHIFT,
    UNKNOWN,
    block_capacity,
    bounds_hold,
    coarse_cell,
    fixed_value,
    geometry,
    ivec3,
    set_tile_cell,
    tile_capacity,
    tile_cell,
    tile_id_at,
    top_slot,
    vec3,
)


@ti.func
def claim_tile(m: ti.template(), geo: ti.template(), bc: ivec3) -> ti.i32:
    """The tile of coarse cell bc (inside the bounds), claimed when it has none: its id, or -1
    when another thread of this launch claimed it (a miss, counted) or the pool is full.

    Fresh tiles need no init: their cells hold zeros, UNKNOWN (`tsdf_lookup`). Past the
    tile capacity `tile_count` still counts, so the host learns how many were needed.
    """
    t = tile_id_at(m, geo, bc)
    if t == -1:  # no tile yet (-2: the tile pool overflowed)
        tc = bc >> TILE_SHIFT
        top = top_slot(geo, tc)
        if ti.atomic_or(m.tile_flag[top], 1) == 0:
            nid = ti.atomic_add(m.tile_count[None], 1)
            if nid < tile_capacity(m):
                m.tile_coord[nid] = tc
                m.tile_of[top] = nid + 1
                t = nid
            else:
                m.tile_of[top] = TILE_OVERFLOW
        else:
            ti.atomic_add(m.tile_misses[None], 1)
    return t


@ti.func
def allocate_block(m: ti.template(), geo: ti.template(), bx: ti.i32, by: ti.i32, bz: ti.i32):
    """Give block (bx, by, bz) a pool slot; exactly one thread wins (atomic flag + counter).

    Readers must look at the coarse cell in a later launch. Past capacity the counter still
    counts, so the caller learns how many blocks were needed. A block that was FREE keeps
    that evidence in `free_hits` here, so slots that are still zero need no init pass. A
    cell whose tile this launch could not use yet (a miss) is left for the next launch.
    """
    bc = ivec3(bx, by, bz)
    if bounds_hold(geo, bc):
        t = claim_tile(m, geo, bc)
        if t >= 0:
            c = tile_cell(m, t, bc)
            # nested ifs and no `in`: Taichi does not short-circuit `and` nor support `in`
            if c == UNKNOWN or c == FREE:  # noqa: SIM102, SIM109
                if ti.atomic_or(m.cell_flag[t, bx & (TILE - 1), by & (TILE - 1),
                                            bz & (TILE - 1)], 1) == 0:
                    nid = ti.atomic_add(m.block_count[None], 1)
                    if nid < block_capacity(m):
                        m.block_coord[nid] = bc
                        m.block_free[nid] = 1 if c == FREE else 0
                        if ti.static(m.writable):  # noqa: SIM102 (compile-time if)
                            if c == FREE:
                                for v in range(BLOCK * BLOCK * BLOCK):
                                    m.free_hits[nid, v >> 6, (v >> 3) & 7, v & 7] = FREE_WEIGHT
                        set_tile_cell(m, t, bc, nid)
                    else:
                        set_tile_cell(m, t, bc, OVERFLOW)


@ti.func
def mark_free(m: ti.template(), geo: ti.template(), bc: ivec3, claim: ti.template()):
    """Coarse cell bc (inside the bounds) UNKNOWN -> FREE. With `claim` a missing tile is
    claimed (a miss when another thread of the launch holds it), else such a cell stays
    unknown (the carving pass: its tiles were claimed by the allocation pass)."""
    t = -1
    if ti.static(claim):  # noqa: SIM108 (compile-time if)
        t = claim_tile(m, geo, bc)
    else:
        t = tile_id_at(m, geo, bc)
    if t >= 0:  # noqa: SIM102
        if tile_cell(m, t, bc) == UNKNOWN:
            set_tile_cell(m, t, bc, FREE)


@ti.func
def clear_sums(m: ti.template(), b: ti.i32, i: ti.i32, j: ti.i32, h: ti.i32):
    """The fixed-point build sums of a voxel (when the map has them) back to zero."""
    if ti.static(m.exact_sums):
        m.sum_w[b, i, j, h] = 0
        m.sum_wd[b, i, j, h] = 0


@ti.kernel
def set_geometry(m: ti.template(), origin_m: vec3, dims: ivec3, top: ivec3, blocks: ti.i32,
                 tiles: ti.i32):
    """The map's geometry into the 0-d fields kernels read it from (tsdf_lookup): origin,
    coarse and top-grid dims, and the blocks and tiles that may be used."""
    m.geo_origin[None] = origin_m
    m.geo_dims[None] = dims
    m.geo_top[None] = top
    m.geo_caps[None] = ti.math.ivec2(blocks, tiles)


@ti.kernel
def zero_top(m: ti.template(), start: ti.i32, count: ti.i32):
    """No tile (and no claim) over flat top-grid cells [start, start + count)."""
    for k in range(count):
        m.tile_of[start + k] = 0
        m.tile_flag[start + k] = 0


@ti.kernel
def zero_tiles(m: ti.template(), start: ti.i32, count: ti.i32):
    """Tiles [start, start + count) back to zeros: every cell UNKNOWN and unclaimed."""
    for k, i, j, h in ti.ndrange(count, TILE, TILE, TILE):
        m.cells[start + k, i, j, h] = 0
        m.cell_flag[start + k, i, j, h] = 0


@ti.kernel
def read_tiles(m: ti.template(), start: ti.i32, count: ti.i32,
               coords: ti.types.ndarray(dtype=ivec3, ndim=1),
               cells: ti.types.ndarray(dtype=ti.i32, ndim=4)):
    """Tiles [start, start + count): their top-grid coordinates and cell values."""
    for k, i, j, h in ti.ndrange(count, TILE, TILE, TILE):
        if i == 0 and j == 0 and h == 0:
            coords[k] = m.tile_coord[start + k]
        cells[k, i, j, h] = m.cells[start + k, i, j, h] - 1


@ti.kernel
def reset_count(m: ti.template()):
    m.block_count[None] = 0
    m.tile_count[None] = 0
    m.tile_misses[None] = 0


@ti.kernel
def take_misses(m: ti.template()) -> ti.i32:
    """The misses of the launches since the last call (and reset them)."""
    n = m.tile_misses[None]
    m.tile_misses[None] = 0
    return n


@ti.kernel
def init_blocks(m: ti.template(), start: ti.i32, count: ti.i32, as_sums: ti.i32):
    """Fresh blocks [start, start+count): unknown, or free when the block was FREE before.

    With `as_sums` the distance slot starts at 0 (an empty sum), else at +truncation.
    """
    d0 = m.truncation_m * (1.0 - ti.cast(as_sums, ti.f32))
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        m.sdf[b, i, j, h] = ti.cast(d0, m.sdf.dtype)
        m.weight[b, i, j, h] = ti.cast(0.0, m.weight.dtype)
        if ti.static(m.writable):
            clear_sums(m, b, i, j, h)
            m.free_hits[b, i, j, h] = ti.cast(m.block_free[b], ti.f32) * FREE_WEIGHT


@ti.kernel
def zero_blocks(m: ti.template(), start: ti.i32, count: ti.i32):
    """Blocks [start, start+count) back to zero, the state of never used slots."""
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        m.sdf[b, i, j, h] = ti.cast(0.0, m.sdf.dtype)
        m.weight[b, i, j, h] = ti.cast(0.0, m.weight.dtype)
        if ti.static(m.writable):
            clear_sums(m, b, i, j, h)
            m.free_hits[b, i, j, h] = 0.0


@ti.kernel
def allocate_coords(m: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                    n: ti.i32):
    for i in range(n):
        c = coords[i]
        allocate_block(m, geometry(m), c[0], c[1], c[2])


@ti.kernel
def mark_free_coords(m: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                     n: ti.i32):
    """Blocks known to be free of surfaces: UNKNOWN -> FREE (allocated blocks stay)."""
    for i in range(n):
        c = coords[i]
        geo = geometry(m)
        if bounds_hold(geo, c):
            mark_free(m, geo, c, True)


@ti.kernel
def write_blocks(m: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                 sdf: ti.types.ndarray(dtype=ti.f32, ndim=4),
                 weight: ti.types.ndarray(dtype=ti.f32, ndim=4), n: ti.i32):
    """Copy values of already allocated blocks, addressed by block coordinates."""
    for k, i, j, h in ti.ndrange(n, BLOCK, BLOCK, BLOCK):
        b = coarse_cell(m, coords[k])
        if b >= 0:
            m.sdf[b, i, j, h] = ti.cast(sdf[k, i, j, h], m.sdf.dtype)
            m.weight[b, i, j, h] = ti.cast(weight[k, i, j, h], m.weight.dtype)


@ti.kernel
def read_blocks(m: ti.template(), start: ti.i32, count: ti.i32,
                coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                sdf: ti.types.ndarray(dtype=ti.f32, ndim=4),
                weight: ti.types.ndarray(dtype=ti.f32, ndim=4), as_sums: ti.i32):
    """Blocks [start, start+count): distances and weights, or while building (`as_sums`)
    the running sums of w*d and w."""
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        if i == 0 and j == 0 and h == 0:
            coords[k] = m.block_coord[b]
        sdf[k, i, j, h] = ti.cast(m.sdf[b, i, j, h], ti.f32)
        weight[k, i, j, h] = ti.cast(m.weight[b, i, j, h], ti.f32)
        if ti.static(m.exact_sums):  # noqa: SIM102 (compile-time if)
            if as_sums:
                sdf[k, i, j, h] = m.truncation_m * fixed_value(m.sum_wd[b, i, j, h])
                weight[k, i, j, h] = fixed_value(m.sum_w[b, i, j, h])
