"""Place evidence on the device (mcl3d.localization.evidence): places, their scores, the
sampling noise, the particle floor and the rival test, with only counts and a few scalars
crossing to the host.

A place is a cell of position and yaw. The particles are sorted by (place, random key) with
a stable LSD radix sort (8-bit digits, block-ordered counts: the same order on every run and
thread count, no atomics), so each place is a run of the sorted order whose members come in
random order: the first `sample` of a run are `sample` of its particles drawn at random, the
next `sample` a disjoint second draw. Per-place work is a serial loop over its run (maxima,
weight sums in sorted order: the same bits every run); the median of the leading places'
differences is a serial quickselect. Maxima are order-independent, so they may be reduced
in parallel.
"""

import taichi as ti

from mcl3d.kernels.random import counter_hash

SORT_BLOCK = 256  # particles per block of the radix sort's counts and of the place scan
RADIX = 256  # 8-bit digits
RAND_BITS = 24  # the random key that orders a place's particles
NEG = -3.0e38  # "no value" of a maximum
MAX_FACTOR = 1.0e38  # the largest resampling factor (finite: w * factor stays finite)
_TWO_PI = 6.283185307179586
# slots of `out`, the statistics that come back to the host
OUT_PLACES, OUT_LEADERS, OUT_MAD, OUT_MAX_PRIOR, OUT_MAX_VALUE, OUT_LIVE, OUT_TOTAL = range(7)
OUT_INSIDE, OUT_AWAY, OUT_N_INSIDE, OUT_N_AWAY = 7, 8, 9, 10
OUT_SIZE = 11


class PlaceFields:
    """The device state of the place evidence for up to `capacity` particles (and places)."""

    _data_oriented = True  # passed to kernels as one ti.template()

    def __init__(self, capacity: int):
        c = int(capacity)
        blocks = (c + SORT_BLOCK - 1) // SORT_BLOCK
        self.cell = ti.Vector.field(4, ti.i32, shape=c)  # x, y, z cell and yaw bin
        self.bounds = ti.Vector.field(4, ti.i32, shape=2)  # lowest and highest cell
        self.key = ti.field(ti.u64, shape=(2, c))  # place key (ping-pong buffers of the sort)
        self.rand = ti.field(ti.u32, shape=(2, c))  # random key within the place
        self.idx = ti.field(ti.i32, shape=(2, c))  # particle index
        self.hist = ti.field(ti.i32, shape=(blocks, RADIX))  # per block digit counts/offsets
        self.digit_start = ti.field(ti.i32, shape=RADIX)
        self.block_count = ti.field(ti.i32, shape=blocks)  # places starting in a block
        self.place_of = ti.field(ti.i32, shape=c)  # place of each particle
        self.start = ti.field(ti.i32, shape=c + 1)  # first sorted slot of each place
        self.prior = ti.field(ti.f32, shape=c)  # best evidence among the place's particles
        self.best = ti.field(ti.f32, shape=c)  # best increment of the first draw
        self.second = ti.field(ti.f32, shape=c)  # best increment of the second draw
        self.weight = ti.field(ti.f32, shape=c)  # the place's share of the weight
        self.factor = ti.field(ti.f32, shape=c)  # the place's resampling factor
        self.live = ti.field(ti.i32, shape=c)  # not ruled out
        self.scratch = ti.field(ti.f32, shape=c)  # the leaders' differences (median)
        self.block_sum = ti.field(ti.f32, shape=blocks)
        self.out = ti.field(ti.f32, shape=OUT_SIZE)


