"""The bounded statistics the localizer takes from the device instead of every particle:
the same numbers as the host computations they replace, on tiny particle sets."""

import numpy as np
import pytest

from mcl3d.core import geometry


def _particles(n, seed):
    from mcl3d.localization.particle_set import ParticleSet

    rng = np.random.default_rng(seed)
    p = ParticleSet(n + 5)  # capacity above n: only the first n count
    pos = rng.normal(size=(n, 3))
    quat = geometry.rot_to_quat(geometry.random_rotations(rng, n))
    log_w = rng.normal(scale=3.0, size=n).astype(np.float32)
    p.set_host(pos, quat, log_w)
    match, ll = rng.random(n).astype(np.float32), -rng.random(n).astype(np.float32)
    p.match.from_numpy(np.pad(match, (0, 5)))
    p.ll_mean.from_numpy(np.pad(ll, (0, 5)))
    w = np.exp(log_w.astype(np.float64) - log_w.max())
    return p, pos.astype(np.float32), quat.astype(np.float32), w, match, ll


def test_cloud_stats_and_sample_match_host(ti_runtime):
    from mcl3d.localization.estimate import systematic_sample
    from mcl3d.localization.particle_stats import ParticleSampler, cloud_stats
    from mcl3d.localization.resampling import compute_weights

    n = 700
    p, pos, quat, w, match, ll = _particles(n, 1)
    weights = compute_weights(p)
    assert weights.total == pytest.approx(w.sum(), rel=1e-5)
    s = cloud_stats(p, weights.total)
    wn = w / w.sum()
    assert s.match_ratio == pytest.approx(wn @ match, rel=1e-5)
    assert s.mean_log_likelihood == pytest.approx(wn @ ll, rel=1e-5)
    assert s.best_match_ratio == pytest.approx(match.max())
    assert np.allclose(s.T_best[:3, 3], pos[np.argmax(w)])
    k, u0 = 200, 0.37
    got_pos, got_quat = ParticleSampler(300).by_weight(p, weights.total, k, u0)
    idx = systematic_sample(wn, k, type("Rng", (), {"random": lambda self: u0})())
    # the same draws (f32 CDF against f64: a slot on a boundary may pick the neighbour)
    assert np.mean(np.all(got_pos == pos[idx], axis=1)) > 0.98
    assert np.mean(np.all(got_quat == quat[idx], axis=1)) > 0.98


