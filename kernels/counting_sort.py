"""Counting sort of small integer keys on the device: the order in which to visit particles.

The keys (0 <= key < number of bins) are counted per bin (integer atomics: exact), the counts
turn into each bin's first slot by a blocked exclusive scan, and every index is scattered to
its bin's next free slot. The order within one bin depends on the thread schedule; callers use
it only as a visiting order (each particle's result does not depend on it).
"""

import taichi as ti

SCAN_BLOCK = 256


@ti.kernel
def sort_by_key(keys: ti.template(), n: ti.i32, starts: ti.template(),
                block_sums: ti.template(), order: ti.template()):
    """order[0:n] = the indices 0..n-1 grouped by ascending keys[i]; `starts` (one per bin)
    and `block_sums` (one per SCAN_BLOCK bins) are scratch."""
    n_bins = starts.shape[0]
    n_blocks = (n_bins + SCAN_BLOCK - 1) // SCAN_BLOCK
    for b in range(n_bins):
        starts[b] = 0
    for i in range(n):
        ti.atomic_add(starts[keys[i]], 1)
    for blk in range(n_blocks):  # exclusive scan inside each block; block totals
        s = 0
        for b in range(blk * SCAN_BLOCK, ti.min((blk + 1) * SCAN_BLOCK, n_bins)):
            c = starts[b]
            starts[b] = s
            s += c
        block_sums[blk] = s
    ti.loop_config(serialize=True)
    for blk in range(1, n_blocks):
        block_sums[blk] += block_sums[blk - 1]
    for b in range(SCAN_BLOCK, n_bins):
        starts[b] += block_sums[b // SCAN_BLOCK - 1]
    for i in range(n):
        order[ti.atomic_add(starts[keys[i]], 1)] = i
