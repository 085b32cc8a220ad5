"""Surface normals of an unorganized scan (a Livox's rosette, a KITTI .bin: no range image),
on the device, from each point's k nearest neighbours in a voxel neighbourhood.

The points come sorted by the Morton code of their fine cell (`cells`, `FINE_CELL_M` in the
host's maps/voxel_normals.py, counted from an origin that keeps every level's neighbours
non-negative). A Morton code shifted right by 6 bits is the code of the cell four
times larger that holds it, so the one sorted order also sorts every coarser level, and each
level's cells are runs of it: `keys` (sorted codes) with `starts`/`ends` (their runs), level l
at `offsets[l]`..`offsets[l + 1]`. A point searches the level whose cells hold about as many
points as it needs: the finest where its own cell holds at least `min_own`, so a dense
near-range surface is searched in 5 cm cells and a sparse far one in 80 cm or 3.2 m cells.
There it keeps the k nearest in the 3x3x3 cells around its own (scan_grid.keep_nearest:
ties keep the earlier in sorted order), the point included. The normal is the smallest
eigenvector of their scatter (at least MIN_NEIGHBORS; along a line, the direction across
it as scan_normals.across_line), facing the sensor (the origin of the scan's frame); zeros
with fewer neighbours, which the fusion kernels read as "use the ray" (projective
distance), as for the range-image normals (scan_normals.py).
"""

import taichi as ti

from mcl3d.kernels.covariance import smallest_eigenvector
from mcl3d.kernels.scan_grid import MAX_K, keep_nearest, neighbour_scatter
from mcl3d.kernels.scan_normals import MIN_NEIGHBORS, across_line, line_only

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3

LEVELS = 7  # cells 5 cm, 10 cm, ... 3.2 m
LEVEL_SHIFT = 1  # each level's cells are twice as large along each axis
MORTON_BITS = 21  # per axis: 2^21 fine cells of 5 cm = 105 km


@ti.func
def morton(c: ivec3) -> ti.i64:
    """Bits of x, y, z interleaved (x lowest), MORTON_BITS each; c >= 0."""
    code = ti.i64(0)
    for b in ti.static(range(MORTON_BITS)):
        for a in ti.static(range(3)):
            code |= ti.cast((c[a] >> b) & 1, ti.i64) << (3 * b + a)
    return code


X_BITS = sum(1 << (3 * b) for b in range(MORTON_BITS))  # the x bits of a Morton code


@ti.func
def axis_parts(code: ti.i64) -> ti.template():
    """parts[a, j]: axis a's bits of the Morton code of the cell j - 1 cells away from
    `code`'s along a (dilated-integer arithmetic: no de- and re-interleaving); a neighbour's
    code is the OR of one part per axis."""
    parts = ti.Matrix.zero(ti.i64, 3, 3)
    for a in ti.static(range(3)):
        mask = ti.i64(X_BITS << a)
        own = code & mask
        parts[a, 0] = (own - ti.i64(1 << a)) & mask
        parts[a, 1] = own
        parts[a, 2] = ((own | ~mask) + ti.i64(1 << a)) & mask
    return parts


@ti.func
def find_cell(keys: ti.template(), lo: ti.i32, hi: ti.i32, key: ti.i64) -> ti.i32:
    """Index of `key` in the sorted keys[lo:hi], or -1 (a branch-free lower bound: the
    comparisons of a cell search are unpredictable)."""
    base = lo
    length = hi - lo
    while length > 1:
        half = length // 2
        base = ti.select(keys[base + half] <= key, base + half, base)
        length -= half
    found = -1
    if length == 1 and keys[base] == key:
        found = base
    return found


@ti.kernel
def estimate(pts: ti.types.ndarray(dtype=vec3, ndim=1),
             cells: ti.types.ndarray(dtype=ivec3, ndim=1), n: ti.i32,
             keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
             starts: ti.types.ndarray(dtype=ti.i32, ndim=1),
             ends: ti.types.ndarray(dtype=ti.i32, ndim=1),
             offsets: ti.types.ndarray(dtype=ti.i32, ndim=1), k: ti.i32, min_own: ti.i32,
             normals: ti.types.ndarray(dtype=vec3, ndim=1)):
    for i in range(n):
        nbr, found, _ = k_nearest(pts, cells, i, keys, starts, ends, offsets, k, min_own)
        normals[i] = plane_normal(pts, nbr, found, pts[i])


@ti.func
def k_nearest(pts: ti.template(), cells: ti.template(), i: ti.i32, keys: ti.template(),
              starts: ti.template(), ends: ti.template(), offsets: ti.template(), k: ti.i32,
              min_own: ti.i32):
    """(neighbours, how many, the farthest one's squared distance) of point i: its k
    nearest in the 3x3x3 cells around its own at the level described above."""
    p = pts[i]
    code = morton(cells[i])
    level = LEVELS - 1
    for lv in ti.static(range(LEVELS - 1)):
        if level == LEVELS - 1:  # its own cell at level lv (a code shifted: that cell's)
            c = find_cell(keys, offsets[lv], offsets[lv + 1], code >> (3 * LEVEL_SHIFT * lv))
            if c >= 0 and ends[c] - starts[c] >= min_own:
                level = lv
    own = code >> (3 * LEVEL_SHIFT * level)
    dist = ti.Vector.zero(ti.f32, MAX_K)
    nbr = ti.Vector.zero(ti.i32, MAX_K)
    found = 0
    far = 0
    far_d2 = -1.0
    parts = axis_parts(own)
    for m in range(27):  # x slowest, z fastest
        near = parts[0, m // 9] | parts[1, (m // 3) % 3] | parts[2, m % 3]
        c = find_cell(keys, offsets[level], offsets[level + 1], near)
        if c >= 0:
            for j in range(starts[c], ends[c]):
                keep_nearest(j, (pts[j] - p).norm_sqr(), k, found, far, far_d2, dist, nbr)
    return nbr, found, far_d2


@ti.func
def plane_normal(pts: ti.template(), nbr: ti.template(), found: ti.i32, p: vec3) -> vec3:
    """The smallest eigenvector of the neighbours' scatter, facing the origin; zeros with
    fewer than MIN_NEIGHBORS. Neighbours along a line (one ring's arc: the k nearest of a
    sparse scan's ground all lie on it, the next ring being metres away) take the direction
    across it that the range-image normals take (scan_normals.across_line: the vertical for
    a level arc, the ray for a steep line); with zeros the ground fused along its grazing
    rays, and bench_km_map's map tracked worse (docs/map-fusion.md)."""
    normal = vec3(0.0)
    if found >= MIN_NEIGHBORS:
        S = neighbour_scatter(pts, nbr, found, p)
        nrm = smallest_eigenvector(S)
        if line_only(S, nrm):
            nrm = across_line(S, p)
        normal = -nrm if nrm.dot(p) > 0.0 else nrm
    return normal
