"""The parts the paper preset switches on: independent uniform 6-DoF initialization
(`init.stratified: false`, `init.uniform_rotation: true`, `height_band_m: none`) and the
weighted mean of all particles (`estimate.mean: all`)."""

import numpy as np

from mcl3d.core import geometry
from mcl3d.localization.estimate import (
    WeightedParticles,
    estimate_pose,
    with_mean_of_all,
)
from mcl3d.localization.localization_config import EstimateConfig


def _fields(n):
    import taichi as ti

    return (ti.Vector.field(3, ti.f32, shape=n), ti.Vector.field(4, ti.f32, shape=n),
            ti.field(ti.f32, shape=n))


def test_independent_uniform_6dof_draws(ti_runtime):
    """stratified = 0: cells drawn independently (about 1/e of 2000 cells stay empty with
    2000 particles; the stratified draw fills every one), positions uniform inside a cell,
    rotations uniform on SO(3) (E[R] = 0, angle density (1 - cos t) / pi); with gravity the
    yaw is uniform and independent of the particle index."""
    from mcl3d.kernels.particles import init_cells

    n_cells = 2000
    cells = np.column_stack([np.arange(n_cells), np.zeros(n_cells), np.zeros(n_cells)]
                            ).astype(np.float32)
    pos, quat, log_w = _fields(n_cells)
    init_cells(pos, quat, log_w, n_cells, cells, n_cells, 1.0, 0, 0.0, 0.0, 0.0, 0, 1.0, 7, 0)
    p = pos.to_numpy()
    empty = np.mean(np.bincount(np.floor(p[:, 0]).astype(int), minlength=n_cells) == 0)
    assert abs(empty - np.exp(-1)) < 0.04
    init_cells(pos, quat, log_w, n_cells, cells, n_cells, 1.0, 0, 0.0, 0.0, 0.0, 1, 1.0, 7, 0)
    assert np.all(np.bincount(np.floor(pos.to_numpy()[:, 0]).astype(int)) == 1)

    n = 40_000
    cells = np.array([[0, 0, 0], [3, 0, 0]], np.float32)
    pos, quat, log_w = _fields(n)
    init_cells(pos, quat, log_w, n, cells, 2, 0.5, 0, 0.0, 0.0, 0.0, 0, 1.0, 3, 1)
    p = pos.to_numpy()
    owner = (p[:, 0] > 2.0).astype(int)
    inside = np.all((p >= cells[owner]) & (p < cells[owner] + 0.5), axis=1)
    assert inside.all()
    np.testing.assert_allclose(np.bincount(owner) / n, 0.5, atol=0.01)
    hist, _ = np.histogram((p - cells[owner]) / 0.5, bins=5, range=(0, 1))
    np.testing.assert_allclose(hist / (3 * n), 0.2, atol=0.01)  # x, y, z offsets
    R = geometry.quat_to_rot(quat.to_numpy().astype(np.float64))
    assert np.abs(R.mean(axis=0)).max() < 0.02
    angle = geometry.rotation_angle(R)
    for t in (0.5, 1.5, 2.5):
        assert abs(np.mean(angle <= t) - (t - np.sin(t)) / np.pi) < 0.01
    init_cells(pos, quat, log_w, n, cells, 2, 0.5, 1, 0.0, 0.0, 0.0, 0, 1.0, 3, 1)
    yaw = geometry.rot_to_rpy(geometry.quat_to_rot(quat.to_numpy().astype(np.float64)))[:, 2]
    hist, _ = np.histogram(yaw, bins=8, range=(-np.pi, np.pi))
    np.testing.assert_allclose(hist / n, 1 / 8, atol=0.01)
    # independent, not a golden-ratio sequence: consecutive yaws are uncorrelated
    assert abs(np.corrcoef(np.cos(yaw[:-1]), np.cos(yaw[1:]))[0, 1]) < 0.02


def test_uniform_rotation_ignores_gravity_and_none_band_takes_all_free_space(ti_runtime):
    """The localizer under the paper's init: with the IMU's roll/pitch known the rotations
    are still uniform on SO(3), and the candidates are every free cell (no floor band)."""
    from support import localize_world

    from mcl3d.localization.initialization import InitConfig, free_cells
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    tsdf = localize_world.build_map(0.1)
    init = {"height_band_m": "none", "covered": False, "uniform_rotation": True,
            "stratified": False}
    cfg = LocalizerConfig(particles=20_000, seed=1, init=InitConfig(**init))
    loc = Localizer(tsdf, cfg, imu_roll_pitch=(0.0, 0.0))
    loc.init_global()
    pos, quat, _ = loc.particles.host()
    R = geometry.quat_to_rot(quat.astype(np.float64))
    assert np.abs(R.mean(axis=0)).max() < 0.03  # upright would give E[R_zz] = 1
    every = free_cells(tsdf, InitConfig(height_band_m=None, covered=False))
    banded = free_cells(tsdf, InitConfig())
    assert len(loc.free_space().corners_m) == len(every.corners_m) > len(banded.corners_m)
    assert pos[:, 2].max() > 2.5  # particles also above the 0.2-2.5 m band


def test_mean_of_all_particles_averages_across_modes():
    """Two modes weighted 0.7 / 0.3: the default estimate is the heavy mode, the paper's is
    the weighted mean of everything (between them), with the spread of everything."""
    rng = np.random.default_rng(0)
    n = 2000
    a = np.array([2.0, 1.0, 0.5]) + rng.normal(scale=0.05, size=(n, 3))
    b = np.array([12.0, 1.0, 0.5]) + rng.normal(scale=0.05, size=(n, 3))
    yaws = np.concatenate([np.full(n, 0.2), np.full(n, 0.6)])
    quats = geometry.rot_to_quat(geometry.so3_exp(np.column_stack([0 * yaws, 0 * yaws, yaws])))
    w = np.concatenate([np.full(n, 0.7 / n), np.full(n, 0.3 / n)])
    cloud = WeightedParticles(np.vstack([a, b]), quats, w, np.zeros(2 * n), np.zeros(2 * n))
    cluster = estimate_pose(cloud, EstimateConfig(), np.random.default_rng(1))
    assert np.linalg.norm(cluster.T_map_lidar[:3, 3] - [2.0, 1.0, 0.5]) < 0.05
    mean = with_mean_of_all(cluster, cloud)
    np.testing.assert_allclose(mean.T_map_lidar[:3, 3], w @ cloud.positions, atol=1e-9)
    assert abs(mean.T_map_lidar[0, 3] - 5.0) < 0.01
    yaw = geometry.rot_to_rpy(mean.T_map_lidar[:3, :3])[2]
    assert abs(yaw - 0.32) < 0.01  # the weighted mean rotation
    assert np.sqrt(mean.covariance[3, 3]) > 4.0  # x spread across both modes (~4.6 m)
    assert mean.hypotheses == cluster.hypotheses and mean.dominant == cluster.dominant
