"""The SLAM particles' draw from the Gaussian posterior of their Gauss-Newton step, on the
device (mcl3d.slam.slam_particles.SlamParticles.spread says why): only a count comes back, so
the step's cost and traffic do not grow with the particles on the host.

Each moved particle draws δ ~ N(0, P), P = info⁻¹, info = Σ⁻¹ + k Σ_j H_j, by a Cholesky
factor of info itself: with info = L Lᵀ, δ = L⁻ᵀ z (z ~ N(0, I)) has covariance
L⁻ᵀ L⁻¹ = info⁻¹, so nothing is inverted. info is scaled to a unit diagonal first
(D info D, D = diag(info)^-1/2, δ = D L⁻ᵀ z), so f32 keeps its precision when rotation and
translation information differ by orders of magnitude.
"""

import taichi as ti

from mcl3d.kernels.random import normal2
from mcl3d.kernels.se3 import pose_retract
from mcl3d.kernels.slam import NEIGHBOURS, mat6, vec3, vec6

FIRST_STREAM = 8  # counter streams 8..13 (predict takes 0..5, shift_vertical 6)


@ti.func
def posterior_draw(info: mat6, z: vec6) -> vec6:
    """δ with covariance info⁻¹ from standard normals z (info symmetric positive definite)."""
    d = vec6(0.0)
    for a in ti.static(range(6)):
        d[a] = 1.0 / ti.sqrt(ti.max(info[a, a], 1e-30))
    A = info * d.outer_product(d)
    L = mat6(0.0)  # A = L Lᵀ, column by column
    for c in ti.static(range(6)):
        s = A[c, c]
        for k in ti.static(range(c)):
            s -= L[c, k] * L[c, k]
        L[c, c] = ti.sqrt(ti.max(s, 1e-12))
        for r in ti.static(range(c + 1, 6)):
            s = A[r, c]
            for k in ti.static(range(c)):
                s -= L[r, k] * L[c, k]
            L[r, c] = s / L[c, c]
    x = vec6(0.0)  # Lᵀ x = z, last row first
    for r in ti.static(range(5, -1, -1)):
        s = z[r]
        for k in ti.static(range(r + 1, 6)):
            s -= L[k, r] * x[k]
        x[r] = s / L[r, r]
    return d * x


@ti.kernel
def draw_posterior(n: ti.i32, nb: ti.template(), nb_loop: ti.template(), best_H: ti.template(),
                   best_n: ti.template(), corrected: ti.template(), prior_info: mat6,
                   k_points: ti.f32, min_inliers: ti.i32, refined: ti.i32,
                   with_corrected: ti.i32, seed: ti.u32, step: ti.u32, q_cur: ti.template(),
                   t_cur: ti.template()) -> ti.i32:
    """Every particle the last step moved draws from its step's posterior (module docstring):
    with `refined`, those without a loop neighbour that had min_inliers matches; with
    `with_corrected`, those `correct` moved. k = k_points / rows, rows the particle's
    neighbours with matches. Returns how many drew."""
    moved = 0
    for i in range(n):
        H = mat6(0.0)
        rows = 0
        matched = 0
        loop = 0
        for j in ti.static(range(NEIGHBOURS)):
            g = i * NEIGHBOURS + j
            loop |= nb_loop[i, j]
            m = ti.max(best_n[g], 0)
            matched += m
            if nb[i, j] >= 0 and m > 0:
                H += best_H[g]
                rows += 1
        moves = (refined == 1 and rows > 0 and matched >= min_inliers and loop == 0) or (
            with_corrected == 1 and corrected[i] == 1)
        if moves:
            z = vec6(0.0)
            for a in ti.static(range(3)):
                pair = normal2(seed, step, ti.u32(i), ti.u32(FIRST_STREAM + 2 * a))
                z[2 * a] = pair[0]
                z[2 * a + 1] = pair[1]
            delta = posterior_draw(prior_info + (k_points / ti.max(rows, 1)) * H, z)
            q_cur[i], t_cur[i] = pose_retract(q_cur[i], t_cur[i], vec3(delta[0], delta[1],
                                                                        delta[2]),
                                              vec3(delta[3], delta[4], delta[5]))
            moved += 1
    return moved
