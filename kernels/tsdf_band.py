"""A scan point's truncation band: the patch of its tangent plane it fills (columns along
the normal, a voxel apart), the blocks that patch needs, its Gaussian weights and the
running sums it adds to the map (see `tsdf_lookup` for the map container)."""

import taichi as ti

from mcl3d.kernels.tsdf_blocks import allocate_block
from mcl3d.kernels.tsdf_lookup import (
    SUM_ONE,
    UNKNOWN,
    cell_at,
    center_at,
    grid_at,
    ivec3,
    vec3,
)

MAX_FOOTPRINT_STEPS = 4  # a scan point's band patch is at most 4 x 4 voxels (5 x 5 columns)


# ------------------------------------------------------------------ weights and sums
@ti.func
def exp_nonpositive(x: ti.f32) -> ti.f32:
    """exp(x) for x <= 0 (flushed to 2^-126 below -87): absolute error under 3e-7,
    relative error under 5e-6 (it grows with |x| where cpu fast math merges the two ln2 parts).

    The band weights take one exp per voxel sample, a large share of fusion on cpu, where
    ti.exp is a libm call: 2^n * e^f with n = round(x log2 e) and f = x - n ln2 (ln2 split
    in two parts, so n ln2 loses no bits), |f| <= ln2 / 2, e^f by its degree-6 Taylor
    polynomial (remainder < 1.2e-7), 2^n by building the float's exponent bits. The same
    arithmetic on every backend.
    """
    xc = ti.max(x, -87.0)
    n = ti.floor(xc * 1.4426950408889634 + 0.5)
    f = (xc - n * 0.693145751953125) - n * 1.428606765330187e-06
    e_f = 1.0 + f * (1.0 + f * (0.5 + f * (1.0 / 6.0 + f * (1.0 / 24.0 + f * (
        1.0 / 120.0 + f * (1.0 / 720.0))))))
    return e_f * ti.bit_cast((ti.cast(n, ti.i32) + 127) << 23, ti.f32)


@ti.func
def add_fixed(total: ti.template(), x: ti.f32):
    """Add x (|x| < 2^31) to the fixed-point sum `total` (an i64 in units of 2^-32,
    tsdf_lookup): floor(x * 2^32), exact (x times a power of two, floored, is an integer
    an i64 holds), so whole sums are exact whatever the order of the adds."""
    ti.atomic_add(total, ti.cast(ti.floor(x * SUM_ONE), ti.i64))


@ti.func
def add_sums(m: ti.template(), geo: ti.template(), b: ti.i32, g: ivec3, wd: ti.f32,
             w: ti.f32):
    """Add summed observations (sum of w*d, sum of w) to voxel g of pool block b: as
    fixed-point numbers (see tsdf_lookup) whose totals do not depend on the order in which
    threads add, or on Vulkan as floats into the pool (m.exact_sums, see maps.tsdf)."""
    i, j, k = g[0] & 7, g[1] & 7, g[2] & 7
    if ti.static(m.exact_sums):
        add_fixed(m.sum_wd[b, i, j, k], wd * geo.scale[3])
        add_fixed(m.sum_w[b, i, j, k], w)
    else:
        ti.atomic_add(m.sdf[b, i, j, k], wd)
        ti.atomic_add(m.weight[b, i, j, k], w)


@ti.func
def accumulate_sums(m: ti.template(), geo: ti.template(), g: ivec3, wd: ti.f32, w: ti.f32):
    """Add summed observations (sum of w*d, sum of w) to voxel g, if its block exists."""
    b = cell_at(m, geo, g >> 3)
    if b >= 0:
        add_sums(m, geo, b, g, wd, w)


# --------------------------------------------------------------------- patch geometry
@ti.func
def tangent_basis(n: vec3):
    """Two unit vectors orthogonal to unit n and to each other."""
    a = vec3(1.0, 0.0, 0.0)
    if ti.abs(n[0]) > 0.9:
        a = vec3(0.0, 1.0, 0.0)
    t1 = n.cross(a).normalized()
    return t1, n.cross(t1)


