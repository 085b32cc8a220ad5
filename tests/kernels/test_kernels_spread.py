"""kernels.spread: every item once, each thread's contiguous range a like share."""

import numpy as np
import pytest


def _spread_reference(n, threads, min_chunk):
    per_thread = max(-(-n // threads), min_chunk)
    i = np.arange(per_thread * threads)
    item = (i % per_thread) * threads + i // per_thread
    return np.where(item < n, item, -1), per_thread


@pytest.mark.parametrize(("n", "threads"), [(1, 1), (7, 3), (1000, 1), (1024, 2),
                                            (1025, 2), (5000, 16), (70000, 3)])
def test_spread_matches_numpy_and_shares_items_out(ti_runtime, n, threads):
    import taichi as ti

    from mcl3d.kernels import spread

    @ti.kernel
    def items(n: ti.i32, threads: ti.i32, out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(spread.spread_length(n, threads)):
            out[i] = spread.spread_item(i, n, threads)

    want, per_thread = _spread_reference(n, threads, spread.MIN_CHUNK)
    got = np.full(len(want), -7, np.int32)
    items(n, threads, got)
    np.testing.assert_array_equal(got, want)
    assert sorted(got[got >= 0]) == list(range(n))  # every item exactly once
    for t in range(threads):  # thread t's range: items t, t + T, ... in order
        mine = got[t * per_thread:(t + 1) * per_thread]
        mine = mine[mine >= 0]
        np.testing.assert_array_equal(mine, np.arange(t, n, threads))
