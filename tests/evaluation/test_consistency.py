"""The particle-cloud consistency metric: the weighted SE(3) mean and covariance against a
direct NumPy computation, and the 95% fraction on synthetic clouds drawn from the truth's
own distribution (~95%), from a too narrow one (far less) and a too wide one (~100%)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import Mcl3dError
from mcl3d.core.geometry import se3, se3_exp, se3_log, so3_exp
from mcl3d.evaluation.consistency import (
    CHI2_6DOF_95,
    align_start,
    consistency,
    mahalanobis2,
    weighted_pose_mean,
)

SIGMA = np.array([0.02, 0.01, 0.05, 0.1, 0.3, 0.05])  # rad, rad, rad, m, m, m


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return se3(so3_exp(rng.normal(0, 1.0, 3)), rng.normal(0, 20.0, 3))


def correlated_cov(rng: np.random.Generator) -> np.ndarray:
    L = np.diag(SIGMA) @ (np.eye(6) + 0.3 * rng.standard_normal((6, 6)))
    return L @ L.T


def test_chi2_quantile_matches_scipy():
    from scipy.stats import chi2

    assert pytest.approx(chi2.ppf(0.95, 6), rel=1e-12) == CHI2_6DOF_95


def test_mean_and_covariance_match_a_direct_computation():
    rng = np.random.default_rng(1)
    center = random_pose(rng)
    drawn_cov = correlated_cov(rng)
    xi = rng.multivariate_normal(np.zeros(6), drawn_cov, size=4000)
    poses = center @ se3_exp(xi)
    w = rng.random(4000)
    mean, cov = weighted_pose_mean(poses, w)
    # direct: the weighted mean is where the weighted tangent vectors average to zero
    direct = np.array([se3_log(np.linalg.inv(mean) @ T) for T in poses])
    wn = w / w.sum()
    assert np.abs(wn @ direct).max() < 1e-9
    centred = direct - wn @ direct
    direct_cov = sum(wi * np.outer(d, d) for wi, d in zip(wn, centred, strict=True))
    np.testing.assert_allclose(cov, direct_cov, rtol=1e-9, atol=1e-14)
    # and it is the distribution the poses were drawn from
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(drawn_cov)), rtol=0.06)
    np.testing.assert_allclose(se3_log(np.linalg.inv(center) @ mean), 0.0, atol=0.02)


def test_mahalanobis_matches_inverse_covariance():
    rng = np.random.default_rng(2)
    M, T = random_pose(rng), random_pose(rng)
    cov = correlated_cov(rng)
    d = se3_log(np.linalg.inv(M) @ T)
    assert mahalanobis2(M, cov, T) == pytest.approx(d @ np.linalg.inv(cov) @ d, rel=1e-6)


def clouds(rng, scans: int, particles: int, spread: float):
    """Per scan: a truth, a cloud centre drawn from N(truth, Σ), and a cloud drawn from
    N(centre, (spread σ)²): with spread 1 the truth is a draw from the cloud's distribution."""
    cov = correlated_cov(rng)
    means, covs, truths = [], [], []
    for _ in range(scans):
        truth = random_pose(rng)
        centre = truth @ se3_exp(rng.multivariate_normal(np.zeros(6), cov))
        cloud = centre @ se3_exp(rng.multivariate_normal(np.zeros(6), spread**2 * cov,
                                                         size=particles))
        m, c = weighted_pose_mean(cloud, np.ones(particles))
        means.append(m)
        covs.append(c)
        truths.append(truth)
    return np.array(means), np.array(covs), np.array(truths)


def test_calibrated_cloud_holds_the_truth_95_percent():
    rng = np.random.default_rng(3)
    result = consistency(*clouds(rng, 600, 800, 1.0))
    assert result.scans == 600
    assert 0.92 <= result.fraction <= 0.98
    assert 4.5 <= result.median_d2 <= 6.5  # chi-square(6) median 5.35
    assert list(result.axes) == ["rx", "ry", "rz", "x", "y", "z"]
    assert all(0.9 <= f <= 0.99 for f in result.axes.values())


def test_per_axis_shares_match_a_direct_computation():
    rng = np.random.default_rng(6)
    M = np.array([random_pose(rng) for _ in range(50)])
    covs = np.array([correlated_cov(rng) for _ in range(50)])
    T = np.array([m @ se3_exp(rng.normal(0.0, 1.5 * SIGMA)) for m in M])
    T[:, :3, 3] += [0.0, 0.0, 0.4]  # 0.4 m off in the world: too far for some axes
    result = consistency(M, covs, T)
    direct = np.array([np.abs(se3_log(np.linalg.inv(m) @ t)) <= 1.959964 * np.sqrt(np.diag(c))
                       for m, c, t in zip(M, covs, T, strict=True)]).mean(axis=0)
    np.testing.assert_allclose(list(result.axes.values()), direct)
    assert min(result.axes.values()) < 0.5 < max(result.axes.values())


def test_narrow_cloud_is_inconsistent_and_wide_cloud_overcovers():
    rng = np.random.default_rng(4)
    narrow = consistency(*clouds(rng, 200, 400, 0.3))
    assert narrow.fraction < 0.3 and max(narrow.axes.values()) < 0.6
    wide = consistency(*clouds(rng, 200, 400, 3.0))
    assert wide.fraction > 0.99 and min(wide.axes.values()) > 0.99


def test_align_start_puts_the_first_truth_on_the_first_estimate():
    rng = np.random.default_rng(5)
    truths = np.array([random_pose(rng) for _ in range(4)])
    est0 = random_pose(rng)
    aligned = align_start(truths, est0)
    np.testing.assert_allclose(aligned[0], est0, atol=1e-12)
    rel = np.linalg.inv(truths[1]) @ truths[3]
    np.testing.assert_allclose(np.linalg.inv(aligned[1]) @ aligned[3], rel, atol=1e-9)


def test_bad_weights_are_refused():
    with pytest.raises(Mcl3dError, match="weight"):
        weighted_pose_mean(np.tile(np.eye(4), (3, 1, 1)), np.zeros(3))