@ti.func
def patch_tangents(n: vec3, k: ti.i32):
    """The patch's tangent axes; a one-column patch (k = 0) needs none (zeros)."""
    e1 = vec3(0.0)
    e2 = vec3(0.0)
    if k > 0:
        e1, e2 = tangent_basis(n)
    return e1, e2


@ti.func
def footprint_steps(geo: ti.template(), r: ti.f32, spacing_rad: ti.f32) -> ti.i32:
    """Half-width k, in half voxels, of the patch a point covers on its surface: half the
    gap to the next ray (r * spacing / 2), so neighbouring rays' patches meet. The patch
    is sampled by (k + 1)^2 columns along the normal, a voxel apart (see column_base)."""
    rho = 0.5 * r * spacing_rad
    return ti.min(ti.cast(rho / (0.5 * geo.scale[0]), ti.i32), MAX_FOOTPRINT_STEPS)


@ti.func
def column_base(pg: vec3, e1: vec3, e2: vec3, k: ti.i32, a: ti.i32, b: ti.i32) -> vec3:
    """Grid position of column (a, b), 0 <= a, b <= k, of the band patch around the point
    at grid position pg: a voxel apart along the tangents e1, e2, spanning +-k/2 voxels
    (a voxel spacing covers the same voxels as a finer one on axis-aligned surfaces)."""
    hk = 0.5 * k
    return pg + (a - hk) * e1 + (b - hk) * e2


@ti.func
def patch_block(pg: vec3, e1: vec3, e2: vec3, nv: vec3, k: ti.i32, a: ti.i32, b: ti.i32,
                s: ti.f32) -> ivec3:
    """Block of the band sample at column (a, b), depth s (as scan_fuse computes it)."""
    return ti.cast(ti.floor(column_base(pg, e1, e2, k, a, b) + s * nv), ti.i32) >> 3


@ti.func
def band_samples(geo: ti.template(), behind_m: ti.f32) -> ti.i32:
    """Samples along the normal, a voxel apart, from -behind_m to +truncation (both ends)."""
    return ti.cast(ti.ceil((behind_m + geo.scale[2]) / geo.scale[0]), ti.i32) + 1


def max_band_samples(truncation_m: float, voxel_size_m: float) -> int:
    """An upper bound of band_samples for any behind_m <= truncation (f32 ceil included),
    for ti.static (maps.tsdf keeps it as `band_slots`: it depends on the truncation in
    voxels alone, so maps of any size share the kernels)."""
    return int(2.0 * truncation_m / voxel_size_m) + 3


