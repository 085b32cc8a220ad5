"""Cluster membership of every particle and the clusters' weights, on the device, for the
mode-preserving resampling of a global search (mcl3d.localization.search): the host sends at
most MAX_CENTRES cluster centres and gets back one weight per cluster, then sends one
resampling factor per cluster.

Weights are summed per block of SCAN_BLOCK particles, then over the blocks in order (no
atomic float sums): the same bits on every run and thread count.
"""

import taichi as ti

from mcl3d.kernels.resample import SCAN_BLOCK

MAX_CENTRES = 16
vec3 = ti.math.vec3
vec4 = ti.math.vec4


@ti.kernel
def label_by_centres(pos: ti.template(), quat: ti.template(), n: ti.i32,
                     centres: ti.template(), n_centres: ti.i32, radius_m: ti.f32,
                     cos_half_angle: ti.f32, label: ti.template()):
    """label[i] = the first centre (x y z qx qy qz qw) within `radius_m` of particle i and
    turned by at most the angle whose half has cosine `cos_half_angle`; -1 for none."""
    for i in range(n):
        found = -1
        for c in range(n_centres):
            if found < 0:
                ctr = centres[c]
                t = vec3(ctr[0], ctr[1], ctr[2])
                q = vec4(ctr[3], ctr[4], ctr[5], ctr[6])
                if (pos[i] - t).norm() <= radius_m and ti.abs(quat[i].dot(q)) >= cos_half_angle:
                    found = c
        label[i] = found


@ti.kernel
def label_weight_partials(w: ti.template(), label: ti.template(), n: ti.i32,
                          partial: ti.template()):
    """partial[b][c] = the sum of w over block b's particles labelled c."""
    for blk in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        acc = ti.Vector([0.0] * MAX_CENTRES)
        for k in range(blk * SCAN_BLOCK, ti.min((blk + 1) * SCAN_BLOCK, n)):
            lab = label[k]
            for c in ti.static(range(MAX_CENTRES)):
                acc[c] += ti.select(lab == c, w[k], 0.0)
        partial[blk] = acc


@ti.kernel
def label_factors(label: ti.template(), n: ti.i32, table: ti.template(), keep_max: ti.i32,
                  factor: ti.template()):
    """factor[i] = table[label[i] + 1] (table[0]: unlabelled), or the larger of that and
    the factor[i] already there when `keep_max`."""
    for i in range(n):
        f = table[label[i] + 1]
        if keep_max:
            f = ti.max(f, factor[i])
        factor[i] = f
