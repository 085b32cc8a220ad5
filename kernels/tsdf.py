"""Two-level TSDF kernels: lookups for other kernels, block allocation, fusion, block I/O.

Every function takes the map `m` as `ti.template()` (mcl3d.maps.tsdf.TsdfMap, compiled
once per map: its geometry is baked in as constants), a data-oriented container holding

- fields `coarse` (i32 [cx, cy, cz]: block id >= 0, or UNKNOWN / OVERFLOW / FREE),
  `sdf`, `weight` (pool [capacity, 8, 8, 8], f32 or f16), `alloc_flag` (i32 like
  `coarse`), `block_count` (i32 scalar), `block_coord` (ivec3 [capacity]), `block_free`
  (i32 [capacity]) and, when `writable`, `free_hits` (f32 pool: rays that crossed a voxel
  in front of their band);
- constants `voxel_size_m`, `truncation_m`, `origin_m` (3 floats: the corner of voxel
  (0, 0, 0)), `coarse_dims` (3 ints), `capacity`, `writable` (bool).

Voxel (i, j, k) covers origin + [i, i+1) x [j, j+1) x [k, k+1) voxels; its value is the
signed distance at its centre, positive in free space, clamped to +-truncation.

While a map is being built the pool holds running sums (sdf = sum of w*d, weight = sum of
w), so that rays and points fuse with atomic adds and no update is lost when several rays
touch one voxel in the same launch; `finalize_blocks` turns sums into distances once.
"""

import taichi as ti

from mcl3d.kernels.se3 import quat_conj, quat_exp, quat_log, quat_mul, quat_normalize, quat_rotate
from mcl3d.kernels.spread import spread_item, spread_length

BLOCK = 8
UNKNOWN = -1  # never observed
OVERFLOW = -2  # needed, but the pool was full
FREE = -3  # observed, every voxel free (no surface within truncation)
FREE_WEIGHT = 1.0  # the weight a query reports for a voxel of a FREE block
MAX_FOOTPRINT_STEPS = 4  # a scan point's band patch is at most 4 x 4 voxels (5 x 5 columns)

STATE_UNKNOWN = 0
STATE_OBSERVED = 1  # observed, near or behind a surface (d < truncation)
STATE_FREE = 2  # observed, at least the truncation distance from any surface

vec2 = ti.math.vec2
vec3 = ti.math.vec3
vec4 = ti.math.vec4
ivec3 = ti.math.ivec3
_BIG = 1e30


# ----------------------------------------------------------------------------- lookups
@ti.func
def world_to_grid(m: ti.template(), p: vec3) -> vec3:
    """Continuous voxel coordinates: voxel i spans [i, i+1)."""
    o = vec3(m.origin_m[0], m.origin_m[1], m.origin_m[2])
    return (p - o) * (1.0 / m.voxel_size_m)


@ti.func
def voxel_center(m: ti.template(), g: ivec3) -> vec3:
    o = vec3(m.origin_m[0], m.origin_m[1], m.origin_m[2])
    return o + (ti.cast(g, ti.f32) + 0.5) * m.voxel_size_m


@ti.func
def in_grid(m: ti.template(), g: ivec3) -> bool:
    return (0 <= g[0] < m.coarse_dims[0] * BLOCK and 0 <= g[1] < m.coarse_dims[1] * BLOCK
            and 0 <= g[2] < m.coarse_dims[2] * BLOCK)


@ti.func
def voxel_dw(m: ti.template(), g: ivec3) -> vec2:
    """(signed distance, weight) of voxel g; unknown and outside the map give (trunc, 0)."""
    out = vec2(m.truncation_m, 0.0)
    if in_grid(m, g):
        b = m.coarse[g[0] >> 3, g[1] >> 3, g[2] >> 3]
        if b >= 0:
            out = vec2(ti.cast(m.sdf[b, g[0] & 7, g[1] & 7, g[2] & 7], ti.f32),
                       ti.cast(m.weight[b, g[0] & 7, g[1] & 7, g[2] & 7], ti.f32))
        elif b == FREE:
            out = vec2(m.truncation_m, FREE_WEIGHT)
    return out


@ti.func
def sdf_nearest(m: ti.template(), p: vec3) -> vec2:
    """(d, w) of the voxel containing world point p (w = 0: unknown)."""
    return voxel_dw(m, ti.cast(ti.floor(world_to_grid(m, p)), ti.i32))


