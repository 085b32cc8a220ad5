"""Point-cloud maps: pools sized from the cells the points' bands reach, grown and retried
when short, and slab-by-slab fusion giving the same map as one pass."""

import numpy as np
import pytest
from support import tsdf_world as world

from mcl3d.core.errors import MapError
from mcl3d.maps import build as build_module
from mcl3d.maps import point_build as build
from mcl3d.maps.build import BuildConfig


@pytest.fixture(scope="module")
def samples():
    """Surface samples of the tsdf test room seen from inside, and the viewpoints."""
    vertices, triangles = world.room_mesh()
    pts = world.surface_samples(vertices, triangles, 20000, np.random.default_rng(0))
    return world.seen_from_inside(pts), np.array([T[:3, 3] for T in world.POSES])


def test_band_cells_are_the_blocks_the_fusion_allocates(ti_runtime, samples, monkeypatch):
    pts, viewpoints = samples
    band_cells, seen = build.band_cells, []
    monkeypatch.setattr(build, "band_cells", lambda *a: seen.append(band_cells(*a)) or seen[-1])
    tsdf = build.build_from_points(pts, BuildConfig(voxel_size_m=0.1), viewpoints=viewpoints)
    np.testing.assert_array_equal(seen[0], tsdf.blocks().sorted().coords)


def test_short_pools_grow_and_the_map_is_the_same(ti_runtime, samples, monkeypatch):
    """Pools sized from a third of the cells overflow: they are grown and the allocation runs
    again, giving the same blocks and free cells as pools sized right."""
    pts, viewpoints = samples
    cfg = BuildConfig(voxel_size_m=0.1, capacity_blocks=1)
    want = build.build_from_points(pts, cfg, viewpoints=viewpoints).blocks().sorted()
    band_cells = build.band_cells
    monkeypatch.setattr(build, "band_cells", lambda *a: band_cells(*a)[::3])
    monkeypatch.setattr(build_module, "MIN_BUILD_TILES", 1)
    got = build.build_from_points(pts, cfg, viewpoints=viewpoints).blocks().sorted()
    for field in ("coords", "sdf", "weight", "free_coords"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
    tight = BuildConfig(voxel_size_m=0.1, capacity_blocks=1, max_capacity_blocks=20)
    with pytest.raises(MapError, match="max_capacity_blocks"):
        build.build_from_points(pts, tight, viewpoints=viewpoints)


def test_slab_by_slab_fusion_gives_the_same_map(ti_runtime, samples, monkeypatch):
    """Slabs of at most 40 blocks along x (about a dozen slabs): same blocks, distances,
    weights and free cells, in a read-only map."""
    pts, viewpoints = samples
    cfg = BuildConfig(voxel_size_m=0.1)
    want = build.build_from_points(pts, cfg, viewpoints=viewpoints).blocks().sorted()
    monkeypatch.setattr(build, "SLAB_BLOCKS", 40)
    tsdf = build.build_from_points(pts, cfg, viewpoints=viewpoints)
    assert not tsdf.writable and len(build._slabs(want.coords[:, 0], 40)) > 5
    got = tsdf.blocks().sorted()
    for field in ("coords", "sdf", "weight", "free_coords"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))
