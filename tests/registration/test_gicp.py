"""Batched GICP kernels (kernels/gicp.py) against a float64 NumPy reference on tiny inputs."""

from __future__ import annotations

import numpy as np
import pytest
from support.voxel_hash_numpy import numpy_voxel_hash

from mcl3d.core.geometry import hat, se3, se3_exp, so3_exp, transform_points

RES = 1.0


def corner_world(rng, n_per_plane=150):
    """Points on five planes (floor, three walls, a slanted roof): every pose direction is
    observable. Returns points and plane-regularized covariances (normal variance 1e-3)."""
    u = rng.uniform(0.0, 4.0, (5, n_per_plane, 2))
    planes = [
        np.c_[u[0], np.zeros(n_per_plane)],
        np.c_[u[1][:, 0], np.zeros(n_per_plane), u[1][:, 1]],
        np.c_[np.zeros(n_per_plane), u[2]],
        np.c_[u[3][:, 0], np.full(n_per_plane, 4.0), u[3][:, 1]],
        np.c_[u[4], 2.0 + 0.3 * u[4][:, 0]],
    ]
    normals = [[0, 0, 1], [0, 1, 0], [1, 0, 0], [0, 1, 0], [-0.3, 0, 1]]
    pts, covs = [], []
    for p, nrm in zip(planes, normals, strict=True):
        nrm = np.asarray(nrm, float) / np.linalg.norm(nrm)
        C = np.eye(3) - (1 - 1e-3) * np.outer(nrm, nrm)
        pts.append(p)
        covs.append(np.tile(C, (len(p), 1, 1)))
    return np.vstack(pts) + 0.5, np.vstack(covs)  # planes mid-voxel, not on voxel faces


def reference_voxels(points, covs):
    keys = np.floor(points / RES).astype(np.int64)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    n = np.bincount(inverse)
    means = np.stack([np.bincount(inverse, points[:, a]) for a in range(3)], 1) / n[:, None]
    avg = np.zeros((len(uniq), 3, 3))
    np.add.at(avg, inverse, covs)
    return {tuple(k): i for i, k in enumerate(uniq)}, means, avg / n[:, None, None]


def faces_away(R, x, a, Ca, facing_cos):
    """Surface validation: the plane normal of Ca (smallest eigenvector), turned towards the
    source sensor at 0 and rotated, within acos(facing_cos) of the ray from 0 to x."""
    w, V = np.linalg.eigh(Ca)
    if np.isclose(w[0], w[2]):
        return False  # identity: no normal
    n = V[:, 0] if a @ V[:, 0] <= 0 else -V[:, 0]
    return x @ (R @ n) > facing_cos * np.linalg.norm(x)


def reference_linearize(vox, src, src_covs, T, facing_cos=None, cost_cap=np.inf):
    """float64 H, b, error, inliers of the GICP cost at pose T (fixed M, one voxel each),
    with surface validation when `facing_cos` is given; no point adds more than `cost_cap`
    to the error."""
    index, means, vcovs = vox
    R, t = T[:3, :3], T[:3, 3]
    H, b, err, n = np.zeros((6, 6)), np.zeros(6), 0.0, 0
    for a, Ca in zip(src, src_covs, strict=True):
        p = R @ a + t
        i = index.get(tuple(np.floor(p / RES).astype(np.int64)))
        if i is None or (facing_cos is not None and faces_away(R, p, a, Ca, facing_cos)):
            continue
        e = means[i] - p
        M = np.linalg.inv(vcovs[i] + R @ Ca @ R.T)
        J = np.hstack([R @ hat(a), -R])
        H += J.T @ M @ J
        b += J.T @ M @ e
        err += min(0.5 * e @ M @ e, cost_cap)
        n += 1
    return H, b, err, n


def reference_step(rows, src, src_covs, T):
    """Float64 Gauss-Newton step of the summed rows' costs at T, rows = [(voxels, T_left)]."""
    H, b = np.zeros((6, 6)), np.zeros(6)
    for vox, T_left in rows:
        Hr, br, _, _ = reference_linearize(vox, src, src_covs, T_left @ T)
        H, b = H + Hr, b + br
    return np.linalg.solve(H, -b)