# ---------------------------------------------------------------- allocation and fusion
@ti.func
def allocate_patch(m: ti.template(), geo: ti.template(), p: vec3, nr: vec3, k: ti.i32,
                   behind_m: ti.f32):
    """Allocate the blocks of the band patch of half-width k around world point p.

    The samples lie in the parallelepiped of the 8 corner samples (the 4 corner columns at
    their first and last depth), so when the corners' blocks fill the box of blocks they
    span, those are the blocks (the common case: a patch inside one block or across one
    face). Otherwise column by column: a column whose two end samples lie in the same or
    face-adjacent blocks covers just those two; only the rest walk all their samples.
    """
    e1, e2 = patch_tangents(nr, k)
    pg = grid_at(geo, p)  # the same sample positions as scan_fuse
    vox = geo.scale[0]
    nv = nr * geo.scale[1]
    n_s = band_samples(geo, behind_m)
    s_first = -behind_m
    s_last = ti.min(-behind_m + (n_s - 1) * vox, geo.scale[2])
    by_corners = False
    if k > 0:
        lo = ivec3(1 << 30)
        hi = ivec3(-(1 << 30))
        for c in ti.static(range(8)):
            cb = patch_block(pg, e1, e2, nv, k, k if c & 1 else 0, k if c & 2 else 0,
                             s_last if c & 4 else s_first)
            lo = ti.min(lo, cb)
            hi = ti.max(hi, cb)
        span = hi - lo
        if (span <= 1).all():
            mask = 0
            for c in ti.static(range(8)):
                cb = patch_block(pg, e1, e2, nv, k, k if c & 1 else 0,
                                 k if c & 2 else 0, s_last if c & 4 else s_first) - lo
                mask |= 1 << (cb[0] * 4 + cb[1] * 2 + cb[2])
            full = 0
            for c in ti.static(range(8)):
                if c >> 2 <= span[0] and (c >> 1) & 1 <= span[1] and c & 1 <= span[2]:
                    full |= 1 << c
            if mask == full:
                by_corners = True
                for c in ti.static(range(8)):
                    if (mask >> c) & 1:
                        allocate_block(m, geo, lo[0] + (c >> 2), lo[1] + ((c >> 1) & 1),
                                       lo[2] + (c & 1))
    if not by_corners:
        for a, b in ti.ndrange(k + 1, k + 1):
            first = patch_block(pg, e1, e2, nv, k, a, b, s_first)
            last = patch_block(pg, e1, e2, nv, k, a, b, s_last)
            allocate_block(m, geo, first[0], first[1], first[2])
            if ti.abs(last - first).sum() == 1:
                allocate_block(m, geo, last[0], last[1], last[2])
            elif (last != first).any():
                base = column_base(pg, e1, e2, k, a, b)
                prev = first
                for j in range(1, n_s):
                    sj = ti.min(-behind_m + j * vox, geo.scale[2])
                    g = ti.cast(ti.floor(base + sj * nv), ti.i32) >> 3
                    if (g != prev).any():
                        allocate_block(m, geo, g[0], g[1], g[2])
                        prev = g


@ti.func
def band_patch(m: ti.template(), geo: ti.template(), p: vec3, nr: vec3, k: ti.i32,
               behind_m: ti.f32, k_w: ti.f32, e1: vec3, e2: vec3):
    """The band of a point whose patch has more than one column, straight into the map."""
    trunc = geo.scale[2]
    vox = geo.scale[0]
    pg = grid_at(geo, p)  # sample (a, b, j) is at column_base(a, b) + s_j nv
    nv = nr * geo.scale[1]
    cb = ivec3(-(1 << 30))  # the block of the last sample and its id: runs of samples
    bid = UNKNOWN  # in one block look it up once
    for a, b in ti.ndrange(k + 1, k + 1):
        base = column_base(pg, e1, e2, k, a, b)
        base_a = column_base(pg, e1, e2, k, a - 1, b)  # the columns before it along a, b
        base_b = column_base(pg, e1, e2, k, a, b - 1)
        last = ivec3(-(1 << 30))
        for j in range(band_samples(geo, behind_m)):
            s = ti.min(-behind_m + j * vox, trunc)
            g = ti.cast(ti.floor(base + s * nv), ti.i32)
            if (g != last).any():
                last = g
                # a point updates a voxel once (duplicates come from the adjacent columns):
                # skip it when column a-1 or b-1 put its sample at this depth into it
                seen = False
                if a > 0:
                    seen = (ti.cast(ti.floor(base_a + s * nv), ti.i32) == g).all()
                if b > 0 and not seen:
                    seen = (ti.cast(ti.floor(base_b + s * nv), ti.i32) == g).all()
                if not seen:
                    v = center_at(geo, g) - p
                    d = v.dot(nr)
                    if -behind_m <= d <= trunc:
                        if ((g >> 3) != cb).any():
                            cb = g >> 3
                            bid = cell_at(m, geo, cb)
                        if bid >= 0:
                            w = exp_nonpositive(k_w * v.dot(v))
                            add_sums(m, geo, bid, g, w * d, w)


