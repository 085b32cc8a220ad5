"""Monte Carlo SLAM particle kernels (the SLAM paper, Section III).

State, structure of arrays: each particle's current pose in `q_cur` (vec4) / `t_cur` (vec3)
fields, and its own copy of every keyframe pose in one ndarray `kf[N, K, 6]` holding the
translation and the quaternion's vector part (w >= 0 implied): 24 bytes per particle and
keyframe, so 100,000 particles x 100 keyframes take 240 MB. The ndarray is reallocated in
steps as keyframes arrive, so memory follows the keyframe count.

Groups of the batched GICP (kernels/gicp.py) are (particle, neighbour) pairs, `g = 3 i + j`,
one row each: every group owns its sums (no float atomics), and the particle's three
neighbour terms are added here in a fixed order, so runs are bit-for-bit reproducible.
"""

import taichi as ti

from mcl3d.kernels.gicp import GN_DAMPING, damped_step
from mcl3d.kernels.random import normal2
from mcl3d.kernels.se3 import (
    pose_compose,
    pose_inverse,
    pose_retract,
    quat_exp,
    quat_mul,
    quat_normalize,
    quat_rotate,
)

vec3 = ti.math.vec3
vec4 = ti.math.vec4
vec6 = ti.types.vector(6, ti.f32)
mat6 = ti.types.matrix(6, 6, ti.f32)
NEIGHBOURS = 3  # keyframes per particle in the likelihood (the paper's choice)
NO_KEYFRAME = -1
UNSCORED = -3.0e38  # frame log-likelihood of a particle with no neighbour keyframe


@ti.func
def load_keyframe(kf: ti.template(), i: ti.i32, k: ti.i32):
    v = vec3(kf[i, k, 3], kf[i, k, 4], kf[i, k, 5])
    q = vec4(v[0], v[1], v[2], ti.sqrt(ti.max(1.0 - v.dot(v), 0.0)))
    return quat_normalize(q), vec3(kf[i, k, 0], kf[i, k, 1], kf[i, k, 2])


@ti.func
def store_keyframe(kf: ti.template(), i: ti.i32, k: ti.i32, q: vec4, t: vec3):
    s = ti.select(q[3] < 0.0, -1.0, 1.0)
    for a in ti.static(range(3)):
        kf[i, k, a] = t[a]
        kf[i, k, 3 + a] = s * q[a]


@ti.kernel
def predict(n: ti.i32, dq: vec4, dt: vec3, chol: mat6, seed: ti.u32, step: ti.u32,
            q_cur: ti.template(), t_cur: ti.template()):
    """T_i <- T_i ΔT exp(δ_i), δ_i = L z with z ~ N(0, I) (eq. 1; L L^T = Σ_ΔT)."""
    for i in range(n):
        z = vec6(0.0)
        for a in ti.static(range(3)):
            pair = normal2(seed, step, ti.u32(i), ti.u32(2 * a))
            z[2 * a] = pair[0]
            z[2 * a + 1] = pair[1]
        d = chol @ z
        q, t = pose_compose(q_cur[i], t_cur[i], dq, dt)
        q_cur[i], t_cur[i] = pose_retract(q, t, vec3(d[0], d[1], d[2]), vec3(d[3], d[4], d[5]))


@ti.kernel
def shift_vertical(n: ti.i32, shift: vec3, up: vec3, sigma_m: ti.f32, seed: ti.u32,
                   step: ti.u32, t_cur: ti.template()):
    """The elevator model: every particle moves by `shift` (the IMU's vertical motion, or 0)
    plus a random walk of `sigma_m` along `up` (world frame)."""
    for i in range(n):
        t_cur[i] += shift + sigma_m * normal2(seed, step, ti.u32(i), ti.u32(6))[0] * up


@ti.kernel
def select_neighbours(n: ti.i32, num_kf: ti.i32, kf: ti.types.ndarray(ndim=3),
                      t_cur: ti.template(), kf_travel: ti.types.ndarray(ndim=1),
                      travel_now_m: ti.f32, loop_min_travel_m: ti.f32, up: vec3,
                      max_dz_m: ti.f32, nb: ti.template(), nb_loop: ti.template()) -> ti.i32:
    """The 3 keyframes nearest to each particle's current position in its own map (ties go
    to the older keyframe), leaving out keyframes more than `max_dz_m` above or below it
    (another floor); a neighbour is a loop when it is not one of the 3 newest keyframes and
    the odometry travelled more than `loop_min_travel_m` since it. Returns how many particles
    see a loop."""
    looping = 0
    for i in range(n):
        p = t_cur[i]
        best = vec3(3.0e38)
        idx = ti.Vector([NO_KEYFRAME, NO_KEYFRAME, NO_KEYFRAME])
        for k in range(num_kf):
            d = vec3(kf[i, k, 0], kf[i, k, 1], kf[i, k, 2]) - p
            d2 = d.dot(d)
            if d2 < best[2] and ti.abs(d.dot(up)) <= max_dz_m:
                if d2 < best[1]:
                    best[2], idx[2] = best[1], idx[1]
                    if d2 < best[0]:
                        best[1], idx[1] = best[0], idx[0]
                        best[0], idx[0] = d2, k
                    else:
                        best[1], idx[1] = d2, k
                else:
                    best[2], idx[2] = d2, k
        any_loop = 0
        for j in ti.static(range(NEIGHBOURS)):
            k = idx[j]
            nb[i, j] = k
            is_loop = 0
            if k >= 0 and k < num_kf - NEIGHBOURS:
                is_loop = ti.select(travel_now_m - kf_travel[k] > loop_min_travel_m, 1, 0)
            nb_loop[i, j] = is_loop
            any_loop |= is_loop
        looping += any_loop
    return looping


