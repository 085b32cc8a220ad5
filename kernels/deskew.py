"""Per-point motion compensation: move each point into the sensor frame at the reference time."""

import taichi as ti

from mcl3d.kernels.se3 import pose_retract, quat_rotate


@ti.kernel
def deskew_points(points: ti.types.ndarray(), times: ti.types.ndarray(), n: ti.i32,
                  twist_w: ti.math.vec3, twist_v: ti.math.vec3, out: ti.types.ndarray()):
    """out_i = exp(t_i * twist) p_i, twist = (w, v) the constant body velocity (rotation first)."""
    for i in range(n):
        q, t = pose_retract(ti.math.vec4(0.0, 0.0, 0.0, 1.0), ti.math.vec3(0.0),
                            times[i] * twist_w, times[i] * twist_v)
        p = quat_rotate(q, ti.math.vec3(points[i, 0], points[i, 1], points[i, 2])) + t
        for a in ti.static(range(3)):
            out[i, a] = p[a]
