"""Maps of other sizes and origins share their compiled kernels (maps.tsdf.field_slots):
the geometry is read at run time and a writable map's fields come in power-of-two sizes,
so Taichi's offline cache serves a second map's kernels without compiling them again."""

import os
import subprocess
import sys
from pathlib import Path

# a small map in a fresh process: allocate blocks and free cells, write, read back
SCRIPT = """
import sys
import numpy as np
from mcl3d.core import runtime
runtime.init("cpu")
from mcl3d.maps.tsdf import MapGeometry, TsdfMap
dims = tuple(int(x) for x in sys.argv[1:4])
origin = tuple(float(x) for x in sys.argv[4:7])
tsdf = TsdfMap(MapGeometry(0.1, 0.3, origin, dims), int(sys.argv[7]))
coords = np.array([[0, 0, 0], [1, 1, 1], [dims[0] - 1, 0, 1]], np.int32)
tsdf.allocate(coords)
tsdf.mark_free(np.array([[1, 0, 0]], np.int32))
sdf = np.full((3, 8, 8, 8), 0.05, np.float32)
tsdf.write_blocks(coords, sdf, np.full_like(sdf, 2.0))
data = tsdf.blocks().sorted()
print(len(data.coords), len(data.free_coords), float(np.abs(data.sdf - 0.05).max()))
"""


def _cache_files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()
            and p.suffix != ".tcb" and "lock" not in p.name}


def _run_map(cache: Path, dims, origin, capacity: int) -> str:
    env = {**os.environ, "TI_OFFLINE_CACHE_FILE_PATH": str(cache)}
    args = [str(x) for x in (*dims, *origin, capacity)]
    out = subprocess.run([sys.executable, "-c", SCRIPT, *args], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_writable_maps_of_other_sizes_have_the_same_fields(ti_runtime):
    from mcl3d.maps.tsdf import MIN_POOL_SLOTS, MapGeometry, TsdfMap, field_slots

    small = TsdfMap(MapGeometry(0.1, 0.3, (0.0, 0.0, 0.0), (4, 3, 2)), 16)
    large = TsdfMap(MapGeometry(0.1, 0.3, (-3.2, 1.0, 7.5), (90, 31, 17)), 900)
    for name in ("sdf", "weight", "free_hits", "block_coord", "tile_of", "tile_flag",
                 "cells", "tile_coord"):
        assert getattr(small, name).shape == getattr(large, name).shape, name
    assert small.sdf.shape[0] == MIN_POOL_SLOTS and large.capacity == 900
    loaded = TsdfMap(MapGeometry(0.1, 0.3, (0.0, 0.0, 0.0), (4, 3, 2)), 5, writable=False)
    assert loaded.sdf.shape[0] == 5  # read-only maps spend no memory on it
    assert [field_slots(n, 4, True) for n in (1, 4, 5, 1024, 1025)] == [4, 4, 8, 1024, 2048]
    for tsdf in (small, large, loaded):
        tsdf.destroy()


def test_a_map_of_another_size_compiles_no_kernel(tmp_path):
    cache = tmp_path / "kernels"
    first = _run_map(cache, (4, 3, 2), (0.0, 0.0, 0.0), 16)
    compiled = _cache_files(cache)
    assert len(compiled) >= 8  # the map's kernels, compiled by the first process
    second = _run_map(cache, (30, 7, 5), (-12.5, 3.25, -1.0), 700)
    assert _cache_files(cache) == compiled  # every kernel came from the cache
    for out in (first, second):
        n_blocks, n_free, err = out.split()
        assert (int(n_blocks), int(n_free)) == (3, 1) and float(err) < 1e-6
