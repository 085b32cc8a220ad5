"""One scan's voxel grid on the device: downsampling and neighbour search without the host.

The grid is sparse: 4x4x4-voxel bricks found through an open-addressing hash table, each
brick a dense block of 64 cells holding the index of the voxel's output point (valid where
the brick's 64-bit occupancy has the cell's bit set).
Downsampling puts every point in its voxel (one ordered pass, so that the voxel means are
the same bits on every run, numbered in order of first occurrence); the neighbour search
then reads the 5x5x5 voxels around each output point through at most 8 brick lookups, which
is what makes it cheaper than a kd-tree: after downsampling every voxel holds one point, so
the k nearest points within 2 voxels (the usual case on surfaces) are found exactly, and a
sparse point gets the k nearest of that block (fewer than `min_neighbors`: the identity).

One launch per scan: `downsample` (per chunk of raw points: free the previous scan's
bricks, stage, insert, voxel means, and after the last chunk optionally `plane_rows`); few
launches matter because a small scan's math costs less than launching kernels from Python.
Few parallel loops too: on the cpu backend each one costs ~70 us of thread-pool hand-offs
(a 2-core VM, Taichi 1.7.4), so only staging and `plane_rows` run in parallel and the ordered
passes are serialized loops (`ti.loop_config(serialize=True)`: free).

The kernels take the grid as one `ti.template()` (mcl3d.registration.preprocess.ScanGrid:
its fields, and the constants `min_neighbors`, `normal_variance` of `plane_rows`) and write
into a source pool (gicp_state.SourcePool: `points`, and `cov_rows` when `has_cov_rows`).
"""

import taichi as ti

from mcl3d.kernels.covariance import is_scan_line, smallest_eigenvector
from mcl3d.kernels.se3 import pose_retract, quat_to_mat
from mcl3d.kernels.voxel_hash import voxel_hash

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3

BRICK_SHIFT = 2  # bricks of 4x4x4 voxels
BRICK_CELLS = 64
SEARCH = 2  # neighbours are searched within this many voxels (Chebyshev): a 5x5x5 block
MAX_K = 32  # most neighbours per point


@ti.func
def brick_of(key: ivec3) -> ivec3:
    return key >> BRICK_SHIFT  # arithmetic shift: floor division by 4, negatives included


@ti.func
def cell_of(key: ivec3) -> ti.i32:
    local = key & 3
    return (local[0] * 4 + local[1]) * 4 + local[2]


@ti.func
def find_brick(grid: ti.template(), b: ivec3, mask: ti.u32) -> ti.i32:
    """Pool index of brick `b`, or -1 when no point fell in it (the table is never full)."""
    found = -1
    s = voxel_hash(b) & mask
    while grid.slot_brick[ti.cast(s, ti.i32)] >= 0:
        k = grid.slot_key[ti.cast(s, ti.i32)]
        if k[0] == b[0] and k[1] == b[1] and k[2] == b[2]:
            found = grid.slot_brick[ti.cast(s, ti.i32)]
            break
        s = (s + 1) & mask
    return found


@ti.func
def stage_points(points: ti.types.ndarray(), times: ti.types.ndarray(), n: ti.i32,
                 deskew: ti.i32, twist_w: vec3, twist_v: vec3, t_first: ti.f32, t_step: ti.f32,
                 min_range_m: ti.f32, max_range_m: ti.f32, inv_voxel: ti.f32,
                 grid: ti.template()):
    """Range crop (and finite check), deskew p' = exp(t twist) p when `deskew`, voxel key.

    exp(t twist) is evaluated exactly at `grid.knot_R.shape[0]` knots t_first + j t_step spanning
    the point times and interpolated linearly in between (per point that saves the sines and
    square roots, ~2/3 of the cost; over a 0.1 s sweep at 1 rad/s two knots differ by 2 mrad
    and the interpolation error is ~5e-7 rad)."""
    knot_R = ti.static(grid.knot_R)
    knot_t = ti.static(grid.knot_t)
    num_knots = knot_R.shape[0]
    if deskew:
        for j in range(num_knots):
            t = t_first + t_step * j
            q, v = pose_retract(ti.math.vec4(0.0, 0.0, 0.0, 1.0), vec3(0.0), t * twist_w,
                                t * twist_v)
            knot_R[j] = quat_to_mat(q)
            knot_t[j] = v
    for i in range(n):
        p = vec3(points[i, 0], points[i, 1], points[i, 2])
        r = p.norm()
        ok = (r >= min_range_m) & (r <= max_range_m)  # NaN compares false; inf exceeds max
        if deskew:
            x = ti.min(ti.max((times[i] - t_first) / t_step, 0.0), num_knots - 1.0)
            j = ti.min(ti.cast(x, ti.i32), num_knots - 2)
            a = x - j
            p = ((1.0 - a) * knot_R[j] + a * knot_R[j + 1]) @ p \
                + (1.0 - a) * knot_t[j] + a * knot_t[j + 1]
        grid.stage_p[i] = p
        grid.stage_key[i] = ti.cast(ti.floor(p * inv_voxel), ti.i32)
        grid.stage_ok[i] = ti.select(ok, 1, 0)