@ti.kernel
def place_cells(pos: ti.template(), quat: ti.template(), n: ti.i32, cell_m: ti.f32,
                yaw_bins: ti.i32, ev: ti.template()):
    """cell[i] = particle i's cell of `cell_m` and yaw bin of 360/yaw_bins degrees (from
    -180); bounds = the lowest and highest cell over the particles (integer reductions)."""
    lo0, lo1, lo2, lo3 = 2147483647, 2147483647, 2147483647, 2147483647
    hi0, hi1, hi2, hi3 = -2147483647, -2147483647, -2147483647, -2147483647
    for i in range(n):
        q = quat[i]
        yaw = ti.atan2(2.0 * (q[3] * q[2] + q[0] * q[1]), 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2]))
        b = ti.cast(ti.floor((yaw + 0.5 * _TWO_PI) / _TWO_PI * yaw_bins), ti.i32) % yaw_bins
        b = (b + yaw_bins) % yaw_bins
        c = ti.cast(ti.floor(pos[i] / cell_m), ti.i32)
        ev.cell[i] = ti.Vector([c[0], c[1], c[2], b])
        ti.atomic_min(lo0, c[0])
        ti.atomic_min(lo1, c[1])
        ti.atomic_min(lo2, c[2])
        ti.atomic_min(lo3, b)
        ti.atomic_max(hi0, c[0])
        ti.atomic_max(hi1, c[1])
        ti.atomic_max(hi2, c[2])
        ti.atomic_max(hi3, b)
    ev.bounds[0] = ti.Vector([lo0, lo1, lo2, lo3])
    ev.bounds[1] = ti.Vector([hi0, hi1, hi2, hi3])


@ti.kernel
def place_keys(ev: ti.template(), n: ti.i32, dims: ti.math.ivec4, seed: ti.u32,
               counter: ti.u32):
    """key = the cell's index in the particles' bounding box of `dims` cells (x fastest, yaw
    slowest; 64 bits: rooms a kilometre apart span more than 2^32 cells), rand = RAND_BITS
    bits of a counter hash."""
    for i in range(n):
        c = ev.cell[i] - ev.bounds[0]
        key = ti.cast(c[3], ti.u64)
        for a in ti.static((2, 1, 0)):
            key = key * ti.cast(dims[a], ti.u64) + ti.cast(c[a], ti.u64)
        ev.key[0, i] = key
        ev.rand[0, i] = counter_hash(seed, counter, ti.u32(i), ti.u32(0)) >> ti.u32(
            32 - RAND_BITS)
        ev.idx[0, i] = i


@ti.func
def _digit(ev: ti.template(), src: ti.i32, k: ti.i32, word: ti.i32, shift: ti.i32) -> ti.i32:
    d = ti.cast((ev.rand[src, k] >> ti.cast(shift, ti.u32)) & ti.u32(RADIX - 1), ti.i32)
    if word == 1:
        d = ti.cast((ev.key[src, k] >> ti.cast(shift, ti.u64)) & ti.u64(RADIX - 1), ti.i32)
    return d


@ti.kernel
def radix_pass(ev: ti.template(), n: ti.i32, src: ti.i32, word: ti.i32, shift: ti.i32):
    """One stable pass of the LSD radix sort from buffer `src` into 1 - src, by the digit
    at `shift` of rand (word 0) or key (word 1): block counts, their offsets (digit-major,
    block order), then each block scatters its items in order."""
    blocks = (n + SORT_BLOCK - 1) // SORT_BLOCK
    for b in range(blocks):
        for d in range(RADIX):
            ev.hist[b, d] = 0
        for k in range(b * SORT_BLOCK, ti.min((b + 1) * SORT_BLOCK, n)):
            ev.hist[b, _digit(ev, src, k, word, shift)] += 1
    for d in range(RADIX):  # each digit's blocks: exclusive offsets within the digit
        s = 0
        for b in range(blocks):
            c = ev.hist[b, d]
            ev.hist[b, d] = s
            s += c
        ev.digit_start[d] = s
    for _ in range(1):  # the digits' totals: exclusive scan (one thread)
        s = 0
        for d in range(RADIX):
            c = ev.digit_start[d]
            ev.digit_start[d] = s
            s += c
    for b in range(blocks):
        for k in range(b * SORT_BLOCK, ti.min((b + 1) * SORT_BLOCK, n)):
            d = _digit(ev, src, k, word, shift)
            slot = ev.digit_start[d] + ev.hist[b, d]
            ev.hist[b, d] += 1
            ev.key[1 - src, slot] = ev.key[src, k]
            ev.rand[1 - src, slot] = ev.rand[src, k]
            ev.idx[1 - src, slot] = ev.idx[src, k]


