"""Free space along a scan's rays: blocks a ray crosses become FREE as a whole, voxels of
allocated blocks count the rays that crossed them (see `tsdf_lookup` for the map)."""

import taichi as ti

from mcl3d.kernels.tsdf_blocks import claim_tile, mark_free
from mcl3d.kernels.tsdf_lookup import (
    BIG,
    BLOCK,
    TILE,
    UNKNOWN,
    bounds_hold,
    cell_at,
    grid_at,
    grid_holds,
    ivec3,
    vec3,
)


@ti.func
def accumulate_free(m: ti.template(), b: ti.i32, g: ivec3, rays: ti.f32):
    """Count `rays` rays (a bundle's, kernels.tsdf_fusion) passing through voxel g of
    block b in front of their band (free space)."""
    ti.atomic_add(m.free_hits[b, g[0] & 7, g[1] & 7, g[2] & 7], rays)


@ti.func
def lowest_bit(i: ti.i32) -> ti.i32:
    """The largest power of two dividing i (2^20 for i = 0, every stride divides it)."""
    b = 1 << 20
    if i > 0:
        b = ti.min(i & -i, b)
    return b


@ti.func
def carve_ray(m: ti.template(), geo: ti.template(), a: vec3, u: vec3, length: ti.f32,
              stop_after: ti.f32, rays: ti.f32):
    """Free space along a + s u, s in [0, length): unallocated blocks become FREE as a
    whole, voxels of allocated blocks count `rays` hits each, sampled a voxel apart; past
    stop_after the walk ends in the first unallocated block it meets. Blocks become FREE
    only in tiles that exist: `claim_tiles_along` claimed them in the allocation pass.

    scan_fuse walks each ray backwards, from where it comes within truncation of its
    surface toward the sensor, so a ray that need not carve near the sensor still counts
    the voxels of the surface blocks it passes first. Runs of unallocated blocks are walked
    block to block by a 3D DDA (per-axis ray parameters of the next block face, no
    divisions or floors per block); on reaching an allocated block the ray resumes just
    past its face.
    """
    vox = geo.scale[0]
    g0 = grid_at(geo, a)  # the ray in voxel units: g0 + s * ug
    ug = u * geo.scale[1]
    inv = vec3(0.0)  # ray parameter per voxel along each axis
    edge = ivec3(0)  # 1: leaves a block through its upper face, 0: its lower face
    step = ivec3(0)  # -1, 0, +1: how the block index changes along each axis
    for k in ti.static(range(3)):
        if u[k] > 1e-9:
            inv[k] = 1.0 / ug[k]
            edge[k] = 1
            step[k] = 1
        elif u[k] < -1e-9:
            inv[k] = 1.0 / ug[k]
            step[k] = -1
    end = length  # shortened where the walk stops early
    last = ivec3(-(1 << 30))
    s = 0.0
    while s < end:
        g = ti.cast(ti.floor(g0 + s * ug), ti.i32)
        if not grid_holds(geo, g):
            s += BLOCK * vox
        else:
            bc = g >> 3
            b = cell_at(m, geo, bc)
            if b >= 0:
                if (g != last).any():
                    accumulate_free(m, b, g, rays)
                    last = g
                s += vox
            elif s > stop_after:
                end = s
            else:
                face = ti.cast((bc + edge) * BLOCK, ti.f32)
                t = vec3(BIG)  # ray parameter of the block's exit face along each axis
                for k in ti.static(range(3)):
                    if step[k] != 0:
                        t[k] = (face[k] - g0[k]) * inv[k]
                while True:
                    if b == UNKNOWN:
                        mark_free(m, geo, bc, False)
                    axis = 0
                    s_exit = t[0]
                    if t[1] < s_exit:
                        axis = 1
                        s_exit = t[1]
                    if t[2] < s_exit:
                        axis = 2
                        s_exit = t[2]
                    s = ti.max(s_exit, s) + 1e-4
                    if s >= end or s > stop_after:
                        break
                    for k in ti.static(range(3)):
                        if axis == k:
                            bc[k] += step[k]
                            t[k] += BLOCK * ti.abs(inv[k])
                    if not bounds_hold(geo, bc):
                        break
                    b = cell_at(m, geo, bc)
                    if b >= 0:
                        break