@ti.kernel
def build_rows(n: ti.i32, kf: ti.types.ndarray(ndim=3), q_cur: ti.template(),
               t_cur: ti.template(), nb: ti.template(), nb_loop: ti.template(),
               loop_only: ti.i32, num_src: ti.i32, row_group: ti.template(),
               row_map: ti.template(), row_q: ti.template(), row_t: ti.template(),
               row_start: ti.template(), row_count: ti.template(), q_cand: ti.template(),
               t_cand: ti.template()):
    """GICP rows: group g = 3 i + j registers the scan at particle i's pose into keyframe
    nb[i, j]'s voxel map, with left pose T_keyframe_world of that particle's map. Rows
    without a keyframe (or, with `loop_only`, without a loop) get no points."""
    for i, j in ti.ndrange(n, NEIGHBOURS):
        g = i * NEIGHBOURS + j
        k = nb[i, j]
        use = k >= 0 and (loop_only == 0 or nb_loop[i, j] == 1)
        kk = ti.max(k, 0)
        q_kf, t_kf = load_keyframe(kf, i, kk)
        q_inv, t_inv = pose_inverse(q_kf, t_kf)
        row_group[g] = g
        row_map[g] = kk
        row_q[g] = q_inv
        row_t[g] = t_inv
        row_start[g] = 0
        row_count[g] = ti.select(use, num_src, 0)
        q_cand[g] = q_cur[i]
        t_cand[g] = t_cur[i]


@ti.kernel
def correct(n: ti.i32, nb_loop: ti.template(), best_H: ti.template(), best_b: ti.template(),
            best_n: ti.template(), min_inliers: ti.i32, max_rot_rad: ti.f32,
            max_trans_m: ti.f32, q_cur: ti.template(), t_cur: ti.template(),
            shift: ti.template(), corrected: ti.template()):
    """Eq. 5-7: ψ = -H⁻¹ b from the loop neighbours' terms (small_gicp's sign convention),
    clamped to a trust region, and T_i <- T_i exp(ψ). `shift` keeps the move in the world
    frame (rotation vector, translation) for `propagate`."""
    for i in range(n):
        H = mat6(0.0)
        b = vec6(0.0)
        m = 0
        for j in ti.static(range(NEIGHBOURS)):
            g = i * NEIGHBOURS + j
            if nb_loop[i, j] == 1 and best_n[g] > 0:
                H += best_H[g]
                b += best_b[g]
                m += best_n[g]
        moved = vec6(0.0)
        done = 0
        if m >= min_inliers:
            step = damped_step(H, b, GN_DAMPING)
            w = vec3(step[0], step[1], step[2])
            v = vec3(step[3], step[4], step[5])
            scale = ti.min(ti.min(1.0, max_rot_rad / ti.max(w.norm(), 1e-12)),
                           max_trans_m / ti.max(v.norm(), 1e-12))
            q_old, t_old = q_cur[i], t_cur[i]
            q_cur[i], t_cur[i] = pose_retract(q_old, t_old, w * scale, v * scale)
            w_world = quat_rotate(q_old, w * scale)
            dt_world = t_cur[i] - t_old
            moved = vec6(w_world[0], w_world[1], w_world[2], dt_world[0], dt_world[1],
                         dt_world[2])
            done = 1
        shift[i] = moved
        corrected[i] = done


