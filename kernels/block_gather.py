"""Blocks of a map read by pool id in any order: the map file writes them sorted by
coordinate a chunk at a time, without a host copy of the whole pool."""

import taichi as ti

from mcl3d.kernels.tsdf_lookup import BLOCK


@ti.kernel
def read_blocks_at(m: ti.template(), ids: ti.types.ndarray(dtype=ti.i32, ndim=1), count: ti.i32,
                   sdf: ti.types.ndarray(dtype=ti.f32, ndim=4),
                   weight: ti.types.ndarray(dtype=ti.f32, ndim=4)):
    """Distances and weights of pool blocks ids[0:count] (a finalized map)."""
    for k, i, j, h in ti.ndrange(count, BLOCK, BLOCK, BLOCK):
        b = ids[k]
        sdf[k, i, j, h] = ti.cast(m.sdf[b, i, j, h], ti.f32)
        weight[k, i, j, h] = ti.cast(m.weight[b, i, j, h], ti.f32)
