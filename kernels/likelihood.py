"""The scan likelihood of every particle: one kernel over particles x points.

Parallel over particles; each thread transforms the M scan points (lidar frame) by its pose
and looks up the nearest TSDF voxel. `cache_block` (static) keeps the last coarse-cell lookup
like the peer's CUDA kernel; on the cpu backend it measured slower than a plain lookup
(the coarse grid stays in cache; bench/bench_localize.py reports both). Per point
(docs/sensor-model.md):

- observed voxel with d < truncation: log(z_hit exp(-d^2 / (2 sigma^2)) + z_rand), from a
  table filled by mcl3d.sensor_model.hit_table;
- observed free space (d >= truncation, or a FREE block): log_free (a penalty);
- unknown or outside the map: log_unknown (a neutral constant).

log_w[i] += tempering * sum(log-likelihoods); match[i] = fraction of points within
match_dist of a surface; ll_mean[i] = the mean per-point log-likelihood of this scan.
"""

import taichi as ti

from mcl3d.kernels.se3 import quat_to_mat
from mcl3d.kernels.tsdf import BLOCK, FREE

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
TABLE_SIZE = 1024


@ti.func
def point_log_likelihood(d: ti.f32, w: ti.f32, b: ti.i32, trunc: ti.f32, table: ti.template(),
                         log_free: ti.f32, log_unknown: ti.f32):
    """Per-point log-likelihood; the hit term is read from a table over d in [-trunc, trunc)
    (TABLE_SIZE bins, 0.4 mm at 0.2 m truncation) instead of an exp and a log per point."""
    ll = log_unknown
    if b == FREE:
        ll = log_free
    elif b >= 0 and w > 0.0:
        if d >= trunc * 0.999:
            ll = log_free
        else:
            k = ti.cast((d + trunc) * (TABLE_SIZE * 0.5 / trunc), ti.i32)
            ll = table[ti.math.clamp(k, 0, TABLE_SIZE - 1)]
    return ll


@ti.kernel
def scan_log_likelihood(m: ti.template(), pos: ti.template(), quat: ti.template(), n: ti.i32,
                        pts: ti.template(), n_pts: ti.i32, table: ti.template(),
                        log_free: ti.f32, log_unknown: ti.f32,
                        match_dist_m: ti.f32, tempering: ti.f32, log_w: ti.template(),
                        match: ti.template(), ll_mean: ti.template(),
                        cache_block: ti.template()):
    o = vec3(m.origin_m[0], m.origin_m[1], m.origin_m[2])
    inv_vox = 1.0 / m.voxel_size_m
    trunc = m.truncation_m
    dims = ivec3(m.coarse_dims[0], m.coarse_dims[1], m.coarse_dims[2])
    for i in range(n):
        R = quat_to_mat(quat[i])
        t = (pos[i] - o) * inv_vox
        Rs = R * inv_vox
        total = 0.0
        hits = 0
        last_c = ivec3(-(1 << 30))
        b = -1
        for j in range(n_pts):
            g = ti.cast(ti.floor(Rs @ pts[j] + t), ti.i32)
            c = g >> 3
            if ti.static(cache_block):
                if (c != last_c).any():
                    last_c = c
                    b = -1
                    if 0 <= c[0] < dims[0] and 0 <= c[1] < dims[1] and 0 <= c[2] < dims[2]:
                        b = m.coarse[c[0], c[1], c[2]]
            else:
                b = -1
                if 0 <= c[0] < dims[0] and 0 <= c[1] < dims[1] and 0 <= c[2] < dims[2]:
                    b = m.coarse[c[0], c[1], c[2]]
            d = trunc
            w = 0.0
            if b >= 0:
                lx = g[0] & (BLOCK - 1)
                ly = g[1] & (BLOCK - 1)
                lz = g[2] & (BLOCK - 1)
                d = ti.cast(m.sdf[b, lx, ly, lz], ti.f32)
                w = 1.0  # never-observed voxels hold d = +trunc: only then is w needed
                if d >= trunc * 0.999:
                    w = ti.cast(m.weight[b, lx, ly, lz], ti.f32)
            total += point_log_likelihood(d, w, b, trunc, table, log_free, log_unknown)
            if b >= 0 and w > 0.0 and ti.abs(d) < match_dist_m:
                hits += 1
        inv_m = 1.0 / ti.max(n_pts, 1)
        log_w[i] += tempering * total
        match[i] = hits * inv_m
        ll_mean[i] = total * inv_m
