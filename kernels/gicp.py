"""Batched GICP (distribution-to-distribution) against Gaussian voxel maps.

Terms: a *group* is one pose being optimized, `T_frame_source` (a particle, a scan); a *row*
is one registration term of a group: a source point range, a target map and a fixed left
pose `L` so that the row's pose is `L T` (for a keyframe map, L = T_keyframe_frame). With a
right perturbation `T exp(δ)` the row pose moves by the same `δ`, so every row of a group adds
to one 6x6 system: particles x neighbour keyframes, or one scan x several map resolutions.

Per correspondence (one voxel lookup, no distance threshold):
  e = μ_B − R μ_A − t,  M = (C_B + R C_A Rᵀ)⁻¹,  J = [R hat(μ_A), −R]  (rotation first),
  H += Jᵀ M J,  b += Jᵀ M e,  error += ½ eᵀ M e
(accumulated with J_c = [hat(R μ_A), −I] in 3x3 blocks, mapped by J = J_c diag(R, R) once per
chunk: the same numbers, fewer operations), so that error(δ) ≈ error + bᵀδ + ½ δᵀHδ
(small_gicp's convention) and δ = −H⁻¹ b. Symmetric 3x3 matrices travel as their upper
triangles: R C_A Rᵀ is one 6x6 product with a per-row basis, M an adjugate inverse, and the
two symmetric blocks of H_c take 6 sums each. Source covariances of the plane form
C_A = αI + β nnᵀ (every plane-regularized or identity covariance; see batch_gicp.plane_form)
travel as (n, α, β) instead, and R C_A Rᵀ = αI + β (Rn)(Rn)ᵀ costs 15 multiply-adds instead of
36. On cpu the per-point loops are branch-free so that LLVM vectorizes them: about 7 ns of
cpu time per correspondence (10,000 poses x 512 points: ~35 cpu-ms per iteration, from 52
before the plane form and the slot passes described in `linearize`).

`linearize` runs over (row, chunk of source points), so one pose uses many threads and
100,000 poses use them all the same way; each task stores its own sums (a batch with one row
per pose and whole rows per task stores them straight into its group) and `reduce_tasks`
adds them up in a fixed order, so results are the same bits on every run; `step` then
solves every group's system (Jacobi-scaled, unrolled 6x6 Cholesky) with Gauss-Newton or
Levenberg-Marquardt acceptance and proposes the next candidate. The three are Taichi
functions run by the one kernel `iterate`: one launch per iteration. A small problem (one
scan of odometry) runs them all on the calling thread on cpu; `download_results` also counts
the scan's overlap with the keyframe maps in the same launch.

The state arrives as `ti.template()` containers (mcl3d/registration/gicp_state.py): `pool`
(points, cov_rows), `rows` (group, map, q, t, start, count), `poses` (q_cur, t_cur, q_cand,
t_cand, lam, status, iters, and the sums `acc`, `best`), `tasks` (sums H, b, e, n per task)
and `maps` (the Gaussian voxel maps: hash table `vox`, voxel size `res` per map).
"""

import taichi as ti

from mcl3d.kernels.se3 import pose_compose, pose_retract, quat_to_mat
from mcl3d.kernels.voxel_hash import EMPTY_KEY, lookup, lookup_from, pack_key, probe_slot, same_key

vec3 = ti.math.vec3
vec6 = ti.types.vector(6, ti.f32)
mat6 = ti.types.matrix(6, 6, ti.f32)
SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # upper-triangle order of vec6

RUNNING = 0
CONVERGED = 1
NO_CORRESPONDENCES = 2
STALLED = 3  # LM damping blew up without an accepted step: no descent direction left

LOOKAHEAD = 64  # points per block of linearize (home slots first, then the math)
GN_DAMPING = 1e-6  # on the Jacobi-scaled system: conditioning only
LM_MIN_LAMBDA = 1e-7
LM_MAX_LAMBDA = 1e7


