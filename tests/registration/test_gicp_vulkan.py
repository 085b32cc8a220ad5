"""Batched GICP and its voxel maps give the same numbers on Vulkan (Mesa's lavapipe in CI) as
on cpu.

Two GICP failures this catches, both silent: summing a pose's chunk sums with `acc[g] +=`
in a loop kept only some chunks (125 of 297 inliers), and an overlap counted by one thread per
pose lost lookups after a few thousand of them (18 of 241 hits)."""

import numpy as np
import pytest
from test_gicp import RES, corner_world

from mcl3d.core.geometry import se3, so3_exp

pytestmark = pytest.mark.vulkan


def _run(backend):
    """One linearization of four poses in chunks of 64 points, and their overlap with two
    maps (one seen from a frame 10 m away), on `backend`."""
    from mcl3d.core import runtime
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    runtime.init(backend)
    target, target_covs = corner_world(np.random.default_rng(7))
    T_shift = se3(so3_exp(np.array([0.0, 0.0, 0.3])), [10.0, 0.0, 0.0])
    maps = GaussianVoxelMaps(max_maps=2, buckets_per_map=1 << 9, max_points=1024)
    maps.clear(0, RES)
    maps.insert(0, target, target_covs)
    maps.clear(1, RES)
    maps.insert(1, target, target_covs, T_shift)
    source, source_covs = corner_world(np.random.default_rng(8), 60)
    gicp = BatchGicp(maps, max_groups=4, max_source_points=512)
    gicp.set_source(source, source_covs)
    poses = np.stack([se3(so3_exp([0.0, 0.0, 0.02 * g]), [0.4 * g, 0.1, 0.0])
                      for g in range(4)])
    gicp.set_problem(poses, row_group=np.arange(4), row_map=np.zeros(4))
    gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0, chunk=64)
    return gicp.result(overlap_maps=[1, 0], overlap_T_left=np.stack([T_shift, np.eye(4)]))


def test_batched_gicp_on_cpu_and_vulkan_agree(on_vulkan):
    vk = on_vulkan(_run)
    cpu = _run("cpu")
    assert (cpu.num_inliers > 200).all()
    np.testing.assert_array_equal(vk.num_inliers, cpu.num_inliers)
    np.testing.assert_allclose(vk.error, cpu.error, rtol=1e-4)
    np.testing.assert_allclose(vk.H, cpu.H, rtol=1e-3, atol=1e-4 * np.abs(cpu.H).max())
    np.testing.assert_allclose(vk.b, cpu.b, rtol=1e-3, atol=1e-3 * np.abs(cpu.b).max())
    assert cpu.overlap.min() > 0.7
    np.testing.assert_allclose(vk.overlap, cpu.overlap, atol=1.5 / 300)


def _voxel_means(backend, points):
    from mcl3d.core import runtime
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    runtime.init(backend)
    maps = GaussianVoxelMaps(max_maps=1, buckets_per_map=1 << 12, max_points=len(points))
    maps.clear(0, 1.0)
    maps.insert(0, points, np.tile(np.eye(3), (len(points), 1, 1)))
    means, _ = maps.voxels(0)
    return means[np.lexsort(means.T)]


def test_a_large_insert_adds_every_point_on_vulkan(on_vulkan):
    """100,000 points in one insert: every one reaches its voxel's mean on Vulkan too (the
    ordered sums once ran in one launch, and lavapipe stopped that loop at 65,535 points)."""
    points = np.random.default_rng(1).uniform(0.0, 10.0, (100000, 3))
    cpu = _voxel_means("cpu", points)
    assert len(cpu) == 1000
    np.testing.assert_allclose(on_vulkan(_voxel_means, points), cpu, atol=1e-4)