@ti.func
def dense_range(geo: ti.template(), spacing_rad: ti.f32) -> ti.f32:
    """The range at which neighbouring rays are half a voxel apart (0 without a spacing)."""
    s_dense = 0.0
    if spacing_rad > 0.0:
        s_dense = 0.5 * geo.scale[0] / spacing_rad
    return s_dense


@ti.func
def carve_in_front(m: ti.template(), geo: ti.template(), i: ti.i32, o: vec3, u: vec3, r: ti.f32,
                   c: ti.f32, s_dense: ti.f32, rays: ti.f32):
    """Carve ray i of a scan (sensor o, unit direction u, range r, |cos incidence| c), for
    `rays` rays (a bundle's), from where it comes within truncation of its surface plane
    back toward the sensor. Near the sensor only a subset of the rays carves: ray i counts
    voxels from s_dense / lowbit(i) on and walks unallocated blocks from twice that on (see
    tsdf_fusion.scan_fuse)."""
    s_free = r - geo.scale[2] / c
    s_voxels = s_dense / ti.cast(lowest_bit(i), ti.f32)
    carve_ray(m, geo, o + s_free * u, -u, s_free - s_voxels, s_free - 2.0 * s_voxels, rays)


@ti.func
def claim_tiles_along(m: ti.template(), geo: ti.template(), a: vec3, u: vec3, length: ti.f32):
    """Claim the tiles of the coarse index that the segment a + s u, s in [0, length]
    crosses (a 3D DDA over tiles), so that carving, a later launch, finds them."""
    tile_vox = ti.static(TILE * BLOCK)
    g0 = grid_at(geo, a) * (1.0 / tile_vox)  # the ray in tile units: g0 + s * ut
    ut = u * (geo.scale[1] * (1.0 / tile_vox))
    tc = ti.cast(ti.floor(g0), ti.i32)
    t = vec3(BIG)  # ray parameter of the next tile face along each axis
    dt = vec3(BIG)
    step = ivec3(0)
    for k in ti.static(range(3)):
        if ut[k] > 1e-12:
            step[k] = 1
            dt[k] = 1.0 / ut[k]
            t[k] = (ti.cast(tc[k] + 1, ti.f32) - g0[k]) * dt[k]
        elif ut[k] < -1e-12:
            step[k] = -1
            dt[k] = -1.0 / ut[k]
            t[k] = (g0[k] - ti.cast(tc[k], ti.f32)) * dt[k]
    s = 0.0
    while s <= length:
        bc = tc * TILE
        if bounds_hold(geo, bc):
            claim_tile(m, geo, bc)
        axis = 0
        if t[1] < t[axis]:
            axis = 1
        if t[2] < t[axis]:
            axis = 2
        s = t[axis]
        for k in ti.static(range(3)):
            if axis == k:
                tc[k] += step[k]
                t[k] += dt[k]


@ti.func
def claim_carve_tiles(m: ti.template(), geo: ti.template(), i: ti.i32, o: vec3, u: vec3,
                      r: ti.f32, c: ti.f32, s_dense: ti.f32):
    """The tiles `carve_in_front` may mark FREE blocks in (the same ray, up to where its
    walk of unallocated blocks stops), claimed in the allocation pass; a block's margin
    past the stop covers the walk's last step."""
    s_free = r - geo.scale[2] / c
    s_voxels = s_dense / ti.cast(lowest_bit(i), ti.f32)
    stop = ti.min(s_free - s_voxels, s_free - 2.0 * s_voxels)
    if stop >= 0.0:
        claim_tiles_along(m, geo, o + s_free * u, -u, stop + BLOCK * geo.scale[0])
