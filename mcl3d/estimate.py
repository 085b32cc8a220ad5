"""Pose estimates from a weighted particle set: dominant cluster, hypotheses, convergence.

A weighted mean over all particles is meaningless while the filter is multi-modal (the
peer tsdf_localization averages across modes during global localization). Here the estimate
is the mean of the heaviest cluster only; the other clusters are reported as hypotheses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d import geometry


@dataclass(frozen=True)
class Hypothesis:
    T_map_lidar: np.ndarray  # (4, 4) weighted mean pose of the cluster
    covariance: np.ndarray  # (6, 6) rotation-first tangent covariance at the mean [rad^2, m^2]
    weight: float  # fraction of the total weight in this cluster
    n_particles: int

    @property
    def position_std_m(self) -> float:
        """Square root of the largest positional variance (the cluster's worst-axis spread)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.covariance[3:, 3:]).max()))

    @property
    def rotation_std_rad(self) -> float:
        return float(np.sqrt(np.linalg.eigvalsh(self.covariance[:3, :3]).max()))


@dataclass(frozen=True)
class ClusterParams:
    radius_m: float = 1.0  # particles within this distance of a cluster centre belong to it
    angle_rad: float = 0.5  # ... and within this rotation angle of the centre's orientation
    max_hypotheses: int = 3
    mean_shift_iterations: int = 3


def average_quaternions(q_xyzw: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean rotation: the principal eigenvector of sum(w q q^T) (Markley et al.)."""
    M = (q_xyzw * weights[:, None]).T @ q_xyzw
    q = np.linalg.eigh(M)[1][:, -1]
    return q if q[3] >= 0 else -q


def _angle_to(q_xyzw: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    dot = np.clip(np.abs(q_xyzw @ q_ref), 0.0, 1.0)
    return 2.0 * np.arccos(dot)


def _cluster_seed(positions: np.ndarray, weights: np.ndarray, radius_m: float) -> int:
    """Index of the heaviest particle inside the heaviest position cell."""
    keys = np.floor(positions / radius_m).astype(np.int64)
    _, cell = np.unique(keys, axis=0, return_inverse=True)
    cell = cell.ravel()
    cell_weight = np.bincount(cell, weights=weights)
    in_best = np.flatnonzero(cell == np.argmax(cell_weight))
    return int(in_best[np.argmax(weights[in_best])])


def _hypothesis(positions, quats, weights, total) -> Hypothesis:
    w = weights / weights.sum()
    t_mean = w @ positions
    q_mean = average_quaternions(quats, w)
    T_mean = geometry.se3_from_tq(t_mean, q_mean)
    T_members = geometry.se3_from_tq(positions, quats)
    xi = geometry.se3_log(geometry.se3_inverse(T_mean)[None] @ T_members)
    centred = xi - w @ xi
    covariance = (centred * w[:, None]).T @ centred
    return Hypothesis(T_mean, covariance, float(weights.sum() / total), len(weights))


def cluster_hypotheses(positions: np.ndarray, quats_xyzw: np.ndarray, weights: np.ndarray,
                       params: ClusterParams = ClusterParams()) -> list[Hypothesis]:
    """Up to `max_hypotheses` clusters, heaviest first, found by seeded mean shift."""
    positions = np.asarray(positions, dtype=np.float64)
    quats = np.asarray(quats_xyzw, dtype=np.float64)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    weights = np.asarray(weights, dtype=np.float64)
    total = weights.sum()
    remaining = np.flatnonzero(weights > 0)
    hypotheses: list[Hypothesis] = []
    while remaining.size and len(hypotheses) < params.max_hypotheses:
        pos, q, w = positions[remaining], quats[remaining], weights[remaining]
        seed = _cluster_seed(pos, w, params.radius_m)
        centre, q_centre = pos[seed], q[seed]
        members = np.zeros(len(remaining), dtype=bool)
        for _ in range(params.mean_shift_iterations):
            members = (np.linalg.norm(pos - centre, axis=1) <= params.radius_m) & (
                _angle_to(q, q_centre) <= params.angle_rad)
            if not members.any():
                members[seed] = True
            wm = w[members] / w[members].sum()
            centre = wm @ pos[members]
            q_centre = average_quaternions(q[members], wm)
        hypotheses.append(_hypothesis(pos[members], q[members], w[members], total))
        remaining = remaining[~members]
    hypotheses.sort(key=lambda h: h.weight, reverse=True)
    return hypotheses


def kld_sample_count(occupied_bins: int, epsilon: float, delta: float, n_min: int,
                     n_max: int) -> int:
    """Fox's KLD-sampling bound: particles needed so the KL error stays below `epsilon`
    with probability 1 - `delta`, using the real upper normal quantile z_{1-delta}."""
    from scipy.stats import norm

    k = occupied_bins
    if k <= 1:
        return n_min
    z = norm.ppf(1.0 - delta)
    a = 2.0 / (9.0 * (k - 1))
    n = (k - 1) / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return int(np.clip(np.ceil(n), n_min, n_max))