@ti.func
def voxel_state(m: ti.template(), g: ivec3) -> ti.i32:
    dw = voxel_dw(m, g)
    state = STATE_UNKNOWN
    if dw[1] > 0.0:
        state = STATE_OBSERVED
        if dw[0] >= m.truncation_m * 0.999:
            state = STATE_FREE
    return state


@ti.func
def state_at(m: ti.template(), p: vec3) -> ti.i32:
    return voxel_state(m, ti.cast(ti.floor(world_to_grid(m, p)), ti.i32))


@ti.func
def sdf_trilinear(m: ti.template(), p: vec3) -> vec2:
    """(d, w): d interpolated between the 8 surrounding voxel centres; w their smallest weight.

    Unknown corners count as +truncation, so w = 0 flags a value that mixes in unknowns.
    """
    g = world_to_grid(m, p) - 0.5
    i0 = ti.cast(ti.floor(g), ti.i32)
    f = g - ti.cast(i0, ti.f32)
    d = 0.0
    w = _BIG
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        dw = voxel_dw(m, i0 + ivec3(dx, dy, dz))
        c = ((f[0] if dx else 1.0 - f[0]) * (f[1] if dy else 1.0 - f[1])
             * (f[2] if dz else 1.0 - f[2]))
        d += c * dw[0]
        w = ti.min(w, dw[1])
    return vec2(d, w)


@ti.func
def sdf_trilinear_grad(m: ti.template(), p: vec3) -> vec4:
    """(d, dd/dx, dd/dy, dd/dz) of the trilinear interpolant at p, gradient in 1/m units."""
    g = world_to_grid(m, p) - 0.5
    i0 = ti.cast(ti.floor(g), ti.i32)
    f = g - ti.cast(i0, ti.f32)
    out = vec4(0.0)
    for dx, dy, dz in ti.static(ti.ndrange(2, 2, 2)):
        v = voxel_dw(m, i0 + ivec3(dx, dy, dz))[0]
        wx = f[0] if dx else 1.0 - f[0]
        wy = f[1] if dy else 1.0 - f[1]
        wz = f[2] if dz else 1.0 - f[2]
        sx = 1.0 if dx else -1.0
        sy = 1.0 if dy else -1.0
        sz = 1.0 if dz else -1.0
        out += v * vec4(wx * wy * wz, sx * wy * wz, wx * sy * wz, wx * wy * sz)
    inv = 1.0 / m.voxel_size_m
    return vec4(out[0], out[1] * inv, out[2] * inv, out[3] * inv)


# ------------------------------------------------------------------------- allocation
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
            m.free_hits[b, i, j, h] = ti.cast(m.block_free[b], ti.f32) * FREE_WEIGHT


@ti.kernel
def zero_blocks(m: ti.template(), start: ti.i32, count: ti.i32):
    """Blocks [start, start+count) back to zero, the state of never used slots."""
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        m.sdf[b, i, j, h] = ti.cast(0.0, m.sdf.dtype)
        m.weight[b, i, j, h] = ti.cast(0.0, m.weight.dtype)
        if ti.static(m.writable):
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


# ------------------------------------------------------------------------ block I/O
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
                weight: ti.types.ndarray(dtype=ti.f32, ndim=4)):
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        if i == 0 and j == 0 and h == 0:
            coords[k] = m.block_coord[b]
        sdf[k, i, j, h] = ti.cast(m.sdf[b, i, j, h], ti.f32)
        weight[k, i, j, h] = ti.cast(m.weight[b, i, j, h], ti.f32)


@ti.kernel
def finalize_blocks(m: ti.template(), start: ti.i32, count: ti.i32):
    """Build-time sums -> distances for blocks [start, start+count).

    Voxels with band observations get their weighted mean distance; voxels only crossed by
    rays become free (+truncation) with the negated number of crossings as weight, a mark
    for `refine_free_voxels` (run next, then `unmark_free_voxels`).
    """
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        w = ti.cast(m.weight[b, i, j, h], ti.f32)
        d = m.truncation_m
        if w > 0.0:
            d = ti.math.clamp(ti.cast(m.sdf[b, i, j, h], ti.f32) / w,
                              -m.truncation_m, m.truncation_m)
        else:
            w = -m.free_hits[b, i, j, h]
        m.sdf[b, i, j, h] = ti.cast(d, m.sdf.dtype)
        m.weight[b, i, j, h] = ti.cast(w, m.weight.dtype)
        m.free_hits[b, i, j, h] = 0.0


