"""kernels/claim_check.py against NumPy on tiny inputs."""

import numpy as np
import pytest
import taichi as ti

from mcl3d.core import geometry

N = 64


@pytest.fixture(scope="module")
def fields(backend):
    from mcl3d.core import runtime

    runtime.init(backend)

    class F:
        pos = ti.Vector.field(3, ti.f32, shape=N)
        quat = ti.Vector.field(4, ti.f32, shape=N)
        pos2 = ti.Vector.field(3, ti.f32, shape=N)
        quat2 = ti.Vector.field(4, ti.f32, shape=N)
        score = ti.field(ti.f32, shape=N)
        group = ti.field(ti.i32, shape=N)
        best = ti.field(ti.f32, shape=N)
        arg = ti.field(ti.i32, shape=N)
        counts = ti.field(ti.i32, shape=N)
        log_w = ti.field(ti.f32, shape=N)
        log_l = ti.field(ti.f32, shape=N)

    return F


def random_poses(rng, n):
    t = rng.uniform(-3.0, 3.0, (n, 3))
    q = geometry.rot_to_quat(geometry.so3_exp(rng.normal(0.0, 1.0, (n, 3))))
    return t, q


def upload(field, values, width):
    out = np.zeros((N, width), np.float32)
    out[:len(values)] = values
    field.from_numpy(out)


