"""Monte Carlo SLAM kernels against NumPy on tiny particle sets: prediction, neighbour
selection, the Gauss-Newton updates (loop and refine), propagation weights, likelihood,
pruning and copies."""

import numpy as np
import pytest

from mcl3d.core import geometry
from mcl3d.slam.monte_carlo_slam import prune_plan, resample_all
from mcl3d.slam.slam_config import PruningConfig
from mcl3d.slam.slam_particles import unpack_poses


def random_poses(rng, n, spread=5.0):
    return geometry.se3(geometry.random_rotations(rng, n), rng.uniform(-spread, spread, (n, 3)))


def pose_fields(T):
    import taichi as ti

    n = len(T)
    q = ti.Vector.field(4, ti.f32, n)
    t = ti.Vector.field(3, ti.f32, n)
    q.from_numpy(geometry.rot_to_quat(T[:, :3, :3]).astype(np.float32))
    t.from_numpy(T[:, :3, 3].astype(np.float32))
    return q, t


def read_poses(q, t):
    qn = q.to_numpy().astype(np.float64)
    return geometry.se3(geometry.quat_to_rot(qn / np.linalg.norm(qn, axis=1, keepdims=True)),
                        t.to_numpy().astype(np.float64))


def pack(T):
    """(N, K, 4, 4) -> the kernels' (N, K, 6) rows (translation, quaternion vector, w >= 0)."""
    q = geometry.rot_to_quat(T[..., :3, :3])
    q = np.where(q[..., 3:4] < 0, -q, q)
    return np.concatenate([T[..., :3, 3], q[..., :3]], axis=-1).astype(np.float32)


def keyframe_array(T):
    import taichi as ti

    arr = ti.ndarray(ti.f32, (*T.shape[:2], 6))
    arr.from_numpy(pack(T))
    return arr


def test_keyframe_rows_round_trip(ti_runtime):
    rng = np.random.default_rng(0)
    T = random_poses(rng, 12)
    back = unpack_poses(pack(T[None])[0])
    np.testing.assert_allclose(back, T, atol=2e-5)


def test_predict_composes_and_spreads_with_the_covariance(ti_runtime):
    from mcl3d.kernels import slam

    rng = np.random.default_rng(1)
    n = 30_000
    T0 = random_poses(rng, 1)[0]
    q, t = pose_fields(np.repeat(T0[None], n, axis=0))
    dT = geometry.se3(geometry.rpy_to_rot(0.01, -0.02, 0.3), [0.4, 0.1, -0.05])
    A = rng.normal(size=(6, 6)) * 0.01
    cov = A @ A.T + np.diag([1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 3e-3])
    L = np.linalg.cholesky(cov).astype(np.float32)
    slam.predict(n, geometry.rot_to_quat(dT[:3, :3]).astype(np.float32),
                 dT[:3, 3].astype(np.float32), L, 5, 2, q, t)
    delta = geometry.se3_log(geometry.se3_inverse(T0 @ dT)[None] @ read_poses(q, t))
    np.testing.assert_allclose(delta.mean(axis=0), 0.0, atol=2e-3)
    np.testing.assert_allclose(np.cov(delta.T), cov, atol=0.05 * np.abs(cov).max())
    q0, t0 = pose_fields(np.repeat(T0[None], 4, axis=0))
    slam.predict(4, geometry.rot_to_quat(dT[:3, :3]).astype(np.float32),
                 dT[:3, 3].astype(np.float32), np.zeros((6, 6), np.float32), 5, 2, q0, t0)
    np.testing.assert_allclose(read_poses(q0, t0), np.repeat((T0 @ dT)[None], 4, 0), atol=2e-5)