@ti.kernel
def refine_free_voxels(m: ti.template(), start: ti.i32, count: ti.i32):
    """Free-only voxels next to the band: distance bounded through band neighbours.

    A ray crossing a voxel proves it free, not that the surface is a truncation away
    (rays skim floors and pass edges). For a band voxel n at k steps along one of the 26
    grid directions,
    d(v) <= k * voxel + |d(n)| (triangle inequality), so the smallest such bound replaces
    +truncation.
    """
    radius = ti.static(int(m.truncation_m / m.voxel_size_m + 0.999))
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        if m.weight[b, i, j, h] < 0.0:
            g = m.block_coord[b] * BLOCK + ivec3(i, j, h)
            best = m.truncation_m
            for n in range(27):
                e = ivec3(n // 9 - 1, (n // 3) % 3 - 1, n % 3 - 1)
                length = ti.sqrt(ti.cast(e.dot(e), ti.f32))
                if n != 13:
                    for step in range(1, radius + 1):
                        dw = voxel_dw(m, g + step * e)
                        if dw[1] > 0.0:
                            best = ti.min(best, step * length * m.voxel_size_m
                                          + ti.abs(dw[0]))
            m.sdf[b, i, j, h] = ti.cast(best, m.sdf.dtype)


@ti.kernel
def unmark_free_voxels(m: ti.template(), start: ti.i32, count: ti.i32):
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        m.weight[b, i, j, h] = ti.abs(m.weight[b, i, j, h])


# --------------------------------------------------------------------- scan fusion
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
def block_id(m: ti.template(), bc: ivec3) -> ti.i32:
    """coarse[bc]: the pool id of block bc, or UNKNOWN outside the grid."""
    b = UNKNOWN
    if (0 <= bc[0] < m.coarse_dims[0] and 0 <= bc[1] < m.coarse_dims[1]
            and 0 <= bc[2] < m.coarse_dims[2]):
        b = m.coarse[bc[0], bc[1], bc[2]]
    return b


@ti.func
def add_sums(m: ti.template(), b: ti.i32, g: ivec3, wd: ti.f32, w: ti.f32):
    """Add summed observations (sum of w*d, sum of w) to voxel g of pool block b."""
    ti.atomic_add(m.sdf[b, g[0] & 7, g[1] & 7, g[2] & 7], wd)
    ti.atomic_add(m.weight[b, g[0] & 7, g[1] & 7, g[2] & 7], w)


@ti.func
def accumulate_sums(m: ti.template(), g: ivec3, wd: ti.f32, w: ti.f32):
    """Add summed observations (sum of w*d, sum of w) to voxel g, if its block exists."""
    b = block_id(m, g >> 3)
    if b >= 0:
        add_sums(m, b, g, wd, w)


@ti.func
def accumulate(m: ti.template(), g: ivec3, d: ti.f32, w: ti.f32):
    """Add one observation (d, w) to the running sums of voxel g, if its block exists."""
    accumulate_sums(m, g, w * d, w)


@ti.func
def accumulate_free(m: ti.template(), b: ti.i32, g: ivec3):
    """Count a ray passing through voxel g of block b in front of its band (free space)."""
    ti.atomic_add(m.free_hits[b, g[0] & 7, g[1] & 7, g[2] & 7], 1.0)


@ti.func
def scan_motion(q0: vec4, q1: vec4) -> vec3:
    """Rotation vector from the scan's start to its end orientation (shortest way): the
    part of slerp that is the same for every point, computed once per launch."""
    q1s = q1
    if q0.dot(q1) < 0.0:
        q1s = -q1
    return quat_log(quat_mul(quat_conj(q0), q1s))


@ti.func
def ray_setup(p_l: vec3, n_l: vec3, alpha: ti.f32, q0: vec4, t0: vec3, delta: vec3, t1: vec3,
              use_normals: ti.template()):
    """World point, sensor origin, ray direction, range, surface normal (facing the
    sensor; the reversed ray without normals) and the |cos| of the incidence angle.

    The pose is interpolated at the point's time (deskewing); a scan without motion skips
    the slerp (the same q, bit for bit: its factor exp(0) is exactly the identity).
    """
    q = q0
    if (delta != 0.0).any():
        q = quat_mul(q0, quat_exp(alpha * delta))  # slerp, as pose_interpolate
    q = quat_normalize(q)
    t = t0 + alpha * (t1 - t0)
    p = quat_rotate(q, p_l) + t
    r = (p - t).norm()
    u = (p - t) / ti.max(r, 1e-9)
    nrm = -u
    c = 1.0
    if ti.static(use_normals):
        nw = quat_rotate(q, n_l)
        nn = nw.norm()
        if nn > 0.5:
            nw = nw / nn
            if nw.dot(u) > 0.0:
                nw = -nw
            nrm = nw
            c = ti.max(-nw.dot(u), 1e-3)
    return p, t, u, r, nrm, c


@ti.func
def point_ok(p_l: vec3, min_range: ti.f32, max_range: ti.f32) -> bool:
    r = p_l.norm()
    return (r >= min_range) and (r <= max_range) and (r == r)


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
def footprint_steps(m: ti.template(), r: ti.f32, spacing_rad: ti.f32) -> ti.i32:
    """Half-width k, in half voxels, of the patch a point covers on its surface: half the
    gap to the next ray (r * spacing / 2), so neighbouring rays' patches meet. The patch
    is sampled by (k + 1)^2 columns along the normal, a voxel apart (see column_base)."""
    rho = 0.5 * r * spacing_rad
    return ti.min(ti.cast(rho / (0.5 * m.voxel_size_m), ti.i32), MAX_FOOTPRINT_STEPS)


@ti.kernel
def scan_allocate(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1),
                  nrm: ti.types.ndarray(dtype=vec3, ndim=1),
                  alpha: ti.types.ndarray(dtype=ti.f32, ndim=1), n: ti.i32,
                  q0: vec4, t0: vec3, q1: vec4, t1: vec3, min_range: ti.f32,
                  max_range: ti.f32, spacing_rad: ti.f32, behind_m: ti.f32,
                  use_normals: ti.template(), ray_p: ti.types.ndarray(dtype=vec4, ndim=1),
                  ray_n: ti.types.ndarray(dtype=vec4, ndim=1), run_length: ti.i32,
                  threads: ti.i32):
    """Pass 1 of a scan: allocate the blocks that hold samples of each point's band patch
    (exactly those scan_fuse visits), testing as few samples as that takes.

    Each point's ray setup (deskewed world point, normal) is kept for pass 2, which would
    otherwise repeat it: ray_p[i] = (world point, range), ray_n[i] = (normal facing the
    sensor, |cos incidence|), the latter 0 for a point that is skipped (out of range).

    Runs of run_length consecutive points are spread over the cpu threads (kernels.spread).
    """
    delta = scan_motion(q0, q1)
    n_runs = (n + run_length - 1) // run_length
    for index in range(spread_length(n_runs, threads)):
        run = spread_item(index, n_runs, threads)
        if run >= 0:
            for i in range(run * run_length, ti.min(n, (run + 1) * run_length)):
                ray_n[i] = vec4(0.0)
                if point_ok(pts[i], min_range, max_range):
                    p, _o, _u, r, nr, c = ray_setup(pts[i], nrm[i], alpha[i], q0, t0, delta,
                                                    t1, use_normals)
                    ray_p[i] = vec4(p, r)
                    ray_n[i] = vec4(nr, c)
                    allocate_patch(m, p, nr, footprint_steps(m, r, spacing_rad), behind_m)