def test_grid_poses_take_position_then_yaw_with_the_given_roll_pitch(fields):
    from mcl3d.kernels import claim_check as kcc

    positions = np.array([[1.0, 2.0, 0.5], [3.0, -1.0, 0.7], [0.0, 0.0, 1.0]])
    upload(fields.pos2, positions, 3)
    n_yaw, start, count = 4, 3, 7
    kcc.grid_poses(fields.pos2, n_yaw, start, count, 0.02, -0.03, fields.pos, fields.quat)
    j = start + np.arange(count)
    np.testing.assert_allclose(fields.pos.to_numpy()[:count], positions[j // n_yaw], atol=1e-6)
    R = np.stack([geometry.rpy_to_rot(0.02, -0.03, 2 * np.pi * (k % n_yaw) / n_yaw) for k in j])
    got = geometry.quat_to_rot(fields.quat.to_numpy()[:count].astype(np.float64))
    np.testing.assert_allclose(got, R, atol=1e-5)


def test_moved_poses_compose_each_base_pose_with_the_relative_pose(fields):
    from mcl3d.kernels import claim_check as kcc

    rng = np.random.default_rng(1)
    t, q = random_poses(rng, 10)
    upload(fields.pos2, t, 3)
    upload(fields.quat2, q, 4)
    T_rel = geometry.se3(geometry.so3_exp(np.array([0.1, -0.2, 0.3])), [0.5, -0.4, 0.1])
    t_rel, q_rel = geometry.tq_from_se3(T_rel)
    kcc.moved_poses(fields.pos2, fields.quat2, 10, ti.math.vec3(*t_rel), ti.math.vec4(*q_rel),
                    fields.pos, fields.quat)
    expected = geometry.se3_from_tq(t, q) @ T_rel
    got = geometry.se3_from_tq(fields.pos.to_numpy()[:10].astype(np.float64),
                               fields.quat.to_numpy()[:10].astype(np.float64))
    np.testing.assert_allclose(got, expected, atol=1e-5)


def test_group_best_and_arg_over_chunks_match_numpy(fields):
    """Poses j of a grid with `per` yaws per position; group = place of the position times
    `bins` yaw bins; two chunks reduce into the same maxima."""
    from mcl3d.kernels import claim_check as kcc

    rng = np.random.default_rng(2)
    per, bins, positions = 6, 3, 8
    place = rng.integers(0, 4, positions)
    scores = rng.normal(0.0, 1.0, positions * per).astype(np.float32)
    fields.group.from_numpy(np.pad(place, (0, N - positions)).astype(np.int32))
    kcc.reset_best(fields.best, fields.arg, 4 * bins)
    for start, count in ((0, 20), (20, positions * per - 20)):
        fields.score.from_numpy(np.pad(scores[start:start + count], (0, N - count)))
        kcc.group_best(fields.score, fields.group, per, bins, start, count, fields.best)
        kcc.group_arg(fields.score, fields.group, per, bins, start, count, fields.best,
                      fields.arg)
    j = np.arange(positions * per)
    g = place[j // per] * bins + (j % per) * bins // per
    best = fields.best.to_numpy()[:4 * bins]
    arg = fields.arg.to_numpy()[:4 * bins]
    for k in range(4 * bins):
        members = g == k
        if not members.any():
            assert arg[k] == -1 and best[k] < -1e37
            continue
        assert best[k] == scores[members].max()
        assert g[arg[k]] == k and scores[arg[k]] == best[k]


def test_around_centres_keeps_each_centre_and_spreads_the_rest(fields):
    from mcl3d.kernels import claim_check as kcc

    rng = np.random.default_rng(3)
    t, q = random_poses(rng, 2)
    upload(fields.pos2, t, 3)
    upload(fields.quat2, q, 4)
    per = 32
    kcc.around_centres(fields.pos2, fields.quat2, per, 2 * per, ti.math.vec3(0.1, 0.2, 0.0),
                       ti.math.vec3(0.0, 0.0, 0.05), 7, 9, fields.pos, fields.quat)
    pos = fields.pos.to_numpy()[:2 * per].astype(np.float64)
    quat = fields.quat.to_numpy()[:2 * per].astype(np.float64)
    for c in range(2):
        block = slice(c * per, (c + 1) * per)
        np.testing.assert_allclose(pos[c * per], t[c], atol=1e-6)
        np.testing.assert_allclose(np.abs(quat[c * per] @ q[c]), 1.0, atol=1e-6)
        d = pos[block] - t[c]
        assert np.all(d[:, 2] == pytest.approx(0.0, abs=1e-5))  # zero std in z
        assert 0.03 < d[1:, 0].std() < 0.2 and 0.08 < d[1:, 1].std() < 0.4
        rel = geometry.quat_to_rot(quat[block]) @ geometry.quat_to_rot(q[c]).T
        assert np.all(geometry.rotation_angle(rel) < 0.3)


def test_count_near_counts_particles_within_radius_and_angle(fields):
    from mcl3d.kernels import claim_check as kcc

    rng = np.random.default_rng(4)
    t, q = random_poses(rng, 40)
    centres_t, centres_q = t[:3] + 0.1, q[:3]
    upload(fields.pos, t, 3)
    upload(fields.quat, q, 4)
    upload(fields.pos2, centres_t, 3)
    upload(fields.quat2, centres_q, 4)
    radius, angle = 2.5, 1.5
    kcc.count_near(fields.pos, fields.quat, 40, fields.pos2, fields.quat2, 3, radius,
                   np.cos(angle / 2), fields.counts)
    for c in range(3):
        d = np.linalg.norm(t - centres_t[c], axis=1)
        a = 2 * np.arccos(np.clip(np.abs(q @ centres_q[c]), 0, 1))
        assert fields.counts[c] == int(((d <= radius) & (a <= angle)).sum())


def test_inject_writes_a_stride_of_particles_and_leaves_the_rest(fields):
    from mcl3d.kernels import claim_check as kcc

    fields.pos.from_numpy(np.zeros((N, 3), np.float32))
    fields.log_w.from_numpy(np.full(N, -1.0, np.float32))
    fields.log_l.from_numpy(np.full(N, -9.0, np.float32))
    t0 = np.array([5.0, 1.0, 0.5])
    kcc.inject(fields.pos, fields.quat, fields.log_w, fields.log_l, 3, 10, 5, ti.math.vec3(*t0),
               ti.math.vec4(0.0, 0.0, 0.0, 1.0), ti.math.vec3(0.05, 0.05, 0.01),
               ti.math.vec3(0.01, 0.01, 0.02), 0.0, -2.5, 1, 2)
    written = 3 + 10 * np.arange(5)
    others = np.setdiff1d(np.arange(N), written)
    pos, log_w, log_l = fields.pos.to_numpy(), fields.log_w.to_numpy(), fields.log_l.to_numpy()
    assert np.all(np.linalg.norm(pos[written] - t0, axis=1) < 0.5)
    assert np.all(log_w[written] == 0.0) and np.all(log_l[written] == -2.5)
    assert np.all(pos[others] == 0.0) and np.all(log_w[others] == -1.0)
    assert np.all(log_l[others] == -9.0)


def test_take_gathers_the_poses_at_the_given_indices(fields):
    from mcl3d.kernels import claim_check as kcc

    rng = np.random.default_rng(5)
    t, q = random_poses(rng, 10)
    upload(fields.pos2, t, 3)
    upload(fields.quat2, q, 4)
    fields.pos.from_numpy(np.zeros((N, 3), np.float32))
    fields.arg.from_numpy(np.pad([4, -1, 7], (0, N - 3)).astype(np.int32))
    kcc.take(fields.pos2, fields.quat2, fields.arg, 3, fields.pos, fields.quat)
    pos = fields.pos.to_numpy()
    np.testing.assert_allclose(pos[0], t[4], atol=1e-6)
    np.testing.assert_allclose(pos[1], 0.0)
    np.testing.assert_allclose(pos[2], t[7], atol=1e-6)
