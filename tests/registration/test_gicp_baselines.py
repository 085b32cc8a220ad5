"""bench/gicp_baselines.py, the batched-GICP bench's baseline, computes what kernels/gicp.py
computes: the bench's speed ratios compare the same arithmetic."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mcl3d.core.geometry import se3, so3_exp

pytest.importorskip("numba", reason="the bench baselines need numba: pip install -e '.[test]'")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import gicp_baselines as gb
from test_gicp import RES, corner_world


def test_numpy_baseline_matches_the_kernel_on_shared_and_own_maps(ti_runtime):
    from mcl3d.registration.batch_gicp import BatchGicp, plane_form
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps

    rng = np.random.default_rng(3)
    target, target_covs = corner_world(rng)
    source, source_covs = corner_world(np.random.default_rng(4), 40)
    maps = GaussianVoxelMaps(max_maps=3, buckets_per_map=1 << 9, max_points=1024)
    base = gb.VoxelMaps(RES, 1 << 9, 3)
    for k in range(3):  # map k: a different 80% of the target
        keep = rng.random(len(target)) < 0.8
        maps.clear(k, RES)
        maps.insert(k, target[keep], target_covs[keep])
        base.insert(k, target[keep], target_covs[keep])
        assert maps.num_voxels(k) == base.num_voxels[k]
    base.finish()
    poses = np.stack([se3(so3_exp(0.05 * rng.normal(size=3)), 0.2 * rng.normal(size=3))
                      for _ in range(6)])
    map_of = np.array([0, 0, 1, 1, 2, 2])
    gicp = BatchGicp(maps, max_groups=6, max_source_points=len(source))
    gicp.set_source(source, source_covs)
    gicp.set_problem(poses, row_group=np.arange(6), row_map=map_of)
    gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
    at_start = gicp.result()
    gicp.iterate(rotation_eps_rad=0.0, translation_eps_m=0.0)
    after_step = gicp.result()

    R = np.ascontiguousarray(at_start.T[:, :3, :3], np.float32)
    t = np.ascontiguousarray(at_start.T[:, :3, 3], np.float32)
    plane = plane_form(source_covs)[:, :5].astype(np.float32)
    H, b, err, inliers = gb.numpy_iterate(R, t, source.astype(np.float32), plane, map_of, base)

    np.testing.assert_array_equal(inliers, at_start.num_inliers)
    scale = np.abs(at_start.H).max()
    np.testing.assert_allclose(H, at_start.H, atol=1e-4 * scale)
    np.testing.assert_allclose(b, at_start.b, atol=1e-4 * np.abs(at_start.b).max())
    np.testing.assert_allclose(err, at_start.error, rtol=1e-4)
    np.testing.assert_allclose(t, after_step.T[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(R, after_step.T[:, :3, :3], atol=1e-5)
