"""Gaussian voxel maps (kernels/voxel_hash.py) against NumPy references on tiny inputs."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError, MapError, PointCloudError
from mcl3d.core.geometry import random_rotations, se3, transform_points


def reference_voxels(points, covs, res):
    """Mean of the points and mean of the covariances per voxel, sorted by mean."""
    keys = np.floor(points / res).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    means = np.array([points[inverse == i].mean(0) for i in range(inverse.max() + 1)])
    avg = np.array([covs[inverse == i].mean(0) for i in range(inverse.max() + 1)])
    order = np.lexsort(means.T)
    return means[order], avg[order]


def sorted_voxels(maps, map_id):
    means, covs = maps.voxels(map_id)
    order = np.lexsort(means.T)
    return means[order], covs[order]


def random_cloud(rng, n, extent=3.0, offset=0.0):
    pts = rng.uniform(-extent, extent, (n, 3)) + offset
    A = rng.normal(size=(n, 3, 3))
    return pts, A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(3)


@pytest.fixture(scope="module")
def maps(backend):
    from mcl3d.core import runtime
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    runtime.init(backend)
    return GaussianVoxelMaps(max_maps=3, buckets_per_map=1 << 11, max_points=700, max_probes=32)


def test_mean_and_averaged_covariance_match_numpy(maps):
    rng = np.random.default_rng(0)
    pts, covs = random_cloud(rng, 2000, offset=100.0)  # far from the origin: offsets keep f32 exact
    maps.clear(0, 0.7)
    count = maps.insert(0, pts, covs)  # 2000 points in 700-point chunks
    ref_means, ref_covs = reference_voxels(pts, covs, 0.7)
    means, vcovs = sorted_voxels(maps, 0)
    assert count == len(ref_means) == maps.num_voxels(0)
    np.testing.assert_allclose(means, ref_means, atol=2e-5)
    np.testing.assert_allclose(vcovs, ref_covs, rtol=1e-5, atol=1e-5)


def test_incremental_insert_with_pose_equals_one_insert(maps):
    rng = np.random.default_rng(1)
    pts, covs = random_cloud(rng, 900)
    T = se3(random_rotations(rng, 1)[0], [1.0, -2.0, 0.5])
    R = T[:3, :3]
    maps.clear(1, 0.5)
    maps.insert(1, pts[:400], covs[:400], T)
    maps.insert(1, pts[400:], covs[400:], T)
    world = transform_points(T, pts)
    ref_means, ref_covs = reference_voxels(world, R @ covs @ R.T, 0.5)
    means, vcovs = sorted_voxels(maps, 1)
    np.testing.assert_allclose(means, ref_means, atol=2e-5)
    np.testing.assert_allclose(vcovs, ref_covs, rtol=1e-4, atol=1e-4)


def test_overlap_is_the_fraction_in_any_map(maps):
    rng = np.random.default_rng(2)
    a, ca = random_cloud(rng, 300, extent=1.0)
    b, cb = random_cloud(rng, 300, extent=1.0, offset=10.0)
    maps.clear(0, 0.5)
    maps.insert(0, a, ca)
    maps.clear(2, 0.5)
    maps.insert(2, b, cb)
    query = np.vstack([a[:50], b[:30], a[:20] + 50.0])  # 80 of 100 land in a voxel
    shift = se3(np.eye(3), [0.0, 0.0, 0.0])
    assert maps.overlap(query, [0], [shift]) == pytest.approx(0.5)
    assert maps.overlap(query, [0, 2], [shift, shift]) == pytest.approx(0.8)
    moved = se3(np.eye(3), [50.0, 0.0, 0.0])  # map 2 seen from a frame 50 m away
    assert maps.overlap(b[:10] - [50.0, 0, 0], [2], [moved]) == pytest.approx(1.0)


def test_device_rows_insert_and_overlap_equal_the_host_ones(maps):
    """insert_rows / overlap_of read points already on the device (a GICP source pool):
    plane rows (n, α, β) and upper triangles give the same voxels as insert()."""
    import taichi as ti

    from mcl3d.registration.preprocess import plane_rows_to_covs

    rng = np.random.default_rng(4)
    pts = rng.uniform(-2, 2, (500, 3))
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    plane = np.c_[n, np.ones(500), np.full(500, -0.999), np.zeros(500)]
    covs = plane_rows_to_covs(plane)
    field_pts = ti.Vector.field(3, ti.f32, 500)
    field_rows = ti.Vector.field(6, ti.f32, 500)
    field_pts.from_numpy(pts.astype(np.float32))
    T = se3(random_rotations(rng, 1)[0], [0.3, -0.2, 1.0])
    iu, ju = np.triu_indices(3)
    for rows, is_plane in ((plane, True), (covs[:, iu, ju], False)):
        field_rows.from_numpy(np.c_[rows, np.zeros((500, 6 - rows.shape[1]))].astype(np.float32))
        maps.clear(0, 0.6)
        maps.insert(0, pts, covs, T)
        maps.clear(1, 0.6)
        maps.insert_rows(1, field_pts, field_rows, 500, is_plane, T)
        for host, device in zip(sorted_voxels(maps, 0), sorted_voxels(maps, 1), strict=True):
            np.testing.assert_allclose(device, host, atol=1e-5)
    assert maps.overlap_of(field_pts, 500, [1, 0], [T, T]) == 1.0
    shifted = [T @ se3(np.eye(3), [1.5, 0.0, 0.0])]  # part of the cloud leaves the map
    fraction = maps.overlap_of(field_pts, 500, [1], shifted)
    assert 0.2 < fraction < 0.9 and fraction == maps.overlap(pts, [1], shifted)
    with pytest.raises(ConfigError, match="at most"):
        maps.insert_rows(1, field_pts, field_rows, 701, True)


def test_overlaps_of_counts_each_map_on_its_own(maps):
    """overlaps_of (kernels/voxel_hash.count_hits_each) against a NumPy count: per map, the
    share of every stride-th device point whose voxel that map holds, serial or not."""
    import taichi as ti

    rng = np.random.default_rng(6)
    a, ca = random_cloud(rng, 300, extent=2.0)
    b, cb = random_cloud(rng, 300, extent=2.0, offset=3.0)
    maps.clear(0, 0.5)
    maps.insert(0, a, ca)
    maps.clear(2, 0.8)
    maps.insert(2, b, cb)
    query = np.vstack([a[:100], b[:100]]) + rng.normal(0.0, 0.2, (200, 3))
    query = np.vstack([query, rng.uniform(-3.0, 6.0, (201, 3))])
    field_pts = ti.Vector.field(3, ti.f32, len(query))
    field_pts.from_numpy(query.astype(np.float32))
    poses = [np.eye(4), se3(random_rotations(rng, 1)[0], [0.4, -0.3, 0.2])]

    def reference(stride):
        out = []
        for cloud, res, T in ((a, 0.5, poses[0]), (b, 0.8, poses[1])):
            held = {tuple(k) for k in np.floor(cloud / res).astype(np.int64)}
            keys = np.floor(transform_points(T, query[::stride]) / res).astype(np.int64)
            out.append(np.mean([tuple(k) in held for k in keys]))
        return out

    for stride in (1, 3):
        got = maps.overlaps_of(field_pts, len(query), [0, 2], poses, stride)
        np.testing.assert_allclose(got, reference(stride), atol=1.5 / len(query))
        assert got.min() > 0.05 and got.max() < 0.95  # neither empty nor full: a real test
    with pytest.MonkeyPatch.context() as mp:  # the parallel path gives the same counts
        mp.setattr("mcl3d.registration.gaussian_voxels.SERIAL_LOOKUPS", 0)
        np.testing.assert_array_equal(maps.overlaps_of(field_pts, len(query), [0, 2], poses),
                                      maps.overlaps_of(field_pts, len(query), [0, 2], poses, 1))
    assert maps.overlaps_of(field_pts, len(query), [2], poses[1:])[0] == \
        maps.overlap_of(field_pts, len(query), [2], poses[1:])
    with pytest.raises(ConfigError, match="stride"):
        maps.overlaps_of(field_pts, len(query), [0], poses[:1], 0)


def test_full_map_raises_a_clear_error(ti_runtime):
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    small = GaussianVoxelMaps(max_maps=1, buckets_per_map=16, max_points=64, max_probes=4)
    small.clear(0, 1.0)
    pts = np.stack(np.meshgrid(np.arange(5), np.arange(5), [0]), -1).reshape(-1, 3) + 0.5
    with pytest.raises(MapError, match="buckets_per_map"):
        small.insert(0, pts, np.tile(np.eye(3), (len(pts), 1, 1)))


def test_keys_pack_the_whole_coordinate_range(maps):
    """Cells at both ends of the ±2^20 packable range are stored and found apart; a point
    beyond it is refused with a clear error instead of aliasing onto another cell."""
    edge = np.array([[-1048575.5, 3.5, -2.5], [1048574.5, -1048575.5, 0.5], [-0.5, -0.5, 0.5]])
    maps.clear(2, 1.0)
    assert maps.insert(2, edge, np.tile(np.eye(3), (3, 1, 1))) == 3
    means, _ = sorted_voxels(maps, 2)
    np.testing.assert_array_equal(means, edge[np.lexsort(edge.T)])
    assert maps.overlap(edge, [2], [np.eye(4)]) == 1.0
    assert maps.overlap(edge + np.array([0.0, 1.0, 0.0]), [2], [np.eye(4)]) == 0.0
    with pytest.raises(MapError, match="2\\^20 voxels"):
        maps.insert(2, np.array([[1048576.5, 0.0, 0.0]]), np.eye(3)[None])


def test_bad_input_is_rejected(maps):
    maps.clear(0, 1.0)
    with pytest.raises(PointCloudError, match="NaN"):
        maps.insert(0, np.array([[0.0, np.nan, 1.0]]), np.eye(3)[None])
    with pytest.raises(PointCloudError, match="covs"):
        maps.insert(0, np.zeros((2, 3)), np.eye(3)[None])
    with pytest.raises(ConfigError, match="map id"):
        maps.clear(5, 1.0)
    with pytest.raises(ConfigError, match="voxel_size_m"):
        maps.clear(0, 0.0)
    with pytest.raises(ConfigError, match="power of two"):
        type(maps)(buckets_per_map=1000)
