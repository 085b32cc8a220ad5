"""Coarse cells on the host as sparse lists (NumPy only): what the maps' host users look up
instead of a dense copy of the coarse grid, which a kilometre-scale map cannot afford (the
device index is sparse too: mcl3d.maps.tsdf).

Tiles of TILE^3 coarse cells group cells for the file format's FREE masks (mcl3d.maps.map_file)
and for sizing the device's tile pool.
"""

from __future__ import annotations

import numpy as np

TILE = 8  # mcl3d.kernels.tsdf_lookup.TILE
UNKNOWN = -1  # mcl3d.kernels.tsdf_lookup.UNKNOWN
MASK_BYTES = TILE**3 // 8


def cell_keys(coords: np.ndarray, dims) -> np.ndarray:
    """One int64 per cell of a grid of `dims` (row-major), for sorting and searching."""
    c = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    return (c[:, 0] * int(dims[1]) + c[:, 1]) * int(dims[2]) + c[:, 2]


def unique_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted distinct values of an int array: sort and keep the first of each run
    (NumPy 2.4's np.unique takes a hash path for plain integer arrays that is ~100x slower:
    28 s instead of 0.2 s for 7 M keys)."""
    k = np.sort(np.asarray(keys).reshape(-1))
    return k[np.r_[True, k[1:] != k[:-1]]] if len(k) else k


class CellLookup:
    """Values of the listed coarse cells (block ids, FREE, ...), UNKNOWN for every other
    cell and outside `dims`: a binary search in the sorted keys, memory per listed cell."""

    def __init__(self, coords: np.ndarray, values: np.ndarray, dims):
        self.dims = np.asarray(dims, dtype=np.int64)
        keys = cell_keys(coords, self.dims)
        order = np.argsort(keys, kind="stable")
        self.keys = keys[order]
        self.values = np.asarray(values, dtype=np.int32).reshape(-1)[order]

    def __call__(self, coords: np.ndarray) -> np.ndarray:
        """Values of cells (..., 3) (any int dtype)."""
        c = np.asarray(coords, dtype=np.int64)
        shape = c.shape[:-1]
        c = c.reshape(-1, 3)
        inside = np.all((c >= 0) & (c < self.dims), axis=1)
        out = np.full(len(c), UNKNOWN, np.int32)
        if len(self.keys):
            keys = cell_keys(np.where(inside[:, None], c, 0), self.dims)
            pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
            hit = inside & (self.keys[pos] == keys)
            out[hit] = self.values[pos[hit]]
        return out.reshape(shape)


def _unique_rows(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of non-negative int coordinates (n, 3), lexicographic, and each row's
    index among them: through one int64 key per row (np.unique(axis=0) is far slower)."""
    if len(c) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    dims = c.max(axis=0) + 1
    keys, inverse = np.unique(cell_keys(c, dims), return_inverse=True)
    rows = np.stack([keys // (dims[1] * dims[2]), (keys // dims[2]) % dims[1], keys % dims[2]],
                    axis=1)
    return rows, inverse.reshape(-1)


def tiles_of(coords: np.ndarray) -> np.ndarray:
    """The distinct tiles (k, 3) int32 holding the given cells (lexicographic order)."""
    c = np.asarray(coords, dtype=np.int64).reshape(-1, 3) >> 3
    return _unique_rows(c)[0].astype(np.int32)


def cells_to_masks(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells (non-negative) as (tiles (k, 3) int32, masks (k, 64) uint8): bit (x, y, z)
    of a tile's mask, in C order and np.packbits' bit order, is set for each listed cell of
    the tile."""
    c = np.asarray(coords, dtype=np.int64).reshape(-1, 3)
    tiles, inverse = _unique_rows(c >> 3)
    bits = np.zeros((len(tiles), TILE**3), bool)
    local = c & (TILE - 1)
    bits[inverse, (local[:, 0] * TILE + local[:, 1]) * TILE + local[:, 2]] = True
    return tiles.astype(np.int32).reshape(-1, 3), np.packbits(bits, axis=1)


def masks_to_cells(tiles: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """The cells (n, 3) int32 that `cells_to_masks` packed, tile by tile in C order."""
    bits = np.unpackbits(np.asarray(masks, dtype=np.uint8).reshape(-1, MASK_BYTES), axis=1)
    t, flat = np.nonzero(bits)
    local = np.stack([flat // (TILE * TILE), (flat // TILE) % TILE, flat % TILE], axis=1)
    return (np.asarray(tiles, dtype=np.int64).reshape(-1, 3)[t] * TILE + local).astype(np.int32)


def dilate_cells(coords: np.ndarray, radius: int, dims) -> np.ndarray:
    """Cells (n, 3) within `radius` cells (a cube) of the given ones (inside `dims`), inside
    `dims`: three separable passes over the sparse list, never a dense grid."""
    dims = np.asarray(dims, dtype=np.int64)
    keys = unique_keys(cell_keys(coords, dims))
    strides = np.array([dims[1] * dims[2], dims[2], 1], np.int64)
    for axis in range(3):
        if radius <= 0 or len(keys) == 0:
            break
        along = (keys // strides[axis]) % dims[axis]
        parts = []
        for k in range(-radius, radius + 1):
            ok = (along + k >= 0) & (along + k < dims[axis])
            parts.append(keys[ok] + k * strides[axis])
        keys = unique_keys(np.concatenate(parts))
    return np.stack([keys // strides[0], (keys // strides[1]) % dims[1], keys % dims[2]],
                    axis=1).astype(np.int32)
