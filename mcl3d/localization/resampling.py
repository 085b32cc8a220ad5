"""Weights and systematic resampling of the particle set on the device.

Weights are exp(log_w - max) with their sum and sum of squares (ESS); resampling draws
`n_out` parents along the weights' CDF with one random offset, gathers them into the back
buffers and swaps. Mode-preserving resampling draws along weight * factor instead and gives
each copy the log-weight -log(factor) of its parent, so the posterior is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core import geometry
from mcl3d.kernels import resample as kr
from mcl3d.kernels.particles import gather
from mcl3d.localization.estimate import WeightedParticles, kld_sample_count, systematic_sample
from mcl3d.localization.localization_config import ResampleConfig
from mcl3d.localization.particle_set import ParticleSet

MIN_WEIGHT_SQUARES = 1e-30  # keeps the ESS finite when every weight underflowed


@dataclass(frozen=True)
class Weights:
    total: float  # sum of the shifted weights now in the particle set's `w`
    ess: float  # effective sample size


def compute_weights(p: ParticleSet) -> Weights:
    """The particles' weights into `p.w`, shifted by the largest log-weight."""
    n = p.n
    shift = kr.max_log_weight(p.log_w, n)
    kr.shifted_weights(p.log_w, n, shift, p.w, p.partial_sums)
    kr.sum_partials(p.partial_sums, n, p.sums)
    s1, s2 = float(p.sums[0]), float(p.sums[1])
    return Weights(s1, s1 * s1 / max(s2, MIN_WEIGHT_SQUARES))


def kld_count(cloud: WeightedParticles, cfg: ResampleConfig, samples: int, capacity: int,
              rng: np.random.Generator) -> int:
    """Particles to draw by KLD-sampling: bins of x, y, z and yaw of a weighted subsample."""
    pos, quat, w = cloud.positions, cloud.quats_xyzw, cloud.weights
    k = min(len(w), samples)
    idx = systematic_sample(w, k, rng)
    R = geometry.quat_to_rot(quat[idx])
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    keys = np.column_stack([np.floor(pos[idx] / cfg.kld_bin_m),
                            np.floor(yaw / cfg.kld_bin_rad)]).astype(np.int64)
    bins = len(np.unique(keys, axis=0))
    lo = min(cfg.min_particles, capacity)
    return kld_sample_count(bins, cfg.kld_epsilon, cfg.kld_delta, lo, capacity)


def resample(p: ParticleSet, n_out: int, weights: Weights, u0: float,
             mode_factors: np.ndarray | None = None, cloud: WeightedParticles | None = None,
             keep_posterior: bool = True) -> None:
    """Draw `n_out` particles (offset `u0` in [0, 1)) by weight, or by weight * factor when
    `mode_factors` are given (then `cloud` holds the weights, and `keep_posterior` gives
    each copy its parent's -log(factor))."""
    n = p.n
    total = weights.total
    if mode_factors is not None:
        total = _upload_floored_weights(p, cloud.weights, mode_factors)
    kr.scan_blocks(p.w, n, p.cdf, p.block_sums)
    kr.scan_block_sums(p.block_sums, (n + kr.SCAN_BLOCK - 1) // kr.SCAN_BLOCK)
    kr.add_block_offsets(p.cdf, n, p.block_sums, total)
    kr.systematic_select(p.cdf, n, n_out, u0, p.parent)
    gather(p.pos, p.quat, p.parent, n_out, p.pos_back, p.quat_back, p.log_w)
    p.swap()
    p.n = n_out
    if mode_factors is not None and keep_posterior:
        _restore_posterior(p, mode_factors, n_out)


def _upload_floored_weights(p: ParticleSet, w: np.ndarray, factors: np.ndarray) -> float:
    """Resampling weights w * factor (mode-preserving) into p.w; returns their sum."""
    host = np.zeros(p.capacity, np.float32)
    host[:len(w)] = w * factors
    p.w.from_numpy(host)
    return float(host.sum(dtype=np.float64))


def _restore_posterior(p: ParticleSet, factors: np.ndarray, n_out: int) -> None:
    """Each copy carries log(weight / resampling weight) of its parent: the floored modes
    keep their particles but not more than their share of the posterior."""
    parent = p.parent.to_numpy()[:n_out]
    log_w = np.zeros(p.capacity, np.float32)
    log_w[:n_out] = -np.log(factors[parent])
    p.log_w.from_numpy(log_w)
