"""Surface normals of a spinning lidar's scan from its range image, on the device.

A scan whose points carry their ring (laser) is a range image: row = ring, column = the
point's azimuth binned into `width` columns over a full turn (so an Ouster's staggered
beams line up too). Each pixel keeps the smallest point index that falls in it (atomic
min: the same image whatever the thread order). A point's normal is the smallest
eigenvector of the scatter of the pixels around its own, in the `row_reach` rows above and
below and its own, at `n_cols` columns `col_step` apart centred on it (about as far along
the ring as the rows reach), keeping only neighbours within `gate` of the point (no
smoothing over depth edges). A surface seen at a grazing angle (a ceiling far ahead) puts
the next rows beyond that gate, leaving one ring's arc, across which any direction is a
normal: then the window is read again with a WIDE_GATE times wider gate; if it is still a
line, the normal is the direction across it nearest the vertical (a level arc: the ground
or a ceiling far off) or nearest the ray (a steep one: a pole). It needs MIN_NEIGHBORS points
(the point included) and faces the sensor (the origin of the scan's frame). Points without
a normal get zeros: the fusion kernels then use the ray direction (projective distance).

The scan's own order of points is not needed (clouds with dropped returns, any layout).

Near the sensor neighbouring pixels lie far closer than a map voxel, and their windows
differ by one column: in each three columns a point beside the middle one takes the normal
of the middle column's point when that lies within `share_m` (`share_columns` before
`estimate`, which then skips it, and `copy_shared` after), a third of the work where rays
are denser than the map can use.
"""

import taichi as ti

from mcl3d.kernels.covariance import smallest_eigenvector

vec3 = ti.math.vec3
mat3 = ti.math.mat3

EMPTY = 2**31 - 1  # a pixel no point fell in
MIN_NEIGHBORS = 5  # neighbours (the point included) a normal needs
LINE_RATIO = 0.05  # middle / largest eigenvalue below this: a line, no normal
MAX_COLS = 7  # column samples per row (odd)
STEEP_LINE = 0.7  # a line with |t_z| above this is steep (see across_line)
WIDE_GATE = 4.0  # fewer than MIN_NEIGHBORS within the gate, or only one ring's arc (a
# surface seen at a grazing angle spreads the rows far apart): again with this wider gate


@ti.kernel
def clear_image(image: ti.types.ndarray(dtype=ti.i32, ndim=1), size: ti.i32):
    for k in range(size):
        image[k] = EMPTY


@ti.func
def column_of(p: vec3, width: ti.i32) -> ti.i32:
    """Azimuth bin of p in [0, width): bin 0 starts at -pi."""
    a = ti.atan2(p[1], p[0]) * (0.5 / ti.math.pi) + 0.5
    c = ti.cast(ti.floor(a * width), ti.i32)
    return ti.min(ti.max(c, 0), width - 1)


