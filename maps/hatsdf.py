"""Import of tsdf_localization / HATSDF maps (HDF5), behind the optional `h5py` extra.

Layout (uos/tsdf_localization `util/tsdf.h`, `map/map_util.h`): group `/map`, one dataset
per chunk named "x_y_z" (chunk indices, may be negative), each 64³ `uint32` entries
indexed 64·64·i + 64·j + k, an entry packing `int16 value` (low half, millimetres) and
`int16 weight` (high half). Voxels are 64 mm, grid point i sits at i · 64 mm, truncation
600 mm; weight 0 means unobserved.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, MapError
from mcl3d.maps.sparse_cells import tiles_of
from mcl3d.maps.tsdf import BLOCK, MapGeometry, TsdfMap

CHUNK = 64
VOXEL_M = 0.064
TRUNCATION_M = 0.6
_NAME = re.compile(r"^(-?\d+)_(-?\d+)_(-?\d+)$")


def _h5py():
    try:
        import h5py
    except ImportError as exc:
        raise InputError("reading HDF5 (HATSDF) maps needs h5py: pip install 'mcl3d[h5]'"
                         ) from exc
    return h5py


def read_hatsdf_chunks(path: Path) -> dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]]:
    """{chunk index: (value_m (64,64,64) f32, weight (64,64,64) f32)} from the file."""
    h5py = _h5py()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise MapError(f"{path} is not a readable HDF5 file ({exc})") from exc
    chunks = {}
    with f:
        if "map" not in f:
            raise MapError(f"{path}: no group '/map'; not a tsdf_localization/HATSDF map "
                           f"(groups: {', '.join(f.keys()) or 'none'})")
        for name, ds in f["map"].items():
            match = _NAME.match(name)
            if match is None:
                continue  # e.g. "<tag>_int" companions written by some HATSDF versions
            raw = np.asarray(ds[()])
            if raw.size != CHUNK**3 or raw.dtype.itemsize != 4:
                raise MapError(f"{path}: dataset /map/{name} has {raw.size} entries of "
                               f"{raw.dtype}; expected {CHUNK}³ 32-bit entries")
            packed = raw.astype(np.uint32).reshape(CHUNK, CHUNK, CHUNK)
            value = (packed & 0xFFFF).astype(np.uint16).view(np.int16).astype(np.float32)
            weight = (packed >> 16).astype(np.uint16).view(np.int16).astype(np.float32)
            chunks[tuple(int(x) for x in match.groups())] = (value * 1e-3, weight)
    if not chunks:
        raise MapError(f"{path}: '/map' holds no chunk datasets named x_y_z")
    return chunks


def import_hatsdf(path: Path, truncation_m: float = TRUNCATION_M, frame_id: str = "map"
                  ) -> TsdfMap:
    """A TSDF from a HATSDF file: 64 mm voxels, observed voxels kept, free blocks collapsed."""
    chunks = read_hatsdf_chunks(path)
    keys = np.array(sorted(chunks), dtype=np.int64)
    lo_vox = keys.min(axis=0) * CHUNK
    hi_vox = (keys.max(axis=0) + 1) * CHUNK
    # our voxel centres sit on their grid points: origin = lo * 64 mm - 32 mm
    dims = tuple(int(x) for x in np.ceil((hi_vox - lo_vox) / BLOCK))
    origin = tuple(float(x) for x in lo_vox * VOXEL_M - 0.5 * VOXEL_M)
    geometry = MapGeometry(VOXEL_M, truncation_m, origin, dims)
    per_chunk = CHUNK // BLOCK
    coords, sdf, weight, free = [], [], [], []
    for key in map(tuple, keys):
        value, w = chunks[key]
        base = (np.asarray(key) * CHUNK - lo_vox) // BLOCK
        v = np.clip(value, -truncation_m, truncation_m)
        v = v.reshape(per_chunk, BLOCK, per_chunk, BLOCK, per_chunk, BLOCK)
        v = v.transpose(0, 2, 4, 1, 3, 5).reshape(-1, BLOCK, BLOCK, BLOCK)
        ww = w.reshape(per_chunk, BLOCK, per_chunk, BLOCK, per_chunk, BLOCK)
        ww = np.maximum(ww.transpose(0, 2, 4, 1, 3, 5).reshape(-1, BLOCK, BLOCK, BLOCK), 0)
        local = np.argwhere(np.ones((per_chunk,) * 3, bool))
        observed = (ww > 0).reshape(len(ww), -1)
        all_free = observed.all(axis=1) & (v.reshape(len(v), -1) >= truncation_m).all(axis=1)
        keep = observed.any(axis=1) & ~all_free
        coords.append(base + local[keep])
        free.append(base + local[all_free])
        sdf.append(np.where(ww[keep] > 0, v[keep], truncation_m))
        weight.append(ww[keep])
    coords, free = np.concatenate(coords).astype(np.int32), np.concatenate(free)
    tsdf = TsdfMap(geometry, max(len(coords), 1), writable=False, frame_id=frame_id,
                   capacity_tiles=max(len(tiles_of(np.concatenate([coords, free]))), 1))
    tsdf.mark_free(free)
    tsdf.allocate(coords)
    tsdf.write_blocks(coords, np.concatenate(sdf), np.concatenate(weight))
    return tsdf
