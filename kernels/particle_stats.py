"""Reductions and gathers over the particle set, so that only bounded results leave the
device: the ESS of a tempered increment (annealing), weighted sums (match ratio, mean
log-likelihood), the first heaviest particle, the particles a sample index selects, and the
moments of the weighted mean pose and of the tangent covariance about it (`estimate.mean:
all`). Sums are block-ordered (SCAN_BLOCK particles per block, then the blocks in order, as
in `resample`): the same bits on every run and thread count.
"""

import taichi as ti

from mcl3d.kernels.resample import SCAN_BLOCK
from mcl3d.kernels.se3 import (
    quat_conj,
    quat_log,
    quat_mul,
    quat_normalize,
    quat_rotate,
    so3_left_jacobian_inv_apply,
)

# the upper triangles (i <= j) of a 4x4 and a 6x6 symmetric matrix, row by row
_QI, _QJ = zip(*[(i, j) for i in range(4) for j in range(i, 4)], strict=True)
_XI, _XJ = zip(*[(i, j) for i in range(6) for j in range(i, 6)], strict=True)


@ti.kernel
def tempered_sums(log_w: ti.template(), inc: ti.template(), n: ti.i32, coef: ti.f32,
                  partial: ti.template(), sums: ti.template()):
    """sums = (sum w, sum w^2) of w = exp(log_w + coef * inc - shift), shift the largest
    exponent, summed per block then over the blocks in order: one launch per candidate
    tempering of the annealing's bisection."""
    shift = -3.0e38
    for i in range(n):
        ti.atomic_max(shift, log_w[i] + coef * inc[i])
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        s = 0.0
        s2 = 0.0
        for k in range(b * SCAN_BLOCK, ti.min((b + 1) * SCAN_BLOCK, n)):
            wk = ti.exp(log_w[k] + coef * inc[k] - shift)
            s += wk
            s2 += wk * wk
        partial[b] = ti.math.vec2(s, s2)
    for _ in range(1):
        s = 0.0
        s2 = 0.0
        for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
            s += partial[b][0]
            s2 += partial[b][1]
        sums[0] = s
        sums[1] = s2


@ti.kernel
def weighted_partials(w: ti.template(), a: ti.template(), b: ti.template(), n: ti.i32,
                      partial: ti.template()):
    """partial[k] = (sum w * a, sum w * b) over block k."""
    for blk in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        sa = 0.0
        sb = 0.0
        for k in range(blk * SCAN_BLOCK, ti.min((blk + 1) * SCAN_BLOCK, n)):
            sa += w[k] * a[k]
            sb += w[k] * b[k]
        partial[blk] = ti.math.vec2(sa, sb)


@ti.kernel
def first_index_of(x: ti.template(), n: ti.i32, value: ti.f32) -> ti.i32:
    """The smallest i < n with x[i] == value (n when there is none)."""
    first = n
    for i in range(n):
        if x[i] == value:
            ti.atomic_min(first, i)
    return first


@ti.kernel
def gather_poses(pos: ti.template(), quat: ti.template(), idx: ti.template(), k: ti.i32,
                 out_pos: ti.template(), out_quat: ti.template()):
    """out[s] = particle idx[s] for s < k."""
    for s in range(k):
        j = idx[s]
        out_pos[s] = pos[j]
        out_quat[s] = quat[j]


@ti.kernel
def gather_values(x: ti.template(), idx: ti.template(), k: ti.i32, out: ti.template()):
    """out[s] = x[idx[s]] for s < k."""
    for s in range(k):
        out[s] = x[idx[s]]


@ti.kernel
def pose_moment_partials(pos: ti.template(), quat: ti.template(), w: ti.template(), n: ti.i32,
                         partial: ti.template()):
    """partial[b] = block b's (sum w, sum w t (3), sum w q q^T (the 10 entries xx xy xz xw
    yy yz yw zz zw ww)) of the unit quaternions: the weighted mean pose's moments."""
    for blk in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        acc = ti.Vector([0.0] * 14)
        for k in range(blk * SCAN_BLOCK, ti.min((blk + 1) * SCAN_BLOCK, n)):
            wk = w[k]
            q = quat_normalize(quat[k])
            acc[0] += wk
            for a in ti.static(range(3)):
                acc[1 + a] += wk * pos[k][a]
            for e in ti.static(range(10)):
                acc[4 + e] += wk * q[_QI[e]] * q[_QJ[e]]
        partial[blk] = acc


@ti.kernel
def tangent_moment_partials(pos: ti.template(), quat: ti.template(), w: ti.template(),
                            n: ti.i32, t_mean: ti.math.vec3, q_mean: ti.math.vec4,
                            partial: ti.template()):
    """partial[b] = block b's (sum w xi (6), sum w xi_i xi_j (the 21 entries i <= j)) of
    xi = se3_log(T_mean^-1 T_k), rotation first: the covariance about the mean pose."""
    q_inv = quat_conj(q_mean)
    for blk in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        acc = ti.Vector([0.0] * 27)
        for k in range(blk * SCAN_BLOCK, ti.min((blk + 1) * SCAN_BLOCK, n)):
            wk = w[k]
            rot = quat_log(quat_mul(q_inv, quat_normalize(quat[k])))
            v = so3_left_jacobian_inv_apply(rot, quat_rotate(q_inv, pos[k] - t_mean))
            xi = ti.Vector([rot[0], rot[1], rot[2], v[0], v[1], v[2]])
            for a in ti.static(range(6)):
                acc[a] += wk * xi[a]
            for e in ti.static(range(21)):
                acc[6 + e] += wk * xi[_XI[e]] * xi[_XJ[e]]
        partial[blk] = acc


@ti.kernel
def sum_vector_partials(partial: ti.template(), n: ti.i32, out: ti.template()):
    """out = the sum of the block partials of n particles, in block order."""
    out[0] = ti.Vector([0.0] * out.n)
    ti.loop_config(serialize=True)
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        out[0] += partial[b]
