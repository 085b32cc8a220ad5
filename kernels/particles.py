"""Particle kernels: initialization (Gaussian around a pose, uniform over free-space cells),
re-seeding a random fraction for recovery, and the SoA gather that applies resampling.

Particles live in separate f32 fields (structure of arrays): `pos` (vec3, T_map_lidar
translation), `quat` (vec4, x y z w), `log_w`. Every random draw is a counter-based hash of
(seed, step, particle, stream), so a run is the same on every backend and thread count.
"""

import taichi as ti

from mcl3d.kernels.random import counter_hash, normal2, uniform
from mcl3d.kernels.se3 import quat_exp, quat_mul, quat_normalize

vec3 = ti.math.vec3
vec4 = ti.math.vec4
_TWO_PI = 6.283185307179586

# random streams (each normal2 uses `stream` and `stream + 1`)
S_SELECT, S_N0, S_N1, S_N2, S_U0, S_U1, S_U2, S_U3, S_U4, S_U5 = (
    0, 2, 4, 6, 10, 11, 12, 13, 14, 15)


@ti.func
def _chosen(seed: ti.u32, step: ti.u32, i: ti.i32, fraction: ti.f32) -> bool:
    return fraction >= 1.0 or uniform(seed, step, ti.u32(i), ti.u32(S_SELECT)) < fraction


@ti.func
def _golden(i: ti.i32, offset: ti.u32) -> ti.f32:
    """frac(i / phi + offset / 2^32) in [0, 1): a low-discrepancy sequence (integer
    arithmetic: in f32, i / phi keeps no fraction bits for large i)."""
    bits = (ti.u32(i) * ti.u32(2654435769) + offset) >> ti.u32(8)
    return ti.cast(bits, ti.f32) * (1.0 / 16777216.0)


@ti.func
def _rpy_quat(roll: ti.f32, pitch: ti.f32, yaw: ti.f32) -> vec4:
    """R = Rz(yaw) Ry(pitch) Rx(roll) as an (x, y, z, w) quaternion."""
    qx = vec4(ti.sin(0.5 * roll), 0.0, 0.0, ti.cos(0.5 * roll))
    qy = vec4(0.0, ti.sin(0.5 * pitch), 0.0, ti.cos(0.5 * pitch))
    qz = vec4(0.0, 0.0, ti.sin(0.5 * yaw), ti.cos(0.5 * yaw))
    return quat_mul(qz, quat_mul(qy, qx))


@ti.kernel
def init_gaussian(pos: ti.template(), quat: ti.template(), log_w: ti.template(), n: ti.i32,
                  t0: vec3, q0: vec4, std_t: vec3, std_r: vec3, fraction: ti.f32,
                  seed: ti.u32, step: ti.u32):
    """Particles (all, or a random `fraction`) around (q0, t0): t = t0 + N(0, std_t) in the
    map frame, q = q0 exp(N(0, std_r)) (body-frame rotation noise)."""
    for i in range(n):
        if _chosen(seed, step, i, fraction):
            a = normal2(seed, step, ti.u32(i), ti.u32(S_N0))
            b = normal2(seed, step, ti.u32(i), ti.u32(S_N1))
            c = normal2(seed, step, ti.u32(i), ti.u32(S_N2))
            pos[i] = t0 + vec3(a[0], a[1], b[0]) * std_t
            w = vec3(b[1], c[0], c[1]) * std_r
            quat[i] = quat_normalize(quat_mul(q0, quat_exp(w)))
            log_w[i] = 0.0