@ti.func
def insert_points(n: ti.i32, first_chunk: ti.i32, voxel_m: ti.f32, grid: ti.template()):
    """Add the staged points to their voxels in one ordered pass (a new voxel gets the next
    output index; sums are offsets from the voxel centre so f32 stays precise far out).
    counts[None] = (voxels, bricks, overflow): overflow 1 when a voxel or brick did not fit,
    then the scan must take another path. Where consecutive points share a brick (scan order
    of some sensors) they skip the hash lookup."""
    num_voxels = 0
    num_bricks = 0
    overflow = 0
    if not first_chunk:
        num_voxels = grid.counts[None][0]
        num_bricks = grid.counts[None][1]
        overflow = grid.counts[None][2]
    last_b = ivec3(-(1 << 30))
    last_brick = -1
    # in order; a serialized top-level loop, not one inside a `for _ in range(1)` task: that
    # costs a parallel launch, and Vulkan (lavapipe) loses counters such as num_voxels there
    ti.loop_config(serialize=True)
    for i in range(n):
        if grid.stage_ok[i] and overflow == 0:
            key = grid.stage_key[i]
            b = brick_of(key)
            brick = last_brick
            if b[0] != last_b[0] or b[1] != last_b[1] or b[2] != last_b[2]:
                brick = brick_for(grid, b, num_bricks)
                last_b = b
                last_brick = brick
            if brick < 0:
                overflow = 1
            else:
                v = voxel_for(grid, brick, key, num_voxels)
                if v < 0:
                    overflow = 1
                else:
                    centre = (ti.cast(key, ti.f32) + 0.5) * voxel_m
                    grid.voxel_sum[v] += grid.stage_p[i] - centre
                    grid.voxel_count[v] += 1
    grid.counts[None] = ivec3(num_voxels, num_bricks, overflow)


@ti.func
def brick_for(grid: ti.template(), b: ivec3, num_bricks: ti.template()) -> ti.i32:
    """Pool index of brick `b`, added (the next index: `num_bricks` grows) when no point fell
    in it yet; -2 when the pool is full."""
    mask = ti.cast(grid.slot_key.shape[0] - 1, ti.u32)
    s = voxel_hash(b) & mask
    brick = -1
    while brick == -1:
        si = ti.cast(s, ti.i32)
        if grid.slot_brick[si] < 0:
            if num_bricks < grid.brick_slot.shape[0]:
                brick = num_bricks
                num_bricks += 1
                grid.slot_brick[si] = brick
                grid.slot_key[si] = b
                grid.brick_slot[brick] = si
                grid.occupancy[2 * brick] = ti.u32(0)
                grid.occupancy[2 * brick + 1] = ti.u32(0)
                grid.brick_head[brick] = -1
            else:
                brick = -2
        elif grid.slot_key[si][0] == b[0] and grid.slot_key[si][1] == b[1] \
                and grid.slot_key[si][2] == b[2]:
            brick = grid.slot_brick[si]
        s = (s + 1) & mask
    return brick


