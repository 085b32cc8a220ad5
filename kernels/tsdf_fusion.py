"""The fusion kernels: a scan in two passes (scan_allocate, then scan_fuse: truncation
bands + free-space carving) and the end of a build, when the running sums become distances
(finalize_blocks, refine_free_voxels, unmark_free_voxels); point-cloud maps' bands are in
point_fusion. The map container is described in `tsdf_lookup`.
"""

import taichi as ti

from mcl3d.kernels.se3 import quat_conj, quat_log, quat_mul, quat_normalize, quat_rotate
from mcl3d.kernels.spread import spread_item, spread_length
from mcl3d.kernels.tsdf_band import (
    allocate_patch,
    band_samples,
    flush_slots,
    footprint_steps,
    point_band,
)
from mcl3d.kernels.tsdf_blocks import clear_sums
from mcl3d.kernels.tsdf_carve import carve_in_front, claim_carve_tiles, dense_range
from mcl3d.kernels.tsdf_lookup import (
    BLOCK,
    UNKNOWN,
    fixed_value,
    geometry,
    grid_at,
    ivec3,
    vec3,
    vec4,
    voxel_dw_at,
)

ivec4 = ti.math.ivec4

# ----------------------------------------------------------------------------- scans
BUNDLE_COS = 0.95  # consecutive one-column rays in one voxel bundle when their normals
# agree within 18 degrees (a crease's two faces stay apart)


@ti.func
def scan_motion(q0: vec4, q1: vec4) -> vec3:
    """Rotation vector from the scan's start to its end orientation (shortest way): the
    part of slerp that is the same for every point, computed once per launch."""
    q1s = q1
    if q0.dot(q1) < 0.0:
        q1s = -q1
    return quat_log(quat_mul(quat_conj(q0), q1s))


@ti.func
def scan_quat_exp(w: vec3) -> vec4:
    """quat_exp (kernels.se3) for the rotation within one scan: sin and cos of the half
    angle h by their Taylor polynomials for h < 0.5 rad (truncation errors under 2e-11,
    below f32 rounding), as ti.sin / ti.cos beyond: on cpu those are libm calls, a fifth of
    the allocation pass when taken per point."""
    h2 = 0.25 * w.dot(w)
    k = 0.5 * (1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0 * (1.0 - h2 / 72.0))))
    c = 1.0 - h2 / 2.0 * (1.0 - h2 / 12.0 * (1.0 - h2 / 30.0 * (1.0 - h2 / 56.0 * (
        1.0 - h2 / 90.0))))
    if h2 >= 0.25:
        theta = ti.sqrt(4.0 * h2)
        k = ti.sin(0.5 * theta) / theta
        c = ti.cos(0.5 * theta)
    return vec4(k * w[0], k * w[1], k * w[2], c)


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
        q = quat_mul(q0, scan_quat_exp(alpha * delta))  # slerp, as pose_interpolate
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
def bundle_key(geo: ti.template(), spacing_rad: ti.f32, rp: vec4, rn: vec4) -> ivec4:
    """A ray's voxel (rp, rn as in ray_p, ray_n) and 1 when it may join a bundle (fused,
    with a one-column band), else 0."""
    may = rn[3] > 0.0 and footprint_steps(geo, rp[3], spacing_rad) == 0
    g = ti.cast(ti.floor(grid_at(geo, rp.xyz)), ti.i32)
    return ivec4(g[0], g[1], g[2], 1 if may else 0)


@ti.func
def joins(prev_key: ivec4, prev_n: vec4, key: ivec4, rn: vec4) -> bool:
    """Whether a ray continues the bundle of the ray before it in the scan (keys from
    bundle_key): both may bundle, their points in one voxel, their normals within
    BUNDLE_COS."""
    return key[3] == 1 and (key == prev_key).all() and prev_n.xyz.dot(rn.xyz) >= BUNDLE_COS


@ti.func
def bundle_point(head: vec3, sum_dp: vec3, sum_n: vec3, count: ti.f32):
    """A bundle's mean point and unit mean normal."""
    return head + sum_dp / count, sum_n.normalized()


