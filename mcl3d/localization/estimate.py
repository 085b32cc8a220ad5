"""Pose estimates from a weighted particle set: dominant cluster, hypotheses, convergence.

A weighted mean over all particles is meaningless while the filter is multi-modal (the
peer tsdf_localization averages across modes during global localization). Here the estimate
is the mean of the heaviest cluster only; the other clusters are reported as hypotheses.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import norm

from mcl3d.core import geometry
from mcl3d.localization.localization_config import EstimateConfig


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
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) < 2.0 ** 62:
        # one int64 per cell, in the rows' lexicographic order: the same cells, ~20x faster
        code = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        cell = np.unique(code, return_inverse=True)[1]
    else:
        cell = np.unique(keys, axis=0, return_inverse=True)[1]
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


def label_particles(positions: np.ndarray, quats_xyzw: np.ndarray, centres: list[np.ndarray],
                    radius_m: float, angle_rad: float) -> np.ndarray:
    """Index of the first cluster centre (a 4x4 pose) within `radius_m` and `angle_rad` of
    each particle, -1 for none: cluster membership for every particle, not just a sample."""
    labels = np.full(len(positions), -1, dtype=np.int64)
    for c, T in enumerate(centres):
        q_c = geometry.rot_to_quat(T[:3, :3])
        free = labels < 0
        near = free & (np.linalg.norm(positions - T[:3, 3], axis=1) <= radius_m)
        near[near] = _angle_to(quats_xyzw[near], q_c) <= angle_rad
        labels[near] = c
    return labels


@dataclass(frozen=True)
class ModeFloor:
    factors: np.ndarray  # (N,) resampling weight = weight * factor for each particle
    rivals: int  # protected clusters besides the heaviest one


def mode_floor(labels: np.ndarray, weights: np.ndarray, share: float, min_weight: float,
               max_modes: int) -> ModeFloor:
    """Resampling factors that keep at least `share` of the particles in every cluster whose
    posterior weight is at least `min_weight` (the `max_modes` heaviest such clusters).

    Resampling by weight alone lets a mode that is as good as the winner, but momentarily a
    little lighter, die out by chance within a few updates (the 180-degree mirror pose in a
    near-symmetric hall); once it has no particles no evidence can bring it back. Resampling
    with weight * factor keeps its particles; each copy then carries the log-weight
    -log(factor) of its parent, so the posterior (cluster weights, estimate) is unchanged.
    `rivals` > 0 says another mode still holds non-negligible weight.
    """
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    k = int(labels.max()) + 1 if len(labels) else 0
    cluster_w = np.bincount(labels[labels >= 0], weights=w[labels >= 0], minlength=k)
    table, rivals = mode_floor_table(cluster_w, share, min_weight, max_modes)
    return ModeFloor(table[labels + 1], rivals)


def mode_floor_table(cluster_w: np.ndarray, share: float, min_weight: float, max_modes: int
                     ) -> tuple[np.ndarray, int]:
    """`mode_floor` from the clusters' shares of the weight: (factor per label + 1, entry 0
    for the particles of no cluster, rivals), what the device applies to every particle."""
    cluster_w = np.asarray(cluster_w, dtype=np.float64)
    order = [c for c in np.argsort(-cluster_w, kind="stable") if cluster_w[c] >= min_weight]
    kept = order[:max_modes]
    table = np.ones(len(cluster_w) + 1)
    if len(kept) < 2:
        return table, 0
    floored = [c for c in kept if cluster_w[c] < share]
    if floored:  # they get `share` each; everything else shares the rest by weight
        others_w = 1.0 - cluster_w[floored].sum()
        table[:] = (1.0 - share * len(floored)) / others_w
        for c in floored:
            table[c + 1] = share / cluster_w[c]
    return table, len(kept) - 1


def kld_sample_count(occupied_bins: int, epsilon: float, delta: float, n_min: int,
                     n_max: int) -> int:
    """Fox's KLD-sampling bound: particles needed so the KL error stays below `epsilon`
    with probability 1 - `delta`, using the real upper normal quantile z_{1-delta}."""
    k = occupied_bins
    if k <= 1:
        return n_min
    z = norm.ppf(1.0 - delta)
    a = 2.0 / (9.0 * (k - 1))
    n = (k - 1) / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3
    return int(np.clip(np.ceil(n), n_min, n_max))


@dataclass(frozen=True)
class WeightedParticles:
    """One update's particles on the host (float64), weights normalized to sum 1."""

    positions: np.ndarray  # (n, 3) m
    quats_xyzw: np.ndarray  # (n, 4)
    weights: np.ndarray  # (n,)
    match: np.ndarray  # (n,) fraction of scan points on a surface
    mean_ll: np.ndarray  # (n,) mean per-point log-likelihood


