"""Normals and local spacing of a point-cloud map on the device (kernels.point_fusion), the
points sorted by the Morton code of their 5 cm cell (maps.voxel_normals' cells and levels).

The sorted order is kept for the rest of a point build: neighbouring points come next to
each other, so the fusion's one-column bands share voxels within a thread's run. Memory is
a few tens of bytes a point (the codes, their order, the cells of one chunk), never a
k-d tree or a neighbour list.
"""

from __future__ import annotations

import numpy as np

from mcl3d.core.errors import PointCloudError
from mcl3d.kernels import point_fusion, voxel_normals
from mcl3d.maps.voxel_normals import FINE_CELL_M, cell_tables, fits, min_own, morton_codes

CHUNK_POINTS = 1 << 22  # points per launch and per host chunk (under Vulkan's 8M limit)


def fine_cells(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(n, 3) int32 5 cm cells of float32 points counted from origin."""
    return np.floor((points - origin) / np.float32(FINE_CELL_M)).astype(np.int32)


def sorted_normals(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order, normals, spacing_m): the points' Morton order, and per point in that order its
    unit normal (arbitrary sign; zeros where none was found: fewer than 5 neighbours or a
    line) and the spacing of its neighbours (0 where no normal)."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if not fits(pts, k):
        raise PointCloudError(f"the point cloud spans {np.ptp(pts, axis=0).max():.0f} m, more "
                              f"than the normal search reaches, or k={k} is out of range")
    coarsest_m = FINE_CELL_M * (1 << (voxel_normals.LEVEL_SHIFT * (voxel_normals.LEVELS - 1)))
    origin = ((np.floor(pts.min(axis=0) / coarsest_m) - 1.0) * coarsest_m).astype(np.float32)
    codes = np.concatenate([morton_codes(fine_cells(pts[s:s + CHUNK_POINTS], origin))
                            for s in range(0, len(pts), CHUNK_POINTS)])
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    tables = cell_tables(codes)
    del codes
    pts_sorted = pts[order]
    cells = np.concatenate([fine_cells(pts_sorted[s:s + CHUNK_POINTS], origin)
                            for s in range(0, len(pts), CHUNK_POINTS)])
    normals = np.zeros_like(pts_sorted)
    spacing = np.zeros(len(pts), np.float32)
    for s in range(0, len(pts), CHUNK_POINTS):
        point_fusion.normals_and_spacing(pts_sorted, cells, s, min(CHUNK_POINTS, len(pts) - s),
                                         *tables, k, min_own(k), normals, spacing)
    return order, normals, spacing