@ti.kernel
def scan_allocate(m: ti.template(), pts: ti.types.ndarray(dtype=vec3, ndim=1),
                  nrm: ti.types.ndarray(dtype=vec3, ndim=1),
                  alpha: ti.types.ndarray(dtype=ti.f32, ndim=1), n: ti.i32,
                  q0: vec4, t0: vec3, q1: vec4, t1: vec3, min_range: ti.f32,
                  max_range: ti.f32, spacing_rad: ti.f32, behind_m: ti.f32,
                  use_normals: ti.template(), ray_p: ti.types.ndarray(dtype=vec4, ndim=1),
                  ray_n: ti.types.ndarray(dtype=vec4, ndim=1), run_length: ti.i32,
                  threads: ti.i32, carve: ti.template()):
    """Pass 1 of a scan: allocate the blocks that hold samples of each band patch (exactly
    those scan_fuse visits: a bundle's column at its mean, see scan_fuse), testing as few
    samples as that takes.

    Each point's ray setup (deskewed world point, normal) is kept for pass 2, which would
    otherwise repeat it: ray_p[i] = (world point, range), ray_n[i] = (normal facing the
    sensor, |cos incidence|), the latter 0 for a point that is skipped (out of range).

    Runs of run_length consecutive points are spread over the cpu threads (kernels.spread);
    a run's bundles are those whose first ray is in it (the rays next to the run, which
    another thread keeps, are set up again here). With `carve`, also claims the
    coarse-index tiles that scan_fuse's carving will mark FREE blocks in (along the rays
    that carve: not those a bundle's first ray carves for). Idempotent: the host
    relaunches it while tiles were missed.
    """
    delta = scan_motion(q0, q1)
    n_runs = (n + run_length - 1) // run_length
    for index in range(spread_length(n_runs, threads)):
        run = spread_item(index, n_runs, threads)
        if run >= 0:
            geo = geometry(m)
            s_dense = dense_range(geo, spacing_rad)
            allocate_run(m, geo, pts, nrm, alpha, run * run_length,
                         ti.min(n, (run + 1) * run_length), n, q0, t0, delta, t1, min_range,
                         max_range, spacing_rad, behind_m, use_normals, ray_p, ray_n, s_dense,
                         carve)