@dataclass(frozen=True)
class PoseEstimate:
    """The estimate's parts: the dominant cluster's mean and spread, the other clusters."""

    T_map_lidar: np.ndarray  # (4, 4) mean of the heaviest cluster
    T_best: np.ndarray  # (4, 4) the heaviest particle
    covariance: np.ndarray  # (6, 6) of the heaviest cluster, rotation-first [rad^2, m^2]
    hypotheses: list[Hypothesis]  # the strong clusters (at least the heaviest one)
    clusters: list[Hypothesis]  # every cluster found, heaviest first
    dominant: bool  # the heaviest cluster is heavy and compact enough to be converged
    match_ratio: float  # weighted mean fraction of scan points on a surface
    mean_log_likelihood: float  # weighted mean per-point log-likelihood


def systematic_sample(weights: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """`k` indices drawn by systematic resampling of `weights` (one random offset)."""
    cdf = np.cumsum(weights)
    cdf /= cdf[-1]
    return np.minimum(np.searchsorted(cdf, (np.arange(k) + rng.random()) / k), len(cdf) - 1)


def estimate_pose(cloud: WeightedParticles, cfg: EstimateConfig, rng: np.random.Generator
                  ) -> PoseEstimate:
    """Clusters of a weighted subsample of `cfg.samples` particles; the heaviest is the
    estimate, dominant when it passes the convergence test."""
    pos, quat, w = cloud.positions, cloud.quats_xyzw, cloud.weights
    best = int(np.argmax(w))
    k = min(len(w), cfg.samples)
    idx = systematic_sample(w, k, rng)
    return estimate_from_sample(pos[idx], quat[idx], geometry.se3_from_tq(pos[best], quat[best]),
                                float(w @ cloud.match), float(w @ cloud.mean_ll), cfg)


def estimate_from_sample(positions: np.ndarray, quats_xyzw: np.ndarray, T_best: np.ndarray,
                         match_ratio: float, mean_log_likelihood: float, cfg: EstimateConfig
                         ) -> PoseEstimate:
    """`estimate_pose` from particles already drawn by weight (equal weights) and the
    cloud's weighted statistics: what the localizer computes on the device."""
    k = len(positions)
    hyps = cluster_hypotheses(positions, quats_xyzw, np.full(k, 1.0 / k),
                              ClusterParams(cfg.cluster_radius_m, cfg.cluster_angle_rad,
                                            cfg.max_hypotheses))
    h0 = hyps[0]
    compact = (h0.position_std_m <= cfg.converged_std_m
               and h0.rotation_std_rad <= cfg.converged_std_rad)
    strong = [h for h in hyps if h.weight >= cfg.hypothesis_min_weight]
    return PoseEstimate(
        T_map_lidar=h0.T_map_lidar, T_best=T_best, covariance=h0.covariance,
        hypotheses=strong or hyps[:1], clusters=hyps,
        dominant=h0.weight >= cfg.converged_weight and compact,
        match_ratio=float(match_ratio), mean_log_likelihood=float(mean_log_likelihood))


def with_mean_of_all(estimate: PoseEstimate, cloud: WeightedParticles) -> PoseEstimate:
    """`estimate` with the pose and covariance of the weighted mean of every particle
    (`estimate.mean: all`, the paper's estimate) instead of the heaviest cluster's; the
    clusters, and so the convergence test, stay as they were."""
    w = np.asarray(cloud.weights, dtype=np.float64)
    keep = w > 0
    quats = cloud.quats_xyzw[keep] / np.linalg.norm(cloud.quats_xyzw[keep], axis=1,
                                                     keepdims=True)
    mean = _hypothesis(cloud.positions[keep], quats, w[keep], w.sum())
    return replace(estimate, T_map_lidar=mean.T_map_lidar, covariance=mean.covariance)
