"""The paper's sensor model (`sensor.model: paper`, kernels/paper_likelihood) against its
NumPy twin and against numbers computed by hand on a tiny map."""

import numpy as np
from support.floor_map import TRUNC, floor_map

from mcl3d.core import geometry
from mcl3d.localization.sensor_model import (
    NumpyTsdf,
    SensorModelConfig,
    paper_log_likelihood_numpy,
    paper_value,
)

SIGMA = 0.1


def run_kernel(tsdf, positions, quats, points, cfg):
    import taichi as ti

    from mcl3d.kernels import likelihood as kl
    from mcl3d.kernels import paper_likelihood as kpl

    n, m = len(positions), len(points)
    pos = ti.Vector.field(3, ti.f32, shape=n)
    quat = ti.Vector.field(4, ti.f32, shape=n)
    pts = ti.Vector.field(3, ti.f32, shape=m)
    log_w, match, ll_mean = (ti.field(ti.f32, shape=n) for _ in range(3))
    pos.from_numpy(positions.astype(np.float32))
    quat.from_numpy(quats.astype(np.float32))
    pts.from_numpy(points.astype(np.float32))
    log_w.from_numpy(np.full(n, 2.0, np.float32))  # the kernel adds to the previous weight
    order = ti.field(ti.i32, shape=n)
    order.from_numpy(np.random.default_rng(n).permutation(n).astype(np.int32))
    values = ti.field(ti.f32, shape=(tsdf.capacity + 2, 8, 8, 8))
    slots = ti.field(ti.i32, shape=kl.slot_shape(tsdf))
    kl.build_slots(tsdf, slots)
    kpl.build_paper_values(tsdf, values, tsdf.n_blocks, SIGMA, cfg.z_hit)
    match_value = float(paper_value(cfg.match_dist_m, cfg, TRUNC, SIGMA))
    kpl.paper_scan_log_likelihood(tsdf, values, slots, order, pos, quat, n, pts, m,
                                  cfg.z_rand / cfg.max_range_m, match_value, log_w,
                                  match, ll_mean)
    return log_w.to_numpy() - 2.0, match.to_numpy(), ll_mean.to_numpy()


def test_paper_kernel_matches_numpy_twin(ti_runtime):
    """Random poses over the whole map (the floor, the FREE and unknown blocks, outside)."""
    tsdf = floor_map()
    cfg = SensorModelConfig(model="paper", sigma_m=SIGMA)
    rng = np.random.default_rng(0)
    n, m = 41, 29
    positions = rng.uniform([-0.3, -0.3, 0.3], [1.9, 1.9, 1.7], size=(n, 3))
    quats = geometry.rot_to_quat(geometry.random_rotations(rng, n))
    points = rng.normal(scale=0.6, size=(m, 3))
    k_ll, k_match, k_mean = run_kernel(tsdf, positions, quats, points, cfg)
    r_ll, r_match, r_mean = paper_log_likelihood_numpy(NumpyTsdf.of(tsdf), positions, quats,
                                                       points, cfg, SIGMA)
    np.testing.assert_allclose(k_ll, r_ll, atol=2e-4)
    np.testing.assert_allclose(k_mean, r_mean, atol=2e-4)
    assert np.mean(np.abs(k_match - r_match) < 1e-6) > 0.9  # f32 ties at the threshold


def test_paper_model_by_hand():
    """Eq. 3 with the normalisation, clamped at the truncation; a point between two voxel
    centres gets the linear blend of their values; outside the map d = truncation."""
    cfg = SensorModelConfig(model="paper", sigma_m=SIGMA)
    peak = cfg.z_hit / np.sqrt(2 * np.pi * SIGMA**2)
    np.testing.assert_allclose(paper_value(0.0, cfg, TRUNC, SIGMA), peak)
    np.testing.assert_allclose(paper_value(-0.1, cfg, TRUNC, SIGMA), peak * np.exp(-0.5))
    np.testing.assert_allclose(paper_value(5.0, cfg, TRUNC, SIGMA), peak * np.exp(-4.5))
    host = NumpyTsdf.of(floor_map())
    identity = np.array([[0.0, 0.0, 0.0, 1.0]])
    z = 0.85 + 0.02  # between the centres at 0.85 (d = 0) and 0.95 (d = 0.1), 0.2 / 0.8
    points = np.array([[0.55, 0.55, z], [-5.0, 0.5, 0.5]])
    floor = cfg.z_rand / cfg.max_range_m
    first = 0.8 * peak + 0.2 * peak * np.exp(-0.5)
    outside = peak * np.exp(-0.5 * (TRUNC / SIGMA) ** 2)
    ll, match, mean = paper_log_likelihood_numpy(host, np.zeros((1, 3)), identity, points,
                                                 cfg, SIGMA)
    np.testing.assert_allclose(ll, np.log(first + outside + 2 * floor), rtol=1e-6)  # f32 map
    np.testing.assert_allclose(mean, ll - np.log(2))
    np.testing.assert_allclose(match, 0.5)  # the first point is within match_dist
