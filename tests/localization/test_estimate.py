"""Pose estimate: the dominant cluster, never a mean across modes."""

import numpy as np
import pytest

from mcl3d.core import geometry
from mcl3d.localization.estimate import (
    ClusterParams,
    average_quaternions,
    cluster_hypotheses,
    kld_sample_count,
    label_particles,
    mode_floor,
)


def _mode(rng, n, centre, yaw, pos_std, yaw_std):
    positions = centre + rng.normal(scale=pos_std, size=(n, 3))
    yaws = yaw + rng.normal(scale=yaw_std, size=n)
    R = geometry.so3_exp(np.stack([np.zeros(n), np.zeros(n), yaws], axis=1))
    return positions, geometry.rot_to_quat(R), yaws


def test_dominant_cluster_is_the_heavy_mode_not_the_average():
    rng = np.random.default_rng(0)
    p1, q1, _ = _mode(rng, 3000, np.array([2.0, 1.0, 0.5]), 0.3, 0.1, 0.02)
    p2, q2, _ = _mode(rng, 3000, np.array([12.0, 1.0, 0.5]), 0.3 + np.pi, 0.1, 0.02)
    positions, quats = np.vstack([p1, p2]), np.vstack([q1, q2])
    weights = np.concatenate([np.full(3000, 0.7 / 3000), np.full(3000, 0.3 / 3000)])
    hyps = cluster_hypotheses(positions, quats, weights)
    assert len(hyps) == 2
    assert hyps[0].weight == pytest.approx(0.7, abs=1e-9)
    np.testing.assert_allclose(hyps[0].T_map_lidar[:3, 3], p1.mean(axis=0), atol=1e-9)
    assert geometry.rot_to_rpy(hyps[0].T_map_lidar[:3, :3])[2] == pytest.approx(0.3, abs=0.002)
    np.testing.assert_allclose(hyps[1].T_map_lidar[:3, 3], p2.mean(axis=0), atol=1e-9)


def test_covariance_matches_sample_covariance():
    rng = np.random.default_rng(1)
    positions, quats, yaws = _mode(rng, 20000, np.zeros(3), 1.0, np.array([0.1, 0.2, 0.05]),
                                   0.05)
    weights = np.full(len(positions), 1.0 / len(positions))
    (hyp,) = cluster_hypotheses(positions, quats, weights, ClusterParams(radius_m=2.0))
    cov = hyp.covariance
    # translation part in the mean's body frame: rotate the world covariance by R^T
    R = hyp.T_map_lidar[:3, :3]
    expected_t = R.T @ np.cov(positions.T, bias=True) @ R
    np.testing.assert_allclose(cov[3:, 3:], expected_t, rtol=0.03, atol=1e-4)
    assert cov[2, 2] == pytest.approx(np.var(yaws), rel=0.03)
    assert hyp.position_std_m == pytest.approx(0.2, rel=0.03)


def test_weighted_quaternion_mean_handles_sign_flips():
    q = geometry.rot_to_quat(geometry.so3_exp(np.array([[0, 0, 0.5], [0, 0, 0.7]])))
    q[1] *= -1  # same rotation, opposite sign
    mean = average_quaternions(q, np.array([0.5, 0.5]))
    assert geometry.rot_to_rpy(geometry.quat_to_rot(mean))[2] == pytest.approx(0.6, abs=1e-6)


def test_kld_bound_uses_the_real_quantile():
    # Fox (2003): k bins, epsilon 0.05, delta 0.01 -> z = 2.326
    from scipy.stats import chi2

    n = kld_sample_count(100, 0.05, 0.01, 10, 10**7)
    exact = chi2.ppf(0.99, 99) / (2 * 0.05)  # the Wilson-Hilferty formula approximates this
    assert n == pytest.approx(exact, rel=0.01)
    assert kld_sample_count(1, 0.05, 0.01, 500, 10**6) == 500
    assert kld_sample_count(10**6, 0.05, 0.01, 500, 300_000) == 300_000


def test_label_particles_by_position_and_angle():
    centres = [geometry.se3(np.eye(3), [0.0, 0.0, 0.0]),
               geometry.se3(geometry.rpy_to_rot(0.0, 0.0, np.pi), [10.0, 0.0, 0.0])]
    positions = np.array([[0.5, 0, 0], [0.5, 0, 0], [10.2, 0, 0], [10.2, 0, 0], [5.0, 0, 0]])
    yaws = np.array([0.1, 1.0, np.pi - 0.2, 0.0, 0.0])
    quats = geometry.rot_to_quat(geometry.so3_exp(np.column_stack([0 * yaws, 0 * yaws, yaws])))
    labels = label_particles(positions, quats, centres, radius_m=1.0, angle_rad=0.5)
    assert labels.tolist() == [0, -1, 1, -1, -1]


def test_mode_floor_keeps_a_light_mode_and_preserves_the_posterior():
    # particles 0-5 in mode 0 (weight 0.97), 6-7 in mode 1 (0.02), 8-9 unlabeled (0.01)
    labels = np.array([0] * 6 + [1] * 2 + [-1] * 2)
    w = np.array([0.97 / 6] * 6 + [0.01, 0.01] + [0.005, 0.005])
    floor = mode_floor(labels, w, share=0.2, min_weight=1e-3, max_modes=3)
    assert floor.rivals == 1
    resampling = w * floor.factors
    assert resampling[labels == 1].sum() == pytest.approx(0.2)  # the floor
    assert resampling.sum() == pytest.approx(1.0)
    # the rest share the remaining 0.8 in proportion to their weight
    assert resampling[labels == -1].sum() == pytest.approx(0.01 * 0.8 / 0.98)
    assert resampling[labels == 0].sum() == pytest.approx(0.97 * 0.8 / 0.98)
    # copies carry log(w / resampling weight): the posterior per mode is unchanged
    counts = np.round(resampling * 1000)
    posterior = counts * w / resampling
    assert posterior[labels == 1].sum() / posterior.sum() == pytest.approx(0.02, rel=0.05)


def test_mode_floor_ignores_negligible_modes_and_single_modes():
    labels = np.array([0, 0, 0, 1])
    one = mode_floor(labels, np.array([0.3, 0.3, 0.3999, 1e-4]), 0.2, 1e-3, 3)
    assert one.rivals == 0 and np.all(one.factors == 1.0)
    heavy = mode_floor(labels, np.array([0.3, 0.3, 0.1, 0.3]), 0.2, 1e-3, 3)
    assert heavy.rivals == 1 and np.allclose(heavy.factors, 1.0)  # both above the floor
    capped = mode_floor(np.array([0, 1, 2, -1]), np.array([0.8, 0.15, 0.05, 0.0]), 0.2, 1e-3, 2)
    assert capped.rivals == 1 and capped.factors[2] == pytest.approx(0.8 / 0.85)  # 2 kept