@ti.kernel
def propagate(n: ti.i32, num_kf: ti.i32, kf: ti.types.ndarray(ndim=3), nb: ti.template(),
              kf_travel: ti.types.ndarray(ndim=1), travel_now_m: ti.f32,
              shift: ti.template(), corrected: ti.template(), fixed_travel: ti.template()):
    """Eq. 8-10: keyframe k after the oldest neighbour o takes the fraction
    α_k = d(o, k) / d(o, now) of the current pose's correction. Two deviations
    (docs/slam.md): the fraction is of the correction as seen in the world (turn by α ω about
    the keyframe's own position, move by α Δt), not of ψ in each keyframe's own frame, so a
    keyframe facing another way moves the way the current pose moved; and the path starts at
    the particle's previous correction when that is later than o, so re-driving an old loop
    spreads only the drift since then instead of bending the whole loop again each scan."""
    for i, k in ti.ndrange(n, num_kf):
        if corrected[i] == 1:
            base = 3.0e38
            for j in ti.static(range(NEIGHBOURS)):
                if nb[i, j] >= 0:
                    base = ti.min(base, kf_travel[nb[i, j]])
            base = ti.max(base, fixed_travel[i])
            span = travel_now_m - base
            if kf_travel[k] > base and span > 0.0:
                alpha = ti.min((kf_travel[k] - base) / span, 1.0)
                s = shift[i]
                q_kf, t_kf = load_keyframe(kf, i, k)
                dq = quat_exp(alpha * vec3(s[0], s[1], s[2]))
                store_keyframe(kf, i, k, quat_normalize(quat_mul(dq, q_kf)),
                               t_kf + alpha * vec3(s[3], s[4], s[5]))


@ti.kernel
def mark_fixed(n: ti.i32, travel_now_m: ti.f32, corrected: ti.template(), shift: ti.template(),
               settled_rad: ti.f32, settled_m: ti.f32, fixed_travel: ti.template()):
    """A correction this small means the particle sits on the loop (it is re-driving it):
    later corrections spread from here. A larger one (the first steps of a closure, a
    step cut by the trust region) leaves the start where it was, so the rest of the
    closure still bends the whole loop."""
    for i in range(n):
        s = shift[i]
        small = (vec3(s[0], s[1], s[2]).norm() <= settled_rad
                 and vec3(s[3], s[4], s[5]).norm() <= settled_m)
        if corrected[i] == 1 and small:
            fixed_travel[i] = travel_now_m


@ti.kernel
def likelihood(n: ti.i32, num_src: ti.i32, nb: ti.template(), best_e: ti.template(),
               best_n: ti.template(), outlier_cost: ti.f32, points_weight: ti.f32,
               frame_ll: ti.template(), log_w: ti.template()):
    """Eq. 2-3 and 11, per point: the GICP cost eᵀΩe of a matched point, `outlier_cost`
    for a point with no voxel; log p = -½ points_weight · mean cost over the neighbour
    rows, added to the cumulative log weight. A particle without neighbours gets UNSCORED
    and no weight (the host gives it the typical particle's likelihood)."""
    for i in range(n):
        cost = 0.0
        rows = 0
        for j in ti.static(range(NEIGHBOURS)):
            g = i * NEIGHBOURS + j
            if nb[i, j] >= 0:
                rows += 1
                matched = ti.max(best_n[g], 0)
                if matched > 0:
                    cost += 2.0 * best_e[g]
                cost += outlier_cost * ti.cast(num_src - matched, ti.f32)
        if rows > 0:
            ll = -0.5 * points_weight * cost / ti.cast(rows * num_src, ti.f32)
            frame_ll[i] = ll
            log_w[i] += ll
        else:
            frame_ll[i] = UNSCORED


@ti.kernel
def insert_keyframe(n: ti.i32, k: ti.i32, q_cur: ti.template(), t_cur: ti.template(),
                    kf: ti.types.ndarray(ndim=3)):
    for i in range(n):
        store_keyframe(kf, i, k, q_cur[i], t_cur[i])


@ti.kernel
def copy_keyframes(n: ti.i32, num_kf: ti.i32, src: ti.types.ndarray(ndim=3),
                   dst: ti.types.ndarray(ndim=3)):
    for i, k, a in ti.ndrange(n, num_kf, 6):
        dst[i, k, a] = src[i, k, a]


@ti.kernel
def respawn(m: ti.i32, dead: ti.types.ndarray(ndim=1), source: ti.types.ndarray(ndim=1),
            num_kf: ti.i32, q_cur: ti.template(), t_cur: ti.template(),
            fixed_travel: ti.template(), kf: ti.types.ndarray(ndim=3)):
    """Dead particle dead[r] becomes a copy of living particle source[r] (current pose,
    last correction, every keyframe pose). Sources are never among the dead, so copies
    cannot race."""
    for r, k in ti.ndrange(m, num_kf + 1):
        d = dead[r]
        s = source[r]
        if k == num_kf:
            q_cur[d] = q_cur[s]
            t_cur[d] = t_cur[s]
            fixed_travel[d] = fixed_travel[s]
        else:
            for a in ti.static(range(6)):
                kf[d, k, a] = kf[s, k, a]


@ti.kernel
def gather_keyframes(i: ti.i32, num_kf: ti.i32, kf: ti.types.ndarray(ndim=3),
                     out: ti.types.ndarray(ndim=2)):
    for k, a in ti.ndrange(num_kf, 6):
        out[k, a] = kf[i, k, a]
