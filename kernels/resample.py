"""Weights and systematic (low-variance) resampling over the first `n` particles.

All steps are O(N) parallel kernels that behave the same on cpu, cuda and vulkan, and give
the same bits on every run (no atomic float sums): a max-shifted exp of the log-weights
(nothing underflows) with block-ordered sums, a blocked inclusive scan (no PrefixSumExecutor,
which is wrong on some Vulkan devices), and a range fill where particle j writes its copies
into output slots [ceil(N*C_{j-1} - u0), ceil(N*C_j - u0)).
"""

import taichi as ti

SCAN_BLOCK = 256


@ti.kernel
def max_log_weight(log_w: ti.template(), n: ti.i32) -> ti.f32:
    m = -3.0e38
    for i in range(n):
        ti.atomic_max(m, log_w[i])
    return m


@ti.kernel
def shifted_weights(log_w: ti.template(), n: ti.i32, shift: ti.f32, w: ti.template(),
                    partial: ti.template()):
    """w = exp(log_w - shift); partial[b] = (sum w, sum w^2) over block b, summed in a fixed
    order (atomic float sums would differ in the last bits from run to run, and so would
    the resampling that depends on them)."""
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        s = 0.0
        s2 = 0.0
        for k in range(b * SCAN_BLOCK, ti.min((b + 1) * SCAN_BLOCK, n)):
            wk = ti.exp(log_w[k] - shift)
            w[k] = wk
            s += wk
            s2 += wk * wk
        partial[b] = ti.math.vec2(s, s2)


@ti.kernel
def sum_partials(partial: ti.template(), n: ti.i32, sums: ti.template()):
    """sums = (sum w, sum w^2) from the block partials, in block order."""
    sums[0] = 0.0
    sums[1] = 0.0
    ti.loop_config(serialize=True)
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        sums[0] += partial[b][0]
        sums[1] += partial[b][1]


@ti.kernel
def scan_blocks(x: ti.template(), n: ti.i32, out: ti.template(), block_sums: ti.template()):
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        s = 0.0
        for k in range(b * SCAN_BLOCK, ti.min((b + 1) * SCAN_BLOCK, n)):
            s += x[k]
            out[k] = s
        block_sums[b] = s


@ti.kernel
def scan_block_sums(block_sums: ti.template(), n_blocks: ti.i32):
    ti.loop_config(serialize=True)
    for b in range(1, n_blocks):
        block_sums[b] += block_sums[b - 1]


@ti.kernel
def add_block_offsets(out: ti.template(), n: ti.i32, block_sums: ti.template(), total: ti.f32):
    """Adds the preceding blocks' sums and divides by `total` (normalized CDF)."""
    for k in range(n):
        offset = 0.0
        if k >= SCAN_BLOCK:
            offset = block_sums[k // SCAN_BLOCK - 1]
        out[k] = (out[k] + offset) / total


@ti.kernel
def systematic_select(cdf: ti.template(), n_in: ti.i32, n_out: ti.i32, u0: ti.f32,
                      parent: ti.template()):
    """parent[k] = index of the particle whose CDF interval holds (k + u0) / n_out."""
    for j in range(n_in):
        c_prev = 0.0
        if j > 0:
            c_prev = cdf[j - 1]
        a = ti.max(0, ti.cast(ti.ceil(c_prev * n_out - u0), ti.i32))
        b = n_out
        if j < n_in - 1:
            b = ti.min(n_out, ti.cast(ti.ceil(cdf[j] * n_out - u0), ti.i32))
        for k in range(a, b):
            parent[k] = j
