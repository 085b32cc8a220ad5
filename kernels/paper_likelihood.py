"""The paper's sensor model (Eisoldt et al., eq. 3; `sensor.model: paper`): one kernel over
particles x points, like `likelihood.scan_log_likelihood`, on a pool of precomputed values.

`build_paper_values` evaluates the Gaussian of eq. 3 once per voxel of the read-only map,
z_hit / sqrt(2 pi sigma^2) exp(-d^2 / 2 sigma^2) with d clamped to +-truncation (the paper:
cells beyond the truncation hold the truncation value), so the hot loop needs no exp. Voxels
of unallocated, FREE or outside cells read the value at d = truncation (two constant blocks
after the pool, reached through the same coarse-cell `slot` as the default model's codes).

`paper_scan_log_likelihood` interpolates the precomputed values trilinearly between the
eight voxel centres around each point (the paper's "pseudo-continuous state via
interpolation") and scores a particle by the sum over points of value + floor (floor =
z_rand / max_range, as in the authors' tsdf_localization, which sums the per-point terms;
the paper leaves their combination open):

log_w[i] += log(total) (untempered, as the paper); match[i] = fraction of points whose
interpolated value is at least `match_value` (the value at match_dist from a surface);
ll_mean[i] = log(total / M), the log of the mean per-point term.
"""

import taichi as ti

from mcl3d.kernels.likelihood import slot_of
from mcl3d.kernels.se3 import quat_to_mat
from mcl3d.kernels.tsdf_lookup import BLOCK

vec3 = ti.math.vec3


@ti.kernel
def build_paper_values(m: ti.template(), values: ti.template(), n_blocks: ti.i32,
                       sigma_m: ti.f32, z_hit: ti.f32):
    """Eq. 3 per voxel of the blocks [0, n_blocks) and of the two constant blocks after the
    pool (index capacity and capacity + 1: d = truncation everywhere)."""
    trunc = m.truncation_m
    norm = z_hit / ti.sqrt(2.0 * 3.141592653589793 * sigma_m * sigma_m)
    for b in range(n_blocks + 2):
        for lx, ly, lz in ti.ndrange(BLOCK, BLOCK, BLOCK):
            d = trunc
            if b < n_blocks:
                d = ti.math.clamp(ti.cast(m.sdf[b, lx, ly, lz], ti.f32), -trunc, trunc)
            dst = ti.select(b < n_blocks, b, m.capacity + b - n_blocks)
            values[dst, lx, ly, lz] = norm * ti.exp(-0.5 * d * d / (sigma_m * sigma_m))


@ti.func
def _value(m: ti.template(), values: ti.template(), slot: ti.template(), g) -> ti.f32:
    """The precomputed value of voxel g (the constant block outside the grid)."""
    s = slot_of(m, slot, g >> 3)
    return values[s, g[0] & (BLOCK - 1), g[1] & (BLOCK - 1), g[2] & (BLOCK - 1)]


@ti.kernel
def paper_scan_log_likelihood(m: ti.template(), values: ti.template(), slot: ti.template(),
                              order: ti.template(), pos: ti.template(), quat: ti.template(),
                              n: ti.i32,
                              pts: ti.template(), n_pts: ti.i32, floor: ti.f32,
                              match_value: ti.f32, log_w: ti.template(),
                              match: ti.template(), ll_mean: ti.template()):
    o = vec3(m.origin_m[0], m.origin_m[1], m.origin_m[2])
    inv_vox = 1.0 / m.voxel_size_m
    ti.loop_config(block_dim=64)
    for k in range(n):
        i = order[k]
        Rs = quat_to_mat(quat[i]) * inv_vox
        t = (pos[i] - o) * inv_vox - 0.5  # voxel centres at integer coordinates
        total = 0.0
        hits = 0
        for j in range(n_pts):
            u = Rs @ pts[j] + t
            base = ti.floor(u)
            f = u - base
            g0 = ti.cast(base, ti.i32)
            s = 0.0
            for cx, cy, cz in ti.static(ti.ndrange(2, 2, 2)):
                w = ((f[0] if cx else 1.0 - f[0]) * (f[1] if cy else 1.0 - f[1])
                     * (f[2] if cz else 1.0 - f[2]))
                s += w * _value(m, values, slot, g0 + ti.math.ivec3(cx, cy, cz))
            total += s + floor
            hits += ti.cast(s >= match_value, ti.i32)
        inv_m = 1.0 / ti.max(n_pts, 1)
        log_w[i] += ti.log(total)
        match[i] = hits * inv_m
        ll_mean[i] = ti.log(total * inv_m)
