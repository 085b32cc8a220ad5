"""ScanGrid (kernels/scan_grid.py): device downsampling, deskewing and neighbour covariances
against NumPy references on tiny clouds."""

from __future__ import annotations

import numpy as np
import pytest
from support.scan_lines import scan_lines

from mcl3d.core.errors import ConfigError, PointCloudError
from mcl3d.registration.gicp_state import SourcePool
from mcl3d.registration.preprocess import (
    ScanGrid,
    deskew,
    download_rows,
    plane_rows_to_covs,
    voxel_downsample,
)


@pytest.fixture
def grid(ti_runtime):
    g = ScanGrid(max_points=256, max_voxels=2048)  # 256: several chunks per cloud
    g.out = SourcePool(2048)
    g.out_points = SourcePool(2048, with_cov_rows=False)
    return g


def run(grid, points, voxel_m, k=10, **kw):
    n = grid.downsample(points, voxel_m, grid.out, k_neighbors=k, **kw)
    if n is None:
        return None, None
    return download_rows(grid.out, n)


def by_voxel(points, voxel_m):
    """Rows sorted by voxel key (output orders differ: first occurrence vs sorted keys)."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    return points[np.lexsort(keys.T[::-1])]


def reference_covariances(points, voxel_m, k, min_neighbors=5):
    """float64 NumPy reference of the grid's plane covariances: the k nearest within 2 voxels
    (Chebyshev), else within the 3x3x3 bricks of 4^3 voxels; eigenvalues (1e-3, 1, 1), the
    identity for a scan line (scan_lines.py)."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    bricks = np.floor_divide(keys, 4)
    out = np.tile(np.eye(3), (len(points), 1, 1))
    for i, p in enumerate(points):
        near = np.flatnonzero(np.abs(keys - keys[i]).max(axis=1) <= 2)
        if len(near) < min_neighbors:
            near = np.flatnonzero(np.abs(bricks - bricks[i]).max(axis=1) <= 1)
        if len(near) < min_neighbors:
            continue
        d = np.linalg.norm(points[near] - p, axis=1)
        nb = points[near[np.argsort(d, kind="stable")[:k]]]
        c = nb - nb.mean(axis=0)
        S = c.T @ c / len(nb)
        if not scan_lines(S[None])[0]:
            U = np.linalg.eigh(S)[1]
            out[i] = U @ np.diag([1e-3, 1.0, 1.0]) @ U.T
    return out


def test_downsample_matches_numpy_with_crop_and_bad_points(grid):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (900, 3))  # negative voxel keys, several chunks of 256
    pts[::50] = np.nan
    pts[1::70] = [np.inf, 0.0, 0.0]
    r = np.linalg.norm(pts, axis=1)
    kept = pts[np.isfinite(r) & (r >= 0.5) & (r <= 4.0)]
    got, _ = run(grid, pts, 0.5, min_range_m=0.5, max_range_m=4.0)
    ref = voxel_downsample(kept, 0.5)
    assert len(got) == len(ref)
    np.testing.assert_allclose(by_voxel(got, 0.5), by_voxel(ref, 0.5), atol=2e-6)


def test_deskew_matches_the_host_deskew(grid):
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (400, 3))
    times = np.sort(rng.uniform(-0.05, 0.05, 400))
    twist = np.array([0.3, -0.2, 1.2, 3.0, 0.5, -0.2])
    got, _ = run(grid, pts, 0.01, times_s=times, twist=twist)  # one point per voxel
    ref = deskew(pts, times, twist)
    assert len(got) == 400
    np.testing.assert_allclose(by_voxel(got, 0.01), by_voxel(ref, 0.01), atol=1e-4)


def test_covariances_match_numpy_on_surfaces_and_sparse_points(grid):
    rng = np.random.default_rng(2)
    wall = np.c_[rng.uniform(0, 3, 500), np.full(500, 1.3), rng.uniform(-1, 1, 500)]
    floor = np.c_[rng.uniform(0, 3, 300), rng.uniform(-1, 1.2, 300), np.full(300, -1.1)]
    lone = rng.uniform(-8, 8, (40, 3)) + np.array([12.0, 0.0, 0.0])  # identity
    # a sparse plane (~2 points/m²): too few within 2 voxels, a plane within the bricks
    thin = np.c_[rng.uniform(-3, 3, (80, 2)) + np.array([0.0, 8.0]), np.full(80, 2.9)]
    # a lone scan line on the ground, 4.9 m from the floor: a line, no normal (identity)
    ring = np.c_[np.linspace(-3, 3, 40), np.full(40, -6.0), np.full(40, -1.1)]
    pts = np.vstack([wall, floor, lone, thin, ring]) + 0.002 * rng.normal(size=(960, 3))
    for k in (5, 10, 32):  # one grid: a new one would compile the kernel again
        got, rows = run(grid, pts, 0.2, k=k)
        ref = reference_covariances(got.astype(np.float64), 0.2, k)
        np.testing.assert_allclose(plane_rows_to_covs(rows), ref, atol=2e-3)
        identity = (rows[:, 4] == 0)
        assert identity.any() and not identity.all()
        on_ring = np.abs(got[:, 1] + 6.0) < 0.1
        assert on_ring.sum() > 20 and identity[on_ring].all()
    # the same bits on every run (fixed-order sums, no float atomics)
    again_pts, again_rows = run(grid, pts, 0.2, k=k)
    assert np.array_equal(got, again_pts) and np.array_equal(rows, again_rows)


def test_too_many_voxels_give_none_and_bad_parameters_raise(grid, ti_runtime):
    pts = np.random.default_rng(3).uniform(-50, 50, (4000, 3))
    assert grid.downsample(pts, 0.05, grid.out_points) is None  # more voxels than max_voxels
    small = SourcePool(10, with_cov_rows=False)
    assert grid.downsample(pts[:100], 0.05, small) is None  # more than the output holds
    with pytest.raises(ConfigError, match="voxel_size_m"):
        grid.downsample(pts, 0.0, grid.out_points)
    assert grid.downsample(pts[:100], 0.05, SourcePool(10)) is None
    with pytest.raises(ConfigError, match="k_neighbors"):
        grid.downsample(pts, 0.2, grid.out, k_neighbors=40)
    with pytest.raises(PointCloudError, match="twist"):
        grid.downsample(pts, 0.2, grid.out_points, times_s=np.zeros(len(pts)), twist=np.zeros(5))
    n = grid.downsample(np.zeros((0, 3)), 0.5, grid.out_points)
    assert n == 0