@pytest.mark.parametrize("facing_neighbours", [False, True])
def test_select_neighbours_matches_numpy(ti_runtime, facing_neighbours):
    import taichi as ti

    from mcl3d.kernels import slam

    rng = np.random.default_rng(2)
    n, K = 9, 8
    kf = random_poses(rng, n * K, spread=4.0).reshape(n, K, 4, 4)
    kf[0, 5] = kf[0, 2]  # a tie: the older keyframe comes first
    cur = random_poses(rng, n, spread=4.0)
    cur[0, :3, 3] = kf[0, 2, :3, 3] + 0.01
    q, t = pose_fields(cur)
    travel = np.array([0.0, 3.0, 6.0, 9.0, 14.0, 20.0, 26.0, 30.0], np.float32)
    travel_arr = ti.ndarray(ti.f32, K)
    travel_arr.from_numpy(travel)
    seq = np.array([8, 1, 2, 9, 4, 10, 6, 7], np.int32)  # slots 0, 3, 5 reused: newest
    seq_arr = ti.ndarray(ti.i32, K)
    seq_arr.from_numpy(seq)
    nb = ti.field(ti.i32, (n, 3))
    nb_loop = ti.field(ti.i32, (n, 3))
    up = np.array([0.0, 0.6, 0.8])
    min_cos = np.cos(np.deg2rad(100.0))
    looping = slam.select_neighbours(n, K, keyframe_array(kf), q, t, travel_arr, seq_arr, 8,
                                     31.0, 10.0, min_cos, up.astype(np.float32), 3.0,
                                     int(facing_neighbours), nb, nb_loop)
    kf_t = pack(kf)[..., :3].astype(np.float64)
    d = kf_t - t.to_numpy()[:, None, :]
    all_facing = np.einsum("nka,na->nk", kf[:, :, :3, 0], cur[:, :3, 0])  # +x axes
    newest = seq >= 8  # numbers 8, 9, 10
    eligible = np.abs(d @ up) <= 3.0
    if facing_neighbours:
        facing_away = ~newest[None, :] & (all_facing < min_cos)
        assert (eligible & facing_away).any()  # the facing gate leaves some out
        eligible &= ~facing_away
    d2 = np.where(eligible, np.sum(d**2, axis=2), np.inf)
    want = np.argsort(d2, axis=1, kind="stable")[:, :3]
    want = np.where(np.isfinite(np.take_along_axis(d2, want, axis=1)), want, -1)
    assert (want == -1).any() and (want >= 0).any()  # the vertical gate left some out
    np.testing.assert_array_equal(nb.to_numpy(), want)
    facing = np.take_along_axis(all_facing, np.maximum(want, 0), axis=1)
    not_newest = (want >= 0) & ~newest[np.maximum(want, 0)]
    old_enough = not_newest & (31.0 - travel[want] > 10.0)
    want_loop = old_enough & (facing >= min_cos)
    assert want_loop.any()
    # without facing_neighbours some old neighbours face away: the gate keeps them from loops
    assert (old_enough & ~want_loop).any() != facing_neighbours
    np.testing.assert_array_equal(nb_loop.to_numpy(), want_loop.astype(np.int32))
    assert looping == int(want_loop.any(axis=1).sum())
    assert nb.to_numpy()[0, 0] == 2 and nb.to_numpy()[0, 1] == 5