def test_tempered_ess_and_anneal_match_numpy(ti_runtime):
    from mcl3d.localization.particle_stats import tempered_ess
    from mcl3d.localization.search import ANNEAL_BISECTIONS, anneal

    n = 500
    p, _, _, _, _, ll = _particles(n, 2)
    log_w = p.log_w.to_numpy()[:n].astype(np.float64)

    def ess(x):
        w = np.exp(x - x.max())
        return w.sum() ** 2 / (w @ w)

    scale = 40.0
    assert tempered_ess(p, -0.5 * scale) == pytest.approx(
        ess(log_w - 0.5 * scale * ll), rel=1e-4)
    target = 0.5 * n
    lo, hi = 0.0, 1.0  # the host bisection the device one replaces
    for _ in range(ANNEAL_BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ess(log_w + (mid - 1.0) * scale * ll) >= target else (lo, mid)
    assert ess(log_w) < target  # the test anneals
    assert anneal(p, scale, 0.5) == pytest.approx(lo, abs=2.0 ** -ANNEAL_BISECTIONS)
    assert np.allclose(p.log_w.to_numpy()[:n], log_w + (lo - 1.0) * scale * ll, atol=1e-3)


def test_mode_preserving_resampling_matches_host(ti_runtime):
    """Draws along weight * factor, each copy carrying -log(factor) of its parent."""
    from mcl3d.localization.resampling import compute_weights, resample

    n = 400
    p, pos, _, w, _, _ = _particles(n, 3)
    factors = np.where(np.arange(n) < 40, 25.0, 1.0)
    weights = compute_weights(p)
    p.factor.from_numpy(np.pad(factors, (0, 5), constant_values=1.0).astype(np.float32))
    resample(p, n, weights, 0.25, floored=True)
    cdf = np.cumsum(w * factors)
    cdf /= cdf[-1]
    parent = np.minimum(np.searchsorted(cdf, (np.arange(n) + 0.25) / n), n - 1)
    got = p.parent.to_numpy()[:n]
    assert np.mean(got == parent) > 0.98
    assert np.allclose(p.pos.to_numpy()[:n], pos[got])
    assert np.allclose(p.log_w.to_numpy()[:n], -np.log(factors[got]), atol=1e-6)


def test_mean_of_all_matches_host(ti_runtime):
    """The paper's estimate from device moments equals `with_mean_of_all` on the host."""
    from mcl3d.localization.estimate import WeightedParticles, estimate_pose, with_mean_of_all
    from mcl3d.localization.localization_config import EstimateConfig
    from mcl3d.localization.particle_set import ParticleSet
    from mcl3d.localization.particle_stats import MeanOfAll
    from mcl3d.localization.resampling import compute_weights

    rng = np.random.default_rng(5)
    n = 600
    pos = np.array([3.0, -1.0, 0.5]) + rng.normal(scale=[0.4, 0.2, 0.05], size=(n, 3))
    yaw = np.array([0.0, 0.0, 2.0])
    rot = geometry.so3_exp(rng.normal(scale=[0.02, 0.02, 0.3], size=(n, 3)) + yaw)
    quat = geometry.rot_to_quat(rot)
    log_w = rng.normal(scale=1.0, size=n).astype(np.float32)
    p = ParticleSet(n)
    p.set_host(pos, quat, log_w)
    weights = compute_weights(p)
    T, cov = MeanOfAll(n)(p)
    w = np.exp(log_w.astype(np.float64) - log_w.max())
    cloud = WeightedParticles(pos.astype(np.float32).astype(np.float64),
                              quat.astype(np.float32).astype(np.float64), w / w.sum(),
                              np.zeros(n), np.zeros(n))
    expected = with_mean_of_all(estimate_pose(cloud, EstimateConfig(samples=100),
                                              np.random.default_rng(0)), cloud)
    assert weights.total > 0
    np.testing.assert_allclose(T, expected.T_map_lidar, atol=2e-5)
    np.testing.assert_allclose(cov, expected.covariance, rtol=2e-3, atol=1e-6)


def test_cluster_labels_and_mode_floor_match_host(ti_runtime):
    """Device labels, cluster weights and factors (with a place floor kept where larger)
    equal `label_particles` and `mode_floor` on the host."""
    from mcl3d.localization.estimate import label_particles, mode_floor, mode_floor_table
    from mcl3d.localization.particle_stats import ClusterLabels
    from mcl3d.localization.resampling import compute_weights

    n = 900
    p, pos, quat, w, _, _ = _particles(n, 6)
    centres = [geometry.se3_from_tq(pos[i].astype(np.float64), quat[i].astype(np.float64))
               for i in (0, 1, 2)]
    weights = compute_weights(p)
    labels = ClusterLabels(n + 5)
    cluster_w = labels.weights(p, centres, 1.2, 1.5, weights.total)
    expected = label_particles(pos.astype(np.float64), quat.astype(np.float64), centres, 1.2,
                               1.5)
    got = p.label.to_numpy()[:n]
    assert np.mean(got == expected) > 0.99 and (got >= 0).any() and (got < 0).any()
    wn = w / w.sum()
    np.testing.assert_allclose(cluster_w, [wn[expected == c].sum() for c in range(3)],
                               rtol=1e-4, atol=1e-7)
    table, rivals = mode_floor_table(cluster_w, 0.3, 1e-4, 3)
    host = mode_floor(expected, w, 0.3, 1e-4, 3)
    assert rivals == host.rivals >= 1
    place = np.where(np.arange(n) % 7 == 0, 3.0, 1.0)
    p.factor.from_numpy(np.pad(place, (0, p.capacity - n)).astype(np.float32))
    labels.apply(p, table, keep_place_factors=True)
    np.testing.assert_allclose(p.factor.to_numpy()[:n], np.maximum(host.factors, place),
                               rtol=1e-4)
    labels.apply(p, table, keep_place_factors=False)
    np.testing.assert_allclose(p.factor.to_numpy()[:n], host.factors, rtol=1e-4)