@ti.func
def point_band(m: ti.template(), geo: ti.template(), p: vec3, nr: vec3, k: ti.i32,
               behind_m: ti.f32, k_w: ti.f32, n_s: ti.i32, slot_g: ti.template(),
               slot_wd: ti.template(), slot_w: ti.template(), cb: ti.template(),
               bid: ti.template(), count: ti.f32):
    """A point's band of half-width k: a patch straight into the map, or a one-column band
    of weight `count` (the points a bundle stands for, kernels.tsdf_fusion) into the run's
    slots (column_into_slots), flushed by the caller at the run's end."""
    if k > 0:
        e1, e2 = tangent_basis(nr)
        band_patch(m, geo, p, nr, k, behind_m, k_w, e1, e2)
    else:
        column_into_slots(m, geo, p, nr, behind_m, k_w, n_s, slot_g, slot_wd, slot_w, cb,
                          bid, count)


# --------------------------------------------------- one-column bands of a run of points
@ti.func
def column_into_slots(m: ti.template(), geo: ti.template(), p: vec3, nr: vec3,
                      behind_m: ti.f32, k_w: ti.f32, n_s: ti.i32, slot_g: ti.template(),
                      slot_wd: ti.template(), slot_w: ti.template(), cb: ti.template(),
                      bid: ti.template(), count: ti.f32):
    """The one-column band of world point p, with weight `count` (the points a bundle
    stands for, kernels.tsdf_fusion), added to a run's slots (registers): slot j holds
    the voxel of depth sample j (slot_g[j]) and its sums (slot_wd[j], slot_w[j]); a slot
    goes to the map (flush_slot) when this point's sample j leaves its voxel. cb, bid: the
    block last flushed and its pool id, looked up again only when the block changes."""
    trunc = geo.scale[2]
    vox = geo.scale[0]
    pg = grid_at(geo, p)
    nv = nr * geo.scale[1]
    last = ivec3(-(1 << 30))
    for j in ti.static(range(m.band_slots)):
        if j < n_s:
            s = ti.min(-behind_m + j * vox, trunc)
            g = ti.cast(ti.floor(pg + s * nv), ti.i32)
            if (g != last).any():
                last = g
                v = center_at(geo, g) - p
                d = v.dot(nr)
                if -behind_m <= d <= trunc:
                    w = count * exp_nonpositive(k_w * v.dot(v))
                    same = (slot_g[j, 0] == g[0] and slot_g[j, 1] == g[1]
                            and slot_g[j, 2] == g[2])
                    if slot_w[j] > 0.0 and not same:
                        flush_slot(m, geo, j, slot_g, slot_wd, slot_w, cb, bid)
                    for a in ti.static(range(3)):
                        slot_g[j, a] = g[a]
                    slot_wd[j] += w * d
                    slot_w[j] += w


@ti.func
def flush_slot(m: ti.template(), geo: ti.template(), j: ti.template(), slot_g: ti.template(),
               slot_wd: ti.template(), slot_w: ti.template(), cb: ti.template(),
               bid: ti.template()):
    """Add slot j's sums to its voxel and empty it (j is a compile-time index, so the slots
    stay in registers)."""
    gs = ivec3(slot_g[j, 0], slot_g[j, 1], slot_g[j, 2])
    if ((gs >> 3) != cb).any():
        cb = gs >> 3
        bid = cell_at(m, geo, cb)
    if bid >= 0:
        add_sums(m, geo, bid, gs, slot_wd[j], slot_w[j])
    slot_w[j] = 0.0
    slot_wd[j] = 0.0


@ti.func
def flush_slots(m: ti.template(), geo: ti.template(), slot_g: ti.template(),
                slot_wd: ti.template(), slot_w: ti.template()):
    """Add every slot still holding sums to its voxel: the end of a run."""
    for j in ti.static(range(m.band_slots)):
        if slot_w[j] > 0.0:
            accumulate_sums(m, geo, ivec3(slot_g[j, 0], slot_g[j, 1], slot_g[j, 2]),
                            slot_wd[j], slot_w[j])
