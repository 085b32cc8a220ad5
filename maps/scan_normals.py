"""Normals of a spinning lidar's scan from its range image, on the device (kernels.scan_normals).

A scan can be read as a range image when its points carry their ring and the rings sweep
the azimuth densely (a Velodyne, an Ouster, a Hesai, a RoboSense: not a Livox, whose few
`line`s draw a rosette). `RangeImageNormals.layout` decides that and sizes the image; scans
that fail it keep the host normals (maps/normals.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import taichi as ti

from mcl3d.kernels import scan_normals

MIN_RINGS = 8  # fewer rings: not a range image (a Livox's lines)
MAX_RINGS = 512
MIN_COLUMNS = 256  # points per ring and turn below this: too sparse for column neighbours
AZIMUTH_BINS = 360  # the share of 1-degree bins holding points: the scan's azimuth coverage
SAMPLE = 4096  # points sampled for the elevation spread
DENSE_RINGS = 32  # this many rings or more: neighbours from two rows each side, else one
GATE_GAPS = 1.0  # neighbours within this many times the window's reach (in row gaps at
GATE_MIN_M = 0.1  # the point's range, one past its farthest row) of the point, plus this


@dataclass(frozen=True)
class ImageLayout:
    """How a scan maps into its range image, and the neighbourhood each normal takes."""

    width: int  # columns over a full turn
    height: int  # rows (ring numbers 0 .. height-1)
    row_reach: int  # rows each side of a point's own in its window
    n_cols: int  # column samples per row
    col_step: int  # columns between them
    gate_per_m: float  # neighbour gate: gate_min_m + gate_per_m * range
    gate_min_m: float


def layout(points: np.ndarray, rings: np.ndarray | None) -> ImageLayout | None:
    """The scan's range-image layout, or None when it is not a spinning lidar's scan."""
    if rings is None or len(rings) != len(points) or len(points) < MIN_RINGS * MIN_COLUMNS:
        return None
    ring = np.asarray(rings)
    if ring.dtype.kind not in "iu" or ring.min() < 0 or ring.max() >= MAX_RINGS:
        return None
    counts = np.bincount(ring.astype(np.int64))
    used = int(np.count_nonzero(counts))
    if used < MIN_RINGS:
        return None
    step = max(1, len(points) // SAMPLE)
    sub = points[::step]
    azimuth = np.arctan2(sub[:, 1], sub[:, 0])
    bins = np.floor((azimuth + np.pi) * (AZIMUTH_BINS / (2 * np.pi))).astype(np.int64)
    coverage = len(np.unique(np.clip(bins, 0, AZIMUTH_BINS - 1))) / AZIMUTH_BINS
    width = round(float(counts.max()) / max(coverage, 1e-3))
    if width < MIN_COLUMNS:
        return None
    r = np.linalg.norm(sub, axis=1)
    ok = r > 0
    elevation = np.arcsin(np.clip(sub[ok, 2] / r[ok], -1, 1))
    lo, hi = np.percentile(elevation, [1, 99]) if len(elevation) else (0.0, 0.0)
    row_gap = max(float(hi - lo) / max(used - 1, 1), 1e-4)
    col_gap = 2 * np.pi / width
    row_reach = 2 if used >= DENSE_RINGS else 1
    # columns as far along the ring as the window's rows reach (isotropic), MAX_COLS at most
    reach = max(1, round(row_reach * row_gap / col_gap))
    n_cols = min(2 * reach + 1, scan_normals.MAX_COLS)
    col_step = max(1, round(reach / (n_cols // 2)))
    return ImageLayout(width, int(ring.max()) + 1, row_reach, n_cols, col_step,
                       GATE_GAPS * (row_reach + 1) * row_gap, GATE_MIN_M)


class RangeImageNormals:
    """Range-image normals of scans (module docstring); the image is allocated once and
    regrown only for a larger one."""

    def __init__(self):
        self._image = None

    def __call__(self, points: np.ndarray, rings: np.ndarray, shape: ImageLayout,
                 share_m: float = 0.0) -> np.ndarray:
        """(n, 3) float32 unit normals facing the sensor, zeros where none was found; with
        share_m > 0 a point within share_m of its neighbour in the middle column of its
        three takes that one's normal (kernels.scan_normals)."""
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        n = len(pts)
        size = shape.width * shape.height
        if self._image is None or self._image.shape[0] < size:
            self._image = ti.ndarray(ti.i32, shape=1 << max(size - 1, 1).bit_length())
        rows = np.ascontiguousarray(rings, dtype=np.int32)
        pixel = np.empty(n, np.int32)
        normals = np.empty((n, 3), np.float32)
        scan_normals.clear_image(self._image, size)
        scan_normals.project(pts, rows, n, shape.width, shape.height, pixel, self._image)
        source = None
        if share_m > 0.0:
            source = np.empty(n, np.int32)
            scan_normals.share_columns(pts, pixel, n, shape.width, self._image, share_m,
                                       source)
        scan_normals.estimate(pts, pixel, n, shape.width, shape.height, self._image,
                              shape.row_reach, shape.n_cols, shape.col_step, shape.gate_per_m,
                              shape.gate_min_m, normals)
        if source is not None:
            scan_normals.copy_shared(pts, source, n, normals)
        return normals
