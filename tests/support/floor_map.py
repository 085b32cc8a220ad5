"""The likelihood kernels' tiny map: 2x2x2 blocks of 8^3 voxels (a 1.6 m cube) with a floor
plane, one FREE block, one unknown block and a never-observed row of voxels."""

from __future__ import annotations

import numpy as np

VOX = 0.1
TRUNC = 0.3
FLOOR_Z = 0.85


def floor_map():
    """A floor plane at z = FLOOR_Z in blocks (0|1, 0|1, 0|1) except block (1, 1, 1), which
    is FREE; block (1, 1, 0) is unknown; in block (0, 0, 0) the voxels with i == 0 were never
    observed (they hold +truncation, the map's invariant)."""
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf = TsdfMap(MapGeometry(VOX, TRUNC, (0.0, 0.0, 0.0), (2, 2, 2)), 8)
    coords = np.array([[i, j, k] for i in range(2) for j in range(2) for k in range(2)
                       if (i, j, k) not in ((1, 1, 1), (1, 1, 0))], np.int32)
    tsdf.mark_free(np.array([[1, 1, 1]], np.int32))
    tsdf.allocate(coords)
    z = (coords[:, 2, None, None, None] * 8 + np.arange(8)[None, None, None, :] + 0.5) * VOX
    sdf = np.clip(np.broadcast_to(z - FLOOR_Z, (len(coords), 8, 8, 8)), -TRUNC, TRUNC).copy()
    weight = np.ones_like(sdf)
    first = np.flatnonzero((coords == 0).all(axis=1))[0]
    sdf[first, 0], weight[first, 0] = TRUNC, 0.0
    tsdf.write_blocks(coords, sdf.astype(np.float32), weight.astype(np.float32))
    return tsdf
