"""Copy host arrays into the first `n` rows of preallocated fields (nothing is reallocated)."""

import taichi as ti


@ti.kernel
def vector_rows(src: ti.types.ndarray(), n: ti.i32, dst: ti.template()):
    for i in range(n):
        for a in ti.static(range(dst.n)):
            dst[i][a] = src[i, a]


@ti.kernel
def matrix_rows(src: ti.types.ndarray(), n: ti.i32, dst: ti.template()):
    for i in range(n):
        for a in ti.static(range(dst.n)):
            for b in ti.static(range(dst.m)):
                dst[i][a, b] = src[i, a, b]