@pytest.fixture(scope="module")
def problem(backend):
    from mcl3d.core import runtime
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    runtime.init(backend)
    rng = np.random.default_rng(7)
    target, target_covs = corner_world(rng)
    maps = GaussianVoxelMaps(max_maps=2, buckets_per_map=1 << 9, max_points=1024)
    maps.clear(0, RES)
    maps.insert(0, target, target_covs)
    maps.clear(1, RES)  # the same world seen from a frame shifted by 10 m
    T_shift = se3(so3_exp(np.array([0.0, 0.0, 0.3])), [10.0, 0.0, 0.0])
    maps.insert(1, target, target_covs, T_shift)
    source, source_covs = corner_world(np.random.default_rng(8), 60)
    gicp = BatchGicp(maps, max_groups=64, max_rows=128, max_source_points=512)
    gicp.set_source(source, source_covs)
    vox = reference_voxels(target, target_covs)
    R = T_shift[:3, :3]
    vox1 = reference_voxels(transform_points(T_shift, target), R @ target_covs @ R.T)
    return {"gicp": gicp, "vox": vox, "vox1": vox1, "src": source, "src_covs": source_covs,
            "T_shift": T_shift}


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    a = rng.normal(size=3)
    T = se3(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    J = np.hstack([T[:3, :3] @ hat(a), -T[:3, :3]])  # d e / d delta of e = mu_B - T exp(d) a
    eps = 1e-6
    fd = np.zeros((3, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        plus = -transform_points(T @ se3_exp(d), a[None])[0]
        minus = -transform_points(T @ se3_exp(-d), a[None])[0]
        fd[:, k] = (plus - minus) / (2 * eps)
    np.testing.assert_allclose(J, fd, atol=1e-6)


def test_gradient_b_matches_finite_differences_of_the_cost(problem):
    T = se3(so3_exp(np.array([0.02, -0.01, 0.03])), [0.05, -0.04, 0.02])
    _, b, _, _ = reference_linearize(problem["vox"], problem["src"], problem["src_covs"], T)
    index, means, vcovs = problem["vox"]
    R = T[:3, :3]
    pairs = []  # correspondences and weights frozen at T, as the Gauss-Newton model holds them
    for a, Ca in zip(problem["src"], problem["src_covs"], strict=True):
        i = index.get(tuple(np.floor(transform_points(T, a[None])[0] / RES).astype(np.int64)))
        if i is not None:
            pairs.append((a, means[i], np.linalg.inv(vcovs[i] + R @ Ca @ R.T)))

    def cost(d):
        Td = T @ se3_exp(d)
        return sum(0.5 * (m - transform_points(Td, a[None])[0]) @ M
                   @ (m - transform_points(Td, a[None])[0]) for a, m, M in pairs)

    eps = 1e-6
    fd = [(cost(eps * np.eye(6)[k]) - cost(-eps * np.eye(6)[k])) / (2 * eps) for k in range(6)]
    np.testing.assert_allclose(b, fd, rtol=1e-5, atol=1e-6)


def test_kernel_cost_hessian_gradient_match_numpy(problem):
    gicp = problem["gicp"]
    rng = np.random.default_rng(4)
    poses = [se3(so3_exp(0.05 * rng.normal(size=3)), 0.1 * rng.normal(size=3)) for _ in range(5)]
    gicp.set_problem(np.stack(poses), row_group=np.arange(5), row_map=np.zeros(5))
    out = gicp.optimize(max_iterations=1)  # evaluation only: H, b, error at the given poses
    for k, T in enumerate(poses):
        H, b, err, n = reference_linearize(problem["vox"], problem["src"], problem["src_covs"], T)
        assert out.num_inliers[k] == n > 100
        np.testing.assert_allclose(out.T[k], T, atol=1e-6)
        np.testing.assert_allclose(out.error[k], err, rtol=1e-4)
        np.testing.assert_allclose(out.b[k], b, rtol=1e-3, atol=1e-3 * np.abs(b).max())
        np.testing.assert_allclose(out.H[k], H, rtol=1e-3, atol=1e-4 * np.abs(H).max())


def test_a_capped_cost_truncates_each_points_error_alone(problem):
    """iterate(cost_cap=c): the error sums min(½ eᵀMe, c) per point; H, b and the inliers
    keep every point."""
    gicp = problem["gicp"]
    rng = np.random.default_rng(5)
    poses = [se3(so3_exp(0.05 * rng.normal(size=3)), 0.1 * rng.normal(size=3)) for _ in range(3)]
    for cap in (np.inf, 0.5, 0.05):
        gicp.set_problem(np.stack(poses), row_group=np.arange(3), row_map=np.zeros(3))
        gicp.iterate(cost_cap=cap)
        out = gicp.result()
        for k, T in enumerate(poses):
            H, _, err, n = reference_linearize(problem["vox"], problem["src"],
                                               problem["src_covs"], T, cost_cap=cap)
            _, _, uncapped, _ = reference_linearize(problem["vox"], problem["src"],
                                                    problem["src_covs"], T)
            assert out.num_inliers[k] == n > 100
            np.testing.assert_allclose(out.error[k], err, rtol=1e-4)
            assert (err < 0.9 * uncapped) == (cap < 1)  # the caps bind on these poses
            np.testing.assert_allclose(out.H[k], H, rtol=1e-3, atol=1e-4 * np.abs(H).max())


def test_surface_validation_drops_what_the_map_sensor_could_not_see(problem):
    """validate_surfaces: map 1's sensor sits at the world's (-9.6, 3.0, 0), beyond the
    y = 0.5 wall from the source sensor at 0: points of that wall seen at an angle face away
    from it and weigh nothing; in map 0 (the same sensor position) every point counts."""
    from mcl3d.registration.batch_gicp import SURFACE_VALIDATION_COS

    gicp, src, covs, T_shift = (problem[k] for k in ("gicp", "src", "src_covs", "T_shift"))
    T = se3(so3_exp([0.01, -0.02, 0.03]), [0.1, -0.05, 0.05])
    kept = []
    for map_id, vox, T_left in ((0, problem["vox"], np.eye(4)), (1, problem["vox1"], T_shift)):
        gicp.set_problem(T[None], row_group=[0], row_map=[map_id], T_left=T_left[None])
        out = gicp.optimize(max_iterations=1, validate_surfaces=True)
        H, b, err, n = reference_linearize(vox, src, covs, T_left @ T, SURFACE_VALIDATION_COS)
        _, _, _, n_all = reference_linearize(vox, src, covs, T_left @ T)
        assert out.num_inliers[0] == n
        np.testing.assert_allclose(out.error[0], err, rtol=1e-4)
        np.testing.assert_allclose(out.b[0], b, rtol=1e-3, atol=1e-3 * np.abs(b).max())
        np.testing.assert_allclose(out.H[0], H, rtol=1e-3, atol=1e-4 * np.abs(H).max())
        kept.append((n, n_all))
    assert kept[0][0] == kept[0][1] and 0 < kept[1][1] - kept[1][0] < kept[1][1] // 3


def test_one_gauss_newton_step_matches_numpy(problem):
    gicp = problem["gicp"]
    T0 = se3(so3_exp(np.array([0.03, 0.02, -0.04])), [0.12, -0.08, 0.05])
    H, b, _, _ = reference_linearize(problem["vox"], problem["src"], problem["src_covs"], T0)
    expected = T0 @ se3_exp(np.linalg.solve(H, -b))
    gicp.set_problem(T0[None], row_group=[0], row_map=[0])
    out = gicp.optimize(max_iterations=2, use_lm=False)  # linearize, step, accept the step
    np.testing.assert_allclose(out.T[0][:3, 3], expected[:3, 3], atol=2e-5)
    np.testing.assert_allclose(out.T[0][:3, :3], expected[:3, :3], atol=2e-5)
    assert out.iterations[0] == 2


@pytest.mark.parametrize("use_lm", [True, False])
def test_batch_converges_and_rows_share_one_pose(problem, use_lm):
    """32 perturbed poses: even ones against map 0, odd ones against map 1 reached through a
    left pose; the last one has both rows. All must converge to identity."""
    gicp = problem["gicp"]
    rng = np.random.default_rng(5)
    G = 33
    T0 = np.stack([se3(so3_exp(0.05 * rng.normal(size=3)), 0.15 * rng.normal(size=3))
                   for _ in range(G)])
    T_left = problem["T_shift"]  # T_map1_world: rows of map 1 see the pose through it
    groups = np.r_[np.arange(G), G - 1]
    maps_ = np.r_[np.arange(G) % 2, 0]
    left = np.stack([T_left if m == 1 else np.eye(4) for m in maps_])
    gicp.set_problem(T0, row_group=groups, row_map=maps_, T_left=left)
    out = gicp.optimize(max_iterations=30, use_lm=use_lm)
    assert out.converged.all()
    src, covs = problem["src"], problem["src_covs"]
    rows0 = [(problem["vox"], np.eye(4))]
    rows1 = [(problem["vox1"], T_left)]
    for k, T in enumerate(out.T):
        # Near a stationary point of the float64 cost: the residual step is limited by the f32
        # sums and by correspondences that flip between voxels (the cost is piecewise smooth).
        rows = rows0 + rows1 if k == G - 1 else (rows0 if k % 2 == 0 else rows1)
        # LM stops where no damped step lowers the cost, which can be a few mm short.
        delta = reference_step(rows, src, covs, T)
        limit = 1e-2 if use_lm else 1e-3
        assert np.linalg.norm(delta[:3]) < 2e-3 and np.linalg.norm(delta[3:]) < limit
        assert np.linalg.norm(T[:3, 3]) < 0.02
    assert out.num_inliers[-1] > 1.5 * out.num_inliers[0]  # two rows add up


def test_no_correspondences_is_reported(problem):
    gicp = problem["gicp"]
    gicp.set_problem(se3(np.eye(3), [100.0, 0, 0])[None], row_group=[0], row_map=[0])
    out = gicp.optimize(max_iterations=5)
    assert out.status[0] == 2 and out.num_inliers[0] == 0


def test_bad_problems_are_rejected(problem):
    from mcl3d.core.errors import ConfigError

    gicp = problem["gicp"]
    with pytest.raises(ConfigError, match="row_group"):
        gicp.set_problem(np.eye(4)[None], row_group=[1], row_map=[0])
    with pytest.raises(ConfigError, match="map id"):
        gicp.set_problem(np.eye(4)[None], row_group=[0], row_map=[7])
    with pytest.raises(ConfigError, match="fit"):
        gicp.set_problem(np.tile(np.eye(4), (65, 1, 1)), row_group=np.arange(65),
                         row_map=np.zeros(65))


def test_rotated_covariance_and_symmetric_inverse_match_numpy(ti_runtime):
    """The per-point helpers of kernels/gicp.linearize: upper(R A Rᵀ) from the per-row basis,
    the adjugate inverse of a symmetric 3x3, and 0 for an outlier."""
    import taichi as ti

    from mcl3d.kernels.gicp import rotated_cov_basis, sym_inverse

    def run(R, A, C, hit, out_rot, out_inv):
        for i in range(A.shape[0]):
            Rm = ti.math.mat3(0.0)
            for a in ti.static(range(3)):
                for b in ti.static(range(3)):
                    Rm[a, b] = R[i, a, b]
            a6 = ti.Vector.zero(ti.f32, 6)
            c6 = ti.Vector.zero(ti.f32, 6)
            for n in ti.static(range(6)):
                a6[n] = A[i, n]
                c6[n] = C[i, n]
            rot = rotated_cov_basis(Rm) @ a6
            inv = sym_inverse(c6, hit[i])
            for n in ti.static(range(6)):
                out_rot[i, n] = rot[n]
                out_inv[i, n] = inv[n]

    # this module's annotations are strings (from __future__), which Taichi cannot read
    run.__annotations__ = {name: ti.types.ndarray() for name in
                           ("R", "A", "C", "hit", "out_rot", "out_inv")}
    run = ti.kernel(run)
    rng = np.random.default_rng(11)
    n = 8
    R = np.stack([so3_exp(rng.normal(size=3)) for _ in range(n)])
    G = rng.normal(size=(n, 3, 3))
    A = G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(3)
    G = rng.normal(size=(n, 3, 3))
    C = G @ np.swapaxes(G, 1, 2) + 0.5 * np.eye(3)
    C[-1] = 0.0  # singular: an outlier lane must still give 0, not NaN
    hit = np.r_[np.ones(n - 1), 0].astype(np.int32)
    iu, ju = np.triu_indices(3)
    out_rot, out_inv = np.zeros((n, 6), np.float32), np.zeros((n, 6), np.float32)
    run(R.astype(np.float32), A[:, iu, ju].astype(np.float32), C[:, iu, ju].astype(np.float32),
        hit, out_rot, out_inv)
    np.testing.assert_allclose(out_rot, (R @ A @ np.swapaxes(R, 1, 2))[:, iu, ju],
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out_inv[:-1], np.linalg.inv(C[:-1])[:, iu, ju], rtol=1e-4,
                               atol=1e-5)
    assert np.all(out_inv[-1] == 0.0)


def numpy_unpack_keys(keys):
    """kernels/voxel_hash.unpack_key in NumPy: (low, high) words of 21-bit biased coordinates."""
    low, high = keys[:, 0].astype(np.int64) & 0xFFFFFFFF, keys[:, 1].astype(np.int64)
    mask = (1 << 21) - 1
    return np.stack([high >> 10, (low >> 21) | ((high << 11) & mask), low & mask], 1) - (1 << 20)


def test_crowded_table_probes_on_and_matches_numpy(ti_runtime):
    """A map at ~70% load: many voxels sit past their home bucket, so linearize's rare
    longer-probe path runs; H, b, error and inliers must still match the NumPy reference."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    target, target_covs = corner_world(np.random.default_rng(7))
    source, source_covs = corner_world(np.random.default_rng(8), 60)
    vox = reference_voxels(target, target_covs)
    buckets = 128
    assert 0.5 < len(vox[1]) / buckets < 0.9
    maps = GaussianVoxelMaps(max_maps=1, buckets_per_map=buckets, max_points=1024)
    maps.clear(0, RES)
    maps.insert(0, target, target_covs)
    keys = maps.vox.to_numpy()["key"]
    occupied = np.flatnonzero(keys[:, 1] != -1)
    displaced = occupied != numpy_voxel_hash(numpy_unpack_keys(keys[occupied]), buckets)
    assert displaced.sum() >= 5
    gicp = BatchGicp(maps, max_groups=4, max_source_points=512)
    gicp.set_source(source, source_covs)
    rng = np.random.default_rng(12)
    poses = np.stack([se3(so3_exp(0.05 * rng.normal(size=3)), 0.1 * rng.normal(size=3))
                      for _ in range(4)])
    gicp.set_problem(poses, row_group=np.arange(4), row_map=np.zeros(4))
    out = gicp.optimize(max_iterations=1)
    for k, T in enumerate(poses):
        H, b, err, n = reference_linearize(vox, source, source_covs, T)
        assert out.num_inliers[k] == n > 100
        np.testing.assert_allclose(out.error[k], err, rtol=1e-4)
        np.testing.assert_allclose(out.b[k], b, rtol=1e-3, atol=1e-3 * np.abs(b).max())
        np.testing.assert_allclose(out.H[k], H, rtol=1e-3, atol=1e-4 * np.abs(H).max())


def test_chunked_and_whole_row_linearizations_agree(problem):
    """Few poses split rows into chunks summed atomically; many poses take whole rows per
    thread. Both give the same H, b, error and inliers (f32 summation order aside)."""
    gicp = problem["gicp"]
    rng = np.random.default_rng(13)
    poses = np.stack([se3(so3_exp(0.05 * rng.normal(size=3)), 0.1 * rng.normal(size=3))
                      for _ in range(3)])
    results = []
    for chunk in (64, 1 << 20):
        gicp.set_problem(poses, row_group=np.arange(3), row_map=np.zeros(3))
        gicp.iterate(chunk=chunk)
        results.append(gicp.result())
    a, b = results
    assert len(problem["src"]) > 4 * 64  # the chunked run really has several chunks per row
    np.testing.assert_array_equal(a.num_inliers, b.num_inliers)
    np.testing.assert_allclose(a.error, b.error, rtol=1e-5)
    np.testing.assert_allclose(a.b, b.b, rtol=1e-4, atol=1e-5 * np.abs(a.b).max())
    np.testing.assert_allclose(a.H, b.H, rtol=1e-4, atol=1e-5 * np.abs(a.H).max())


def test_plane_form_rebuilds_plane_covariances_and_rejects_others():
    from mcl3d.registration.batch_gicp import plane_form

    rng = np.random.default_rng(14)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    plane = np.eye(3) - (1 - 1e-3) * n[:, :, None] * n[:, None]
    line = 0.01 * np.eye(3) + 2.0 * n[:, :, None] * n[:, None]  # one large eigenvalue
    covs = np.concatenate([plane, line, 3.0 * np.eye(3)[None], np.zeros((1, 3, 3))])
    rows = plane_form(covs.astype(np.float32).astype(np.float64))
    assert rows is not None and rows.shape == (len(covs), 6)
    nn, alpha, beta = rows[:, :3], rows[:, 3], rows[:, 4]
    rebuilt = alpha[:, None, None] * np.eye(3) + beta[:, None, None] * nn[:, :, None] * nn[:, None]
    np.testing.assert_allclose(rebuilt, covs, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(nn, axis=1), 1.0, atol=1e-12)
    G = rng.normal(size=(3, 3))
    assert plane_form(np.concatenate([covs, (G @ G.T)[None]])) is None  # 3 distinct eigenvalues


def test_general_source_covariances_take_the_general_path_and_match_numpy(ti_runtime):
    """Source covariances that are not αI + βnnᵀ use the per-row rotation basis; plane ones the
    (n, α, β) form. Both give NumPy's H, b, error and inliers."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    target, target_covs = corner_world(np.random.default_rng(7))
    source, plane_covs = corner_world(np.random.default_rng(8), 60)
    G = np.random.default_rng(15).normal(size=(len(source), 3, 3))
    general_covs = 0.2 * G @ np.swapaxes(G, 1, 2) + 0.05 * np.eye(3)
    vox = reference_voxels(target, target_covs)
    maps = GaussianVoxelMaps(max_maps=1, buckets_per_map=1 << 9, max_points=1024)
    maps.clear(0, RES)
    maps.insert(0, target, target_covs)
    gicp = BatchGicp(maps, max_groups=2, max_source_points=512)
    rng = np.random.default_rng(16)
    poses = np.stack([se3(so3_exp(0.05 * rng.normal(size=3)), 0.1 * rng.normal(size=3))
                      for _ in range(2)])
    for covs, plane in ((general_covs, False), (plane_covs, True)):
        gicp.set_source(source, covs)
        assert gicp.plane_covs == plane
        gicp.set_problem(poses, row_group=np.arange(2), row_map=np.zeros(2))
        out = gicp.optimize(max_iterations=1)
        for k, T in enumerate(poses):
            H, b, err, n = reference_linearize(vox, source, covs, T)
            assert out.num_inliers[k] == n > 100
            np.testing.assert_allclose(out.error[k], err, rtol=1e-4)
            np.testing.assert_allclose(out.b[k], b, rtol=1e-3, atol=1e-3 * np.abs(b).max())
            np.testing.assert_allclose(out.H[k], H, rtol=1e-3, atol=1e-4 * np.abs(H).max())


def test_result_overlap_matches_numpy(problem):
    """result(overlap_maps=...) counts, at each pose's final T, the source points that land
    in an occupied voxel of any listed map at T_left @ T: NumPy reference per pose."""
    gicp, src = problem["gicp"], problem["src"]
    index0, index1 = problem["vox"][0], problem["vox1"][0]
    T_shift = problem["T_shift"]
    poses = np.stack([se3(so3_exp([0.0, 0.0, 0.02 * g]), [0.4 * g, 0.1, 0.0])
                      for g in range(4)])
    gicp.set_problem(poses, row_group=np.arange(4), row_map=np.zeros(4))
    out = gicp.optimize(max_iterations=1, overlap_maps=[1, 0],
                        overlap_T_left=np.stack([T_shift, np.eye(4)]))
    for g in range(4):
        keys0 = np.floor(transform_points(out.T[g], src) / RES).astype(int)
        keys1 = np.floor(transform_points(T_shift @ out.T[g], src) / RES).astype(int)
        hits = [tuple(a) in index0 or tuple(b) in index1 for a, b in zip(keys0, keys1,
                                                                         strict=True)]
        assert out.overlap[g] == pytest.approx(np.mean(hits), abs=1.5 / len(src))
    assert gicp.result().overlap is None
    from mcl3d.core.errors import ConfigError

    with pytest.raises(ConfigError, match="overlap"):
        gicp.result(overlap_maps=[0, 1], overlap_T_left=np.eye(4)[None])


def test_initial_poses_upload_as_matrices_on_every_quaternion_branch(problem):
    """set_problem sends rotation matrices and the kernel turns them into quaternions
    (Shepperd: trace, then the largest diagonal entry): all four branches against numpy."""
    from mcl3d.core.geometry import rot_to_quat

    gicp = problem["gicp"]
    rotations = [so3_exp([0.1, -0.2, 0.3]), so3_exp([3.0, 0.2, 0.1]),
                 so3_exp([0.1, 3.0, -0.2]), so3_exp([0.2, -0.1, 3.0])]
    poses = np.stack([se3(R, [1.0, -2.0, 0.5 * g]) for g, R in enumerate(rotations)])
    gicp.set_problem(poses, row_group=np.arange(4), row_map=np.zeros(4), T_left=poses[::-1])
    np.testing.assert_allclose(gicp.poses.q_cand.to_numpy()[:4], rot_to_quat(poses[:, :3, :3]),
                               atol=1e-6)
    np.testing.assert_allclose(gicp.poses.t_cand.to_numpy()[:4], poses[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(gicp.rows.q.to_numpy()[:4], rot_to_quat(poses[::-1, :3, :3]),
                               atol=1e-6)
