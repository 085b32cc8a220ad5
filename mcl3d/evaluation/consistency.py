"""Is a particle cloud honest about its error? The weighted mean and covariance of a set of
poses, and the fraction of scans whose true pose lies inside the cloud's 95% region.

A filter whose cloud is far narrower than its drift reports a confidence it does not have;
one far wider wastes its particles. Over a log with ground truth, the squared Mahalanobis
distance of the truth from the cloud's weighted mean (in the se(3) tangent at the mean,
rotation first, right perturbation as everywhere in mcl3d) is chi-square with 6 degrees of
freedom when the cloud is the truth's distribution, so it is below `CHI2_6DOF_95` in 95% of
scans. Per tangent axis, the share of scans whose error along it lies within that axis's own
95% interval (±1.96 σ) says along which axes the cloud is too narrow. Pure NumPy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core.errors import Mcl3dError
from mcl3d.core.geometry import se3_exp, se3_inverse, se3_log

CHI2_6DOF_95 = 12.591587243743977  # scipy.stats.chi2.ppf(0.95, 6)
NORMAL_95 = 1.959963984540054  # scipy.stats.norm.ppf(0.975): one axis's 95% interval, in σ
TANGENT_AXES = ("rx", "ry", "rz", "x", "y", "z")  # rotation first, at the mean (its frame)
MEAN_ITERATIONS = 5  # Gauss-Newton steps of the weighted mean on SE(3)
MEAN_TOLERANCE = 1e-10  # stop when the mean's step is this small (rad, m)
COVARIANCE_FLOOR = 1e-12  # added to the covariance's diagonal (a collapsed cloud)


@dataclass(frozen=True)
class Consistency:
    """How often the truth was inside the cloud's 95% region."""

    scans: int
    inside: int
    fraction: float  # inside / scans: ~0.95 for a calibrated cloud
    median_d2: float  # squared Mahalanobis distance (6 on average for a calibrated cloud)
    axes: dict[str, float]  # per tangent axis: the share of scans within its 95% interval

    def as_dict(self) -> dict:
        return {"scans": self.scans, "inside_95": self.inside, "fraction_95": self.fraction,
                "median_mahalanobis2": self.median_d2, "threshold": CHI2_6DOF_95,
                "axes_within_95": self.axes}


def weighted_pose_mean(poses: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_mean, 6x6 covariance) of poses (N, 4, 4) with weights (N,): the mean is the
    fixed point of M <- M exp(Σ w_i log(M⁻¹ T_i)), started at the heaviest pose's rotation
    and the weighted mean position (one step fewer than from the heaviest pose); the
    covariance is Σ w_i ξ_i ξ_iᵀ of ξ_i = log(M⁻¹ T_i), the last step's ξ once it converged
    (each log of N poses is most of the cost: SLAM computes this every scan)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    w = np.asarray(weights, dtype=np.float64).ravel()
    if len(w) != len(poses) or len(w) == 0 or not np.all(w >= 0) or w.sum() <= 0:
        raise Mcl3dError("weighted_pose_mean needs one non-negative weight per pose, not all "
                         "zero")
    w = w / w.sum()
    mean = poses[int(np.argmax(w))].copy()
    mean[:3, 3] = w @ poses[:, :3, 3]
    for _ in range(MEAN_ITERATIONS):
        xi = se3_log(se3_inverse(mean) @ poses)
        step = w @ xi
        if np.max(np.abs(step)) < MEAN_TOLERANCE:
            break
        mean = mean @ se3_exp(step)
    else:
        xi = se3_log(se3_inverse(mean) @ poses)
    xi -= w @ xi
    return mean, (xi * w[:, None]).T @ xi


def mahalanobis2(T_mean: np.ndarray, covariance: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of the true pose(s) from the mean(s), in the tangent at
    the mean: d = log(M⁻¹ T), d² = dᵀ Σ⁻¹ d. Broadcasts over leading axes."""
    return _mahalanobis2_of(_tangent_error(T_mean, T_true), covariance)


def _tangent_error(T_mean: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """d = log(M⁻¹ T): the true pose(s) in the tangent at the mean(s), rotation first."""
    return se3_log(se3_inverse(np.asarray(T_mean, np.float64)) @ np.asarray(T_true, np.float64))


def _mahalanobis2_of(d: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    cov = np.asarray(covariance, np.float64) + COVARIANCE_FLOOR * np.eye(6)
    return np.einsum("...i,...i->...", d, np.linalg.solve(cov, d[..., None])[..., 0])


def align_start(T_true: np.ndarray, T_est_first: np.ndarray) -> np.ndarray:
    """The true poses in the estimate's frame, aligned at the first pose (SLAM's world frame
    is its first pose's): A T_true with A = T_est_first T_true[0]⁻¹."""
    T_true = np.asarray(T_true, np.float64)
    return (np.asarray(T_est_first, np.float64) @ se3_inverse(T_true[0])) @ T_true


def consistency(T_means: np.ndarray, covariances: np.ndarray, T_true: np.ndarray,
                threshold: float = CHI2_6DOF_95) -> Consistency:
    """The fraction of scans whose true pose (already in the estimate's frame, e.g. by
    `align_start`) has a squared Mahalanobis distance below `threshold` from the cloud."""
    d = _tangent_error(T_means, T_true)
    d2 = _mahalanobis2_of(d, covariances)
    if d2.size == 0:
        raise Mcl3dError("consistency needs at least one scan")
    inside = int(np.sum(d2 <= threshold))
    sigma = np.sqrt(np.einsum("...ii->...i", np.asarray(covariances, np.float64))
                    + COVARIANCE_FLOOR)
    within = np.mean(np.abs(d) <= NORMAL_95 * sigma, axis=tuple(range(d.ndim - 1)))
    return Consistency(int(d2.size), inside, inside / d2.size, float(np.median(d2)),
                       {a: float(f) for a, f in zip(TANGENT_AXES, within, strict=True)})
