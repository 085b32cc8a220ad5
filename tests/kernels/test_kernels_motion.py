"""Motion, initialization and gather kernels against NumPy on small particle sets."""

import numpy as np
import pytest

from mcl3d.core import geometry


def fields(n):
    import taichi as ti

    return (ti.Vector.field(3, ti.f32, shape=n), ti.Vector.field(4, ti.f32, shape=n),
            ti.field(ti.f32, shape=n))


def poses_of(pos, quat):
    return geometry.se3_from_tq(pos.to_numpy().astype(np.float64),
                                quat.to_numpy().astype(np.float64))


def test_propagate_moments(ti_runtime):
    import taichi as ti

    from mcl3d.kernels.motion import propagate

    n = 40_000
    pos, quat, _ = fields(n)
    T0 = geometry.se3(geometry.rpy_to_rot(0.2, -0.1, 1.0), [1.0, 2.0, 0.5])
    t0, q0 = geometry.tq_from_se3(T0)
    pos.from_numpy(np.tile(t0, (n, 1)).astype(np.float32))
    quat.from_numpy(np.tile(q0, (n, 1)).astype(np.float32))
    dT = geometry.se3(geometry.rpy_to_rot(0.0, 0.05, 0.3), [0.5, -0.1, 0.02])
    dt, dq = geometry.tq_from_se3(dT)
    std_r = np.array([0.02, 0.03, 0.05])
    std_t = np.array([0.1, 0.05, 0.01])
    propagate(pos, quat, n, ti.math.vec4(*dq), ti.math.vec3(*dt), ti.math.vec3(*std_r),
              ti.math.vec3(*std_t), 7, 3)
    xi = geometry.se3_log(geometry.se3_inverse(T0 @ dT)[None] @ poses_of(pos, quat))
    np.testing.assert_allclose(xi.mean(axis=0), 0.0, atol=2e-3)
    np.testing.assert_allclose(xi.std(axis=0), np.concatenate([std_r, std_t]), rtol=0.03)
    assert abs(np.corrcoef(xi[:, 0], xi[:, 3])[0, 1]) < 0.03
    first = pos.to_numpy().copy()
    pos.from_numpy(np.tile(t0, (n, 1)).astype(np.float32))
    quat.from_numpy(np.tile(q0, (n, 1)).astype(np.float32))
    propagate(pos, quat, n, ti.math.vec4(*dq), ti.math.vec3(*dt), ti.math.vec3(*std_r),
              ti.math.vec3(*std_t), 7, 3)
    np.testing.assert_array_equal(pos.to_numpy(), first)  # counter RNG: reproducible


def test_propagate_without_noise_composes_exactly(ti_runtime):
    import taichi as ti

    from mcl3d.kernels.motion import propagate

    rng = np.random.default_rng(1)
    n = 50
    pos, quat, _ = fields(n)
    T = geometry.se3_from_tq(rng.normal(size=(n, 3)),
                             geometry.rot_to_quat(geometry.random_rotations(rng, n)))
    t, q = geometry.tq_from_se3(T)
    pos.from_numpy(t.astype(np.float32))
    quat.from_numpy(q.astype(np.float32))
    dT = geometry.se3(geometry.rpy_to_rot(0.1, 0.2, -0.3), [0.3, 0.2, -0.1])
    dt, dq = geometry.tq_from_se3(dT)
    propagate(pos, quat, n, ti.math.vec4(*dq), ti.math.vec3(*dt), ti.math.vec3(0.0),
              ti.math.vec3(0.0), 0, 0)
    np.testing.assert_allclose(poses_of(pos, quat), T @ dT, atol=1e-5)


def test_init_gaussian_and_fraction(ti_runtime):
    import taichi as ti

    from mcl3d.kernels.particles import init_gaussian

    n = 30_000
    pos, quat, log_w = fields(n)
    T0 = geometry.se3(geometry.rpy_to_rot(0.0, 0.0, 2.0), [3.0, -1.0, 0.7])
    t0, q0 = geometry.tq_from_se3(T0)
    std_t, std_r = np.array([0.5, 0.3, 0.1]), np.array([0.05, 0.04, 0.3])
    log_w.from_numpy(np.full(n, -5.0, np.float32))
    init_gaussian(pos, quat, log_w, n, ti.math.vec3(*t0), ti.math.vec4(*q0),
                  ti.math.vec3(*std_t), ti.math.vec3(*std_r), 1.0, 3, 1)
    p = pos.to_numpy()
    np.testing.assert_allclose(p.mean(axis=0), t0, atol=0.01)
    np.testing.assert_allclose(p.std(axis=0), std_t, rtol=0.03)
    R = geometry.quat_to_rot(quat.to_numpy().astype(np.float64))
    w = geometry.so3_log(T0[:3, :3].T[None] @ R)
    np.testing.assert_allclose(w.std(axis=0), std_r, rtol=0.03)
    assert np.all(log_w.to_numpy() == 0.0)
    # re-seed a fraction: about that share changes, the rest stays bit-identical
    before = pos.to_numpy().copy()
    init_gaussian(pos, quat, log_w, n, ti.math.vec3(0.0), ti.math.vec4(0, 0, 0, 1),
                  ti.math.vec3(1.0), ti.math.vec3(0.1), 0.25, 3, 2)
    changed = np.any(pos.to_numpy() != before, axis=1)
    assert abs(changed.mean() - 0.25) < 0.015


