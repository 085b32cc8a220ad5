"""The `.tsdf` map file: a zip of .npy arrays (numpy's npz) with a JSON header.

Members:
- `header` — JSON text: format name and version, geometry (voxel size, truncation, origin,
  coarse dims), frame id, dtypes, block counts, how and from what the map was built, and
  the mcl3d version: the inputs, not the clock (no date, no build time), so that the same
  inputs give the same file, byte for byte (members carry a fixed zip date too);
- `block_coords` (n, 3) int32 — coordinates of the allocated blocks, lexicographic order;
- `sdf` (n, 8, 8, 8) float32 or float16 — signed distance in m at voxel centres, indexed
  [block, x, y, z];
- `weight` (n, 8, 8, 8) same dtype — observation weight, 0 = unknown;
- `free_tiles` (k, 3) int32 and `free_masks` (k, 64) uint8 — blocks observed free of
  surfaces, as tiles of 8³ coarse cells (lexicographic order) with one bit per cell
  (C order, np.packbits' bit order): a kilometre of carved free space costs a few bytes per
  tile instead of 12 per block.

Version 1 (still read, converted on load) stored the free blocks as `free_coords` (k, 3)
int32 instead of the tiles and masks, and had no `coarse_index` in its header.

Zip members carry CRC-32 checksums, so truncated or corrupted files are caught on load.
Only allocated blocks are stored, compressed; unknown space costs nothing.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d import __version__
from mcl3d.core.errors import ConfigError, MapError
from mcl3d.core.outputs import atomic_path
from mcl3d.kernels import block_gather
from mcl3d.maps.sparse_cells import MASK_BYTES, TILE, cells_to_masks, masks_to_cells, tiles_of
from mcl3d.maps.tsdf import BLOCK, CHUNK_BLOCKS, FREE, BlockData, MapGeometry, TsdfMap

FORMAT = "mcl3d-tsdf"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
MEMBERS = {1: ("header", "block_coords", "sdf", "weight", "free_coords"),
           2: ("header", "block_coords", "sdf", "weight", "free_tiles", "free_masks")}
ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # every member's date (the earliest a zip can hold)
COMPRESS_LEVEL = 1  # deflate level of every member


def make_header(tsdf: TsdfMap, n_blocks: int, n_free_blocks: int, source: dict, build: dict,
                f16: bool) -> dict:
    g = tsdf.geometry
    dtype = "float16" if f16 else "float32"
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "mcl3d_version": __version__,
        "frame_id": tsdf.frame_id,
        "voxel_size_m": g.voxel_size_m,
        "truncation_m": g.truncation_m,
        "origin_m": list(g.origin_m),
        "coarse_dims": list(g.coarse_dims),
        "block_size_voxels": BLOCK,
        "distance_dtype": dtype,
        "weight_dtype": dtype,
        "n_blocks": n_blocks,
        "n_free_blocks": n_free_blocks,
        "coarse_index": {"kind": "tiles", "tile_cells": TILE},
        "source": source,
        "build": build,
    }


def save_map(path: Path, tsdf: TsdfMap, *, source: dict, build: dict,
             f16: bool = False) -> dict:
    """Write the map atomically (a temp file renamed over `path`); returns the header.

    Blocks go out in lexicographic order a chunk at a time, read straight from the map
    (`_SortedBlocks`): a city's voxels are never copied to the host whole. Deflate level
    COMPRESS_LEVEL: level 6 (savez's) takes 1.5x the cpu time for members 4 % smaller
    (128 MiB of a city map's distances and weights).
    """
    tsdf.finalize()
    blocks = _SortedBlocks(tsdf, np.float16 if f16 else np.float32)
    header = make_header(tsdf, len(blocks.coords), len(blocks.free_coords), source, build, f16)
    free_tiles, free_masks = cells_to_masks(blocks.free_coords)
    header["n_free_tiles"] = len(free_tiles)
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
        _write_npz(f, {"header": np.array(json.dumps(header)), "block_coords": blocks.coords,
                       "sdf": blocks.member(0), "weight": blocks.member(1),
                       "free_tiles": free_tiles, "free_masks": free_masks})
    return header


class _SortedBlocks:
    """A map's blocks in lexicographic order, each voxel array as a member written in chunks."""

    def __init__(self, tsdf: TsdfMap, dtype):
        self.tsdf, self.dtype = tsdf, np.dtype(dtype)
        coords = tsdf.block_coord.to_numpy()[:tsdf.n_blocks]
        self.ids = (np.lexsort(coords.T[::-1]) if len(coords) else np.arange(0)).astype(np.int32)
        self.coords = coords[self.ids].astype(np.int32)
        cells, values = tsdf.coarse_cells()
        free = cells[values == FREE]
        self.free_coords = free[np.lexsort(free.T[::-1])] if len(free) else free

    def member(self, which: int) -> _Chunks:
        """The distances (0) or weights (1), as chunks in block order."""
        shape = (len(self.ids), BLOCK, BLOCK, BLOCK)
        return _Chunks(shape, self.dtype, lambda: (
            self._read(self.ids[s:s + CHUNK_BLOCKS])[which].astype(self.dtype, copy=False)
            for s in range(0, len(self.ids), CHUNK_BLOCKS)))

    def _read(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sdf = np.empty((len(ids), BLOCK, BLOCK, BLOCK), np.float32)
        weight = np.empty_like(sdf)
        block_gather.read_blocks_at(self.tsdf, ids, len(ids), sdf, weight)
        return sdf, weight


@dataclass
class _Chunks:
    """An array written as consecutive C-order chunks (its .npy header first)."""

    shape: tuple
    dtype: np.dtype
    chunks: Callable[[], Iterator[np.ndarray]]


def _write_npz(f, arrays: dict[str, np.ndarray | _Chunks]) -> None:
    """What np.savez_compressed writes (one deflated .npy per member), but with ZIP_DATE on
    every member instead of the time of writing, so the bytes depend on the arrays alone."""
    with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, array in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            _set_compress_level(info, COMPRESS_LEVEL)
            info.external_attr = 0o600 << 16  # -rw------- as savez gives its members
            with zf.open(info, "w", force_zip64=True) as member:
                if isinstance(array, _Chunks):
                    np.lib.format.write_array_header_1_0(member, {
                        "descr": np.lib.format.dtype_to_descr(array.dtype),
                        "fortran_order": False, "shape": array.shape})
                    for chunk in array.chunks():
                        member.write(np.ascontiguousarray(chunk).data)
                else:
                    np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def _set_compress_level(info: zipfile.ZipInfo, level: int) -> None:
    """A member's deflate level (ZipInfo.compress_level from Python 3.13, before that only
    the private _compresslevel)."""
    if hasattr(type(info), "compress_level"):
        info.compress_level = level
    else:
        info._compresslevel = level


def _open(path: Path):
    path = Path(path)
    if not path.is_file():
        raise MapError(f"map file {path} does not exist")
    if not zipfile.is_zipfile(path):
        raise MapError(f"{path} is not an mcl3d map (.tsdf): not a zip container; it may be "
                       f"truncated or another format")
    try:
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise MapError(f"{path} is truncated or corrupt: {exc}") from exc
    _check_members(path, npz, ("header",))
    return npz


def _check_members(path: Path, npz, names) -> None:
    missing = [m for m in names if m not in npz.files]
    if missing:
        raise MapError(f"{path} lacks the member(s) {', '.join(missing)}; "
                       f"it is not a complete mcl3d map")


def _member(npz, path: Path, name: str) -> np.ndarray:
    try:
        return npz[name]
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        raise MapError(f"{path}: member '{name}' is truncated or corrupt ({exc})") from exc


def _check_header(path: Path, header: dict) -> MapGeometry:
    if header.get("format") != FORMAT:
        raise MapError(f"{path} is not an mcl3d TSDF map (format {header.get('format')!r})")
    version = header.get("format_version")
    if version not in READ_VERSIONS:
        raise MapError(f"{path} has map format version {version}; this mcl3d "
                       f"({__version__}) reads versions 1 and {FORMAT_VERSION}; rebuild the "
                       f"map with `mcl3d build-map` or use a matching mcl3d version")
    for key in ("voxel_size_m", "truncation_m", "origin_m", "coarse_dims", "n_blocks",
                "n_free_blocks", "distance_dtype", "frame_id"):
        if key not in header:
            raise MapError(f"{path}: header lacks '{key}'")
    if version >= 2 and header.get("coarse_index") != {"kind": "tiles", "tile_cells": TILE}:
        raise MapError(f"{path}: unknown coarse index {header.get('coarse_index')!r}, expected "
                       f"tiles of {TILE} cells")
    if header.get("block_size_voxels") != BLOCK:
        raise MapError(f"{path}: block size {header.get('block_size_voxels')} voxels, "
                       f"expected {BLOCK}")
    if header["distance_dtype"] not in ("float32", "float16"):
        raise MapError(f"{path}: unknown distance dtype {header['distance_dtype']!r}")
    try:
        return MapGeometry(float(header["voxel_size_m"]), float(header["truncation_m"]),
                           tuple(float(x) for x in header["origin_m"]),
                           tuple(int(x) for x in header["coarse_dims"]))
    except (TypeError, ValueError, ConfigError) as exc:
        raise MapError(f"{path}: invalid map geometry in header ({exc})") from exc


def read_header(path: Path) -> dict:
    """The header of a map file, validated (without loading the blocks)."""
    npz = _open(path)
    with npz:
        try:
            header = json.loads(str(_member(npz, path, "header")))
        except json.JSONDecodeError as exc:
            raise MapError(f"{path}: the header is not valid JSON ({exc})") from exc
        if not isinstance(header, dict):
            raise MapError(f"{path}: the header is not a JSON object")
        _check_header(path, header)
    return header


def _check_coords(path: Path, name: str, coords: np.ndarray, n: int, dims) -> None:
    if coords.ndim != 2 or coords.shape != (n, 3) or coords.dtype.kind != "i":
        raise MapError(f"{path}: '{name}' has shape {coords.shape} dtype {coords.dtype}; the "
                       f"header says {n} blocks of 3 int coordinates (inconsistent sizes)")
    if n and ((coords.min(axis=0) < 0).any() or (coords.max(axis=0) >= dims).any()):
        raise MapError(f"{path}: '{name}' has block coordinates outside the coarse grid {dims}")
    if n and len(np.unique(coords, axis=0)) != n:
        raise MapError(f"{path}: '{name}' lists a block twice")


def read_blocks(path: Path) -> tuple[dict, MapGeometry, BlockData]:
    """Header, geometry and blocks of a map file, with every size and value checked."""
    path = Path(path)
    header = read_header(path)
    geometry = _check_header(path, header)
    dims = np.asarray(geometry.coarse_dims)
    with _open(path) as npz:
        _check_members(path, npz, MEMBERS[header["format_version"]])
        coords = _member(npz, path, "block_coords")
        sdf = _member(npz, path, "sdf")
        weight = _member(npz, path, "weight")
        free = (_member(npz, path, "free_coords") if header["format_version"] == 1
                else _free_cells(path, header, _member(npz, path, "free_tiles"),
                                 _member(npz, path, "free_masks"), geometry.top_dims))
    n = int(header["n_blocks"])
    _check_coords(path, "block_coords", coords, n, dims)
    _check_coords(path, "free_coords", free, int(header["n_free_blocks"]), dims)
    for name, arr in (("sdf", sdf), ("weight", weight)):
        if arr.shape != (n, BLOCK, BLOCK, BLOCK):
            raise MapError(f"{path}: '{name}' has shape {arr.shape}, expected "
                           f"({n}, {BLOCK}, {BLOCK}, {BLOCK}) (inconsistent sizes)")
        if arr.dtype != np.dtype(header["distance_dtype"]):
            raise MapError(f"{path}: '{name}' is {arr.dtype}, the header says "
                           f"{header['distance_dtype']}")
        if not np.isfinite(arr).all():
            raise MapError(f"{path}: '{name}' contains NaN or inf")
    if n and np.abs(sdf).max() > geometry.truncation_m * 1.01:
        raise MapError(f"{path}: distances exceed the truncation {geometry.truncation_m} m")
    if n and weight.min() < 0:
        raise MapError(f"{path}: negative weights")
    if n and len(free) and (coarse_overlap(coords, free)):
        raise MapError(f"{path}: a block is both allocated and free")
    return header, geometry, BlockData(coords.astype(np.int32), sdf, weight,
                                       free.astype(np.int32))


def _free_cells(path: Path, header: dict, tiles: np.ndarray, masks: np.ndarray,
                top_dims) -> np.ndarray:
    """The FREE cells of a version-2 file, its tiles and masks checked."""
    k = int(header.get("n_free_tiles", -1))
    _check_coords(path, "free_tiles", tiles, k, np.asarray(top_dims))
    if masks.shape != (k, MASK_BYTES) or masks.dtype != np.uint8:
        raise MapError(f"{path}: 'free_masks' has shape {masks.shape} dtype {masks.dtype}, "
                       f"expected ({k}, {MASK_BYTES}) uint8 (inconsistent sizes)")
    return masks_to_cells(tiles, masks)


def coarse_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    both = np.concatenate([a, b]).astype(np.int64)
    return len(np.unique(both, axis=0)) != len(both)


def load_map(path: Path, *, f16: bool | None = None) -> TsdfMap:
    """Load a map file onto the device (Taichi must be started), read-only: distances and
    weights, without the build-time sums.

    `f16` None keeps the file's precision.
    """
    header, geometry, data = read_blocks(path)
    use_f16 = header["distance_dtype"] == "float16" if f16 is None else f16
    n_tiles = len(tiles_of(np.concatenate([data.coords, data.free_coords])))
    tsdf = TsdfMap(geometry, max(len(data.coords), 1), f16=use_f16, writable=False,
                   frame_id=str(header["frame_id"]), capacity_tiles=max(n_tiles, 1))
    tsdf.mark_free(data.free_coords)
    tsdf.allocate(data.coords)
    tsdf.write_blocks(data.coords, data.sdf, data.weight)
    tsdf.header = header
    return tsdf
