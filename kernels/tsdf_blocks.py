"""The TSDF's block pool: allocating blocks (one thread wins each), resetting and
initializing pool slots, and copying blocks between the host and the device. The map
container is described in `tsdf_lookup`."""

import taichi as ti

from mcl3d.kernels.tsdf_lookup import (
    BLOCK,
    FREE,
    FREE_WEIGHT,
    OVERFLOW,
    UNKNOWN,
    fixed_value,
    ivec3,
)


@ti.func
def allocate_block(m: ti.template(), bx: ti.i32, by: ti.i32, bz: ti.i32):
    """Give block (bx, by, bz) a pool slot; exactly one thread wins (atomic flag + counter).

    Readers must look at `coarse` in a later launch. Past capacity the counter still counts,
    so the caller learns how many blocks were needed. A block that was FREE keeps that
    evidence in `free_hits` here, so slots that are still zero need no init pass.
    """
    if (0 <= bx < m.coarse_dims[0] and 0 <= by < m.coarse_dims[1]
            and 0 <= bz < m.coarse_dims[2]):
        c = m.coarse[bx, by, bz]
        # nested ifs and no `in`: Taichi does not short-circuit `and` nor support `in`
        if c == UNKNOWN or c == FREE:  # noqa: SIM102, SIM109
            if ti.atomic_or(m.alloc_flag[bx, by, bz], 1) == 0:
                nid = ti.atomic_add(m.block_count[None], 1)
                if nid < m.capacity:
                    m.block_coord[nid] = ivec3(bx, by, bz)
                    m.block_free[nid] = 1 if c == FREE else 0
                    if ti.static(m.writable):  # noqa: SIM102 (compile-time if)
                        if c == FREE:
                            for v in range(BLOCK * BLOCK * BLOCK):
                                m.free_hits[nid, v >> 6, (v >> 3) & 7, v & 7] = FREE_WEIGHT
                    m.coarse[bx, by, bz] = nid
                else:
                    m.coarse[bx, by, bz] = OVERFLOW


@ti.func
def clear_sums(m: ti.template(), b: ti.i32, i: ti.i32, j: ti.i32, h: ti.i32):
    """The fixed-point build sums of a voxel (when the map has them) back to zero."""
    if ti.static(m.exact_sums):
        m.sum_w[b, i, j, h] = 0
        m.sum_wd[b, i, j, h] = 0


@ti.kernel
def fill_coarse(m: ti.template(), start: ti.i32, count: ti.i32, value: ti.i32):
    """coarse = value and alloc_flag = 0 over flat cells [start, start + count)."""
    ny = m.coarse_dims[1]
    nz = m.coarse_dims[2]
    for k in range(count):
        i = start + k
        x = i // (ny * nz)
        y = (i // nz) % ny
        z = i % nz
        m.coarse[x, y, z] = value
        m.alloc_flag[x, y, z] = 0


@ti.kernel
def reset_count(m: ti.template()):
    m.block_count[None] = 0


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
        allocate_block(m, c[0], c[1], c[2])


@ti.kernel
def mark_free_coords(m: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                     n: ti.i32):
    """Blocks known to be free of surfaces: UNKNOWN -> FREE (allocated blocks stay)."""
    for i in range(n):
        c = coords[i]
        if (0 <= c[0] < m.coarse_dims[0] and 0 <= c[1] < m.coarse_dims[1]
                and 0 <= c[2] < m.coarse_dims[2]) and m.coarse[c[0], c[1], c[2]] == UNKNOWN:
            m.coarse[c[0], c[1], c[2]] = FREE


@ti.kernel
def write_blocks(m: ti.template(), coords: ti.types.ndarray(dtype=ivec3, ndim=1),
                 sdf: ti.types.ndarray(dtype=ti.f32, ndim=4),
                 weight: ti.types.ndarray(dtype=ti.f32, ndim=4), n: ti.i32):
    """Copy values of already allocated blocks, addressed by block coordinates."""
    for k, i, j, h in ti.ndrange(n, BLOCK, BLOCK, BLOCK):
        c = coords[k]
        b = m.coarse[c[0], c[1], c[2]]
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