@ti.func
def allocate_patch(m: ti.template(), p: vec3, nr: vec3, k: ti.i32, behind_m: ti.f32):
    """Allocate the blocks of the band patch of half-width k around world point p.

    The samples lie in the parallelepiped of the 8 corner samples (the 4 corner columns at
    their first and last depth), so when the corners' blocks fill the box of blocks they
    span, those are the blocks (the common case: a patch inside one block or across one
    face). Otherwise column by column: a column whose two end samples lie in the same or
    face-adjacent blocks covers just those two; only the rest walk all their samples.
    """
    e1, e2 = patch_tangents(nr, k)
    pg = world_to_grid(m, p)  # the same sample positions as scan_fuse
    nv = nr * (1.0 / m.voxel_size_m)
    n_s = band_samples(m, behind_m)
    s_first = -behind_m
    s_last = ti.min(-behind_m + (n_s - 1) * m.voxel_size_m, m.truncation_m)
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
                        allocate_block(m, lo[0] + (c >> 2), lo[1] + ((c >> 1) & 1),
                                       lo[2] + (c & 1))
    if not by_corners:
        for a, b in ti.ndrange(k + 1, k + 1):
            first = patch_block(pg, e1, e2, nv, k, a, b, s_first)
            last = patch_block(pg, e1, e2, nv, k, a, b, s_last)
            allocate_block(m, first[0], first[1], first[2])
            if ti.abs(last - first).sum() == 1:
                allocate_block(m, last[0], last[1], last[2])
            elif (last != first).any():
                base = column_base(pg, e1, e2, k, a, b)
                prev = first
                for j in range(1, n_s):
                    sj = ti.min(-behind_m + j * m.voxel_size_m, m.truncation_m)
                    g = ti.cast(ti.floor(base + sj * nv), ti.i32) >> 3
                    if (g != prev).any():
                        allocate_block(m, g[0], g[1], g[2])
                        prev = g


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
def band_samples(m: ti.template(), behind_m: ti.f32) -> ti.i32:
    """Samples along the normal, a voxel apart, from -behind_m to +truncation (both ends)."""
    return ti.cast(ti.ceil((behind_m + m.truncation_m) / m.voxel_size_m), ti.i32) + 1


