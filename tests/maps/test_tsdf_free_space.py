"""Free-space sampling: inside observed free space, uniform, and in a height band."""

import numpy as np
import pytest
from support import tsdf_world as world

from mcl3d.core.errors import ConfigError, MapError


@pytest.fixture
def room_map(ti_runtime):
    from mcl3d.maps.build import BuildConfig, build_from_mesh

    vertices, triangles = world.room_mesh()
    tsdf = build_from_mesh(vertices, triangles, BuildConfig())
    return tsdf, world.scene_of(vertices, triangles)


def _exact(scene, pts):
    return scene.signed_distance(pts, "normals")


def test_samples_lie_in_free_space_uniformly(room_map):
    from scipy.stats import ks_2samp

    from mcl3d.maps.free_space import HostMap, sample_free_space

    tsdf, scene = room_map
    host = HostMap(tsdf)
    rng = np.random.default_rng(0)
    pts = sample_free_space(tsdf, 20000, rng, host=host)
    assert pts.shape == (20000, 3)
    half_diag = 0.5 * np.sqrt(3) * tsdf.voxel_size_m
    assert (_exact(scene, pts) >= tsdf.truncation_m - half_diag).all()
    # NumPy reference: rejection sampling of the bounding box by the voxel state
    lo, hi = tsdf.geometry.extent_m
    cand = rng.uniform(lo, hi, size=(200000, 3))
    d, w = host.voxel_dw(np.floor(host.to_grid(cand)).astype(int))
    ref = cand[(w > 0) & (d >= tsdf.truncation_m * 0.999)]
    assert len(ref) > 20000
    for axis in range(3):
        assert ks_2samp(pts[:, axis], ref[:, axis]).pvalue > 1e-3
    same_seed = sample_free_space(tsdf, 100, np.random.default_rng(7), host=host)
    np.testing.assert_array_equal(same_seed,
                                  sample_free_space(tsdf, 100, np.random.default_rng(7),
                                                    host=host))


def test_height_band_keeps_samples_above_floors(room_map):
    import open3d as o3d

    from mcl3d.maps.free_space import sample_free_space

    tsdf, scene = room_map
    pts = sample_free_space(tsdf, 3000, np.random.default_rng(1), height_band_m=(0.3, 1.2))
    rays = np.concatenate([pts, np.tile([0.0, 0.0, -1.0], (len(pts), 1))], axis=1)
    height = scene.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    v = tsdf.voxel_size_m
    assert np.isfinite(height).all()
    assert (height >= 0.3 - v).all() and (height <= 1.2 + v).all()
    on_box = (np.abs(pts[:, 0] - 1.4) < 0.3) & (np.abs(pts[:, 1] - 1.3) < 0.2)
    assert on_box.any() and (pts[on_box, 2] > 0.9 + 0.3 - v).all()  # above the box top


def test_bad_requests(room_map):
    from mcl3d.maps.free_space import sample_free_space
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf, _ = room_map
    with pytest.raises(ConfigError, match="height band"):
        sample_free_space(tsdf, 10, np.random.default_rng(0), height_band_m=(1.0, 0.5))
    with pytest.raises(MapError, match=r"found only 0 of 10"):
        sample_free_space(tsdf, 10, np.random.default_rng(0), height_band_m=(50.0, 60.0))
    empty = TsdfMap(MapGeometry(0.1, 0.3, (0.0, 0.0, 0.0), (2, 2, 2)), 4)
    with pytest.raises(MapError, match="no observed free space"):
        sample_free_space(empty, 10, np.random.default_rng(0))