def random_gn_terms(rng, groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Well-conditioned GICP Hessians (SPD) and gradients, one per neighbour group."""
    Hs = np.zeros((groups, 6, 6))
    for g in range(groups):
        A = rng.normal(size=(6, 6))
        Hs[g] = A @ A.T + 6 * np.eye(6)
    return Hs, rng.normal(size=(groups, 6)) * 0.5


def gn_fields(Hs: np.ndarray, bs: np.ndarray, counts: np.ndarray):
    """The per-group H, b and inlier counts as the kernels read them (BatchGicp's best_*)."""
    import taichi as ti

    H = ti.Matrix.field(6, 6, ti.f32, len(Hs))
    b = ti.Vector.field(6, ti.f32, len(bs))
    cnt = ti.field(ti.i32, len(counts))
    H.from_numpy(Hs.astype(np.float32))
    b.from_numpy(bs.astype(np.float32))
    cnt.from_numpy(counts.astype(np.int32))
    return H, b, cnt


def test_correct_takes_the_clamped_gauss_newton_step(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam

    rng = np.random.default_rng(3)
    n = 4
    cur = random_poses(rng, n)
    q, t = pose_fields(cur)
    Hs, bs = random_gn_terms(rng, 3 * n)
    bs[9:] *= 100.0  # particle 3: a step beyond the trust region
    counts = np.full(3 * n, 40)
    counts[3:6] = [10, 0, 5]  # particle 1: too few inliers
    loops = np.array([[1, 0, 1], [1, 1, 1], [0, 0, 0], [1, 1, 0]])
    H, b, cnt = gn_fields(Hs, bs, counts)
    nb_loop = ti.field(ti.i32, (n, 3))
    nb_loop.from_numpy(loops.astype(np.int32))
    shift = ti.Vector.field(6, ti.f32, n)
    corrected = ti.field(ti.i32, n)
    slam.correct(n, nb_loop, H, b, cnt, 30, np.deg2rad(5.0), 0.5, q, t, shift, corrected)
    np.testing.assert_array_equal(corrected.to_numpy(), [1, 0, 0, 1])
    after = read_poses(q, t)
    for i in range(n):
        use = [3 * i + j for j in range(3) if loops[i, j] and counts[3 * i + j] > 0]
        if corrected.to_numpy()[i] == 0:
            np.testing.assert_allclose(after[i], cur[i], atol=1e-6)
            continue
        step = -np.linalg.solve(Hs[use].sum(0), bs[use].sum(0))
        scale = min(1.0, np.deg2rad(5.0) / np.linalg.norm(step[:3]),
                    0.5 / np.linalg.norm(step[3:]))
        want = cur[i] @ geometry.se3_exp(step * scale)
        np.testing.assert_allclose(after[i], want, atol=2e-4)
        moved = shift.to_numpy()[i]
        np.testing.assert_allclose(moved[3:], want[:3, 3] - cur[i][:3, 3], atol=2e-4)
        np.testing.assert_allclose(moved[:3], cur[i][:3, :3] @ (step[:3] * scale), atol=2e-5)


def test_refine_steps_particles_without_a_loop_on_all_their_neighbours(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam

    rng = np.random.default_rng(7)
    n = 4
    cur = random_poses(rng, n)
    q, t = pose_fields(cur)
    Hs, bs = random_gn_terms(rng, 3 * n)
    counts = np.full(3 * n, 40)
    counts[6:9] = [10, 0, 5]  # particle 2: too few inliers
    nbs = np.array([[0, 1, -1], [2, 3, 4], [0, 1, 2], [5, 6, 7]])
    loops = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 0]])  # particle 1: a loop
    H, b, cnt = gn_fields(Hs, bs, counts)
    nb = ti.field(ti.i32, (n, 3))
    nb_loop = ti.field(ti.i32, (n, 3))
    nb.from_numpy(nbs.astype(np.int32))
    nb_loop.from_numpy(loops.astype(np.int32))
    prior = np.diag([1e4] * 3 + [1e2] * 3)  # (0.6°)^-2, (10 cm)^-2
    moved = slam.refine(n, nb, nb_loop, H, b, cnt, 30, prior.astype(np.float32),
                        np.deg2rad(5.0), 0.5, q, t)
    assert moved == 2
    after = read_poses(q, t)
    for i in range(n):
        use = [3 * i + j for j in range(3) if nbs[i, j] >= 0 and counts[3 * i + j] > 0]
        if i in (1, 2):  # a loop (the loop step's job), too few inliers
            np.testing.assert_allclose(after[i], cur[i], atol=1e-6)
            continue
        step = -np.linalg.solve(Hs[use].sum(0) + prior, bs[use].sum(0))
        scale = min(1.0, np.deg2rad(5.0) / np.linalg.norm(step[:3]),
                    0.5 / np.linalg.norm(step[3:]))
        np.testing.assert_allclose(after[i], cur[i] @ geometry.se3_exp(step * scale),
                                   atol=2e-4)
        free = -np.linalg.solve(Hs[use].sum(0), bs[use].sum(0))
        assert np.linalg.norm(step[:3]) < np.linalg.norm(free[:3])  # the prior holds back


def propagate_reference(kf, travel, rows, base_travel, base, now, odo_now, shift):
    """NumPy eq. 8-10 with the drift model (kernels/slam.py propagate) for one particle."""
    w, dt = shift[:3], shift[3:]
    span_w, span_v = now[0] - base[0], now[4] - base[4]
    c_now = (now[1:4] - base[1:4]) / span_w
    rest = dt - np.cross(w, odo_now - c_now)
    out = kf.copy()
    for k in range(len(kf)):
        if travel[k] > base_travel:
            a = np.clip((rows[k, 0] - base[0]) / span_w, 0, 1)
            c = (rows[k, 1:4] - base[1:4]) / span_w
            b = np.clip((rows[k, 4] - base[4]) / span_v, 0, 1)
            move = np.cross(w, a * rows[k, 5:8] - c) + b * rest
            out[k] = geometry.se3(geometry.so3_exp(a * w) @ kf[k, :3, :3], kf[k, :3, 3] + move)
    return out


def drift_rows(rng, K):
    """Drift sums (W, Σ w p, V) along a path with uneven variance, and odometry positions."""
    w = rng.uniform(0.1, 2.0, K + 1) * 1e-5
    v = rng.uniform(0.1, 2.0, K + 1) * 1e-4
    pos = np.cumsum(rng.normal(size=(K + 1, 3)), axis=0)
    sums = np.c_[np.cumsum(w), np.cumsum(w[:, None] * pos, axis=0), np.cumsum(v)]
    return np.c_[sums, pos]


def test_propagate_spreads_the_correction_by_the_drift_model(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam

    rng = np.random.default_rng(4)
    n, K = 3, 6
    kf = random_poses(rng, n * K).reshape(n, K, 4, 4)
    arr = keyframe_array(kf)
    travel = np.array([0.0, 2.0, 5.0, 9.0, 12.0, 16.0], np.float32)
    travel_arr = ti.ndarray(ti.f32, K)
    travel_arr.from_numpy(travel)
    rows = drift_rows(rng, K)  # row K: now
    rows_arr = ti.ndarray(ti.f32, (K, 8))
    rows_arr.from_numpy(rows[:K].astype(np.float32))
    now, odo_now = rows[K, :5], rows[K, 5:]
    nb = ti.field(ti.i32, (n, 3))
    nb.from_numpy(np.array([[1, 4, 5], [3, 4, 5], [0, 1, 2]], np.int32))
    shifts = rng.normal(size=(n, 6)) * [0.02, 0.02, 0.02, 0.3, 0.3, 0.3]
    shift = ti.Vector.field(6, ti.f32, n)
    shift.from_numpy(shifts.astype(np.float32))
    corrected = ti.field(ti.i32, n)
    corrected.from_numpy(np.array([1, 1, 0], np.int32))
    fixed = ti.field(ti.f32, n)
    fixed.from_numpy(np.array([0.0, 10.0, 0.0], np.float32))  # particle 1 settled at 10 m
    settled = 0.5 * (rows[3, :5] + rows[4, :5])  # its drift sums then
    fixed_drift = ti.Vector.field(5, ti.f32, n)
    fixed_drift.from_numpy(np.stack([np.zeros(5), settled, np.zeros(5)]).astype(np.float32))
    slam.propagate(n, K, arr, nb, travel_arr, rows_arr, ti.types.vector(5, ti.f32)(*now),
                   ti.math.vec3(*odo_now), shift, corrected, fixed, fixed_drift)
    got = unpack_poses(arr.to_numpy().reshape(-1, 6)).reshape(n, K, 4, 4)
    want0 = propagate_reference(kf[0], travel, rows, 2.0, rows[1, :5], now, odo_now, shifts[0])
    want1 = propagate_reference(kf[1], travel, rows, 10.0, settled, now, odo_now, shifts[1])
    np.testing.assert_allclose(got[0], want0, atol=5e-5)
    np.testing.assert_allclose(got[1], want1, atol=5e-5)
    np.testing.assert_allclose(got[2], kf[2], atol=2e-5)  # not corrected: untouched
    assert not np.allclose(got[0, 2:], kf[0, 2:], atol=1e-3)  # the correction did spread
    # particle 0 moved 0.3 m: still closing, its start stays; particle 1 settled: it moves
    shift.from_numpy(np.array([[0, 0, 0, 0.3, 0, 0], [0.001, 0, 0, 0.01, 0, 0], [0] * 6],
                              np.float32))
    slam.mark_fixed(n, 20.0, ti.types.vector(5, ti.f32)(*now), corrected, shift,
                    np.deg2rad(0.2), 0.02, fixed, fixed_drift)
    np.testing.assert_array_equal(fixed.to_numpy(), [0.0, 20.0, 0.0])
    np.testing.assert_allclose(fixed_drift.to_numpy()[1], now, rtol=1e-6)
    np.testing.assert_allclose(fixed_drift.to_numpy()[0], 0.0)


def test_propagate_with_even_drift_on_a_line_is_eq_8(ti_runtime):
    """Rotational and translational variance growing evenly along a straight path: every
    keyframe takes α = d(o, k) / d(o, now) of the correction, as eq. 8-10 (world frame) say,
    plus the lever arm of the rotation applied along the way."""
    import taichi as ti

    from mcl3d.kernels import slam

    K = 5
    x = np.array([0.0, 2.0, 4.0, 6.0, 8.0, 10.0])  # keyframes, then now
    rows = np.c_[x, np.zeros((6, 3)), x, np.zeros((6, 3))]
    rows[:, 1] = np.cumsum(np.r_[0.0, np.diff(x)] * x)  # Σ w_j p_j with w per metre = 1
    rows[:, 5] = x
    kf = np.stack([geometry.se3(np.eye(3), [xi, 0, 0]) for xi in x[:K]])[None]
    arr = keyframe_array(kf)
    travel_arr = ti.ndarray(ti.f32, K)
    travel_arr.from_numpy(x[:K].astype(np.float32))
    rows_arr = ti.ndarray(ti.f32, (K, 8))
    rows_arr.from_numpy(rows[:K].astype(np.float32))
    nb = ti.field(ti.i32, (1, 3))
    nb.from_numpy(np.array([[0, 3, 4]], np.int32))
    shift = ti.Vector.field(6, ti.f32, 1)
    shift.from_numpy(np.array([[0.0, 0.0, 0.0, 0.0, 0.5, 0.0]], np.float32))  # pure shift
    corrected = ti.field(ti.i32, 1)
    corrected.fill(1)
    fixed = ti.field(ti.f32, 1)
    fixed_drift = ti.Vector.field(5, ti.f32, 1)
    slam.propagate(1, K, arr, nb, travel_arr, rows_arr,
                   ti.types.vector(5, ti.f32)(*rows[K, :5]), ti.math.vec3(*rows[K, 5:]),
                   shift, corrected, fixed, fixed_drift)
    got = unpack_poses(arr.to_numpy().reshape(-1, 6))
    np.testing.assert_allclose(got[:, 1, 3], 0.5 * x[:K] / 10.0, atol=1e-5)


def row_costs_numpy(nb, err, cnt, seen, M, outlier_cost, seen_cost):
    """Each row's cost (-1 without a keyframe): eᵀΩe of the matched points (none kept
    without a match), `outlier_cost` per unmatched point, `seen_cost` per seen-through one."""
    matched = np.where(cnt > 0, 2.0 * err, 0.0)
    cost = matched + outlier_cost * (M - cnt) + seen_cost * seen
    return np.where(nb.ravel() >= 0, cost, -1.0)


def likelihood_numpy(nb, nb_loop, costs, M, points_weight, local_weight, local_reference):
    """Eq. 2-3 per particle: the mean row cost, a non-loop row costing local_weight × its
    own + the rest × the reference; None for a particle without neighbours."""
    out = []
    for i in range(len(nb)):
        total, rows = 0.0, 0
        for j in range(3):
            c = costs[3 * i + j]
            if nb[i, j] >= 0:
                rows += 1
                total += c if nb_loop[i, j] else local_weight * c + (1 - local_weight) * \
                    local_reference
        out.append(-0.5 * points_weight * total / (rows * M) if rows else None)
    return out


@pytest.mark.parametrize("local_weight", [1.0, 0.25, 0.0])
def test_likelihood_matches_numpy(ti_runtime, local_weight):
    import taichi as ti

    from mcl3d.kernels import slam

    n, M = 4, 100
    nb_rows = np.array([[0, 1, 2], [0, 1, -1], [-1, -1, -1], [3, 4, 5]], np.int32)
    loop_rows = np.array([[0, 1, 0], [0, 0, 0], [0, 0, 0], [1, 1, 0]], np.int32)
    nb = ti.field(ti.i32, (n, 3))
    nb.from_numpy(nb_rows)
    nb_loop = ti.field(ti.i32, (n, 3))
    nb_loop.from_numpy(loop_rows)
    err = np.array([12.0, 30.0, 3.0, 8.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 7.0, 1.0], np.float32)
    cnt = np.array([80, 60, 100, 90, 0, 0, 0, 0, 0, 70, 0, 95], np.int32)
    best_e = ti.field(ti.f32, 3 * n)
    best_n = ti.field(ti.i32, 3 * n)
    best_e.from_numpy(err)
    best_n.from_numpy(cnt)
    seen_rows = np.array([4, 0, 1, 6, 0, 0, 0, 0, 7, 2, 3, 0], np.int32)
    seen = ti.field(ti.i32, 3 * n)  # points in seen-through space, each costing 2.5
    seen.from_numpy(seen_rows)
    costs = np.empty(3 * n, np.float32)
    slam.local_row_costs(n, M, nb, nb_loop, best_e, best_n, 9.0, seen, 2.5, costs)
    want_costs = row_costs_numpy(nb_rows, err, cnt, seen_rows, M, 9.0, 2.5)
    np.testing.assert_allclose(costs, np.where(loop_rows.ravel() == 1, -1.0, want_costs),
                               rtol=1e-6)  # loop rows: -1, as rows without a keyframe
    point_costs = np.empty(3 * n, np.float32)
    slam.local_point_costs(n, nb, nb_loop, best_e, best_n, point_costs)
    local_matched = (nb_rows.ravel() >= 0) & (loop_rows.ravel() == 0) & (cnt > 0)
    np.testing.assert_allclose(point_costs, np.where(local_matched, 2.0 * err / np.maximum(
        cnt, 1), -1.0), rtol=1e-6)  # a matched point's mean cost; -1: loop, none, no match
    frame_ll = ti.field(ti.f32, n)
    log_w = ti.field(ti.f32, n)
    log_w0 = np.array([-1.0, -2.0, 0.0, -0.5], np.float32)
    log_w.from_numpy(log_w0)
    reference = 321.0  # a cost no row has
    slam.likelihood(n, M, nb, nb_loop, best_e, best_n, 9.0, seen, 2.5, 30.0, local_weight,
                    reference, frame_ll, log_w)
    want = likelihood_numpy(nb_rows, loop_rows, want_costs, M, 30.0, local_weight, reference)
    got = frame_ll.to_numpy()
    assert got[2] == np.float32(slam.UNSCORED) and log_w.to_numpy()[2] == 0.0  # no evidence
    for i in (0, 1, 3):
        np.testing.assert_allclose(got[i], want[i], rtol=1e-6)
        np.testing.assert_allclose(log_w.to_numpy()[i], want[i] + log_w0[i], rtol=1e-6)
    if local_weight == 1.0:  # the paper's mean over every neighbour, written out once
        cost0 = 2 * (12 + 30 + 3) + 9 * (20 + 40 + 0) + 2.5 * (4 + 0 + 1)
        np.testing.assert_allclose(got[0], -0.5 * 30 * cost0 / (3 * M), rtol=1e-6)
    if local_weight == 0.0:  # only loop rows tell particles apart
        np.testing.assert_allclose(got[1], -0.5 * 30 * reference / M, rtol=1e-6)


def test_prune_plan_keeps_the_living_and_splits_weights():
    cfg = PruningConfig(posterior=1e-3, likelihood_ratio=1e-6)
    log_w = np.log(np.array([0.5, 0.3, 0.1999, 1e-5, 1e-4]))
    frame_ll = np.array([0.0, -1.0, -20.0, 0.0, 0.0])  # particle 2: frame likelihood too low
    dead, sources, lw = prune_plan(log_w, frame_ll, cfg, np.random.default_rng(0))
    np.testing.assert_array_equal(dead, [2, 3, 4])
    assert set(sources) <= {0, 1}
    post = np.exp(lw)
    copies = np.bincount(sources, minlength=5)
    for s in (0, 1):  # the source and its copies share the source's weight
        np.testing.assert_allclose(post[s] * (1 + copies[s]), np.exp(log_w[s] - log_w.max()))
    none_dead = prune_plan(np.zeros(4), np.zeros(4), cfg, np.random.default_rng(0))
    assert len(none_dead[0]) == 0


def test_prune_plan_never_kills_every_particle():
    cfg = PruningConfig(likelihood_ratio=0.5)
    dead, sources, _ = prune_plan(np.zeros(3), np.array([-5.0, -5.0, -5.0]) - [0, 1, 2], cfg,
                                  np.random.default_rng(0))
    assert 0 not in dead and set(sources) == {0}


def test_respawn_copies_the_whole_state(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam

    rng = np.random.default_rng(5)
    n, K = 5, 4
    kf = random_poses(rng, n * K).reshape(n, K, 4, 4)
    arr = keyframe_array(kf)
    cur = random_poses(rng, n)
    q, t = pose_fields(cur)
    fixed = ti.field(ti.f32, n)
    fixed.from_numpy(np.arange(n, dtype=np.float32))
    drift = rng.normal(size=(n, 5)).astype(np.float32)
    fixed_drift = ti.Vector.field(5, ti.f32, n)
    fixed_drift.from_numpy(drift)
    slam.respawn(2, np.array([1, 3], np.int32), np.array([4, 0], np.int32), K, q, t, fixed,
                 fixed_drift, arr)
    got = unpack_poses(arr.to_numpy().reshape(-1, 6)).reshape(n, K, 4, 4)
    want = kf.copy()
    want[1], want[3] = kf[4], kf[0]
    np.testing.assert_allclose(got, want, atol=2e-5)
    want_cur = cur.copy()
    want_cur[1], want_cur[3] = cur[4], cur[0]
    np.testing.assert_allclose(read_poses(q, t), want_cur, atol=2e-5)
    np.testing.assert_array_equal(fixed.to_numpy(), [0, 4, 2, 0, 4])
    np.testing.assert_array_equal(fixed_drift.to_numpy(), drift[[0, 4, 2, 0, 4]])


@pytest.mark.parametrize("count", [1, 9])
def test_particle_keyframe_storage_is_allocated_up_front_and_keeps_poses(ti_runtime, count):
    from mcl3d.slam.slam_particles import SlamParticles

    p = SlamParticles(3, 64, gicp=None, seed=0)
    storage = p.kf
    assert storage.shape == (3, 64, 6)  # the whole capacity, before any keyframe
    rng = np.random.default_rng(6)
    placed = []
    for k in range(count):
        T = random_poses(rng, 3)
        q, t = pose_fields(T)
        p.q_cur.copy_from(q)
        p.t_cur.copy_from(t)
        assert p.add_keyframe(float(k), np.full(5, float(k)), np.zeros(3)) == k
        placed.append(T)
    assert p.kf is storage  # never reallocated as keyframes come
    for i in range(3):
        np.testing.assert_allclose(p.keyframe_poses(i), np.stack([T[i] for T in placed]),
                                   atol=2e-5)


def test_resample_all_draws_by_weight_and_equalizes():
    log_w = np.log(np.array([0.7, 0.2, 0.1, 1e-9, 1e-9, 1e-9, 1e-9, 1e-9, 1e-9, 1e-9]))
    dead, sources, lw = resample_all(log_w, np.random.default_rng(3))
    assert len(dead) == len(sources) and not set(dead) & set(sources)
    kept = np.bincount(np.r_[np.setdiff1d(np.arange(10), dead), sources], minlength=10)
    assert kept.sum() == 10 and kept[0] == 7 and kept[1] == 2 and kept[2] == 1  # systematic
    np.testing.assert_array_equal(lw, np.zeros(10))
