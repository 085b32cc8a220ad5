"""Normals of a scan without a range image (a Livox, a KITTI .bin) on the device
(kernels.voxel_normals): the host sorts the points by Morton code and lists each level's
cells; the device finds each point's k nearest in the cells around it and fits a plane.

Replaces the host's k-nearest-neighbour normals (Open3D's kd-tree, maps/normals.py) in
build-map's `normals: auto` for such scans. Same neighbours where the k nearest lie within
the searched cells. Points whose neighbours lie on a line (one ring's arc, as on a sparse
scan's ground) take the direction across it that the range-image normals take (the vertical
for a level arc), where the host would fit a plane to noise; points with fewer than 5
neighbours get no normal (zeros: fused along the ray).
"""

from __future__ import annotations

import numpy as np

from mcl3d.kernels import voxel_normals
from mcl3d.kernels.scan_grid import MAX_K

FINE_CELL_M = 0.05
SPREAD = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
          (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249))


def morton_codes(cells: np.ndarray) -> np.ndarray:
    """kernels.voxel_normals.morton of (n, 3) non-negative int cells, vectorized: each axis's
    21 bits spread to every third bit by the usual shift-and-mask steps."""
    code = np.zeros(len(cells), np.int64)
    for a in range(3):
        x = cells[:, a].astype(np.int64) & 0x1FFFFF
        for shift, mask in SPREAD:
            x = (x | (x << shift)) & mask
        code |= x << a
    return code


def cell_tables(codes_sorted: np.ndarray) -> tuple[np.ndarray, ...]:
    """Each level's cells as runs of the sorted codes: (keys, starts, ends, offsets), the
    levels one after the other (level l at offsets[l]..offsets[l + 1])."""
    keys, starts, ends, offsets = [], [], [], [0]
    n = len(codes_sorted)
    for level in range(voxel_normals.LEVELS):
        c = codes_sorted >> (3 * voxel_normals.LEVEL_SHIFT * level)
        first = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        keys.append(c[first])
        starts.append(first)
        ends.append(np.r_[first[1:], n])
        offsets.append(offsets[-1] + len(first))
    return (np.concatenate(keys), np.concatenate(starts).astype(np.int32),
            np.concatenate(ends).astype(np.int32), np.asarray(offsets, np.int32))


def sorted_cells(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order, fine cells, their Morton codes), both in that order: the points' fine cells
    counted from an origin one coarsest cell below their minimum (so that every level's
    neighbour cells have non-negative coordinates)."""
    coarsest_m = FINE_CELL_M * (1 << (voxel_normals.LEVEL_SHIFT * (voxel_normals.LEVELS - 1)))
    origin = (np.floor(points.min(axis=0) / coarsest_m) - 1.0) * coarsest_m
    cells = np.floor((points - origin) / FINE_CELL_M).astype(np.int64)
    codes = morton_codes(cells)
    order = np.argsort(codes, kind="stable")
    return order, cells[order], codes[order]


def min_own(k: int) -> int:
    """Points a cell must hold for its level to be searched (about half the neighbours)."""
    return max(k // 2, 1)


def fits(points: np.ndarray, k: int) -> bool:
    """Whether the device search applies: k within its bound and the scan within the
    Morton code's reach."""
    if not 1 <= k <= MAX_K or len(points) == 0:
        return False
    extent = points.max(axis=0) - points.min(axis=0)
    margin = 2 << (voxel_normals.LEVEL_SHIFT * (voxel_normals.LEVELS - 1))  # coarsest cells
    return float(extent.max()) < FINE_CELL_M * ((1 << voxel_normals.MORTON_BITS) - margin)


def voxel_normals_of(points: np.ndarray, k: int) -> np.ndarray:
    """(n, 3) float32 unit normals facing the sensor (the frame's origin), zeros where none
    was found; `fits(points, k)` must hold."""
    pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    order, cells, codes = sorted_cells(pts.astype(np.float64))
    keys, starts, ends, offsets = cell_tables(codes)
    pts_sorted = np.ascontiguousarray(pts[order])
    out = np.zeros_like(pts_sorted)
    voxel_normals.estimate(pts_sorted, cells.astype(np.int32), len(pts), keys, starts, ends,
                           offsets, k, min_own(k), out)
    normals = np.empty_like(out)
    normals[order] = out
    return normals
