"""Motion update: every particle moves by the measured relative motion plus its own noise.

T_i <- T_i dT exp(delta_i), delta_i ~ N(0, diag(std_rot^2, std_trans^2)) as a rotation-first
tangent in the particle's lidar frame (right perturbation, CONVENTIONS §2). The noise
standard deviations come from the host, where they grow with the size of dT.
"""

import taichi as ti

from mcl3d.kernels.random import normal2
from mcl3d.kernels.se3 import pose_compose, pose_retract

vec3 = ti.math.vec3
vec4 = ti.math.vec4

S_MOTION = 20  # random streams 20..25


@ti.kernel
def propagate(pos: ti.template(), quat: ti.template(), n: ti.i32, dq: vec4, dt: vec3,
              std_rot: vec3, std_trans: vec3, seed: ti.u32, step: ti.u32):
    for i in range(n):
        a = normal2(seed, step, ti.u32(i), ti.u32(S_MOTION))
        b = normal2(seed, step, ti.u32(i), ti.u32(S_MOTION + 2))
        c = normal2(seed, step, ti.u32(i), ti.u32(S_MOTION + 4))
        q, t = pose_compose(quat[i], pos[i], dq, dt)
        q2, t2 = pose_retract(q, t, vec3(a[0], a[1], b[0]) * std_rot,
                              vec3(b[1], c[0], c[1]) * std_trans)
        quat[i] = q2
        pos[i] = t2