@ti.func
def lowest_bit(i: ti.i32) -> ti.i32:
    """The largest power of two dividing i (2^20 for i = 0, every stride divides it)."""
    b = 1 << 20
    if i > 0:
        b = ti.min(i & -i, b)
    return b


@ti.func
def carve_ray(m: ti.template(), a: vec3, u: vec3, length: ti.f32, stop_after: ti.f32):
    """Free space along a + s u, s in [0, length): unallocated blocks become FREE as a
    whole, voxels of allocated blocks count a hit each, sampled a voxel apart; past
    stop_after the walk ends in the first unallocated block it meets.

    scan_fuse walks each ray backwards, from where it comes within truncation of its
    surface toward the sensor, so a ray that need not carve near the sensor still counts
    the voxels of the surface blocks it passes first. Runs of unallocated blocks are walked
    block to block by a 3D DDA (per-axis ray parameters of the next block face, no
    divisions or floors per block); on reaching an allocated block the ray resumes just
    past its face.
    """
    vox = m.voxel_size_m
    g0 = world_to_grid(m, a)  # the ray in voxel units: g0 + s * ug
    ug = u * (1.0 / vox)
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
        if not in_grid(m, g):
            s += BLOCK * vox
        else:
            bc = g >> 3
            b = m.coarse[bc[0], bc[1], bc[2]]
            if b >= 0:
                if (g != last).any():
                    accumulate_free(m, b, g)
                    last = g
                s += vox
            elif s > stop_after:
                end = s
            else:
                face = ti.cast((bc + edge) * BLOCK, ti.f32)
                t = vec3(_BIG)  # ray parameter of the block's exit face along each axis
                for k in ti.static(range(3)):
                    if step[k] != 0:
                        t[k] = (face[k] - g0[k]) * inv[k]
                while True:
                    if b == UNKNOWN:
                        m.coarse[bc[0], bc[1], bc[2]] = FREE
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
                    if not (0 <= bc[0] < m.coarse_dims[0] and 0 <= bc[1] < m.coarse_dims[1]
                            and 0 <= bc[2] < m.coarse_dims[2]):
                        break
                    b = m.coarse[bc[0], bc[1], bc[2]]
                    if b >= 0:
                        break


def max_band_samples(m) -> int:
    """An upper bound of band_samples for any behind_m <= truncation (f32 ceil included),
    for ti.static."""
    return int(2.0 * m.truncation_m / m.voxel_size_m) + 3


