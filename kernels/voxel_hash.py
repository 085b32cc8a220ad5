"""Gaussian voxel maps in one open-addressing hash table made of plain fields.

Lookups read one AoS struct field `vox` (key, mean, cov, count, claim: 64 bytes, so one probe
touches one cache line); the insertion-only sums live in separate fields. A key is the voxel's
three coordinates packed into two i32 words (21 bits each: cells within ±2^20 voxels of the
map's origin, ±262 km at 0.25 m), and a free slot is marked by its high word (EMPTY_KEY), so a
lookup reads and compares two words and no separate state: the batched GICP's cost is mostly
these scattered reads. (One i64 key made LLVM vectorize that loop 4 wide instead of 8.)

The table holds `max_maps` independent maps, each a region of `buckets` (a power of two)
slots: slot `m * buckets + (hash(ix, iy, iz) + probe) & (buckets - 1)`. A voxel keeps the sum
of its points' offsets from the voxel centre (so f32 sums stay precise far from the origin),
the sum of their covariances and a count; `finalize` turns them into the voxel mean and the
*average of the point covariances* (not the scatter of the points), as gtsam_points and
small_gicp do. Clearing a map clears its region only.

Insertion without an atomic compare-and-swap (Taichi's Python API has none) runs in rounds:
pending points `claim` their probe slot with atomic_max of their index, the winners `commit`
their key in a later launch, and every pending point then `resolve`s: its key is there (done),
another key is there (probe on), all in separate launches so no kernel reads what it writes.
"""

import taichi as ti

from mcl3d.kernels.se3 import quat_to_mat

vec3 = ti.math.vec3
ivec2 = ti.math.ivec2
ivec3 = ti.math.ivec3
mat3 = ti.math.mat3

KEY_BITS = 21  # per coordinate; two i32 words hold 63 bits, keeping the lookup loop in i32
KEY_BIAS = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
LOW_BITS = 32 - KEY_BITS  # bits of y in the low word
EMPTY_KEY = -1  # high word of a free slot (a stored key's high word is >= 0)
OUTSIDE_KEY = -2  # high word of a cell beyond ±KEY_BIAS voxels: never stored, never found

Voxel = ti.types.struct(key=ivec2, mean=vec3, cov=mat3, count=ti.i32, claim=ti.i32)


@ti.func
def voxel_coord(p: vec3, res: ti.f32) -> ivec3:
    return ti.cast(ti.floor(p / res), ti.i32)


@ti.func
def voxel_hash(c: ivec3) -> ti.u32:
    """Sum of the coordinates times large primes in wrapping u32 arithmetic (gtsam_points
    xors the products instead, which collides: 34% of an 80x80x6 block of voxels share a hash),
    then MurmurHash3's finalizer so the low bits that pick the bucket depend on every bit."""
    h = ti.cast(c[0], ti.u32) * ti.u32(73856093) + ti.cast(c[1], ti.u32) * ti.u32(19349669) \
        + ti.cast(c[2], ti.u32) * ti.u32(83492791)
    h ^= h >> 16
    h *= ti.u32(0x85EBCA6B)
    h ^= h >> 13
    h *= ti.u32(0xC2B2AE35)
    h ^= h >> 16
    return h


@ti.func
def pack_key(c: ivec3) -> ivec2:
    """The cell's coordinates in two i32 words (low: z and the low bits of y; high: the rest
    of y and x), or high word OUTSIDE_KEY beyond ±KEY_BIAS voxels. In u32 arithmetic so that
    the shifts are logical."""
    u = ti.cast(c + KEY_BIAS, ti.u32)
    inside = (u[0] <= KEY_MASK) & (u[1] <= KEY_MASK) & (u[2] <= KEY_MASK)
    low = u[2] | (u[1] << KEY_BITS)
    high = (u[1] >> LOW_BITS) | (u[0] << (KEY_BITS - LOW_BITS))
    return ivec2(ti.cast(low, ti.i32), ti.select(inside, ti.cast(high, ti.i32), OUTSIDE_KEY))


@ti.func
def unpack_key(key: ivec2) -> ivec3:
    low = ti.cast(key[0], ti.u32)
    high = ti.cast(key[1], ti.u32)
    u = ti.Vector([high >> (KEY_BITS - LOW_BITS),
                   (low >> KEY_BITS) | ((high << LOW_BITS) & KEY_MASK), low & KEY_MASK], ti.u32)
    return ti.cast(u, ti.i32) - KEY_BIAS


@ti.func
def same_key(a: ivec2, b: ivec2) -> ti.i32:
    return (a[0] == b[0]) & (a[1] == b[1])


@ti.func
def probe_slot(c: ivec3, probe: ti.i32, map_id: ti.i32, buckets: ti.i32) -> ti.i32:
    mask = ti.cast(buckets - 1, ti.u32)
    h = (voxel_hash(c) + ti.cast(probe, ti.u32)) & mask
    return map_id * buckets + ti.cast(h, ti.i32)