@ti.kernel
def project(pts: ti.types.ndarray(dtype=vec3, ndim=1),
            rows: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32, width: ti.i32,
            height: ti.i32, pixel: ti.types.ndarray(dtype=ti.i32, ndim=1),
            image: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """Each point's pixel (-1 outside the image: a ring past `height`, a point at the origin)
    and, per pixel, the smallest index of the points in it (image cleared to EMPTY before)."""
    for i in range(n):
        p = pts[i]
        r = rows[i]
        px = -1
        if 0 <= r < height and p.norm_sqr() > 0.0:
            px = r * width + column_of(p, width)
            ti.atomic_min(image[px], i)
        pixel[i] = px


@ti.kernel
def share_columns(pts: ti.types.ndarray(dtype=vec3, ndim=1),
                  pixel: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32, width: ti.i32,
                  image: ti.types.ndarray(dtype=ti.i32, ndim=1), share_m: ti.f32,
                  source: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """source[i]: the point whose normal point i takes (in the middle column of its three,
    columns 3k..3k+2, within share_m), else -1; such points get pixel -1, so `estimate`
    skips them."""
    for i in range(n):
        src = -1
        px = pixel[i]
        row = px // width
        col = px - row * width
        mid = (col // 3) * 3 + 1
        if px >= 0 and col != mid and mid < width:
            j = image[row * width + mid]
            if j != EMPTY:  # noqa: SIM102 (Taichi's `and` does not short-circuit)
                if (pts[j] - pts[i]).norm_sqr() <= share_m * share_m:
                    src = j
                    pixel[i] = -1
        source[i] = src


@ti.kernel
def copy_shared(pts: ti.types.ndarray(dtype=vec3, ndim=1),
                source: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32,
                normals: ti.types.ndarray(dtype=vec3, ndim=1)):
    """The normals `share_columns` assigned, facing the sensor from each point (zeros
    stay)."""
    for i in range(n):
        j = source[i]
        if j >= 0:
            e = normals[j]
            if e.dot(pts[i]) > 0.0:
                e = -e
            normals[i] = e


@ti.func
def line_only(S: mat3, n: vec3) -> bool:
    """λmid < LINE_RATIO λmax for a scatter S with smallest eigenvector n (λmid, λmax from
    the trace and the sum of principal 2x2 minors, as kernels.covariance.is_scan_line)."""
    lam_min = n.dot(S @ n)
    rest = S.trace() - lam_min
    minors = (S[0, 0] * S[1, 1] - S[0, 1] * S[0, 1] + S[0, 0] * S[2, 2] - S[0, 2] * S[0, 2]
              + S[1, 1] * S[2, 2] - S[1, 2] * S[1, 2])
    product = ti.max(minors - lam_min * rest, 0.0)
    gap = ti.sqrt(ti.max(rest * rest - 4.0 * product, 0.0))
    return 0.5 * (rest - gap) < LINE_RATIO * 0.5 * (rest + gap)


@ti.func
def across_line(S: mat3, p: vec3) -> vec3:
    """For neighbours along a line only, some direction across the line (its direction t by
    two power steps from S's longest column). A lone ring arc that runs level (|t_z| <
    STEEP_LINE) lies on a surface seen at a grazing angle from above or below, the ground or
    a ceiling: the direction across it nearest the vertical (the scan's z axis); a steep
    line (a pole, an edge seen by several rings) faces the sensor: the one nearest the ray.
    The ray itself where the two are parallel."""
    v = vec3(S[0, 0], S[1, 0], S[2, 0])
    if S[1, 1] > S[0, 0] and S[1, 1] >= S[2, 2]:
        v = vec3(S[0, 1], S[1, 1], S[2, 1])
    elif S[2, 2] > S[0, 0]:
        v = vec3(S[0, 2], S[1, 2], S[2, 2])
    t = (S @ (S @ v)).normalized()
    u = p.normalized()
    w = u
    if ti.abs(t[2]) < STEEP_LINE:
        w = vec3(0.0, 0.0, 1.0)
    a = w - w.dot(t) * t
    e = u
    if a.norm_sqr() > 1e-6:
        e = a.normalized()
    return e


@ti.func
def window_sums(pts: ti.template(), image: ti.template(), p: vec3, row: ti.i32, col: ti.i32,
                width: ti.i32, height: ti.i32, row_reach: ti.i32, n_cols: ti.i32,
                col_step: ti.i32, gate: ti.f32):
    """Count, sum, squares and cross products of the offsets from p of the window's points
    within `gate` of it."""
    half = (n_cols // 2) * col_step
    s = vec3(0.0)
    sq = vec3(0.0)  # sums of dx², dy², dz²
    sc = vec3(0.0)  # sums of dx dy, dx dz, dy dz
    count = 0
    for dr in range(-row_reach, row_reach + 1):
        rr = row + dr
        if 0 <= rr < height:
            base = rr * width
            for k in range(n_cols):
                cc = col + k * col_step - half  # wrapped around the turn
                if cc < 0:
                    cc += width
                elif cc >= width:
                    cc -= width
                j = image[base + cc]
                if j != EMPTY:
                    d = pts[j] - p  # offsets from p: f32 keeps its bits far out
                    if d.norm_sqr() <= gate * gate:
                        s += d
                        sq += d * d
                        sc += vec3(d[0] * d[1], d[0] * d[2], d[1] * d[2])
                        count += 1
    return count, s, sq, sc


@ti.func
def scatter_normal(count: ti.i32, s: vec3, sq: vec3, sc: vec3):
    """The scatter of the offsets summed by window_sums and its smallest eigenvector."""
    k = 1.0 / ti.max(count, 1)
    mean = s * k
    q = sq * k
    c = sc * k
    S = mat3([[q[0], c[0], c[1]], [c[0], q[1], c[2]], [c[1], c[2], q[2]]]) \
        - mean.outer_product(mean)
    return S, smallest_eigenvector(S)


@ti.kernel
def estimate(pts: ti.types.ndarray(dtype=vec3, ndim=1),
             pixel: ti.types.ndarray(dtype=ti.i32, ndim=1), n: ti.i32, width: ti.i32,
             height: ti.i32, image: ti.types.ndarray(dtype=ti.i32, ndim=1), row_reach: ti.i32,
             n_cols: ti.i32, col_step: ti.i32, gate_per_m: ti.f32, gate_min_m: ti.f32,
             normals: ti.types.ndarray(dtype=vec3, ndim=1)):
    """Normal of each point from its range-image neighbours (module docstring); the gate is
    gate_min_m + gate_per_m * range, WIDE_GATE times that where too few are within it."""
    for i in range(n):
        nrm = vec3(0.0)
        px = pixel[i]
        if px >= 0:
            p = pts[i]
            gate = gate_min_m + gate_per_m * p.norm()
            row = px // width
            col = px - row * width
            count, s, sq, sc = window_sums(pts, image, p, row, col, width, height, row_reach,
                                           n_cols, col_step, gate)
            S, e = scatter_normal(count, s, sq, sc)
            if count < MIN_NEIGHBORS or line_only(S, e):
                count, s, sq, sc = window_sums(pts, image, p, row, col, width, height,
                                               row_reach, n_cols, col_step, WIDE_GATE * gate)
                S, e = scatter_normal(count, s, sq, sc)
            if count >= MIN_NEIGHBORS:
                if line_only(S, e):
                    e = across_line(S, p)
                if e.dot(p) > 0.0:
                    e = -e
                nrm = e
        normals[i] = nrm
