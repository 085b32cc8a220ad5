"""ScanGrid gives the same voxels and covariances on Vulkan (Mesa's lavapipe in CI) as on cpu.

Its ordered insertion once ran inside a `for _ in range(1)` task, where lavapipe lost the
loop's counters: every scan came back empty on Vulkan and only the cpu tests ran. Later a
real-sized scan lost most of its voxels there: lavapipe stops a loop of one thread after
65,535 iterations, and one launch inserted a whole scan, clearing 64 cells per new brick."""

import numpy as np
import pytest

pytestmark = pytest.mark.vulkan


def _run(backend):
    """Downsample and covariances of a small deskewed cloud (several chunks) on `backend`."""
    from mcl3d.core import runtime
    from mcl3d.registration.gicp_state import SourcePool
    from mcl3d.registration.preprocess import ScanGrid, download_rows

    runtime.init(backend)
    rng = np.random.default_rng(3)
    wall = np.c_[rng.uniform(-2, 2, 500), np.full(500, 3.0), rng.uniform(0, 2, 500)]
    floor = np.c_[rng.uniform(-2, 2, (500, 2)), np.zeros(500)]
    pts = np.vstack([wall, floor]) + 0.002 * rng.normal(size=(1000, 3)) + 0.0137
    times = np.linspace(0.0, 0.1, len(pts))
    grid = ScanGrid(max_points=256, max_voxels=2048)
    out = SourcePool(2048)
    n = grid.downsample(pts, 0.2, out, times, np.array([0.0, 0.0, 0.3, 0.5, 0.0, 0.0]),
                        k_neighbors=10)
    return download_rows(out, n)


def test_scan_grid_on_cpu_and_vulkan_agree(on_vulkan):
    vk_pts, vk_rows = on_vulkan(_run)
    cpu_pts, cpu_rows = _run("cpu")
    assert len(cpu_pts) > 100 and len(vk_pts) == len(cpu_pts)
    # the same voxels in the same order (first occurrence), means within f32 rounding
    np.testing.assert_allclose(vk_pts, cpu_pts, atol=1e-5)
    # plane rows (n, α, β): the normal up to its sign
    sign = np.sign(np.einsum("ij,ij->i", vk_rows[:, :3], cpu_rows[:, :3]))
    np.testing.assert_allclose(vk_rows[:, :3] * sign[:, None], cpu_rows[:, :3], atol=1e-3)
    np.testing.assert_allclose(vk_rows[:, 3:5], cpu_rows[:, 3:5], atol=1e-6)


def _count_voxels(backend, pts):
    from mcl3d.core import runtime
    from mcl3d.registration.gicp_state import SourcePool
    from mcl3d.registration.preprocess import ScanGrid

    runtime.init(backend)
    grid = ScanGrid(max_points=1 << 17, max_voxels=1 << 17)
    return grid.downsample(pts, 0.25, SourcePool(1 << 17, with_cov_rows=False))


def test_a_real_sized_scan_keeps_every_voxel_on_vulkan(on_vulkan):
    """70,000 scattered points, nearly one voxel and one brick each: as many voxels as on cpu
    (lavapipe kept 953 of 69,818 when one launch inserted them all)."""
    pts = np.random.default_rng(0).uniform(-30.0, 30.0, (70000, 3))
    cpu = _count_voxels("cpu", pts)
    assert cpu > 69000
    assert on_vulkan(_count_voxels, pts) == cpu