@ti.kernel
def place_runs(ev: ti.template(), n: ti.i32, src: ti.i32):
    """The places as runs of equal keys in sorted buffer `src`: start[p] (start[places] = n),
    place_of[i] for every particle, out[OUT_PLACES] = the number of places."""
    blocks = (n + SORT_BLOCK - 1) // SORT_BLOCK
    for b in range(blocks):
        c = 0
        for j in range(b * SORT_BLOCK, ti.min((b + 1) * SORT_BLOCK, n)):
            c += ti.select((j == 0) | (ev.key[src, j] != ev.key[src, ti.max(j - 1, 0)]), 1, 0)
        ev.block_count[b] = c
    for _ in range(1):  # exclusive scan of the blocks' counts (one thread)
        s = 0
        for b in range(blocks):
            c = ev.block_count[b]
            ev.block_count[b] = s
            s += c
        ev.start[s] = n
        ev.out[OUT_PLACES] = ti.cast(s, ti.f32)
    for b in range(blocks):
        p = ev.block_count[b] - 1
        for j in range(b * SORT_BLOCK, ti.min((b + 1) * SORT_BLOCK, n)):
            if (j == 0) | (ev.key[src, j] != ev.key[src, ti.max(j - 1, 0)]):
                p += 1
                ev.start[p] = j
            ev.place_of[ev.idx[src, j]] = p


@ti.kernel
def place_scores(ev: ti.template(), n: ti.i32, src: ti.i32, log_l: ti.template(),
                 ll_mean: ti.template(), scale: ti.f32, sample: ti.i32):
    """Per place: prior = the best log_l of its particles, best / second = the best
    increment (scale * ll_mean) of the first / second `sample` of its run (a random draw);
    then log_l[i] = prior + best of i's place. out: the largest prior and prior + best."""
    places = ti.cast(ev.out[OUT_PLACES], ti.i32)
    for p in range(places):
        prior, best, second = NEG, NEG, NEG
        a = ev.start[p]
        for j in range(a, ev.start[p + 1]):
            i = ev.idx[src, j]
            prior = ti.max(prior, log_l[i])
            v = scale * ll_mean[i]
            if j - a < sample:
                best = ti.max(best, v)
            elif j - a < 2 * sample:
                second = ti.max(second, v)
        ev.prior[p] = prior
        ev.best[p] = best
        ev.second[p] = second
    max_prior = NEG
    max_value = NEG
    for p in range(places):
        ti.atomic_max(max_prior, ev.prior[p])
        ti.atomic_max(max_value, ev.prior[p] + ev.best[p])
    ev.out[OUT_MAX_PRIOR] = max_prior
    ev.out[OUT_MAX_VALUE] = max_value
    for i in range(n):
        p = ev.place_of[i]
        log_l[i] = ev.prior[p] + ev.best[p]


