"""Monte Carlo SLAM particle kernels (the SLAM paper, Section III).

State, structure of arrays: each particle's current pose in `q_cur` (vec4) / `t_cur` (vec3)
fields, and its own copy of every keyframe pose in one ndarray `kf[N, K, 6]` holding the
translation and the quaternion's vector part (w >= 0 implied): 24 bytes per particle and
keyframe, so 100,000 particles x 100 keyframes take 240 MB. The ndarray is allocated for
`keyframes.capacity` slots at start; once they are full a new keyframe reuses a slot, so a
keyframe's age is its number `kf_seq[k]` (the order keyframes were made in), not its slot.

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
vec5 = ti.types.vector(5, ti.f32)
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
                      q_cur: ti.template(), t_cur: ti.template(),
                      kf_travel: ti.types.ndarray(ndim=1), kf_seq: ti.types.ndarray(ndim=1),
                      first_recent_seq: ti.i32, travel_now_m: ti.f32,
                      loop_min_travel_m: ti.f32, min_facing_cos: ti.f32, up: vec3,
                      max_dz_m: ti.f32, facing_neighbours: ti.i32, nb: ti.template(),
                      nb_loop: ti.template()) -> ti.i32:
    """The 3 keyframes nearest to each particle's current position in its own map (ties go
    to the lower slot), leaving out keyframes more than `max_dz_m` above or below it
    (another floor) and, with `facing_neighbours`, keyframes that are not among the newest
    and face away (they cannot be loops); a neighbour is a loop when it is not one of the
    newest keyframes (its number `kf_seq` is below `first_recent_seq`), the odometry
    travelled more than `loop_min_travel_m` since it, and its lidar faces within
    acos(min_facing_cos) of the particle's (+x axes). Returns how many particles see a
    loop."""
    looping = 0
    for i in range(n):
        p = t_cur[i]
        forward = quat_rotate(q_cur[i], vec3(1.0, 0.0, 0.0))
        best = vec3(3.0e38)
        idx = ti.Vector([NO_KEYFRAME, NO_KEYFRAME, NO_KEYFRAME])
        for k in range(num_kf):
            d = vec3(kf[i, k, 0], kf[i, k, 1], kf[i, k, 2]) - p
            d2 = d.dot(d)
            eligible = d2 < best[2] and ti.abs(d.dot(up)) <= max_dz_m
            if eligible and facing_neighbours != 0 and kf_seq[k] < first_recent_seq:
                q_kf, _ = load_keyframe(kf, i, k)
                eligible = quat_rotate(q_kf, vec3(1.0, 0.0, 0.0)).dot(forward) >= min_facing_cos
            if eligible:
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
            if k >= 0 and kf_seq[k] < first_recent_seq:
                q_kf, _ = load_keyframe(kf, i, k)
                facing = quat_rotate(q_kf, vec3(1.0, 0.0, 0.0)).dot(forward)
                is_loop = ti.select(travel_now_m - kf_travel[k] > loop_min_travel_m
                                    and facing >= min_facing_cos, 1, 0)
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


@ti.func
def clamped_step(q: vec4, t: vec3, H: mat6, b: vec6, max_rot_rad: ti.f32, max_trans_m: ti.f32):
    """T exp(ψ), ψ = -H⁻¹ b (small_gicp's sign convention) scaled into the trust region;
    returns the new pose and the rotation vector of the step in the world frame."""
    step = damped_step(H, b, GN_DAMPING)
    w = vec3(step[0], step[1], step[2])
    v = vec3(step[3], step[4], step[5])
    scale = ti.min(ti.min(1.0, max_rot_rad / ti.max(w.norm(), 1e-12)),
                   max_trans_m / ti.max(v.norm(), 1e-12))
    q_new, t_new = pose_retract(q, t, w * scale, v * scale)
    return q_new, t_new, quat_rotate(q, w * scale)


@ti.kernel
def correct(n: ti.i32, nb_loop: ti.template(), best_H: ti.template(), best_b: ti.template(),
            best_n: ti.template(), min_inliers: ti.i32, max_rot_rad: ti.f32,
            max_trans_m: ti.f32, q_cur: ti.template(), t_cur: ti.template(),
            shift: ti.template(), corrected: ti.template()):
    """Eq. 5-7: ψ = -H⁻¹ b from the loop neighbours' terms, clamped to a trust region, and
    T_i <- T_i exp(ψ). `shift` keeps the move in the world frame (rotation vector,
    translation) for `propagate`."""
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
            t_old = t_cur[i]
            q_new, t_new, w_world = clamped_step(q_cur[i], t_old, H, b, max_rot_rad,
                                                 max_trans_m)
            q_cur[i], t_cur[i] = q_new, t_new
            dt_world = t_new - t_old
            moved = vec6(w_world[0], w_world[1], w_world[2], dt_world[0], dt_world[1],
                         dt_world[2])
            done = 1
        shift[i] = moved
        corrected[i] = done


@ti.kernel
def refine(n: ti.i32, nb: ti.template(), nb_loop: ti.template(), best_H: ti.template(),
           best_b: ti.template(), best_n: ti.template(), min_inliers: ti.i32,
           prior_info: mat6, max_rot_rad: ti.f32, max_trans_m: ti.f32, q_cur: ti.template(),
           t_cur: ti.template()) -> ti.i32:
    """The gradient-guided update without a loop (docs/slam.md): a particle with no loop
    neighbour takes one Gauss-Newton step on the GICP cost against all its neighbours (its
    own newest keyframes) plus the prediction's prior, ψ = -(H + Σ⁻¹)⁻¹ b with
    `prior_info` = Σ⁻¹, so the prediction noise does not pile up along directions the scan
    pins down, while directions it leaves open (a turn that sees few trees) keep their
    spread. Nothing is propagated. Uses the terms the likelihood just linearized. Returns
    how many particles moved."""
    moved = 0
    for i in range(n):
        H = prior_info
        b = vec6(0.0)
        m = 0
        loop = 0
        for j in ti.static(range(NEIGHBOURS)):
            g = i * NEIGHBOURS + j
            loop |= nb_loop[i, j]
            if nb[i, j] >= 0 and best_n[g] > 0:
                H += best_H[g]
                b += best_b[g]
                m += best_n[g]
        if loop == 0 and m >= min_inliers:
            q_new, t_new, _ = clamped_step(q_cur[i], t_cur[i], H, b, max_rot_rad, max_trans_m)
            q_cur[i], t_cur[i] = q_new, t_new
            moved += 1
    return moved


@ti.func
def path_fraction(rows: ti.types.ndarray(ndim=2), k: ti.i32, base: vec5, span_w: ti.f32,
                  span_v: ti.f32):
    """(A, C, B) of keyframe k: its share A of the rotational drift variance and B of the
    translational one accumulated since `base`, and C the position-weighted rotational share
    (Σ w_j p_j / span)."""
    a = ti.min(ti.max((rows[k, 0] - base[0]) / span_w, 0.0), 1.0)
    c = vec3(rows[k, 1] - base[1], rows[k, 2] - base[2], rows[k, 3] - base[3]) / span_w
    b = ti.min(ti.max((rows[k, 4] - base[4]) / span_v, 0.0), 1.0)
    return a, c, b


@ti.kernel
def propagate(n: ti.i32, num_kf: ti.i32, kf: ti.types.ndarray(ndim=3), nb: ti.template(),
              kf_travel: ti.types.ndarray(ndim=1), kf_drift: ti.types.ndarray(ndim=2),
              drift_now: vec5, odo_now: vec3, shift: ti.template(), corrected: ti.template(),
              fixed_travel: ti.template(), fixed_drift: ti.template()):
    """Eq. 8-10 with the odometry's drift model in place of travelled distance: the path
    from the base (the oldest neighbour o, or the particle's last settled correction when
    later) to now takes the current pose's correction (ω, Δt), seen in the world, in the
    proportion in which the prediction's variance accumulated along it.

    `kf_drift[k]` holds, at keyframe k's scan, the cumulative rotational variance W, the
    cumulative Σ w_j p_j (p_j the odometry's position), the cumulative translational
    variance V and the keyframe's odometry position; `drift_now` the same sums now. Keyframe
    k turns by A_k ω about its own position and moves by ω × (A_k p_k − C_k) (the rotation
    applied where it accumulated, with its lever arm) plus B_k of the translation the
    rotation does not explain, Δt − ω × (p_now − C_now). For variance spread evenly
    along a straight path this is eq. 8-10 (with the world-frame reading of docs/slam.md);
    where the odometry was weak (a turn that sees few trees) the path bends there."""
    for i, k in ti.ndrange(n, num_kf):
        if corrected[i] == 1:
            base_travel = 3.0e38
            base = vec5(0.0)
            for j in ti.static(range(NEIGHBOURS)):
                o = nb[i, j]
                if o >= 0 and kf_travel[o] < base_travel:
                    base_travel = kf_travel[o]
                    base = vec5(kf_drift[o, 0], kf_drift[o, 1], kf_drift[o, 2], kf_drift[o, 3],
                                kf_drift[o, 4])
            if fixed_travel[i] > base_travel:
                base_travel = fixed_travel[i]
                base = fixed_drift[i]
            span_w = drift_now[0] - base[0]
            span_v = drift_now[4] - base[4]
            if kf_travel[k] > base_travel and span_w > 0.0 and span_v > 0.0:
                s = shift[i]
                w = vec3(s[0], s[1], s[2])
                a, c, b = path_fraction(kf_drift, k, base, span_w, span_v)
                c_now = vec3(drift_now[1] - base[1], drift_now[2] - base[2],
                             drift_now[3] - base[3]) / span_w
                p_k = vec3(kf_drift[k, 5], kf_drift[k, 6], kf_drift[k, 7])
                rest = vec3(s[3], s[4], s[5]) - w.cross(odo_now - c_now)
                q_kf, t_kf = load_keyframe(kf, i, k)
                dq = quat_exp(a * w)
                store_keyframe(kf, i, k, quat_normalize(quat_mul(dq, q_kf)),
                               t_kf + w.cross(a * p_k - c) + b * rest)


@ti.kernel
def mark_fixed(n: ti.i32, travel_now_m: ti.f32, drift_now: vec5, corrected: ti.template(),
               shift: ti.template(), settled_rad: ti.f32, settled_m: ti.f32,
               fixed_travel: ti.template(), fixed_drift: ti.template()):
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
            fixed_drift[i] = drift_now


@ti.func
def row_cost(g: ti.i32, num_src: ti.i32, best_e: ti.template(), best_n: ti.template(),
             outlier_cost: ti.f32, seen: ti.template(), seen_cost: ti.f32) -> ti.f32:
    """One neighbour row's cost: eᵀΩe summed over the matched points, `outlier_cost` per
    point without a voxel, `seen_cost` per point in seen-through space."""
    matched = ti.max(best_n[g], 0)
    cost = outlier_cost * ti.cast(num_src - matched, ti.f32) + seen_cost * ti.cast(seen[g],
                                                                               ti.f32)
    if matched > 0:
        cost += 2.0 * best_e[g]
    return cost


@ti.kernel
def local_row_costs(n: ti.i32, num_src: ti.i32, nb: ti.template(), nb_loop: ti.template(),
                    best_e: ti.template(), best_n: ti.template(), outlier_cost: ti.f32,
                    seen: ti.template(), seen_cost: ti.f32, out: ti.types.ndarray(ndim=1)):
    """The cost (`row_cost`) of every (particle, neighbour) row that is not a loop; -1 for a
    loop row and a row without a keyframe."""
    for i, j in ti.ndrange(n, NEIGHBOURS):
        g = i * NEIGHBOURS + j
        out[g] = -1.0
        if nb[i, j] >= 0 and nb_loop[i, j] == 0:
            out[g] = row_cost(g, num_src, best_e, best_n, outlier_cost, seen, seen_cost)


@ti.kernel
def local_point_costs(n: ti.i32, nb: ti.template(), nb_loop: ti.template(),
                      best_e: ti.template(), best_n: ti.template(),
                      out: ti.types.ndarray(ndim=1)):
    """The mean eᵀΩe of a matched point in every (particle, neighbour) row that is not a loop;
    -1 for a loop row, a row without a keyframe and a row without a match."""
    for i, j in ti.ndrange(n, NEIGHBOURS):
        g = i * NEIGHBOURS + j
        out[g] = -1.0
        if nb[i, j] >= 0 and nb_loop[i, j] == 0 and best_n[g] > 0:
            out[g] = 2.0 * best_e[g] / ti.cast(best_n[g], ti.f32)


@ti.kernel
def likelihood(n: ti.i32, num_src: ti.i32, nb: ti.template(), nb_loop: ti.template(),
               best_e: ti.template(), best_n: ti.template(), outlier_cost: ti.f32,
               seen: ti.template(), seen_cost: ti.f32, points_weight: ti.f32,
               local_weight: ti.f32, local_reference: ti.f32, frame_ll: ti.template(),
               log_w: ti.template()):
    """Eq. 2-3 and 11, per point: the GICP cost eᵀΩe of a matched point (at most `outlier_cost`
    with likelihood.truncated: best_e is then capped per point), `outlier_cost`
    for a point with no voxel, plus `seen_cost` for each of the row's `seen` points (points
    in the keyframe's seen-through space, kernels/slam_free_space.py, already scaled to the
    scan); log p = -½ points_weight · mean cost over the neighbour rows, added to the
    cumulative log weight. A row that is not a loop costs `local_weight` × its own cost +
    (1 - `local_weight`) × `local_reference` (1: its own, as in the paper). A particle
    without neighbours gets UNSCORED and no weight (the host gives it the typical particle's
    likelihood)."""
    for i in range(n):
        cost = 0.0
        rows = 0
        for j in ti.static(range(NEIGHBOURS)):
            g = i * NEIGHBOURS + j
            if nb[i, j] >= 0:
                rows += 1
                own = row_cost(g, num_src, best_e, best_n, outlier_cost, seen, seen_cost)
                if nb_loop[i, j] == 1:
                    cost += own
                else:
                    cost += local_weight * own + (1.0 - local_weight) * local_reference
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
def respawn(m: ti.i32, dead: ti.types.ndarray(ndim=1), source: ti.types.ndarray(ndim=1),
            num_kf: ti.i32, q_cur: ti.template(), t_cur: ti.template(),
            fixed_travel: ti.template(), fixed_drift: ti.template(),
            kf: ti.types.ndarray(ndim=3)):
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
            fixed_drift[d] = fixed_drift[s]
        else:
            for a in ti.static(range(6)):
                kf[d, k, a] = kf[s, k, a]


@ti.kernel
def gather_keyframes(i: ti.i32, num_kf: ti.i32, kf: ti.types.ndarray(ndim=3),
                     out: ti.types.ndarray(ndim=2)):
    for k, a in ti.ndrange(num_kf, 6):
        out[k, a] = kf[i, k, a]