@ti.func
def lookup_from(vox: ti.template(), c: ivec3, first: ti.i32, map_id: ti.i32, buckets: ti.i32,
                max_probes: ti.i32) -> ti.i32:
    """Slot of voxel `c` in map `map_id` probing from probe `first` on, or -1 when absent."""
    found = -1
    key = pack_key(c)
    for probe in range(first, max_probes):
        s = probe_slot(c, probe, map_id, buckets)
        k = vox[s].key
        if k[1] == EMPTY_KEY:
            break
        if same_key(k, key):
            found = s
            break
    return found


@ti.func
def lookup(vox: ti.template(), c: ivec3, map_id: ti.i32, buckets: ti.i32,
           max_probes: ti.i32) -> ti.i32:
    """Slot of voxel `c` in map `map_id`, or -1 when the voxel is not in the map."""
    return lookup_from(vox, c, 0, map_id, buckets, max_probes)


@ti.kernel
def clear_region(vox: ti.template(), vsum: ti.template(), vsumcov: ti.template(), begin: ti.i32,
                 end: ti.i32):
    for s in range(begin, end):
        vox[s].key = ivec2(0, EMPTY_KEY)
        vox[s].claim = -1
        vox[s].count = 0
        vsum[s] = vec3(0.0)
        vsumcov[s] = mat3(0.0)


@ti.kernel
def begin_insert(pts: ti.template(), covs: ti.template(), n: ti.i32, T: ti.math.mat4,
                 res: ti.f32, coord: ti.template(), probe: ti.template(),
                 slot: ti.template()):
    """Transform the staged points (and covariances) into the map frame; reset probing (a
    point beyond the packable cells is lost at once)."""
    R = mat3([[T[0, 0], T[0, 1], T[0, 2]], [T[1, 0], T[1, 1], T[1, 2]],
              [T[2, 0], T[2, 1], T[2, 2]]])
    t = vec3(T[0, 3], T[1, 3], T[2, 3])
    for i in range(n):
        p = R @ pts[i] + t
        pts[i] = p
        covs[i] = R @ covs[i] @ R.transpose()
        coord[i] = voxel_coord(p, res)
        probe[i] = 0
        slot[i] = ti.select(pack_key(coord[i])[1] == OUTSIDE_KEY, -2, -1)


@ti.kernel
def claim_slots(coord: ti.template(), probe: ti.template(), slot: ti.template(), n: ti.i32,
                map_id: ti.i32, buckets: ti.i32, vox: ti.template()):
    for i in range(n):
        if slot[i] == -1:
            s = probe_slot(coord[i], probe[i], map_id, buckets)
            if vox[s].key[1] == EMPTY_KEY:
                ti.atomic_max(vox[s].claim, i)


@ti.kernel
def commit_slots(coord: ti.template(), probe: ti.template(), slot: ti.template(), n: ti.i32,
                 map_id: ti.i32, buckets: ti.i32, vox: ti.template()):
    for i in range(n):
        if slot[i] == -1:
            s = probe_slot(coord[i], probe[i], map_id, buckets)
            if vox[s].claim == i:
                vox[s].key = pack_key(coord[i])


@ti.kernel
def resolve_slots(coord: ti.template(), probe: ti.template(), slot: ti.template(), n: ti.i32,
                  map_id: ti.i32, buckets: ti.i32, vox: ti.template(),
                  max_probes: ti.i32) -> ti.i32:
    """Settle the points whose key is in their probe slot; the rest probe on. Returns how
    many are still pending (-2 marks a point out of probes: the map is full)."""
    pending = 0
    for i in range(n):
        if slot[i] == -1:
            s = probe_slot(coord[i], probe[i], map_id, buckets)
            if vox[s].claim == i:
                vox[s].claim = -1
            key = vox[s].key
            if key[1] != EMPTY_KEY:
                if same_key(key, pack_key(coord[i])):
                    slot[i] = s
                else:
                    probe[i] += 1
                    if probe[i] >= max_probes:
                        slot[i] = -2
                    else:
                        pending += 1
            else:
                pending += 1
    return pending


@ti.kernel
def accumulate(pts: ti.template(), covs: ti.template(), slot: ti.template(), begin: ti.i32,
               end: ti.i32, res: ti.f32, vox: ti.template(), vsum: ti.template(),
               vsumcov: ti.template()) -> ti.i32:
    """Add settled points [begin, end) to their voxels; returns how many could not be placed.

    One ordered pass: parallel float sums would differ in the last bits from run to run,
    and registration turns those into different trajectories. Points arrive a keyframe at a
    time, so this costs about 2 ms per keyframe on cpu."""
    lost = 0
    ti.loop_config(serialize=True)
    for i in range(begin, end):
        s = slot[i]
        if s >= 0:
            centre = (ti.cast(unpack_key(vox[s].key), ti.f32) + 0.5) * res
            vsum[s] += pts[i] - centre
            vsumcov[s] += covs[i]
            vox[s].count += 1
        else:
            lost += 1
    return lost