@ti.func
def allocate_run(m: ti.template(), geo: ti.template(), pts: ti.template(), nrm: ti.template(),
                 alpha: ti.template(), first: ti.i32, end: ti.i32, n: ti.i32, q0: vec4,
                 t0: vec3, delta: vec3, t1: vec3, min_range: ti.f32, max_range: ti.f32,
                 spacing_rad: ti.f32, behind_m: ti.f32, use_normals: ti.template(),
                 ray_p: ti.template(), ray_n: ti.template(), s_dense: ti.f32,
                 carve: ti.template()):
    """One thread's run of scan_allocate: rays [first, end) set up and kept, the patches of
    the wide rays and of the bundles starting in the run allocated. One loop walks from the
    ray before the run (it only tells whether the first ray continues a bundle) to the end
    of the last open bundle, and each heavy function has one call site: a shader compiler
    (Mesa's lavapipe) takes minutes over a kernel that inlines them three times."""
    prev_key = ivec4(0)
    prev_n = vec4(0.0)
    head = vec3(0.0)  # the open bundle: its first point, sums and count (0: none)
    sum_dp = vec3(0.0)
    sum_n = vec3(0.0)
    count = 0.0
    i = ti.max(first - 1, 0)
    while i <= n and (i < end or count > 0.0):
        rp = vec4(0.0)
        rn = vec4(0.0)
        o = vec3(0.0)
        u = vec3(0.0)
        if i < n:  # noqa: SIM102 (Taichi's `and` evaluates both: pts[n] is past the end)
            if point_ok(pts[i], min_range, max_range):
                p, o, u, r, nr, c = ray_setup(pts[i], nrm[i], alpha[i], q0, t0, delta, t1,
                                              use_normals)
                rp = vec4(p, r)
                rn = vec4(nr, c)
        inside = first <= i < end
        if inside:
            if rn[3] > 0.0:
                ray_p[i] = rp
            ray_n[i] = rn
        key = bundle_key(geo, spacing_rad, rp, rn)
        joined = joins(prev_key, prev_n, key, rn)
        patches = 0  # this ray closes a bundle (its column) and/or is a wide ray (its patch)
        p0 = vec3(0.0)  # the closed bundle's, else the wide ray's
        n0 = vec3(0.0)
        k0 = 0
        if i >= first:
            if joined:
                if count > 0.0:
                    sum_dp += rp.xyz - head
                    sum_n += rn.xyz
                    count += 1.0
            else:
                if count > 0.0:
                    p0, n0 = bundle_point(head, sum_dp, sum_n, count)
                    patches = 1
                    count = 0.0
                if inside and rn[3] > 0.0:
                    if ti.static(carve):  # a bundle carves along its first ray
                        claim_carve_tiles(m, geo, i, o, u, rp[3], rn[3], s_dense)
                    k = footprint_steps(geo, rp[3], spacing_rad)
                    if k > 0:
                        if patches == 0:
                            p0, n0, k0 = rp.xyz, rn.xyz, k
                        patches += 1
                    else:
                        head = rp.xyz
                        sum_dp = vec3(0.0)
                        sum_n = rn.xyz
                        count = 1.0
        for e in range(patches):  # the second is always the wide ray
            if e == 1:
                p0, n0, k0 = rp.xyz, rn.xyz, footprint_steps(geo, rp[3], spacing_rad)
            allocate_patch(m, geo, p0, n0, k0, behind_m)
        prev_key = key
        prev_n = rn
        i += 1


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
    consecutive rays of a scan line often end in one voxel: such a bundle (`joins`) fuses
    once, as voxblox's merged integration does, as one point at its mean with its mean
    normal and its count as weight (the points' spread within a voxel is below what the
    map resolves; the mean keeps their noise averaged), and carves once, along its first
    ray, counting its rays as hits. Which rays bundle depends on the scan alone, not on
    runs or threads. One thread takes a run of run_length consecutive rays (a bundle
    belongs to the run of its first ray, and may reach past it) and sums the one-column
    bands in registers (slot j holds depth sample j), writing a voxel's sums once, when
    the next band's sample j leaves it. The sums are those of updating voxel by voxel,
    only added in another order, so run_length changes no result beyond f32 rounding.
    Runs are spread over the cpu threads as in scan_allocate.
    """
    k_w = -0.5 / (sigma_weight_m * sigma_weight_m)
    n_runs = (n + run_length - 1) // run_length
    for index in range(spread_length(n_runs, threads)):
        run = spread_item(index, n_runs, threads)
        if run >= 0:
            fuse_run(m, ray_p, ray_n, alpha, run * run_length,
                     ti.min(n, (run + 1) * run_length), n, t0, t1, spacing_rad, behind_m,
                     carve, k_w)


@ti.func
def fuse_run(m: ti.template(), ray_p: ti.template(), ray_n: ti.template(),
             alpha: ti.template(), first: ti.i32, end: ti.i32, n: ti.i32, t0: vec3, t1: vec3,
             spacing_rad: ti.f32, behind_m: ti.f32, carve: ti.template(), k_w: ti.f32):
    """One thread's run of rays [first, end) of scan_fuse: each ray with a patch carves and
    fills it straight into the map; each bundle of one-column rays starting in the run
    carves and fills its column into the run's slots (kept in registers until the run
    ends)."""
    geo = geometry(m)  # once per run: the map's geometry is read at run time
    n_s = band_samples(geo, behind_m)
    s_dense = dense_range(geo, spacing_rad)
    n_max = ti.static(m.band_slots)
    slot_g = ti.Matrix.zero(ti.i32, n_max, 3)
    slot_wd = ti.Vector.zero(ti.f32, n_max)
    slot_w = ti.Vector.zero(ti.f32, n_max)
    cb = ivec3(-(1 << 30))  # the block of the last flushed slot and its id
    bid = UNKNOWN
    prev_key = ivec4(0)
    prev_n = vec4(0.0)
    head = 0  # the open bundle: its first ray, sums and count (0: none)
    sum_dp = vec3(0.0)
    sum_n = vec3(0.0)
    count = 0.0
    i = ti.max(first - 1, 0)  # walked as in allocate_run, with the same single call sites
    while i <= n and (i < end or count > 0.0):
        rp = vec4(0.0)
        rn = vec4(0.0)
        if i < n:
            rp = ray_p[i]
            rn = ray_n[i]
        inside = first <= i < end
        key = bundle_key(geo, spacing_rad, rp, rn)
        joined = joins(prev_key, prev_n, key, rn)
        bands = 0  # this ray closes a bundle and/or is a wide ray: their carving and band
        h0 = head  # the closed bundle's (its first ray carves for all), else the wide ray's
        p0 = vec3(0.0)
        n0 = vec3(0.0)
        w0 = count
        k = 0
        if i >= first:
            if joined:
                if count > 0.0:
                    sum_dp += rp.xyz - ray_p[head].xyz
                    sum_n += rn.xyz
                    count += 1.0
            else:
                if count > 0.0:
                    p0, n0 = bundle_point(ray_p[head].xyz, sum_dp, sum_n, count)
                    w0 = count
                    bands = 1
                    count = 0.0
                if inside and rn[3] > 0.0:
                    k = footprint_steps(geo, rp[3], spacing_rad)
                    if k > 0:
                        bands += 1
                    else:
                        head = i
                        sum_dp = vec3(0.0)
                        sum_n = rn.xyz
                        count = 1.0
        for e in range(bands):
            k_e = 0
            if e == bands - 1 and k > 0:  # the wide ray comes last
                h0, p0, n0, w0, k_e = i, rp.xyz, rn.xyz, 1.0, k
            if ti.static(carve):
                o, u = ray_origin(ray_p, alpha, h0, t0, t1)
                carve_in_front(m, geo, h0, o, u, ray_p[h0][3], ray_n[h0][3], s_dense, w0)
            point_band(m, geo, p0, n0, k_e, behind_m, k_w, n_s, slot_g, slot_wd, slot_w, cb,
                       bid, w0)
        prev_key = key
        prev_n = rn
        i += 1
    flush_slots(m, geo, slot_g, slot_wd, slot_w)


@ti.func
def ray_origin(ray_p: ti.template(), alpha: ti.template(), i: ti.i32, t0: vec3, t1: vec3):
    """Sensor position and unit direction of ray i (as ray_setup)."""
    o = t0 + alpha[i] * (t1 - t0)
    return o, (ray_p[i].xyz - o) / ti.max(ray_p[i][3], 1e-9)


# ------------------------------------------------------------------- end of a build
@ti.kernel
def finalize_blocks(m: ti.template(), start: ti.i32, count: ti.i32):
    """Build-time sums -> distances for blocks [start, start+count).

    Voxels with band observations get their weighted mean distance; voxels only crossed by
    rays become free (+truncation) with the negated number of crossings as weight, a mark
    for `refine_free_voxels` (run next, then `unmark_free_voxels`).
    """
    trunc = m.truncation_m
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        w = ti.cast(m.weight[b, i, j, h], ti.f32)
        wd = ti.cast(m.sdf[b, i, j, h], ti.f32)
        if ti.static(m.exact_sums):
            w = fixed_value(m.sum_w[b, i, j, h])
            wd = fixed_value(m.sum_wd[b, i, j, h]) * trunc
        d = trunc
        if w > 0.0:
            d = ti.math.clamp(wd / w, -trunc, trunc)
        else:
            w = -m.free_hits[b, i, j, h]
        m.sdf[b, i, j, h] = ti.cast(d, m.sdf.dtype)
        m.weight[b, i, j, h] = ti.cast(w, m.weight.dtype)
        clear_sums(m, b, i, j, h)
        m.free_hits[b, i, j, h] = 0.0


@ti.kernel
def refine_free_voxels(m: ti.template(), start: ti.i32, count: ti.i32):
    """Free-only voxels next to the band: distance bounded through band neighbours.

    A ray crossing a voxel proves it free, not that the surface is a truncation away
    (rays skim floors and pass edges). For a band voxel n at k steps along one of the 26
    grid directions,
    d(v) <= k * voxel + |d(n)| (triangle inequality), so the smallest such bound replaces
    +truncation. Along each direction no neighbour farther than the bound found is read.
    """
    radius = ti.static(int(m.truncation_m / m.voxel_size_m + 0.999))  # voxels: no size
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        if m.weight[b, i, j, h] < 0.0:
            geo = geometry(m)
            vox = geo.scale[0]
            g = m.block_coord[b] * BLOCK + ivec3(i, j, h)
            best = geo.scale[2]
            for n in range(27):
                e = ivec3(n // 9 - 1, (n // 3) % 3 - 1, n % 3 - 1)
                length = ti.sqrt(ti.cast(e.dot(e), ti.f32))
                if n != 13:
                    for step in range(1, radius + 1):
                        if step * length * vox >= best:  # no farther neighbour can lower it
                            break
                        dw = voxel_dw_at(m, geo, g + step * e)
                        if dw[1] > 0.0:
                            best = ti.min(best, step * length * vox + ti.abs(dw[0]))
            m.sdf[b, i, j, h] = ti.cast(best, m.sdf.dtype)


@ti.kernel
def unmark_free_voxels(m: ti.template(), start: ti.i32, count: ti.i32):
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = start + k
        m.weight[b, i, j, h] = ti.abs(m.weight[b, i, j, h])

