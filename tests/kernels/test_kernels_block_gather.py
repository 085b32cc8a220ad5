"""kernels.block_gather: blocks read by pool id in any order, against the host's copy."""

import numpy as np


def test_read_blocks_at_gathers_the_blocks_named(ti_runtime):
    from mcl3d.kernels.block_gather import read_blocks_at
    from mcl3d.maps.tsdf import BLOCK, MapGeometry, TsdfMap

    rng = np.random.default_rng(2)
    geometry = MapGeometry.around(np.zeros(3), np.full(3, 4.0), 0.1, 0.4, margin_m=0.4)
    coords = np.unique(rng.integers(0, 5, (30, 3)), axis=0).astype(np.int32)
    tsdf = TsdfMap(geometry, len(coords), writable=False)
    tsdf.allocate(coords)
    shape = (len(coords), BLOCK, BLOCK, BLOCK)
    tsdf.write_blocks(coords, rng.uniform(-0.4, 0.4, shape).astype(np.float32),
                      rng.uniform(0, 3, shape).astype(np.float32))
    data = tsdf.blocks()
    ids = rng.permutation(len(coords))[:11].astype(np.int32)
    sdf = np.zeros((len(ids), BLOCK, BLOCK, BLOCK), np.float32)
    weight = np.zeros_like(sdf)
    read_blocks_at(tsdf, ids, len(ids), sdf, weight)
    np.testing.assert_array_equal(sdf, data.sdf[ids])
    np.testing.assert_array_equal(weight, data.weight[ids])
