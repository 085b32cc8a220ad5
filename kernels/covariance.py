"""Plane-regularized point covariances from precomputed neighbour indices (host kNN search).

For each point: the scatter of its neighbours, its smallest eigenvector n (the local surface
normal), and C = I - (1 - 1e-3) n nᵀ, i.e. eigenvalues (1e-3, 1, 1) along (n, surface);
the identity when fewer than `min_neighbors` neighbours were found or when they lie along a
scan line (`is_scan_line`).
"""

import taichi as ti

JACOBI_SWEEPS = 4  # cyclic Jacobi on 3x3 converges quadratically: 4 sweeps reach f32 precision
SEPARATION = 1e-2  # closed form when (λmid - λmin)(λmax - λmin) > this (trace 1), else Jacobi
# middle / largest eigenvalue of the neighbours' scatter below this: a line (std ratio 0.22)
LINE_RATIO = 0.05
# a line within 30° of the cloud frame's xy plane (sin² 30°) is a scan line: a spinning
# lidar's rings are cones of at most ±22.5° (OS1-64), so their arcs lie within it
SCAN_LINE_SIN2_SLOPE = 0.25


@ti.func
def smallest_eigenvector(S: ti.math.mat3) -> ti.math.vec3:
    """Unit eigenvector of the smallest eigenvalue of a symmetric positive semi-definite 3x3
    matrix (a scatter): the eigenvalue in closed form, the vector as the longest cross product
    of two rows of S - λI (both orthogonal to it); ~2x cheaper than Jacobi. Where the
    smallest eigenvalue stands apart (surfaces, most points) this is as precise as Jacobi in
    f32; closer to the middle one the formula loses λ to rounding (acos near 1), so there
    (edges, blobs, exactly collinear points: `SEPARATION`) Jacobi decides, as before."""
    A = S / ti.max(S.trace(), 1e-30)
    p1 = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
    q = A.trace() / 3.0
    B = A - q * ti.math.eye(3)
    p = ti.sqrt((B[0, 0] * B[0, 0] + B[1, 1] * B[1, 1] + B[2, 2] * B[2, 2] + 2.0 * p1) / 6.0)
    r = ti.math.clamp(B.determinant() / (2.0 * ti.max(p * p * p, 1e-30)), -1.0, 1.0)
    lam = q + 2.0 * p * ti.cos(ti.acos(r) / 3.0 + 2.0 * ti.math.pi / 3.0)
    M = A - lam * ti.math.eye(3)
    r0 = ti.math.vec3(M[0, 0], M[0, 1], M[0, 2])
    r1 = ti.math.vec3(M[1, 0], M[1, 1], M[1, 2])
    r2 = ti.math.vec3(M[2, 0], M[2, 1], M[2, 2])
    c = r0.cross(r1)
    c02 = r0.cross(r2)
    c12 = r1.cross(r2)
    if c02.norm_sqr() > c.norm_sqr():
        c = c02
    if c12.norm_sqr() > c.norm_sqr():
        c = c12
    n = c / ti.sqrt(ti.max(c.norm_sqr(), 1e-38))
    if c.norm_sqr() < SEPARATION * SEPARATION:  # |c| ~ (λmid - λ)(λmax - λ), trace 1
        n = jacobi_smallest_eigenvector(A)
    return n