@ti.func
def voxel_for(grid: ti.template(), brick: ti.i32, key: ivec3, num_voxels: ti.template()) -> ti.i32:
    """Output index of voxel `key` of `brick`, added (the next index: `num_voxels` grows, its
    sums zeroed) when its cell is empty; -1 when the voxels are full. Each brick's voxels form
    a list in voxel order (brick_head, voxel_next; brick_tail appends) for the wider search of
    gather_bricks."""
    local = cell_of(key)
    cell = brick * BRICK_CELLS + local
    word = 2 * brick + (local >> 5)
    bit = ti.u32(1) << ti.cast(local & 31, ti.u32)
    v = -1
    if grid.occupancy[word] & bit:  # a cell is read only once its bit is set
        v = grid.cells[cell]
    elif num_voxels < grid.voxel_key.shape[0]:
        v = num_voxels
        num_voxels += 1
        grid.cells[cell] = v
        grid.occupancy[word] |= bit
        grid.voxel_key[v] = key
        if grid.brick_head[brick] < 0:
            grid.brick_head[brick] = v
        else:
            grid.voxel_next[grid.brick_tail[brick]] = v
        grid.brick_tail[brick] = v
        grid.voxel_next[v] = -1
        grid.voxel_sum[v] = vec3(0.0)
        grid.voxel_count[v] = 0
    return v


@ti.func
def finalize_voxels(voxel_m: ti.f32, grid: ti.template(), out_pts: ti.template()):
    """Each voxel's point: the mean of the points that fell in it (none after an overflow)."""
    for v in range(grid.counts[None][0]):
        if grid.counts[None][2] == 0 and v < out_pts.shape[0]:
            centre = (ti.cast(grid.voxel_key[v], ti.f32) + 0.5) * voxel_m
            out_pts[v] = centre + grid.voxel_sum[v] / ti.cast(grid.voxel_count[v], ti.f32)


@ti.kernel
def downsample(points: ti.types.ndarray(), times: ti.types.ndarray(), n: ti.i32,
               first_chunk: ti.i32, last_chunk: ti.i32, deskew: ti.i32, w_x: ti.f32, w_y: ti.f32,
               w_z: ti.f32, v_x: ti.f32, v_y: ti.f32, v_z: ti.f32, t_first: ti.f32,
               t_step: ti.f32, min_range_m: ti.f32, max_range_m: ti.f32, voxel_m: ti.f32,
               k: ti.i32, grid: ti.template(), out: ti.template()) -> ti.i32:
    """One chunk of a scan's points through the grid in one launch: free the previous scan's
    bricks (first chunk), stage, insert, and after the last chunk the voxel means into
    `out.points`, then (when the pool has `cov_rows`) their `plane_rows` (k neighbours) into
    `out.cov_rows`. Returns the voxel count, or -1 when a voxel or brick did not fit (or,
    after the last chunk, the points do not fit the pool).
    The twist (w, v) comes as six scalars: a vector argument costs ~20 us more to launch."""
    if first_chunk:
        clear_grid(grid)
    stage_points(points, times, n, deskew, vec3(w_x, w_y, w_z), vec3(v_x, v_y, v_z), t_first,
                 t_step, min_range_m, max_range_m, 1.0 / voxel_m, grid)
    insert_points(n, first_chunk, voxel_m, grid)
    if last_chunk:
        finalize_voxels(voxel_m, grid, out.points)
    c = grid.counts[None]
    fits = c[2] == 0 and (not last_chunk or c[0] <= out.points.shape[0])
    if ti.static(out.has_cov_rows):
        # a top-level loop over 0 points when there is nothing to do: a loop under an `if`
        # would run on one thread
        plane_rows(ti.select(fits and last_chunk, c[0], 0), k, grid, out.points, out.cov_rows)
    return ti.select(fits, c[0], -1)


@ti.func
def bit_index(power_of_two: ti.u32) -> ti.i32:
    """log2 of a power of two, read from the exponent of its float (exact; ti.math.clz does
    not compile for Vulkan)."""
    return ti.cast((ti.bit_cast(ti.cast(power_of_two, ti.f32), ti.u32) >> 23) & 255, ti.i32) - 127