@ti.func
def to_right_perturbation(R: ti.math.mat3, S_rr: vec6, S_tr: ti.math.mat3, S_tt: vec6,
                          b_r: vec3, b_t: vec3):
    """H, b of the centred perturbation, from its block sums (see linearize), -> rotation-first
    right perturbation of the pose: with D = diag(R, R), H_r = Dᵀ H D and b_r = Dᵀ b, taken
    block by block (Rᵀ X R), as a 6x6 product would, without its 27 products by 0 per entry
    (those took half of `iterate`'s compile time)."""
    Rt = R.transpose()
    rr = (Rt @ sym_to_mat(S_rr)) @ R
    rt = (Rt @ -S_tr.transpose()) @ R
    tt = (Rt @ sym_to_mat(S_tt)) @ R
    br = Rt @ b_r
    bt = Rt @ -b_t
    H = ti.Matrix.zero(ti.f32, 6, 6)
    b = ti.Vector.zero(ti.f32, 6)
    for i in ti.static(range(3)):
        b[i] = br[i]
        b[i + 3] = bt[i]
        for j in ti.static(range(3)):
            H[i, j] = rr[i, j]
            H[i, j + 3] = rt[i, j]
            H[i + 3, j] = rt[j, i]
            H[i + 3, j + 3] = tt[i, j]
    return H, b


@ti.func
def rotated_cov_basis(R: ti.math.mat3):
    """6x6 B with B @ upper(A) = upper(R A Rᵀ) for symmetric A, upper() = (xx xy xz yy yz zz):
    per row once, so that each point pays 36 multiply-adds instead of two 3x3 products."""
    B = ti.Matrix.zero(ti.f32, 6, 6)
    for n in ti.static(range(6)):
        i, j = ti.static(SYM[n])
        for col in ti.static(range(6)):
            u, v = ti.static(SYM[col])
            B[n, col] = R[i, u] * R[j, v]
            if ti.static(u != v):
                B[n, col] += R[i, v] * R[j, u]
    return B


@ti.func
def rotated_source_cov(B, ca: vec6, rn: vec3, plane: ti.template()) -> vec6:
    """upper(R C_A Rᵀ) from the stored source covariance `ca`: upper(C_A) with the row's
    basis B (rotated_cov_basis), or with `plane` (n, α, β) for C_A = αI + β nnᵀ, given
    rn = R n."""
    out = vec6(0.0)
    if ti.static(plane):
        bn = ca[4] * rn
        out = vec6(ca[3] + bn[0] * rn[0], bn[0] * rn[1], bn[0] * rn[2],
                   ca[3] + bn[1] * rn[1], bn[1] * rn[2], ca[3] + bn[2] * rn[2])
    else:
        out = B @ ca
    return out


@ti.func
def sym_inverse(c: vec6, hit: ti.i32) -> vec6:
    """Upper triangle of the inverse of the symmetric 3x3 `c` (adjugate / determinant), or 0
    where `hit` is 0 (an outlier weighs nothing and never divides by 0)."""
    m = vec6(c[3] * c[5] - c[4] * c[4], c[2] * c[4] - c[1] * c[5], c[1] * c[4] - c[2] * c[3],
             c[0] * c[5] - c[2] * c[2], c[1] * c[2] - c[0] * c[4], c[0] * c[3] - c[1] * c[1])
    det = c[0] * m[0] + c[1] * m[1] + c[2] * m[2]
    return m * (ti.select(hit, 1.0, 0.0) / ti.select(hit, det, 1.0))


@ti.func
def faces_map(x: vec3, rn: vec3, p_src: vec3, ca: vec6, facing_cos: ti.f32) -> ti.i32:
    """0 for a plane point whose surface faces away from the map's sensor (GLIM's surface
    validation): its normal n, turned towards the source sensor and rotated into the map
    frame (rn = R n, up to that sign), makes an angle under acos(facing_cos) with the ray
    from the map origin to it, x. The map could not have seen that side: the back of a tree
    trunk matched to its front. 1 for every other point (identity covariances carry no
    normal; facing_cos > 1 turns it off). Compared squared (facing_cos >= 0): no root."""
    c = x.dot(rn) * ti.select(vec3(ca[0], ca[1], ca[2]).dot(p_src) > 0.0, -1.0, 1.0)
    away = (c > 0.0) & (c * c > facing_cos * facing_cos * x.dot(x)) & (ca[4] != 0.0)
    return ti.select(away, 0, 1)


