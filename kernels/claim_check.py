"""Kernels of the convergence check (mcl3d.localization.claim_check): test poses over the
map, the same poses moved to an earlier scan, the best test pose of each group, the filter's
particles near given poses, and fresh particles written over a stride of the set.

Test poses live in the SoA pose fields of a particle set (`pos`, `quat`); the check keeps the
poses of the current scan in a second pair of fields (`base_pos`, `base_quat`) and scores
each earlier scan of its window at base * T_curr_k with the ordinary likelihood kernels.
Every random draw is a counter-based hash of (seed, step, index, stream).
"""

import taichi as ti

from mcl3d.kernels.particles import _rpy_quat
from mcl3d.kernels.random import normal2
from mcl3d.kernels.se3 import pose_compose, quat_exp, quat_mul, quat_normalize

vec3 = ti.math.vec3
vec4 = ti.math.vec4
NEG = -3.0e38  # "no value" of a maximum
_TWO_PI = 6.283185307179586
S_N0, S_N1, S_N2 = 20, 22, 24  # random streams (each normal2 uses stream and stream + 1)


@ti.kernel
def grid_poses(positions: ti.template(), n_yaw: ti.i32, start: ti.i32, count: ti.i32,
               roll: ti.f32, pitch: ti.f32, pos: ti.template(), quat: ti.template()):
    """Test pose j = start + k (k < count) into slot k: position j // n_yaw, yaw
    2 pi (j % n_yaw) / n_yaw, with the given roll and pitch (R = Rz Ry Rx)."""
    for k in range(count):
        j = start + k
        pos[k] = positions[j // n_yaw]
        yaw = _TWO_PI * ti.cast(j % n_yaw, ti.f32) / ti.cast(n_yaw, ti.f32)
        quat[k] = _rpy_quat(roll, pitch, yaw)


@ti.kernel
def around_centres(centre_pos: ti.template(), centre_quat: ti.template(), per: ti.i32,
                   count: ti.i32, std_t: vec3, std_r: vec3, seed: ti.u32, step: ti.u32,
                   pos: ti.template(), quat: ti.template()):
    """Slot k (k < count) holds a pose around centre k // per: the centre itself when
    k % per == 0, else t = t_c + N(0, std_t), q = q_c exp(N(0, std_r))."""
    for k in range(count):
        c = k // per
        t = centre_pos[c]
        q = centre_quat[c]
        if k % per != 0:
            a = normal2(seed, step, ti.u32(k), ti.u32(S_N0))
            b = normal2(seed, step, ti.u32(k), ti.u32(S_N1))
            e = normal2(seed, step, ti.u32(k), ti.u32(S_N2))
            t = t + vec3(a[0], a[1], b[0]) * std_t
            q = quat_normalize(quat_mul(q, quat_exp(vec3(b[1], e[0], e[1]) * std_r)))
        pos[k] = t
        quat[k] = q


@ti.kernel
def moved_poses(base_pos: ti.template(), base_quat: ti.template(), n: ti.i32, t_rel: vec3,
                q_rel: vec4, pos: ti.template(), quat: ti.template()):
    """pose[k] = base[k] * T_rel: where each test pose of the current scan puts an earlier
    scan whose pose relative to the current one is T_rel (from the odometry)."""
    for k in range(n):
        q, t = pose_compose(base_quat[k], base_pos[k], q_rel, t_rel)
        pos[k] = t
        quat[k] = quat_normalize(q)


@ti.kernel
def reset_best(best: ti.template(), arg: ti.template(), n_groups: ti.i32):
    for g in range(n_groups):
        best[g] = NEG
        arg[g] = -1


@ti.kernel
def group_best(score: ti.template(), group: ti.template(), per: ti.i32, bins: ti.i32,
               start: ti.i32, count: ti.i32, best: ti.template()):
    """best[g] = max(best[g], score of each test pose j = start + k of group g =
    group[j // per] * bins + (j % per) * bins // per): a place (cell and yaw bin) of the
    grid, or with bins = 1 the block of `per` poses around one centre."""
    for k in range(count):
        j = start + k
        g = group[j // per] * bins + (j % per) * bins // per
        ti.atomic_max(best[g], score[k])


@ti.kernel
def group_arg(score: ti.template(), group: ti.template(), per: ti.i32, bins: ti.i32,
              start: ti.i32, count: ti.i32, best: ti.template(), arg: ti.template()):
    """arg[g] = the last test pose j of group g that holds its best (after group_best;
    the last of equals: the same pose on every run and thread count)."""
    for k in range(count):
        j = start + k
        g = group[j // per] * bins + (j % per) * bins // per
        if score[k] == best[g]:
            ti.atomic_max(arg[g], j)


@ti.kernel
def count_near(pos: ti.template(), quat: ti.template(), n: ti.i32, centre_pos: ti.template(),
               centre_quat: ti.template(), n_centres: ti.i32, radius_m: ti.f32,
               cos_half_angle: ti.f32, counts: ti.template()):
    """counts[c] = particles within radius_m and the rotation angle of cos_half_angle
    (|q . q_c| >= cos(angle / 2)) of centre c."""
    for c in range(n_centres):
        counts[c] = 0
    for i in range(n):
        for c in range(n_centres):
            if (pos[i] - centre_pos[c]).norm() <= radius_m and ti.abs(
                    quat[i].dot(centre_quat[c])) >= cos_half_angle:
                ti.atomic_add(counts[c], 1)


@ti.kernel
def inject(pos: ti.template(), quat: ti.template(), log_w: ti.template(),
           log_l: ti.template(), first: ti.i32, stride: ti.i32, count: ti.i32, t0: vec3,
           q0: vec4, std_t: vec3, std_r: vec3, log_w_value: ti.f32, log_l_value: ti.f32,
           seed: ti.u32, step: ti.u32):
    """Particles first + k * stride (k < count) around (q0, t0), as init_gaussian, with the
    given log-weight and place evidence: a stride takes a like share of every place."""
    for k in range(count):
        i = first + k * stride
        a = normal2(seed, step, ti.u32(i), ti.u32(S_N0))
        b = normal2(seed, step, ti.u32(i), ti.u32(S_N1))
        e = normal2(seed, step, ti.u32(i), ti.u32(S_N2))
        pos[i] = t0 + vec3(a[0], a[1], b[0]) * std_t
        quat[i] = quat_normalize(quat_mul(q0, quat_exp(vec3(b[1], e[0], e[1]) * std_r)))
        log_w[i] = log_w_value
        log_l[i] = log_l_value


@ti.kernel
def take(src_pos: ti.template(), src_quat: ti.template(), arg: ti.template(), n: ti.i32,
         dst_pos: ti.template(), dst_quat: ti.template()):
    """dst[c] = src[arg[c]] for c < n (unchanged where arg[c] < 0)."""
    for c in range(n):
        j = arg[c]
        if j >= 0:
            dst_pos[c] = src_pos[j]
            dst_quat[c] = src_quat[j]