@ti.func
def band_patch(m: ti.template(), p: vec3, nr: vec3, k: ti.i32, behind_m: ti.f32,
               k_w: ti.f32, e1: vec3, e2: vec3):
    """The band of a point whose patch has more than one column, straight into the map."""
    trunc = m.truncation_m
    pg = world_to_grid(m, p)  # sample (a, b, j) is at column_base(a, b) + s_j nv
    nv = nr * (1.0 / m.voxel_size_m)
    cb = ivec3(-(1 << 30))  # the block of the last sample and its id: runs of samples
    bid = UNKNOWN  # in one block look it up once
    for a, b in ti.ndrange(k + 1, k + 1):
        base = column_base(pg, e1, e2, k, a, b)
        base_a = column_base(pg, e1, e2, k, a - 1, b)  # the columns before it along a, b
        base_b = column_base(pg, e1, e2, k, a, b - 1)
        last = ivec3(-(1 << 30))
        for j in range(band_samples(m, behind_m)):
            s = ti.min(-behind_m + j * m.voxel_size_m, trunc)
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
                    v = voxel_center(m, g) - p
                    d = v.dot(nr)
                    if -behind_m <= d <= trunc:
                        if ((g >> 3) != cb).any():
                            cb = g >> 3
                            bid = block_id(m, cb)
                        if bid >= 0:
                            w = exp_nonpositive(k_w * v.dot(v))
                            add_sums(m, bid, g, w * d, w)


@ti.kernel
def scan_fuse(m: ti.template(), ray_p: ti.types.ndarray(dtype=vec4, ndim=1),
              ray_n: ti.types.ndarray(dtype=vec4, ndim=1),
              alpha: ti.types.ndarray(dtype=ti.f32, ndim=1), n: ti.i32, t0: vec3, t1: vec3,
              spacing_rad: ti.f32, behind_m: ti.f32, carve: ti.template(),
              sigma_weight_m: ti.f32, run_length: ti.i32, threads: ti.i32):
    """Pass 2 of a scan: the truncation band around each point + free-space carving, from
    the rays that scan_allocate set up (ray_p, ray_n; t0, t1 and alpha give each ray's
    sensor position).

    Band: voxels on a patch of the point's tangent plane (half the gap to the next ray
    wide, so sparse far rays leave no holes), from behind_m behind the surface to the
    truncation in front, get the point-to-plane distance (projective distance along the
    ray without normals), weighted by a Gaussian of their distance along the plane so each
    voxel is dominated by the rays that hit next to it. Deeper voxels may be closer to the
    far side of a thin solid, which no ray sees, so the band stops at behind_m.
    Carving: between the sensor and the point where the ray comes within truncation of the
    surface plane, blocks that hold no surface become FREE as a whole (the ray jumps block
    to block) and voxels of allocated blocks count free-space hits; finalize_blocks uses
    them only for voxels no band reached (a ray passing a voxel says it is free, not how
    far the surface is). Near the sensor rays are far denser than voxels, so there only a
    subset carves: ray i (in scan order) counts voxels from range s_dense / lowbit(i) on
    (lowbit(i): the largest power of two dividing i) and walks unallocated blocks from 2x
    that range on, where the rays that do are under one voxel, resp. two voxels apart
    (the spacing of rays i, i + 2^k at range s is about 2^k * spacing_rad * s). Each ray
    walks backwards, from its band toward the sensor, so its own surface blocks come first.

    Near rays are denser than voxels (a one-column band, footprint_steps = 0), so
    consecutive points of a scan line mostly hit the same voxels: one thread takes a run
    of run_length consecutive points and sums their one-column bands in registers (slot j
    holds depth sample j), writing a voxel's sums once, when the next point's sample j
    leaves it. The sums are those of updating voxel by voxel, only added in another order,
    so run_length changes no result beyond f32 rounding. Runs are spread over the cpu
    threads as in scan_allocate.
    """
    trunc = m.truncation_m
    k_w = -0.5 / (sigma_weight_m * sigma_weight_m)
    n_max = ti.static(max_band_samples(m))
    n_s = band_samples(m, behind_m)
    s_dense = 0.0  # neighbouring rays are half a voxel apart at this range
    if spacing_rad > 0.0:
        s_dense = 0.5 * m.voxel_size_m / spacing_rad
    n_runs = (n + run_length - 1) // run_length
    for index in range(spread_length(n_runs, threads)):
        run = spread_item(index, n_runs, threads)
        if run >= 0:
            slot_g = ti.Matrix.zero(ti.i32, n_max, 3)
            slot_wd = ti.Vector.zero(ti.f32, n_max)
            slot_w = ti.Vector.zero(ti.f32, n_max)
            cb = ivec3(-(1 << 30))  # the block of the last flushed slot and its id
            bid = UNKNOWN
            for i in range(run * run_length, ti.min(n, (run + 1) * run_length)):
                c = ray_n[i][3]
                if c > 0.0:
                    p = ray_p[i].xyz
                    r = ray_p[i][3]
                    nr = ray_n[i].xyz
                    o = t0 + alpha[i] * (t1 - t0)  # as ray_setup
                    u = (p - o) / ti.max(r, 1e-9)
                    if ti.static(carve):
                        s_free = r - trunc / c
                        # near the sensor only a subset of the rays carves (see the docstring)
                        s_voxels = s_dense / ti.cast(lowest_bit(i), ti.f32)
                        carve_ray(m, o + s_free * u, -u, s_free - s_voxels,
                                  s_free - 2.0 * s_voxels)
                    k = footprint_steps(m, r, spacing_rad)
                    if k > 0:
                        e1, e2 = tangent_basis(nr)
                        band_patch(m, p, nr, k, behind_m, k_w, e1, e2)
                    else:
                        pg = world_to_grid(m, p)
                        nv = nr * (1.0 / m.voxel_size_m)
                        last = ivec3(-(1 << 30))
                        for j in ti.static(range(n_max)):
                            if j < n_s:
                                s = ti.min(-behind_m + j * m.voxel_size_m, trunc)
                                g = ti.cast(ti.floor(pg + s * nv), ti.i32)
                                if (g != last).any():
                                    last = g
                                    v = voxel_center(m, g) - p
                                    d = v.dot(nr)
                                    if -behind_m <= d <= trunc:
                                        w = exp_nonpositive(k_w * v.dot(v))
                                        same = (slot_g[j, 0] == g[0] and slot_g[j, 1] == g[1]
                                                and slot_g[j, 2] == g[2])
                                        if slot_w[j] > 0.0 and not same:
                                            gs = ivec3(slot_g[j, 0], slot_g[j, 1], slot_g[j, 2])
                                            if ((gs >> 3) != cb).any():
                                                cb = gs >> 3
                                                bid = block_id(m, cb)
                                            if bid >= 0:
                                                add_sums(m, bid, gs, slot_wd[j], slot_w[j])
                                            slot_w[j] = 0.0
                                            slot_wd[j] = 0.0
                                        for a in ti.static(range(3)):
                                            slot_g[j, a] = g[a]
                                        slot_wd[j] += w * d
                                        slot_w[j] += w
            for j in ti.static(range(n_max)):
                if slot_w[j] > 0.0:
                    accumulate_sums(m, ivec3(slot_g[j, 0], slot_g[j, 1], slot_g[j, 2]),
                                    slot_wd[j], slot_w[j])