@ti.func
def point_terms(B, q: vec3, t: vec3, mean: vec3, CB: ti.math.mat3, ca: vec6, rn: vec3,
                hit: ti.i32, plane: ti.template()):
    """One correspondence's terms (all 0 unless `hit`): upper(hat(q)ᵀ M hat(q)), M hat(q),
    upper(M), hat(q)ᵀ M e, M e and ½ eᵀ M e, with q = R μ_A, e = μ_B − q − t (rn: see
    rotated_source_cov)."""
    M = sym_inverse(rotated_source_cov(B, ca, rn, plane)
                    + vec6(CB[0, 0], CB[0, 1], CB[0, 2], CB[1, 1], CB[1, 2], CB[2, 2]), hit)
    e = mean - q - t
    Me = vec3(M[0] * e[0] + M[1] * e[1] + M[2] * e[2],
              M[1] * e[0] + M[3] * e[1] + M[4] * e[2],
              M[2] * e[0] + M[4] * e[1] + M[5] * e[2])
    # M hat(q), row i = (row i of M) x q
    a0 = vec3(M[0], M[1], M[2]).cross(q)
    a1 = vec3(M[1], M[3], M[4]).cross(q)
    a2 = vec3(M[2], M[4], M[5]).cross(q)
    # upper triangle of hat(q)ᵀ M hat(q) = −hat(q) (M hat(q))
    rr = vec6(q[2] * a1[0] - q[1] * a2[0], q[2] * a1[1] - q[1] * a2[1],
              q[2] * a1[2] - q[1] * a2[2], q[0] * a2[1] - q[2] * a0[1],
              q[0] * a2[2] - q[2] * a0[2], q[1] * a0[2] - q[0] * a1[2])
    return rr, ti.Matrix.rows([a0, a1, a2]), M, Me.cross(q), Me, 0.5 * e.dot(Me)


@ti.func
def sym_to_mat(c: vec6) -> ti.math.mat3:
    return ti.math.mat3([[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]])


@ti.func
def linearize(pool: ti.template(), rows: ti.template(), num_rows: ti.i32, chunk: ti.i32,
              num_chunks: ti.i32, poses: ti.template(), maps: ti.template(), buckets: ti.i32,
              max_probes: ti.i32, tasks: ti.template(), exclusive: ti.template(),
              plane_cov: ti.template(), serial: ti.template(), facing_cos: ti.f32,
              cost_cap: ti.f32):
    """Every running row's sums, one task per (row, chunk of its points). `pool.cov_rows`
    holds upper(C_A) (see rotated_cov_basis), or (n, α, β, 0) with `plane_cov` (see
    rotated_source_cov). `exclusive`: every group has one row and one chunk, so each task owns
    its group's sums and stores them in tasks[group] (`tasks` is then poses.acc); otherwise
    task (r, c) stores its sums in tasks[r * num_chunks + c] (zeros when it has none) and
    `reduce_tasks` adds them up in a fixed order: float atomics would make every run differ in
    the last bits, and a tracker or particle filter turns those into different trajectories.
    `serial`: a small problem (one scan) runs on the calling thread, where waking the pool
    costs more than it saves (and on a busy machine a descheduled worker stalls the launch).
    `facing_cos`: see faces_map (plane covariances only). `cost_cap`: each point adds at most
    this to the error (½ eᵀMe; H and b keep every point): a truncated cost."""
    ti.loop_config(serialize=serial)
    for r, c in ti.ndrange(num_rows, num_chunks):
        g = rows.group[r]
        begin = c * chunk
        slot = g
        if ti.static(not exclusive):
            slot = r * num_chunks + c
            tasks.H[slot] = ti.Matrix.zero(ti.f32, 6, 6)
            tasks.b[slot] = ti.Vector.zero(ti.f32, 6)
            tasks.e[slot] = 0.0
            tasks.n[slot] = 0
        if poses.status[g] == RUNNING and begin < rows.count[r]:
            linearize_task(pool, rows, r, begin, ti.min(chunk, rows.count[r] - begin), poses, g,
                           maps, buckets, max_probes, tasks, slot, plane_cov, facing_cos,
                           cost_cap)


