"""Which item a parallel loop index works on, so that every cpu thread gets a like share.

Taichi 1.7.4 on the cpu backend hands each of its T threads one contiguous range of a
parallel loop's indices, at least `MIN_CHUNK` long (its make_cpu_multithreading_loop
pass; `ti.loop_config(block_dim=...)` does not change it): there is no work stealing. So
a loop over a scan's points in scan order leaves the thread with the costly part of the
scan (far points with wide band patches) running while the others wait, and a loop of at
most `MIN_CHUNK` indices runs on one thread. A loop over `spread_length(n, T)` indices
that works on item `spread_item(i, n, T)` (nothing where that is -1) gives thread t the
items t, t + T, t + 2T, ...: a like share of every part of the scan. On GPUs pass T = 1:
index i is item i.
"""

import taichi as ti

MIN_CHUNK = 512  # Taichi 1.7.4's least number of indices per cpu thread


@ti.func
def spread_length(n: ti.i32, threads: ti.i32) -> ti.i32:
    """Indices to loop over for n items: T equal contiguous ranges of at least MIN_CHUNK."""
    per_thread = ti.max((n + threads - 1) // threads, MIN_CHUNK)
    return per_thread * threads


@ti.func
def spread_item(i: ti.i32, n: ti.i32, threads: ti.i32) -> ti.i32:
    """The item of loop index i (of spread_length(n, threads)), or -1 past the n items."""
    per_thread = spread_length(n, threads) // threads
    item = (i % per_thread) * threads + i // per_thread
    if item >= n:
        item = -1
    return item