@ti.func
def _select(a: ti.template(), count: ti.i32, k: ti.i32) -> ti.f32:
    """The k-th smallest of a[0:count] (Hoare's quickselect, middle pivot; reorders a)."""
    lo, hi = 0, count - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                t = a[i]
                a[i] = a[j]
                a[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            lo = hi
    return a[k]


@ti.func
def _median(a: ti.template(), count: ti.i32) -> ti.f32:
    """np.median of a[0:count] (the mean of the two middle values of an even count)."""
    m = count // 2
    med = _select(a, count, m)
    if count % 2 == 0:
        low = a[0]
        for j in range(1, m):
            low = ti.max(low, a[j])
        med = 0.5 * (low + med)
    return med


@ti.kernel
def noise_mad(ev: ti.template(), leaders_nats: ti.f32):
    """out[OUT_MAD] = the median absolute deviation of best - second over the leading places
    (prior within `leaders_nats` of the largest, with a second draw), out[OUT_LEADERS] their
    number; one thread, in place order."""
    for _ in range(1):
        places = ti.cast(ev.out[OUT_PLACES], ti.i32)
        threshold = ev.out[OUT_MAX_PRIOR] - leaders_nats
        count = 0
        for p in range(places):
            if ev.prior[p] >= threshold and ev.second[p] > 0.5 * NEG:
                ev.scratch[count] = ev.best[p] - ev.second[p]
                count += 1
        mad = 0.0
        if count > 0:
            med = _median(ev.scratch, count)
            for j in range(count):
                ev.scratch[j] = ti.abs(ev.scratch[j] - med)
            mad = _median(ev.scratch, count)
        ev.out[OUT_LEADERS] = ti.cast(count, ti.f32)
        ev.out[OUT_MAD] = mad


@ti.kernel
def place_weights(ev: ti.template(), src: ti.i32, w: ti.template(), margin: ti.f32):
    """weight[p] = the sum of the place's weights w (in sorted order; not divided by their
    total: a place ~1e-38 of the heaviest particle would underflow to 0 in f32, and the
    floor's factors do not depend on the normalization), live[p] = its prior + best within
    `margin` of the largest and a weight; out[OUT_LIVE] = the number of live places."""
    places = ti.cast(ev.out[OUT_PLACES], ti.i32)
    threshold = ev.out[OUT_MAX_VALUE] - margin
    for p in range(places):
        s = 0.0
        for j in range(ev.start[p], ev.start[p + 1]):
            s += w[ev.idx[src, j]]
        ev.weight[p] = s
        ev.live[p] = ti.cast((ev.prior[p] + ev.best[p] >= threshold) & (s > 0.0), ti.i32)
    live = 0
    for p in range(places):
        live += ev.live[p]
    ev.out[OUT_LIVE] = ti.cast(live, ti.f32)


@ti.kernel
def place_floor(ev: ti.template(), n: ti.i32, share: ti.f32, factor: ti.template()):
    """factor[i] = the resampling factor of i's place: live places get at least `share` of
    the floored weights (three rounds: the floors change the total they are relative to);
    the total is summed per block of places, then over the blocks in order. A factor is at
    most MAX_FACTOR: an infinite one would make the resampling weights inf or NaN and
    collapse the cloud onto one place."""
    places = ti.cast(ev.out[OUT_PLACES], ti.i32)
    blocks = (places + SORT_BLOCK - 1) // SORT_BLOCK
    for p in range(places):
        ev.factor[p] = 1.0
    for _round in ti.static(range(3)):
        for b in range(blocks):
            s = 0.0
            for p in range(b * SORT_BLOCK, ti.min((b + 1) * SORT_BLOCK, places)):
                s += ev.weight[p] * ev.factor[p]
            ev.block_sum[b] = s
        for _ in range(1):
            total = 0.0
            for b in range(blocks):
                total += ev.block_sum[b]
            ev.out[OUT_TOTAL] = total
        for p in range(places):
            if ev.live[p]:
                ev.factor[p] = ti.min(ti.max(1.0, share * ev.out[OUT_TOTAL] / ev.weight[p]),
                                      MAX_FACTOR)
    for i in range(n):
        factor[i] = ev.factor[ev.place_of[i]]


@ti.kernel
def rival_bests(pos: ti.template(), quat: ti.template(), log_l: ti.template(), n: ti.i32,
                t: ti.math.vec3, q: ti.math.vec4, radius_m: ti.f32, cos_inside: ti.f32,
                cos_away: ti.f32, ev: ti.template()):
    """The best log_l within radius_m / 2 and the angle of cos_inside of the pose (t, q),
    and the best beyond radius_m or the angle of cos_away, with their counts, into out."""
    best_inside, best_away = NEG, NEG
    n_inside, n_away = 0, 0
    for i in range(n):
        d = (pos[i] - t).norm()
        dot = ti.abs(quat[i].dot(q))
        if d <= 0.5 * radius_m and dot >= cos_inside:
            ti.atomic_max(best_inside, log_l[i])
            n_inside += 1
        if not (d <= radius_m and dot >= cos_away):
            ti.atomic_max(best_away, log_l[i])
            n_away += 1
    ev.out[OUT_INSIDE] = best_inside
    ev.out[OUT_AWAY] = best_away
    ev.out[OUT_N_INSIDE] = ti.cast(n_inside, ti.f32)
    ev.out[OUT_N_AWAY] = ti.cast(n_away, ti.f32)