@ti.func
def linearize_task(pool: ti.template(), rows: ti.template(), r: ti.i32, begin: ti.i32,
                   count: ti.i32, poses: ti.template(), g: ti.i32, maps: ti.template(),
                   buckets: ti.i32, max_probes: ti.i32, tasks: ti.template(), slot: ti.i32,
                   plane_cov: ti.template(), facing_cos: ti.f32, cost_cap: ti.f32):
    """Sums of the `count` points of row r from its point `begin`, at its group g's candidate
    pose, into tasks[slot] (left as they are when no point found a voxel).

    Per block of LOOKAHEAD points (the pool is padded by LOOKAHEAD): the home slots
    (block_home_slots), the key checks and the rare probing (settle_slots), then the math,
    its mean and covariance read from the slot's cache line (a miss weighs 0). All but the
    probing are branch-free so that they vectorize. Computing the slots apart, before any
    table read, keeps the reads cheap (~15%); settling every slot before the math keeps the
    probing points in the vectorized math (at half load, 41% less time)."""
    m = rows.map[r]
    quat, t = pose_compose(rows.q[r], rows.t[r], poses.q_cand[g], poses.t_cand[g])
    R = quat_to_mat(quat)
    B = ti.Matrix.zero(ti.f32, 6, 6)
    if ti.static(not plane_cov):
        B = rotated_cov_basis(R)
    inv_res = 1.0 / maps.res[m]
    # blocks of H_c = [[Σ hat(q)ᵀ M hat(q), −(Σ M hat(q))ᵀ], [−Σ M hat(q), Σ M]] and
    # b_c = [Σ hat(q)ᵀ M e, −Σ M e]: 21 sums (two symmetric blocks), no products by 0/1
    S_rr = vec6(0.0)
    S_tr = ti.math.mat3(0.0)
    S_tt = vec6(0.0)
    b_r = vec3(0.0)
    b_t = vec3(0.0)
    err = 0.0
    n = 0
    first = rows.start[r] + begin
    for block in range((count + LOOKAHEAD - 1) // LOOKAHEAD):
        slots = ti.Vector.zero(ti.i32, LOOKAHEAD)
        qs = ti.Matrix.zero(ti.f32, 3, LOOKAHEAD)  # R μ_A of each point
        block_home_slots(pool, first + block * LOOKAHEAD, R, t, inv_res, m, buckets, qs, slots)
        found = ti.Vector.zero(ti.i32, LOOKAHEAD)
        settle_slots(maps, qs, t, inv_res, count - block * LOOKAHEAD, m, buckets, max_probes,
                     slots, found)
        for j in range(LOOKAHEAD):
            k = first + block * LOOKAHEAD + j
            s = slots[j]
            q = vec3(qs[0, j], qs[1, j], qs[2, j])
            hit = found[j]
            rn = vec3(0.0)
            if ti.static(plane_cov):
                rn = R @ vec3(pool.cov_rows[k][0], pool.cov_rows[k][1], pool.cov_rows[k][2])
                hit &= faces_map(q + t, rn, pool.points[k], pool.cov_rows[k], facing_cos)
            rr, tr, tt, br, bt, ee = point_terms(B, q, t, maps.vox[s].mean, maps.vox[s].cov,
                                                 pool.cov_rows[k], rn, hit, plane_cov)
            S_rr += rr
            S_tr += tr
            S_tt += tt
            b_r += br
            b_t += bt
            err += ti.min(ee, cost_cap)
            n += ti.select(hit, 1, 0)
    if n > 0:
        H_r, b_r6 = to_right_perturbation(R, S_rr, S_tr, S_tt, b_r, b_t)
        tasks.H[slot] = H_r
        tasks.b[slot] = b_r6
        tasks.e[slot] = err
        tasks.n[slot] = n


@ti.func
def block_home_slots(pool: ti.template(), first: ti.i32, R: ti.math.mat3, t: vec3,
                     inv_res: ti.f32, m: ti.i32, buckets: ti.i32, qs: ti.template(),
                     slots: ti.template()):
    """q = R μ_A of the block's points from `first` into the columns of `qs`, the home slot
    of q + t's voxel in map m into `slots`: arithmetic only, no table read."""
    for j in range(LOOKAHEAD):
        q = R @ pool.points[first + j]
        for a in ti.static(range(3)):
            qs[a, j] = q[a]
        slots[j] = probe_slot(ti.cast(ti.floor((q + t) * inv_res), ti.i32), 0, m, buckets)


@ti.func
def settle_slots(maps: ti.template(), qs: ti.template(), t: vec3, inv_res: ti.f32,
                 left: ti.i32, m: ti.i32, buckets: ti.i32, max_probes: ti.i32,
                 slots: ti.template(), found: ti.template()):
    """found[j] = 1 where point j's voxel sits in slots[j], 0 for a miss or padding (j >=
    `left`, the points left in the row). The key check against each home slot is branch-free
    (2: another key is there); only those 2s probe on for their slot."""
    num_probe_on = 0
    for j in range(LOOKAHEAD):
        q = vec3(qs[0, j], qs[1, j], qs[2, j])
        key = maps.vox[slots[j]].key
        f = same_key(key, pack_key(ti.cast(ti.floor((q + t) * inv_res), ti.i32)))
        on = (j < left) & (key[1] != EMPTY_KEY)
        found[j] = ti.select(on & f, 1, ti.select(on, 2, 0))
        num_probe_on += ti.select(on & ~f, 1, 0)
    if num_probe_on > 0:
        for j in range(LOOKAHEAD):
            if found[j] == 2:
                q = vec3(qs[0, j], qs[1, j], qs[2, j])
                s = lookup_from(maps.vox, ti.cast(ti.floor((q + t) * inv_res), ti.i32), 1, m,
                                buckets, max_probes)
                found[j] = ti.select(s >= 0, 1, 0)
                slots[j] = ti.select(s >= 0, s, slots[j])


@ti.func
def reduce_tasks(num_rows: ti.i32, num_chunks: ti.i32, rows: ti.template(),
                 poses: ti.template(), tasks: ti.template(), one_row_per_group: ti.template()):
    """Add each running group's task sums into poses.acc in row, then chunk order (see
    linearize): in parallel over rows when every group has one row (summed in registers,
    stored once: with `acc[g] +=` in the chunk loop, Vulkan on lavapipe kept only some
    chunks), else in one ordered pass."""
    acc = poses.acc
    if ti.static(one_row_per_group):
        for r in range(num_rows):
            g = rows.group[r]
            if poses.status[g] == RUNNING:
                H = acc.H[g]
                b = acc.b[g]
                e = acc.e[g]
                n = acc.n[g]
                for c in range(num_chunks):
                    k = r * num_chunks + c
                    H += tasks.H[k]
                    b += tasks.b[k]
                    e += tasks.e[k]
                    n += tasks.n[k]
                acc.H[g] = H
                acc.b[g] = b
                acc.e[g] = e
                acc.n[g] = n
    else:
        ti.loop_config(serialize=True)
        for k in range(num_rows * num_chunks):
            g = rows.group[k // num_chunks]
            if poses.status[g] == RUNNING:
                acc.H[g] += tasks.H[k]
                acc.b[g] += tasks.b[k]
                acc.e[g] += tasks.e[k]
                acc.n[g] += tasks.n[k]


@ti.func
def chol_solve6(A, g):
    """x with A x = g for a symmetric positive definite 6x6 A (fully unrolled Cholesky)."""
    L = ti.Matrix.zero(ti.f32, 6, 6)
    for j in ti.static(range(6)):
        s = A[j, j]
        for k in ti.static(range(j)):
            s -= L[j, k] * L[j, k]
        d = ti.sqrt(ti.max(s, 1e-12))
        L[j, j] = d
        for i in ti.static(range(j + 1, 6)):
            s2 = A[i, j]
            for k in ti.static(range(j)):
                s2 -= L[i, k] * L[j, k]
            L[i, j] = s2 / d
    y = ti.Vector.zero(ti.f32, 6)
    for i in ti.static(range(6)):
        s = g[i]
        for k in ti.static(range(i)):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = ti.Vector.zero(ti.f32, 6)
    for ii in ti.static(range(6)):
        i = ti.static(5 - ii)
        s = y[i]
        for k in ti.static(range(i + 1, 6)):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return x


@ti.func
def damped_step(H, b, lam: ti.f32):
    """δ = −(H + λ diag(H))⁻¹ b, solved on the Jacobi-scaled system so f32 copes with the
    rotation/translation scale gap (Marquardt's diagonal damping)."""
    d = ti.Vector.zero(ti.f32, 6)
    for i in ti.static(range(6)):
        d[i] = 1.0 / ti.sqrt(ti.max(H[i, i], 1e-20))
    A = ti.Matrix.zero(ti.f32, 6, 6)
    g = ti.Vector.zero(ti.f32, 6)
    for i in ti.static(range(6)):
        g[i] = -d[i] * b[i]
        for j in ti.static(range(6)):
            A[i, j] = d[i] * H[i, j] * d[j]
        A[i, i] += lam
    y = chol_solve6(A, g)
    return d * y


@ti.func
def step(num_groups: ti.i32, use_lm: ti.i32, rot_eps: ti.f32, trans_eps: ti.f32,
         poses: ti.template(), serial: ti.template()) -> ti.i32:
    """Accept or reject each running group's candidate, then propose the next one.

    The first linearization (iters == 0) is always accepted; Gauss-Newton accepts every
    candidate; LM accepts one whose error does not grow (λ /= 10), else retries with λ *= 10
    (until λ exceeds LM_MAX_LAMBDA: stalled).
    Returns the number of groups still running. `serial` (few groups) stays on the calling
    thread: waking the thread pool costs more than the work, much more on a busy machine."""
    running = 0
    acc = poses.acc
    best = poses.best
    lam = ti.static(poses.lam)
    status = ti.static(poses.status)
    ti.loop_config(serialize=serial)
    for g in range(num_groups):
        if status[g] == RUNNING:
            n = acc.n[g]
            accept = n > 0 and (poses.iters[g] == 0 or use_lm == 0 or acc.e[g] <= best.e[g])
            if accept:
                poses.q_cur[g] = poses.q_cand[g]
                poses.t_cur[g] = poses.t_cand[g]
                best.H[g] = acc.H[g]
                best.b[g] = acc.b[g]
                best.e[g] = acc.e[g]
                best.n[g] = n
                if use_lm:
                    lam[g] = ti.max(lam[g] * 0.1, LM_MIN_LAMBDA)
            elif use_lm:
                lam[g] = lam[g] * 10.0
            poses.iters[g] += 1
            if best.n[g] == 0 or (not accept and use_lm == 0):
                status[g] = NO_CORRESPONDENCES
            elif use_lm and lam[g] > LM_MAX_LAMBDA:
                status[g] = STALLED
            else:
                damping = GN_DAMPING
                if use_lm:
                    damping = lam[g]
                delta = damped_step(best.H[g], best.b[g], damping)
                w = vec3(delta[0], delta[1], delta[2])
                v = vec3(delta[3], delta[4], delta[5])
                # after a rejection the step is small because λ grew, not because the pose
                # is there: LM converges only on a step proposed from an accepted pose
                if w.norm() < rot_eps and v.norm() < trans_eps and accept:
                    status[g] = CONVERGED
                else:
                    poses.q_cand[g], poses.t_cand[g] = pose_retract(poses.q_cur[g],
                                                                    poses.t_cur[g], w, v)
                    running += 1
            acc.H[g] = ti.Matrix.zero(ti.f32, 6, 6)
            acc.b[g] = ti.Vector.zero(ti.f32, 6)
            acc.e[g] = 0.0
            acc.n[g] = 0
    return running


@ti.kernel
def iterate(pool: ti.template(), rows: ti.template(), num_rows: ti.i32, chunk: ti.i32,
            num_chunks: ti.i32, maps: ti.template(), buckets: ti.i32, max_probes: ti.i32,
            tasks: ti.template(), poses: ti.template(), num_groups: ti.i32, use_lm: ti.i32,
            rot_eps: ti.f32, trans_eps: ti.f32, facing_cos: ti.f32, cost_cap: ti.f32,
            exclusive: ti.template(), plane_cov: ti.template(),
            one_row_per_group: ti.template(), serial: ti.template()) -> ti.i32:
    """One Gauss-Newton/LM iteration of every running group in one launch: `linearize`
    (into the `tasks` sums, which are poses.acc when `exclusive`), `reduce_tasks` (unless
    `exclusive`), then `step`; returns how many groups run on. One launch instead of three
    matters for small problems (a scan of odometry), where launching costs more than the math.
    `serial` (a small problem, see linearize) runs all three on the calling thread."""
    linearize(pool, rows, num_rows, chunk, num_chunks, poses, maps, buckets, max_probes, tasks,
              exclusive, plane_cov, serial, facing_cos, cost_cap)
    if ti.static(not exclusive):
        reduce_tasks(num_rows, num_chunks, rows, poses, tasks, one_row_per_group)
    return step(num_groups, use_lm, rot_eps, trans_eps, poses, serial)


@ti.func
def reset(num_groups: ti.i32, lm_lambda: ti.f32, poses: ti.template(), serial: ti.template()):
    """Start every group at its uploaded candidate pose (the first step accepts it, and
    divides λ by 10, hence the factor). `serial` as in `step`."""
    ti.loop_config(serialize=serial)
    for g in range(num_groups):
        poses.q_cur[g] = poses.q_cand[g]
        poses.t_cur[g] = poses.t_cand[g]
        poses.lam[g] = lm_lambda * 10.0
        poses.status[g] = RUNNING
        poses.iters[g] = 0
        poses.acc.H[g] = ti.Matrix.zero(ti.f32, 6, 6)
        poses.acc.b[g] = ti.Vector.zero(ti.f32, 6)
        poses.acc.e[g] = 0.0
        poses.acc.n[g] = 0
        poses.best.n[g] = 0


@ti.kernel
def reset_groups(num_groups: ti.i32, lm_lambda: ti.f32, poses: ti.template(),
                 serial: ti.template()):
    reset(num_groups, lm_lambda, poses, serial)


@ti.kernel
def upload_source(src: ti.types.ndarray(), n: ti.i32, pool: ti.template(),
                  serial: ti.template()):
    """Rows (x, y, z, c0..c5) into the source pool: one launch instead of two, on the calling
    thread on cpu (`serial`: a copy gains nothing from waking the pool, and loses much on a
    busy machine), in parallel on a GPU."""
    ti.loop_config(serialize=serial)
    for i in range(n):
        pool.points[i] = vec3(src[i, 0], src[i, 1], src[i, 2])
        for a in ti.static(range(6)):
            pool.cov_rows[i][a] = src[i, 3 + a]


@ti.func
def pose_from_row(a: ti.types.ndarray(), i: ti.i32):
    """(q, t) of the pose in row i of `a` = (R row-major, t): Shepperd's method on the larger
    of trace and diagonal, w >= 0 (the host then needs no quaternion conversion)."""
    R = ti.math.mat3(a[i, 0], a[i, 1], a[i, 2], a[i, 3], a[i, 4], a[i, 5], a[i, 6], a[i, 7],
                     a[i, 8])
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = ti.math.vec4(0.0)
    if tr >= R[0, 0] and tr >= R[1, 1] and tr >= R[2, 2]:
        r = 2.0 * ti.sqrt(ti.max(1.0 + tr, 1e-12))
        q = ti.math.vec4((R[2, 1] - R[1, 2]) / r, (R[0, 2] - R[2, 0]) / r,
                         (R[1, 0] - R[0, 1]) / r, 0.25 * r)
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        r = 2.0 * ti.sqrt(ti.max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 1e-12))
        q = ti.math.vec4(0.25 * r, (R[0, 1] + R[1, 0]) / r, (R[0, 2] + R[2, 0]) / r,
                         (R[2, 1] - R[1, 2]) / r)
    elif R[1, 1] >= R[2, 2]:
        r = 2.0 * ti.sqrt(ti.max(1.0 + R[1, 1] - R[0, 0] - R[2, 2], 1e-12))
        q = ti.math.vec4((R[0, 1] + R[1, 0]) / r, 0.25 * r, (R[1, 2] + R[2, 1]) / r,
                         (R[0, 2] - R[2, 0]) / r)
    else:
        r = 2.0 * ti.sqrt(ti.max(1.0 + R[2, 2] - R[0, 0] - R[1, 1], 1e-12))
        q = ti.math.vec4((R[0, 2] + R[2, 0]) / r, (R[1, 2] + R[2, 1]) / r, 0.25 * r,
                         (R[1, 0] - R[0, 1]) / r)
    if q[3] < 0.0:
        q = -q
    return q.normalized(), vec3(a[i, 9], a[i, 10], a[i, 11])


@ti.kernel
def upload_problem(rows_i: ti.types.ndarray(), rows_f: ti.types.ndarray(), num_rows: ti.i32,
                   initial: ti.types.ndarray(), num_groups: ti.i32, lm_lambda: ti.f32,
                   rows: ti.template(), poses: ti.template(), serial: ti.template()):
    """Rows (group, map, start, count | R, t of the left pose) and the initial poses (R, t),
    then `reset_groups`: one launch instead of nine, which matters per scan (odometry) on a
    busy machine. Serial for few groups (`serial` as in `step`)."""
    ti.loop_config(serialize=serial)
    for r in range(num_rows):
        rows.group[r] = rows_i[r, 0]
        rows.map[r] = rows_i[r, 1]
        rows.start[r] = rows_i[r, 2]
        rows.count[r] = rows_i[r, 3]
        rows.q[r], rows.t[r] = pose_from_row(rows_f, r)
    ti.loop_config(serialize=serial)
    for g in range(num_groups):
        poses.q_cand[g], poses.t_cand[g] = pose_from_row(initial, g)
    reset(num_groups, lm_lambda, poses, serial)


RESULT_COLUMNS = 54  # q (4), t (3), H (36), b (6), error, inliers, iterations, status, hits


@ti.kernel
def download_results(num_groups: ti.i32, poses: ti.template(), pool: ti.template(),
                     num_points: ti.i32, queries: ti.types.ndarray(), num_queries: ti.i32,
                     maps: ti.template(), buckets: ti.i32, max_probes: ti.i32,
                     out: ti.types.ndarray(), serial: ti.template(), overlap: ti.template()):
    """Every group's result as one f32 row (counts stay exact below 2^24), with its overlap
    count: how many of the first `num_points` source points land in an occupied voxel of at
    least one listed map, at the group's pose placed in map k by queries[k] = (map id, R
    row-major, t of the left pose) (list the likeliest map first: a hit ends the search).
    One launch instead of eight field reads and a separate overlap query; `serial` as in
    `step`; without `overlap` the count is 0."""
    best = poses.best
    ti.loop_config(serialize=serial)
    for g in range(num_groups):
        for a in ti.static(range(4)):
            out[g, a] = poses.q_cur[g][a]
        for a in ti.static(range(3)):
            out[g, 4 + a] = poses.t_cur[g][a]
        for a in ti.static(range(6)):
            out[g, 43 + a] = best.b[g][a]
            for b in ti.static(range(6)):
                out[g, 7 + 6 * a + b] = best.H[g][a, b]
        out[g, 49] = best.e[g]
        out[g, 50] = ti.cast(best.n[g], ti.f32)
        out[g, 51] = ti.cast(poses.iters[g], ti.f32)
        out[g, 52] = ti.cast(poses.status[g], ti.f32)
        out[g, 53] = 0.0
    if ti.static(overlap):
        # over (group, point) pairs, so that one pose's count spreads over GPU threads too
        # (lavapipe lost lookups once one thread had made a few thousand)
        ti.loop_config(serialize=serial)
        for g, i in ti.ndrange(num_groups, num_points):
            x_g = quat_to_mat(poses.q_cur[g]) @ pool.points[i] + poses.t_cur[g]
            hit = 0
            k = 0
            while k < num_queries and hit == 0:  # the likeliest map first: a hit ends it
                m = ti.cast(queries[k, 0], ti.i32)
                x = vec3(queries[k, 10], queries[k, 11], queries[k, 12])
                for a in ti.static(range(3)):
                    for b in ti.static(range(3)):
                        x[a] += queries[k, 1 + 3 * a + b] * x_g[b]
                if lookup(maps.vox, ti.cast(ti.floor(x / maps.res[m]), ti.i32), m, buckets,
                          max_probes) >= 0:
                    hit = 1
                k += 1
            out[g, 53] += ti.cast(hit, ti.f32)  # exact: counts stay below 2^24
