"""Pose helpers for kernels: f32 unit quaternions (x, y, z, w), Hamilton, plus translations.

Kernels hold poses as `q` (vec4) + `t` (vec3), mapping points `p -> R(q) p + t`, the same
`T_a_b` convention as mcl3d.core.geometry on the numpy side. Tangent vectors are rotation first.
"""

import taichi as ti

vec3 = ti.math.vec3
vec4 = ti.math.vec4


@ti.func
def quat_mul(a: vec4, b: vec4) -> vec4:
    """Hamilton product a*b of (x, y, z, w) quaternions (rotation b first, then a)."""
    return vec4(
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    )


@ti.func
def quat_conj(q: vec4) -> vec4:
    return vec4(-q[0], -q[1], -q[2], q[3])


@ti.func
def quat_normalize(q: vec4) -> vec4:
    return q / ti.max(q.norm(), 1e-12)


@ti.func
def quat_rotate(q: vec4, v: vec3) -> vec3:
    """R(q) v without building the matrix: v + 2w (u x v) + 2 u x (u x v)."""
    u = vec3(q[0], q[1], q[2])
    c = 2.0 * u.cross(v)
    return v + q[3] * c + u.cross(c)


@ti.func
def quat_to_mat(q: vec4) -> ti.math.mat3:
    x, y, z, w = q[0], q[1], q[2], q[3]
    return ti.math.mat3(
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )


@ti.func
def quat_exp(w: vec3) -> vec4:
    """Unit quaternion of the rotation vector w (angle |w| about w/|w|)."""
    theta = w.norm()
    half = 0.5 * theta
    # sin(half)/theta with its Taylor series near 0 (no 0/0)
    k = 0.5 - theta * theta / 48.0
    if theta > 1e-4:
        k = ti.sin(half) / theta
    return vec4(k * w[0], k * w[1], k * w[2], ti.cos(half))


@ti.func
def quat_log(q: vec4) -> vec3:
    """Rotation vector of a unit quaternion (shortest rotation, angle in [0, pi])."""
    qq = q
    if qq[3] < 0.0:
        qq = -qq
    u = vec3(qq[0], qq[1], qq[2])
    s = u.norm()
    k = 2.0 / ti.max(qq[3], 1e-12)  # small-angle limit of 2 atan2(s, w) / s
    if s > 1e-6:
        k = 2.0 * ti.atan2(s, qq[3]) / s
    return k * u


@ti.func
def quat_slerp(a: vec4, b: vec4, alpha: ti.f32) -> vec4:
    """Spherical interpolation a -> b (shortest path) at alpha in [0, 1]."""
    bb = b
    if a.dot(b) < 0.0:
        bb = -b
    delta = quat_log(quat_mul(quat_conj(a), bb))
    return quat_normalize(quat_mul(a, quat_exp(alpha * delta)))


@ti.func
def pose_compose(q_ab: vec4, t_ab: vec3, q_bc: vec4, t_bc: vec3):
    """T_ac = T_ab T_bc, returned as (q_ac, t_ac)."""
    return quat_normalize(quat_mul(q_ab, q_bc)), quat_rotate(q_ab, t_bc) + t_ab


@ti.func
def pose_inverse(q: vec4, t: vec3):
    qi = quat_conj(q)
    return qi, -quat_rotate(qi, t)


@ti.func
def pose_interpolate(q0: vec4, t0: vec3, q1: vec4, t1: vec3, alpha: ti.f32):
    """Pose between two poses: slerp of rotation, lerp of translation (as for deskewing)."""
    return quat_slerp(q0, q1, alpha), t0 + alpha * (t1 - t0)


@ti.func
def so3_left_jacobian_apply(w: vec3, v: vec3) -> vec3:
    """J_l(w) v = v + (1 - cos θ)/θ² (w × v) + (θ - sin θ)/θ³ (w × (w × v))."""
    theta2 = w.dot(w)
    a = 0.5 - theta2 / 24.0
    b = 1.0 / 6.0 - theta2 / 120.0
    if theta2 > 1e-6:
        theta = ti.sqrt(theta2)
        a = (1.0 - ti.cos(theta)) / theta2
        b = (theta - ti.sin(theta)) / (theta2 * theta)
    wv = w.cross(v)
    return v + a * wv + b * w.cross(wv)


@ti.func
def so3_left_jacobian_inv_apply(w: vec3, v: vec3) -> vec3:
    """J_l(w)^-1 v = v - (w × v) / 2 + (1/θ² - (1 + cos θ) / (2 θ sin θ)) (w × (w × v))."""
    theta2 = w.dot(w)
    c = 1.0 / 12.0 + theta2 / 720.0
    if theta2 > 1e-6:
        theta = ti.sqrt(theta2)
        c = 1.0 / theta2 - (1.0 + ti.cos(theta)) / (2.0 * theta * ti.sin(theta))
    wv = w.cross(v)
    return v - 0.5 * wv + c * w.cross(wv)


@ti.func
def pose_retract(q: vec4, t: vec3, xi_w: vec3, xi_v: vec3):
    """T exp(xi): right perturbation by a rotation-first tangent (wx, wy, wz, vx, vy, vz)."""
    dq = quat_exp(xi_w)
    dt = so3_left_jacobian_apply(xi_w, xi_v)
    return quat_normalize(quat_mul(q, dq)), t + quat_rotate(q, dt)