@ti.func
def run_bits(first: ti.i32, last: ti.i32, width: ti.i32) -> ti.u32:
    """Bits [first * width, (last + 1) * width) of a u32 (runs up to 16 bits)."""
    return ((ti.u32(1) << ti.cast((last + 1) * width, ti.u32)) - ti.u32(1)) \
        & ~((ti.u32(1) << ti.cast(first * width, ti.u32)) - ti.u32(1))


@ti.func
def box_bits(lo: ivec3, hi: ivec3, word: ti.i32) -> ti.u32:
    """The bits of occupancy word `word` (x = 2 word: low 16 bits, 2 word + 1: high 16) that
    lie in the box [lo, hi] of brick-local cells (clipped to the brick; may be empty)."""
    first = ti.max(lo, 0)
    last = ti.min(hi, 3)
    yz = run_bits(first[1], last[1], 4) & (run_bits(first[2], last[2], 1) * ti.u32(0x1111))
    x_lo = ti.select(first[0] <= 2 * word and 2 * word <= last[0], yz, ti.u32(0))
    x_hi = ti.select(first[0] <= 2 * word + 1 and 2 * word + 1 <= last[0], yz, ti.u32(0))
    return x_lo | (x_hi << 16)


@ti.func
def gather(p: vec3, key: ivec3, k: ti.i32, pts: ti.template(), grid: ti.template()):
    """The k nearest points to p among the 5x5x5 voxels around its voxel `key`, unsorted
    (keep_nearest). Returns (how many, their indices).

    The box always spans 2x2x2 bricks, looked up once. Each brick's occupancy bits (cell
    x*16 + y*4 + z) masked by the box's cells give the occupied cells directly: most cells of
    a box around a surface point are empty, and skipping them is most of the search. The
    inner 3x3x3 voxels go first: they hold most of the nearest, so that few of the outer ones
    replace a kept point (a replacement rescans the k kept)."""
    mask = ti.cast(grid.slot_key.shape[0] - 1, ti.u32)
    lo = brick_of(key - SEARCH)
    bricks = ti.Vector.zero(ti.i32, 8)
    for c in range(8):
        bricks[c] = find_brick(grid, lo + ivec3(c >> 2, (c >> 1) & 1, c & 1), mask)
    dist = ti.Vector.zero(ti.f32, MAX_K)
    nbr = ti.Vector.zero(ti.i32, MAX_K)
    found = 0
    far = 0
    far_d2 = -1.0
    for ring in range(2):
        for c in range(8):
            brick = bricks[c]
            if brick >= 0:
                base = (lo + ivec3(c >> 2, (c >> 1) & 1, c & 1)) * 4
                for word in range(2):
                    inner = box_bits(key - 1 - base, key + 1 - base, word)
                    bits = inner
                    if ring == 1:
                        bits = box_bits(key - SEARCH - base, key + SEARCH - base, word) & ~inner
                    bits &= grid.occupancy[2 * brick + word]
                    while bits != 0:
                        low = bits & (~bits + ti.u32(1))
                        bits ^= low
                        u = grid.cells[brick * BRICK_CELLS + 32 * word + bit_index(low)]
                        keep_nearest(u, (pts[u] - p).norm_sqr(), k, found, far, far_d2, dist,
                                     nbr)
    return found, nbr


@ti.func
def keep_nearest(u: ti.i32, d2: ti.f32, k: ti.i32, found: ti.template(), far: ti.template(),
                 far_d2: ti.template(), dist: ti.template(), nbr: ti.template()):
    """Offer candidate u at squared distance d2 to the k nearest kept so far (unsorted: a
    closer one replaces the farthest, ties keep the earlier; cheaper than sorting). The
    arguments are updated in place (template: by reference; by value a call would copy both
    arrays in and out, most of the search's time)."""
    if found < k:
        dist[found] = d2
        nbr[found] = u
        if d2 > far_d2:
            far = found
            far_d2 = d2
        found += 1
    elif d2 < far_d2:
        dist[far] = d2
        nbr[far] = u
        far_d2 = d2
        new_far = far
        for j in range(k):  # branch-free: which candidate is kept is unpredictable
            dj = dist[j]
            new_far = ti.select(dj > far_d2, j, new_far)
            far_d2 = ti.max(dj, far_d2)
        far = new_far


