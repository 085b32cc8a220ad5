"""The SLAM particles' posterior draw after a Gauss-Newton step against NumPy on a tiny set:
who draws, and the exact draw δ = L⁻ᵀ z (info = L Lᵀ) from the same counter-based normals."""

import numpy as np

from mcl3d.core import geometry
from tests.kernels.random_numpy import normal2
from tests.kernels.test_kernels_slam import pose_fields, random_poses, read_poses


def fields(n, nb, nb_loop, H, matched, corrected):
    import taichi as ti

    out = {"nb": ti.field(ti.i32, (n, 3)), "nb_loop": ti.field(ti.i32, (n, 3)),
           "best_H": ti.Matrix.field(6, 6, ti.f32, 3 * n), "best_n": ti.field(ti.i32, 3 * n),
           "corrected": ti.field(ti.i32, n)}
    for name, value in (("nb", nb), ("nb_loop", nb_loop), ("best_H", H), ("best_n", matched),
                        ("corrected", corrected)):
        out[name].from_numpy(value)
    return out


def expected_moves(nb, nb_loop, matched, corrected, min_inliers, refined, with_corrected):
    m = np.maximum(matched.reshape(-1, 3), 0)
    rows = (nb >= 0) & (m > 0)
    enough = rows.any(axis=1) & (m.sum(axis=1) >= min_inliers) & ~(nb_loop == 1).any(axis=1)
    return (refined & enough) | (with_corrected & (corrected == 1)), rows


def test_draw_posterior_matches_numpy(ti_runtime):
    from mcl3d.kernels import slam_posterior

    rng = np.random.default_rng(4)
    n, seed, step, k_points, min_inliers = 7, 11, 3, 0.3, 30
    T0 = random_poses(rng, n)
    A = rng.standard_normal((3 * n, 6, 6))
    H = (A @ np.swapaxes(A, 1, 2) * 2e3 + np.diag([4e4, 4e4, 4e4, 1e4, 1e4, 1e4])
         ).astype(np.float32)
    nb = rng.integers(-1, 4, (n, 3)).astype(np.int32)
    nb[0] = -1  # no neighbour: never refined
    matched = rng.integers(0, 60, 3 * n).astype(np.int32)
    matched[3:6] = 5  # particle 1: too few inliers
    nb_loop = np.zeros((n, 3), np.int32)
    nb_loop[2, 1] = 1  # particle 2 loops: refinement did not move it
    corrected = np.zeros(n, np.int32)
    corrected[2] = 1
    cov = np.diag(np.r_[np.full(3, 1e-3**2), np.full(3, 0.02**2)])
    info = np.linalg.inv(cov)
    for refined, with_corrected in ((1, 0), (1, 1), (0, 1)):
        q, t = pose_fields(T0)
        f = fields(n, nb, nb_loop, H, matched, corrected)
        moved = slam_posterior.draw_posterior(
            n, f["nb"], f["nb_loop"], f["best_H"], f["best_n"], f["corrected"],
            info.astype(np.float32), k_points, min_inliers, refined, with_corrected, seed, step,
            q, t)
        moves, rows = expected_moves(nb, nb_loop, matched, corrected, min_inliers,
                                     bool(refined), bool(with_corrected))
        assert moved == moves.sum() > 0
        delta = geometry.se3_log(geometry.se3_inverse(T0) @ read_poses(q, t))
        np.testing.assert_allclose(delta[~moves], 0.0, atol=1e-6)
        z = np.concatenate([normal2(seed, step, np.arange(n), slam_posterior.FIRST_STREAM + 2 * a)
                            for a in range(3)], axis=1)
        for i in np.flatnonzero(moves):
            Hi = (rows[i, :, None, None] * H[3 * i:3 * i + 3].astype(np.float64)).sum(axis=0)
            L = np.linalg.cholesky(info + k_points / max(rows[i].sum(), 1) * Hi)
            want = np.linalg.solve(L.T, z[i])
            np.testing.assert_allclose(delta[i], want, rtol=2e-3, atol=2e-3 * np.abs(want).max())