@ti.kernel
def finalize(vox: ti.template(), vsum: ti.template(), vsumcov: ti.template(), res: ti.f32,
             begin: ti.i32, end: ti.i32) -> ti.i32:
    """Mean and averaged covariance of every voxel of one map; returns its voxel count."""
    voxels = 0
    for s in range(begin, end):
        if vox[s].key[1] != EMPTY_KEY and vox[s].count > 0:
            inv = 1.0 / ti.cast(vox[s].count, ti.f32)
            vox[s].mean = (ti.cast(unpack_key(vox[s].key), ti.f32) + 0.5) * res \
                + vsum[s] * inv
            vox[s].cov = vsumcov[s] * inv
            voxels += 1
    return voxels


@ti.kernel
def count_hits(pts: ti.template(), n: ti.i32, queries: ti.types.ndarray(), num_maps: ti.i32,
               res: ti.template(), buckets: ti.i32, max_probes: ti.i32,
               vox: ti.template()) -> ti.i32:
    """How many points land in an occupied voxel of at least one of the listed maps, each
    point taken into map k's frame by the pose in queries[k] = (map id, qx, qy, qz, qw,
    tx, ty, tz) (the overlap numerator; list the likeliest map first, a hit ends the search)."""
    hits = 0
    for i in range(n):
        hit = 0
        for k in range(num_maps):
            m = ti.cast(queries[k, 0], ti.i32)
            q = ti.math.vec4(queries[k, 1], queries[k, 2], queries[k, 3], queries[k, 4])
            t = vec3(queries[k, 5], queries[k, 6], queries[k, 7])
            p = quat_to_mat(q) @ pts[i] + t
            if lookup(vox, voxel_coord(p, res[m]), m, buckets, max_probes) >= 0:
                hit = 1
                break
        hits += hit
    return hits


@ti.kernel
def count_hits_each(pts: ti.template(), n: ti.i32, stride: ti.i32, queries: ti.types.ndarray(),
                    num_maps: ti.i32, res: ti.template(), buckets: ti.i32, max_probes: ti.i32,
                    vox: ti.template(), out: ti.types.ndarray(), serial: ti.template()):
    """Per listed map k: how many of the points 0, stride, 2 stride, ... < n land in one of its
    occupied voxels, taken into its frame by queries[k] (rows as count_hits'): each map's
    overlap on its own, in one launch. `serial`: a few thousand lookups on the calling thread
    (on cpu, waking the thread pool of a busy machine costs more than they do)."""
    ti.loop_config(serialize=serial)
    for k in range(num_maps):
        out[k] = 0
    ti.loop_config(serialize=serial)
    for i, k in ti.ndrange((n + stride - 1) // stride, num_maps):
        m = ti.cast(queries[k, 0], ti.i32)
        q = ti.math.vec4(queries[k, 1], queries[k, 2], queries[k, 3], queries[k, 4])
        t = vec3(queries[k, 5], queries[k, 6], queries[k, 7])
        p = quat_to_mat(q) @ pts[i * stride] + t
        if lookup(vox, voxel_coord(p, res[m]), m, buckets, max_probes) >= 0:
            ti.atomic_add(out[k], 1)


@ti.kernel
def gather_voxels(vox: ti.template(), begin: ti.i32, end: ti.i32, out_mean: ti.types.ndarray(),
                  out_cov: ti.types.ndarray(), counter: ti.template()):
    """Copy one map's voxels (any order) into ndarrays, for export and tests."""
    for s in range(begin, end):
        if vox[s].key[1] != EMPTY_KEY and vox[s].count > 0:
            j = ti.atomic_add(counter[None], 1)
            for a in ti.static(range(3)):
                out_mean[j, a] = vox[s].mean[a]
                for b in ti.static(range(3)):
                    out_cov[j, a, b] = vox[s].cov[a, b]


@ti.kernel
def stage_rows(src_pts: ti.template(), src_rows: ti.template(), n: ti.i32,
               plane: ti.template(), pts: ti.template(), covs: ti.template()):
    """Device points with covariance rows (upper triangle xx xy xz yy yz zz, or (n, α, β, 0)
    for αI + βnnᵀ with `plane`) into the staging fields of an insertion."""
    for i in range(n):
        pts[i] = src_pts[i]
        r = src_rows[i]
        if ti.static(plane):
            nv = vec3(r[0], r[1], r[2])
            covs[i] = r[3] * ti.math.eye(3) + r[4] * nv.outer_product(nv)
        else:
            covs[i] = mat3([[r[0], r[1], r[2]], [r[1], r[3], r[4]], [r[2], r[4], r[5]]])