@ti.func
def is_scan_line(S: ti.math.mat3, n: ti.math.vec3) -> bool:
    """Whether a scatter S (smallest eigenvector n) is a sparse lidar's scan line: spread along
    one direction only (λmid < LINE_RATIO λmax) and that direction near the sensor's
    horizontal plane, e.g. one ring's arc on the ground. Across such a line the points are
    range noise, so the normal is noise too, and a disc across the wrong normal pulls
    registration along the surface as the rings move from scan to scan: these points take
    the identity. Steep lines keep their disc: a trunk or a pole seen by several rings is an
    arc facing the sensor, whose normal holds. λmid and λmax come from the trace and the sum
    of principal 2x2 minors given λmin = nᵀSn; the line's slope from S_zz ≈ λmax u_z²."""
    lam_min = n.dot(S @ n)
    rest = S.trace() - lam_min  # λmid + λmax
    minors = (S[0, 0] * S[1, 1] - S[0, 1] * S[0, 1] + S[0, 0] * S[2, 2] - S[0, 2] * S[0, 2]
              + S[1, 1] * S[2, 2] - S[1, 2] * S[1, 2])
    product = ti.max(minors - lam_min * rest, 0.0)  # λmid λmax
    gap = ti.sqrt(ti.max(rest * rest - 4.0 * product, 0.0))  # λmax - λmid
    lam_mid, lam_max = 0.5 * (rest - gap), 0.5 * (rest + gap)
    return lam_mid < LINE_RATIO * lam_max and S[2, 2] < SCAN_LINE_SIN2_SLOPE * lam_max


@ti.func
def jacobi_smallest_eigenvector(S: ti.math.mat3) -> ti.math.vec3:
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix by cyclic Jacobi
    rotations: robust where closed forms (and ti.sym_eig) fail, e.g. when the two smallest
    eigenvalues coincide."""
    A = S / ti.max(S.trace(), 1e-30)
    V = ti.math.eye(3)
    for _ in ti.static(range(JACOBI_SWEEPS)):
        for p, q, r in ti.static(((0, 1, 2), (0, 2, 1), (1, 2, 0))):
            apq = A[p, q]
            if ti.abs(apq) > 1e-10:
                theta = (A[q, q] - A[p, p]) / (2.0 * apq)
                t = 1.0 / (ti.abs(theta) + ti.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / ti.sqrt(t * t + 1.0)
                s = t * c
                # A <- Pᵀ A P, V <- V P for the rotation P in the (p, q) plane (P[p, q] = s,
                # P[q, p] = -s), touching only the entries it changes
                arp, arq = A[r, p], A[r, q]
                A[p, p] -= t * apq
                A[q, q] += t * apq
                A[p, q] = 0.0
                A[q, p] = 0.0
                A[r, p] = c * arp - s * arq
                A[p, r] = A[r, p]
                A[r, q] = s * arp + c * arq
                A[q, r] = A[r, q]
                for i in ti.static(range(3)):
                    vp, vq = V[i, p], V[i, q]
                    V[i, p] = c * vp - s * vq
                    V[i, q] = s * vp + c * vq
    smallest = 0
    for a in ti.static(range(1, 3)):
        if A[a, a] < A[smallest, smallest]:
            smallest = a
    return ti.math.vec3(V[0, smallest], V[1, smallest], V[2, smallest]).normalized()


@ti.kernel
def plane_covariances(points: ti.types.ndarray(), neighbors: ti.types.ndarray(),
                      counts: ti.types.ndarray(), n: ti.i32, min_neighbors: ti.i32,
                      normal_variance: ti.f32, out: ti.types.ndarray()):
    for i in range(n):
        C = ti.math.eye(3)
        m = counts[i]
        if m >= min_neighbors:
            mean = ti.math.vec3(0.0)
            for j in range(m):
                nb = neighbors[i, j]
                mean += ti.math.vec3(points[nb, 0], points[nb, 1], points[nb, 2])
            mean /= ti.cast(m, ti.f32)
            S = ti.math.mat3(0.0)
            for j in range(m):
                nb = neighbors[i, j]
                d = ti.math.vec3(points[nb, 0], points[nb, 1], points[nb, 2]) - mean
                S += d.outer_product(d)
            S /= ti.cast(m, ti.f32)
            normal = smallest_eigenvector(S)
            if not is_scan_line(S, normal):
                C = ti.math.eye(3) - (1.0 - normal_variance) * normal.outer_product(normal)
        for a in ti.static(range(3)):
            for b in ti.static(range(3)):
                out[i, a, b] = C[a, b]