# ------------------------------------------------------------ points with normals
@ti.kernel
def points_allocate(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1), n: ti.i32,
                    radius_vox: ti.i32):
    """Allocate every block within radius_vox voxels (a cube) of each world point."""
    for i in range(n):
        g = ti.cast(ti.floor(world_to_grid(m, pts[i])), ti.i32)
        lo = (g - radius_vox) >> 3
        hi = (g + radius_vox) >> 3
        for bx in range(lo[0], hi[0] + 1):
            for by in range(lo[1], hi[1] + 1):
                for bz in range(lo[2], hi[2] + 1):
                    allocate_block(m, bx, by, bz)


@ti.kernel
def points_fuse(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1),
                nrm: ti.types.ndarray(dtype=vec3, ndim=1), n: ti.i32, radius_vox: ti.i32,
                sigma_weight_m: ti.f32, behind_m: ti.f32):
    """Point-to-plane signed distance of each point's oriented plane into nearby voxels.

    Voxels of the cube of radius_vox within truncation in front of the plane and behind_m
    behind it get d = (v - p).n, weighted by a Gaussian of their distance to the point, so
    the nearest points dominate each voxel.
    """
    trunc = m.truncation_m
    k = -0.5 / (sigma_weight_m * sigma_weight_m)
    for i, dx, dy, dz in ti.ndrange(n, (-radius_vox, radius_vox + 1),
                                    (-radius_vox, radius_vox + 1),
                                    (-radius_vox, radius_vox + 1)):
        p = pts[i]
        nr = nrm[i]
        g = ti.cast(ti.floor(world_to_grid(m, p)), ti.i32) + ivec3(dx, dy, dz)
        v = voxel_center(m, g) - p
        d = v.dot(nr)
        if -behind_m <= d <= trunc:
            accumulate(m, g, d, exp_nonpositive(k * v.dot(v)))
