"""Taichi pose helpers against scipy and mcl3d.core.geometry (NumPy) on random inputs."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from mcl3d.core import geometry as geo

N = 64


def _run(fn_name, *arrays):
    """Apply a kernels.se3 function to rows of the given arrays; returns numpy outputs."""
    import taichi as ti

    from mcl3d.kernels import se3

    vec = {3: ti.math.vec3, 4: ti.math.vec4, 1: ti.f32}
    n = len(arrays[0])

    if fn_name == "quat_mul":
        @ti.kernel
        def k(a: ti.types.ndarray(dtype=vec[4], ndim=1), b: ti.types.ndarray(dtype=vec[4], ndim=1),
              out: ti.types.ndarray(dtype=vec[4], ndim=1)):
            for i in range(n):
                out[i] = se3.quat_mul(a[i], b[i])
        out = np.zeros((n, 4), np.float32)
    elif fn_name == "rotate":
        @ti.kernel
        def k(a: ti.types.ndarray(dtype=vec[4], ndim=1), b: ti.types.ndarray(dtype=vec[3], ndim=1),
              out: ti.types.ndarray(dtype=vec[3], ndim=1)):
            for i in range(n):
                out[i] = se3.quat_rotate(a[i], b[i])
        out = np.zeros((n, 3), np.float32)
    elif fn_name == "exp_log":
        @ti.kernel
        def k(a: ti.types.ndarray(dtype=vec[3], ndim=1), out: ti.types.ndarray(dtype=ti.f32,
                                                                               ndim=2)):
            for i in range(n):
                q = se3.quat_exp(a[i])
                w = se3.quat_log(q)
                for j in ti.static(range(4)):
                    out[i, j] = q[j]
                for j in ti.static(range(3)):
                    out[i, 4 + j] = w[j]
        out = np.zeros((n, 7), np.float32)
    elif fn_name == "slerp":
        @ti.kernel
        def k(a: ti.types.ndarray(dtype=vec[4], ndim=1), b: ti.types.ndarray(dtype=vec[4], ndim=1),
              t: ti.types.ndarray(dtype=ti.f32, ndim=1),
              out: ti.types.ndarray(dtype=vec[4], ndim=1)):
            for i in range(n):
                out[i] = se3.quat_slerp(a[i], b[i], t[i])
        out = np.zeros((n, 4), np.float32)
    elif fn_name == "retract":
        @ti.kernel
        def k(q: ti.types.ndarray(dtype=vec[4], ndim=1), t: ti.types.ndarray(dtype=vec[3], ndim=1),
              xi: ti.types.ndarray(dtype=ti.f32, ndim=2),
              out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
            for i in range(n):
                qo, to = se3.pose_retract(q[i], t[i], ti.math.vec3(xi[i, 0], xi[i, 1], xi[i, 2]),
                                          ti.math.vec3(xi[i, 3], xi[i, 4], xi[i, 5]))
                qi, ti_ = se3.pose_inverse(qo, to)
                qc, tc = se3.pose_compose(qo, to, qi, ti_)
                for j in ti.static(range(4)):
                    out[i, j] = qo[j]
                    out[i, 7 + j] = qc[j]
                for j in ti.static(range(3)):
                    out[i, 4 + j] = to[j]
                    out[i, 11 + j] = tc[j]
        out = np.zeros((n, 14), np.float32)
    k(*[np.ascontiguousarray(a, dtype=np.float32) for a in arrays], out)
    return out


def _quats(rng, n=N):
    return Rotation.random(n, random_state=rng.integers(1 << 30)).as_quat()


def test_quat_mul_and_rotate_match_scipy(ti_runtime):
    rng = np.random.default_rng(0)
    a, b = _quats(rng), _quats(rng)
    got = _run("quat_mul", a, b)
    ref = (Rotation.from_quat(a) * Rotation.from_quat(b)).as_quat()
    np.testing.assert_allclose(got * np.sign(got[:, 3:]), ref * np.sign(ref[:, 3:]), atol=1e-6)
    v = rng.normal(size=(N, 3))
    np.testing.assert_allclose(_run("rotate", a, v), Rotation.from_quat(a).apply(v), atol=1e-5)


def test_exp_log_match_scipy_rotvec(ti_runtime):
    rng = np.random.default_rng(1)
    w = rng.normal(size=(N, 3))
    w *= (rng.uniform(0, 3.0, N) / np.linalg.norm(w, axis=1))[:, None]
    w[:4] *= 1e-7  # small-angle branch
    out = _run("exp_log", w)
    ref = Rotation.from_rotvec(w).as_quat()
    np.testing.assert_allclose(out[:, :4], ref, atol=1e-6)
    np.testing.assert_allclose(out[:, 4:], w, atol=1e-5)


def test_slerp_matches_scipy(ti_runtime):
    rng = np.random.default_rng(2)
    a, b = _quats(rng), _quats(rng)
    t = rng.uniform(0, 1, N)
    got = _run("slerp", a, b, t)
    ref = np.array([Slerp([0, 1], Rotation.from_quat([a[i], b[i]]))(t[i]).as_quat()
                    for i in range(N)])
    assert np.allclose(np.abs(np.einsum("ij,ij->i", got, ref)), 1.0, atol=1e-5)


def test_retract_is_the_se3_exponential_and_inverse_composes_to_identity(ti_runtime):
    rng = np.random.default_rng(3)
    q = _quats(rng)
    t = rng.normal(size=(N, 3))
    xi = rng.normal(scale=0.5, size=(N, 6))
    out = _run("retract", q, t, xi)
    T = geo.se3_from_tq(t, q) @ geo.se3_exp(xi)
    ref_t, ref_q = geo.tq_from_se3(T)
    assert np.allclose(np.abs(np.einsum("ij,ij->i", out[:, :4], ref_q)), 1.0, atol=1e-5)
    np.testing.assert_allclose(out[:, 4:7], ref_t, atol=1e-4)
    np.testing.assert_allclose(np.abs(out[:, 10]), 1.0, atol=1e-5)  # identity rotation
    np.testing.assert_allclose(out[:, 11:14], 0.0, atol=1e-4)


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_pose_interpolation_matches_numpy(ti_runtime, alpha):
    import taichi as ti

    from mcl3d.kernels import se3

    rng = np.random.default_rng(4)
    q0, q1 = _quats(rng, 8), _quats(rng, 8)
    t0, t1 = rng.normal(size=(8, 3)), rng.normal(size=(8, 3))

    @ti.kernel
    def k(q0: ti.types.ndarray(dtype=ti.math.vec4, ndim=1),
          t0: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
          q1: ti.types.ndarray(dtype=ti.math.vec4, ndim=1),
          t1: ti.types.ndarray(dtype=ti.math.vec3, ndim=1), a: ti.f32,
          out: ti.types.ndarray(dtype=ti.math.mat3, ndim=1),
          tout: ti.types.ndarray(dtype=ti.math.vec3, ndim=1)):
        for i in range(8):
            q, t = se3.pose_interpolate(q0[i], t0[i], q1[i], t1[i], a)
            out[i] = se3.quat_to_mat(q)
            tout[i] = t

    R = np.zeros((8, 3, 3), np.float32)
    tt = np.zeros((8, 3), np.float32)
    f32 = lambda x: np.ascontiguousarray(x, dtype=np.float32)  # noqa: E731
    k(f32(q0), f32(t0), f32(q1), f32(t1), alpha, R, tt)
    Ta, Tb = geo.se3_from_tq(t0, q0), geo.se3_from_tq(t1, q1)
    ref = geo.interpolate_se3(Ta, Tb, alpha)
    np.testing.assert_allclose(R, ref[:, :3, :3], atol=1e-5)
    np.testing.assert_allclose(tt, t0 + alpha * (t1 - t0), atol=1e-5)