def test_init_cells_uniform_and_gravity(ti_runtime):
    from mcl3d.kernels.particles import init_cells

    n = 40_000
    pos, quat, log_w = fields(n)
    cells = np.array([[0, 0, 0], [2, 0, 0], [0, 4, 1]], np.float32)
    init_cells(pos, quat, log_w, n, cells, len(cells), 0.5, 0, 0.0, 0.0, 0.0, 1, 1.0, 5, 0)
    p = pos.to_numpy()
    owner = np.argmin(np.linalg.norm((p[:, None, :] - (cells[None] + 0.25)), axis=2), axis=1)
    inside = np.all((p >= cells[owner]) & (p < cells[owner] + 0.5), axis=1)
    assert inside.all()
    np.testing.assert_allclose(np.bincount(owner) / n, 1 / 3, atol=0.01)
    # uniform on SO(3): E[R] = 0 and the angle has density (1 - cos t) / pi
    R = geometry.quat_to_rot(quat.to_numpy().astype(np.float64))
    assert np.abs(R.mean(axis=0)).max() < 0.02
    angle = geometry.rotation_angle(R)
    cdf = lambda t: (t - np.sin(t)) / np.pi  # noqa: E731
    for t in (0.5, 1.5, 2.5):
        assert abs(np.mean(angle <= t) - cdf(t)) < 0.01
    # gravity mode: roll/pitch near the given ones, yaw uniform
    init_cells(pos, quat, log_w, n, cells, len(cells), 0.5, 1, 0.1, -0.2, 0.01, 1, 1.0, 5, 1)
    rpy = geometry.rot_to_rpy(geometry.quat_to_rot(quat.to_numpy().astype(np.float64)))
    np.testing.assert_allclose(rpy[:, 0].mean(), 0.1, atol=2e-3)
    np.testing.assert_allclose(rpy[:, 1].mean(), -0.2, atol=2e-3)
    np.testing.assert_allclose(rpy[:, 1].std(), 0.01, rtol=0.05)
    hist, _ = np.histogram(rpy[:, 2], bins=8, range=(-np.pi, np.pi))
    np.testing.assert_allclose(hist / n, 1 / 8, atol=0.01)


def test_init_cells_is_stratified(ti_runtime):
    """Every run of n_cells / n cells gets its particle, and the yaws of any few
    consecutive particles are spread: no cell and no heading left out by chance, unlike
    independent draws (which leave about 1/e of 1000 cells empty with 1000 particles)."""
    from mcl3d.kernels.particles import init_cells

    n_cells = 1000
    cells = np.column_stack([np.arange(n_cells), np.zeros(n_cells), np.zeros(n_cells)]
                            ).astype(np.float32)
    for n in (1000, 4000, 250):
        pos, quat, log_w = fields(n)
        init_cells(pos, quat, log_w, n, cells, n_cells, 1.0, 1, 0.0, 0.0, 0.0, 1, 1.0, 5, 0)
        cell = np.floor(pos.to_numpy()[:, 0]).astype(int)
        per_cell = np.bincount(cell, minlength=n_cells)
        if n >= n_cells:
            assert per_cell.min() == per_cell.max() == n // n_cells
        else:
            runs = per_cell.reshape(n, -1).sum(axis=1)
            assert (runs == 1).all()
        yaw = geometry.rot_to_rpy(geometry.quat_to_rot(quat.to_numpy().astype(np.float64)))[:, 2]
        for start in range(0, n - 16, 16):  # 16 consecutive particles: the largest yaw
            y = np.sort(yaw[start:start + 16])  # gap is 0.09 turn (independent: 0.2 typically)
            assert np.diff(np.r_[y, y[0] + 2 * np.pi]).max() < 0.1 * 2 * np.pi


@pytest.mark.parametrize("n_out", [100, 64, 150])
def test_gather_matches_numpy(ti_runtime, n_out):
    import taichi as ti

    from mcl3d.kernels.particles import gather

    rng = np.random.default_rng(n_out)
    cap = 150
    src_pos, src_quat, log_w = fields(cap)
    dst_pos, dst_quat, _ = fields(cap)
    parent = ti.field(ti.i32, shape=cap)
    p = rng.normal(size=(cap, 3)).astype(np.float32)
    q = geometry.rot_to_quat(geometry.random_rotations(rng, cap)).astype(np.float32)
    idx = np.zeros(cap, np.int32)
    idx[:n_out] = np.sort(rng.integers(0, 100, n_out))
    src_pos.from_numpy(p)
    src_quat.from_numpy(q)
    parent.from_numpy(idx)
    log_w.from_numpy(np.full(cap, -3.0, np.float32))
    gather(src_pos, src_quat, parent, n_out, dst_pos, dst_quat, log_w)
    np.testing.assert_array_equal(dst_pos.to_numpy()[:n_out], p[idx[:n_out]])
    np.testing.assert_array_equal(dst_quat.to_numpy()[:n_out], q[idx[:n_out]])
    assert np.all(log_w.to_numpy()[:n_out] == 0.0)
