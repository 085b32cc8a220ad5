"""Uniform samples of observed free space, for global localization's initial particles.

Free space is every voxel observed at least a truncation away from surfaces: FREE blocks
(512 voxels each) plus free voxels of allocated blocks. Sampling is uniform in volume. For
ground robots, `height_band_m=(lo, hi)` keeps only samples whose floor (the first surface
straight below, seen from above) lies lo..hi metres down; samples above unknown space are
rejected, since their height cannot be told.
"""

from __future__ import annotations

import numpy as np

from mcl3d.core.errors import ConfigError, MapError
from mcl3d.maps.sparse_cells import CellLookup
from mcl3d.maps.tsdf import BLOCK, TsdfMap


class HostMap:
    """A host copy of a map with vectorized nearest-voxel lookups (NumPy reference); its
    coarse cells are sparse lists, memory per known cell."""

    FREE = -3

    def __init__(self, tsdf: TsdfMap):
        self.geometry = tsdf.geometry
        cells, values = tsdf.coarse_cells()
        self.coarse = CellLookup(cells, values, tsdf.coarse_dims)
        self.free_blocks = cells[values == self.FREE]
        self.data = tsdf.blocks()  # block id b is row b (pool order)
        self.trunc = tsdf.truncation_m
        self.dims = np.asarray(tsdf.coarse_dims) * BLOCK

    def voxel_dw(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(d, w) of voxels g (..., 3): unknown/outside -> (trunc, 0), FREE -> (trunc, 1)."""
        g = np.asarray(g, dtype=np.int64)
        shape = g.shape[:-1]
        g = g.reshape(-1, 3)
        d = np.full(len(g), self.trunc, np.float32)
        w = np.zeros(len(g), np.float32)
        inside = np.all((g >= 0) & (g < self.dims), axis=1)
        gi = g[inside]
        b = self.coarse(gi >> 3)
        di = np.full(len(gi), self.trunc, np.float32)
        wi = np.zeros(len(gi), np.float32)
        alloc = b >= 0
        ga = gi[alloc] & 7
        di[alloc] = self.data.sdf[b[alloc], ga[:, 0], ga[:, 1], ga[:, 2]]
        wi[alloc] = self.data.weight[b[alloc], ga[:, 0], ga[:, 1], ga[:, 2]]
        wi[b == self.FREE] = 1.0
        d[inside], w[inside] = di, wi
        return d.reshape(shape), w.reshape(shape)

    def to_grid(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p) - np.asarray(self.geometry.origin_m)) / self.geometry.voxel_size_m

    def free_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower voxel corners and sizes (in voxels) of all free cells (voxels and blocks)."""
        data = self.data
        free = (data.weight > 0) & (data.sdf >= self.trunc * 0.999)
        b, i, j, k = np.nonzero(free)
        vox = data.coords[b].astype(np.int64) * BLOCK + np.stack([i, j, k], axis=1)
        blocks = self.free_blocks.astype(np.int64) * BLOCK
        corners = np.concatenate([vox, blocks])
        sizes = np.concatenate([np.ones(len(vox)), np.full(len(blocks), BLOCK)])
        return corners, sizes


def _floor_depth(host: HostMap, pts: np.ndarray, max_depth_m: float) -> np.ndarray:
    """Distance straight down to the first surface (nan when unknown space or none)."""
    v = host.geometry.voxel_size_m
    g = np.floor(host.to_grid(pts)).astype(np.int64)
    depth = np.full(len(pts), np.nan)
    alive = np.ones(len(pts), bool)
    frac = host.to_grid(pts)[:, 2] - g[:, 2] - 0.5  # height of the point above its voxel centre
    for step in range(int(np.ceil(max_depth_m / v)) + 2):
        q = g.copy()
        q[:, 2] -= step
        d, w = host.voxel_dw(q)
        unknown = alive & (w <= 0)
        alive &= ~unknown
        hit = alive & (d <= 0.0)
        # first voxel at or behind a surface: the surface lies d below its centre
        depth[hit] = (step + frac[hit]) * v + d[hit]
        alive &= ~hit
        if not alive.any():
            break
    return depth


def sample_free_space(tsdf: TsdfMap, n: int, rng: np.random.Generator,
                      height_band_m: tuple[float, float] | None = None,
                      host: HostMap | None = None) -> np.ndarray:
    """(n, 3) points uniform over observed free space (optionally in a height band)."""
    if n < 0:
        raise ConfigError(f"number of free-space samples must be >= 0, got {n}")
    if height_band_m is not None:
        lo, hi = float(height_band_m[0]), float(height_band_m[1])
        if not (0 <= lo < hi):
            raise ConfigError(f"height band must be 0 <= low < high metres, got {height_band_m}")
    host = host or HostMap(tsdf)
    corners, sizes = host.free_cells()
    if len(corners) == 0:
        raise MapError("the map has no observed free space to sample from (built without "
                       "free-space carving, or from a mesh/point cloud with a free margin of 0)")
    volume = sizes**3
    prob = volume / volume.sum()
    v = host.geometry.voxel_size_m
    origin = np.asarray(host.geometry.origin_m)
    out = np.empty((0, 3))
    for attempt in range(100):
        if len(out) >= n or (attempt >= 10 and len(out) == 0):
            break
        batch = max(4 * (n - len(out)), 1024)
        cell = rng.choice(len(corners), size=batch, p=prob)
        pts = origin + (corners[cell] + rng.random((batch, 3)) * sizes[cell, None]) * v
        if height_band_m is not None:
            depth = _floor_depth(host, pts, hi)
            pts = pts[(depth >= lo) & (depth <= hi)]
        out = np.concatenate([out, pts])
    if len(out) < n:
        raise MapError(f"found only {len(out)} of {n} free-space samples with a floor "
                       f"{height_band_m} m below; widen the height band or check the map")
    return out[:n]

