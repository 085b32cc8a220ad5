"""The former coarse search field, a dense grid of codes over the map's bounds, kept as the
reference of the sparse one (mcl3d.localization.coarse_field): the same codes wherever the
dense grid could be allocated."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt


def dense_factor(tsdf, cfg) -> int:
    """The former cell size rule: coarse_cell_m, coarsened while the bounds held more than
    MAX_COARSE_CELLS cells."""
    from mcl3d.localization.coarse_field import MAX_COARSE_CELLS, finest_factor

    f = finest_factor(tsdf.voxel_size_m, cfg)
    while f < 8 and tsdf.geometry.n_cells * (8 // f) ** 3 > MAX_COARSE_CELLS:
        f *= 2
    return f


def dense_codes(tsdf, cfg, f: int | None = None) -> tuple[np.ndarray, float]:
    """(codes (X, Y, Z) int32 over the bounds, cell m): the former implementation, cells of
    f voxels (default: the former rule)."""
    from mcl3d.localization.coarse_field import COARSE_BINS

    f = dense_factor(tsdf, cfg) if f is None else f
    k = 8 // f
    cell = tsdf.voxel_size_m * f
    dims = np.asarray(tsdf.coarse_dims) * k
    observed = np.zeros(dims, bool)
    surface = np.zeros(dims, bool)
    data = tsdf.blocks()
    for c in data.free_coords:
        observed[c[0] * k:(c[0] + 1) * k, c[1] * k:(c[1] + 1) * k, c[2] * k:(c[2] + 1) * k] = True
    if len(data.coords):
        shape = (len(data.coords), k, f, k, f, k, f)
        trunc = np.float32(tsdf.truncation_m)
        obs = (data.weight > 0) | (data.sdf < trunc * np.float32(0.999))
        surf = obs & (np.abs(data.sdf) <= np.float32(0.5 * np.sqrt(3) * tsdf.voxel_size_m))
        ii = np.arange(k)
        g = [data.coords[:, a, None, None, None] * k + np.meshgrid(ii, ii, ii, indexing="ij")[a]
             for a in range(3)]
        observed[g[0], g[1], g[2]] = obs.reshape(shape).any(axis=(2, 4, 6))
        surface[g[0], g[1], g[2]] = surf.reshape(shape).any(axis=(2, 4, 6))
    if surface.any():
        dist = distance_transform_edt(~surface, sampling=cell).astype(np.float32)
    else:
        dist = np.full(dims, np.inf, np.float32)
    near = dist < cfg.coarse_max_dist_m
    codes = np.where(near, np.minimum(dist * (COARSE_BINS / cfg.coarse_max_dist_m),
                                      COARSE_BINS - 1), 0).astype(np.int32)
    codes[~near & observed] = COARSE_BINS
    codes[~near & ~observed] = COARSE_BINS + 1
    return codes, float(cell)


def dense_with_margin(codes: np.ndarray, margin: int) -> np.ndarray:
    """The dense codes padded by `margin` cells of the unknown code (outside the bounds)."""
    from mcl3d.localization.coarse_field import COARSE_UNKNOWN

    return np.pad(codes, margin, constant_values=COARSE_UNKNOWN)


def sparse_over_bounds(field, margin: int) -> np.ndarray:
    """The sparse field's codes at every cell of its bounds plus `margin` cells around."""
    dims = np.asarray(field.coarse_dims) * field.cells_per_block
    g = np.stack(np.meshgrid(*[np.arange(-margin, d + margin) for d in dims], indexing="ij"),
                 axis=-1)
    return field.codes_at(g)