@ti.func
def gather_bricks(p: vec3, key: ivec3, k: ti.i32, pts: ti.template(), grid: ti.template()):
    """The k nearest points to p in the 3x3x3 bricks around key's brick (see gather)."""
    mask = ti.cast(grid.slot_key.shape[0] - 1, ti.u32)
    dist = ti.Vector.zero(ti.f32, MAX_K)
    nbr = ti.Vector.zero(ti.i32, MAX_K)
    found = 0
    far = 0
    far_d2 = -1.0
    c = brick_of(key)
    for bx in range(c[0] - 1, c[0] + 2):
        for by in range(c[1] - 1, c[1] + 2):
            for bz in range(c[2] - 1, c[2] + 2):
                brick = find_brick(grid, ivec3(bx, by, bz), mask)
                if brick >= 0:
                    u = grid.brick_head[brick]
                    while u >= 0:
                        keep_nearest(u, (pts[u] - p).norm_sqr(), k, found, far, far_d2, dist, nbr)
                        u = grid.voxel_next[u]
    return found, nbr


@ti.func
def neighbour_scatter(pts: ti.template(), nbr: ti.template(), found: ti.i32,
                      p: vec3) -> ti.math.mat3:
    """The scatter (covariance) of the `found` points pts[nbr[j]], taken relative to p (the
    point itself, for f32 precision far from the origin)."""
    mean = vec3(0.0)
    for j in range(found):
        mean += pts[nbr[j]] - p
    mean /= ti.cast(found, ti.f32)
    S = ti.math.mat3(0.0)
    for j in range(found):
        d = pts[nbr[j]] - p - mean
        S += d.outer_product(d)
    return S / ti.cast(found, ti.f32)


@ti.func
def plane_rows(num_voxels: ti.i32, k: ti.i32, grid: ti.template(), pts: ti.template(),
               out_plane: ti.template()):
    """Covariance of each point's k nearest points (itself included), plane-regularized:
    C = I - (1 - normal_variance) n nᵀ with n the normal, stored as (n, α=1,
    β=normal_variance-1, 0) (batch_gicp.plane_form's rows); the identity (α=1, β=0) with
    fewer than `min_neighbors` points or points along a scan line (covariance.is_scan_line);
    both constants of the grid.

    The k nearest within the 5x5x5 voxels around the point (exact when the k-th nearest lies
    within 2 voxels: nothing outside is closer); a point with fewer than `min_neighbors` there
    (a sparse surface) takes the k nearest in the 3x3x3 bricks (12x12x12 voxels) around its
    brick instead, so that it still gets a plane when one is within reach."""
    min_neighbors = grid.min_neighbors
    normal_variance = grid.normal_variance
    for v in range(num_voxels):
        key = grid.voxel_key[v]
        p = pts[v]
        found, nbr = gather(p, key, k, pts, grid)
        if found < min_neighbors:
            found, nbr = gather_bricks(p, key, k, pts, grid)
        row = ti.Vector([1.0, 0.0, 0.0, 1.0, 0.0, 0.0], ti.f32)
        if found >= min_neighbors:
            S = neighbour_scatter(pts, nbr, found, p)
            n = smallest_eigenvector(S)
            if not is_scan_line(S, n):
                row = ti.Vector([n[0], n[1], n[2], 1.0, normal_variance - 1.0, 0.0], ti.f32)
        out_plane[v] = row


@ti.func
def clear_grid(grid: ti.template()):
    """Free the hash slots of the bricks in use (their occupancy is reset when reused)."""
    for b in range(grid.counts[None][1]):
        grid.slot_brick[grid.brick_slot[b]] = -1


@ti.kernel
def download_rows(n: ti.i32, pool: ti.template(), out: ti.types.ndarray()):
    """A source pool's points and covariance rows side by side, (x, y, z, r0..r5) per row."""
    for i in range(n):
        for a in ti.static(range(3)):
            out[i, a] = pool.points[i][a]
        for a in ti.static(range(6)):
            out[i, 3 + a] = pool.cov_rows[i][a]