@ti.kernel
def init_cells(pos: ti.template(), quat: ti.template(), log_w: ti.template(), n: ti.i32,
               cells: ti.types.ndarray(dtype=vec3, ndim=1), n_cells: ti.i32, cell_m: ti.f32,
               gravity: ti.i32, roll: ti.f32, pitch: ti.f32, std_rp: ti.f32,
               stratified: ti.i32, fraction: ti.f32, seed: ti.u32, step: ti.u32):
    """Uniform positions over equal cubic cells (`cells` = their lower corners, edge cell_m).

    gravity = 1: roll/pitch from the IMU's gravity (+ N(0, std_rp)), yaw uniform;
    gravity = 0: rotations uniform on SO(3) (Shoemake's method from three uniforms).
    Stratified, not independent: particle i takes a random cell of the i-th of n equal runs
    of the cell list, and its yaw is the i-th point of a golden-ratio sequence, so every part
    of the free space gets its share of particles and neighbouring ones look in different
    directions (independent draws leave random holes, and a hole on the true pose is a
    failed global localization). stratified = 0: independent draws (a uniform cell, and
    with gravity a uniform yaw), as the paper samples.
    """
    per_particle = ti.cast(n_cells, ti.f32) / ti.cast(n, ti.f32)
    yaw_offset = counter_hash(seed, step, ti.u32(0), ti.u32(S_U4))
    for i in range(n):
        if _chosen(seed, step, i, fraction):
            u0 = uniform(seed, step, ti.u32(i), ti.u32(S_U0))
            k = ti.min(ti.cast((ti.cast(i, ti.f32) + u0) * per_particle, ti.i32), n_cells - 1)
            if not stratified:
                k = ti.min(ti.cast(u0 * ti.cast(n_cells, ti.f32), ti.i32), n_cells - 1)
            off = vec3(uniform(seed, step, ti.u32(i), ti.u32(S_U1)),
                       uniform(seed, step, ti.u32(i), ti.u32(S_U2)),
                       uniform(seed, step, ti.u32(i), ti.u32(S_U3)))
            pos[i] = cells[k] + off * cell_m
            q = vec4(0.0, 0.0, 0.0, 1.0)
            if gravity:
                g = normal2(seed, step, ti.u32(i), ti.u32(S_N0))
                yaw_u = _golden(i, yaw_offset)
                if not stratified:
                    yaw_u = uniform(seed, step, ti.u32(i), ti.u32(S_U4))
                q = _rpy_quat(roll + std_rp * g[0], pitch + std_rp * g[1], _TWO_PI * yaw_u)
            else:
                u1 = uniform(seed, step, ti.u32(i), ti.u32(S_U4))
                u2 = uniform(seed, step, ti.u32(i), ti.u32(S_U5))
                u3 = uniform(seed, step, ti.u32(i), ti.u32(S_N1))
                r1 = ti.sqrt(1.0 - u1)
                r2 = ti.sqrt(u1)
                q = vec4(r1 * ti.sin(_TWO_PI * u2), r1 * ti.cos(_TWO_PI * u2),
                         r2 * ti.sin(_TWO_PI * u3), r2 * ti.cos(_TWO_PI * u3))
            quat[i] = quat_normalize(q)
            log_w[i] = 0.0


@ti.kernel
def gather(src_pos: ti.template(), src_quat: ti.template(), parent: ti.template(),
           n_out: ti.i32, dst_pos: ti.template(), dst_quat: ti.template(),
           log_w: ti.template()):
    """dst[k] = src[parent[k]] for the resampled set; weights become uniform (log_w = 0)."""
    for k in range(n_out):
        j = parent[k]
        dst_pos[k] = src_pos[j]
        dst_quat[k] = src_quat[j]
        log_w[k] = 0.0


@ti.kernel
def add_scaled(x: ti.template(), y: ti.template(), n: ti.i32, scale: ti.f32):
    """x += scale * y over the first n entries (re-tempering a likelihood increment)."""
    for i in range(n):
        x[i] += scale * y[i]


@ti.kernel
def apply_factors(w: ti.template(), factor: ti.template(), n: ti.i32):
    """w *= factor over the first n entries (mode-preserving resampling weights)."""
    for i in range(n):
        w[i] *= factor[i]


@ti.kernel
def log_inverse_parent_factor(factor: ti.template(), parent: ti.template(), n_out: ti.i32,
                              log_w: ti.template()):
    """log_w[k] = -log(factor[parent[k]]): each copy keeps its parent's share of the
    posterior after resampling by weight * factor."""
    for k in range(n_out):
        log_w[k] = -ti.log(factor[parent[k]])
