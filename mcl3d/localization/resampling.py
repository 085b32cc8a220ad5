"""Weights and systematic resampling of the particle set on the device.

Weights are exp(log_w - max) with their sum and sum of squares (ESS); resampling draws
`n_out` parents along the weights' CDF with one random offset, gathers them into the back
buffers and swaps. Mode-preserving resampling draws along weight * factor instead and gives
each copy the log-weight -log(factor) of its parent, so the posterior is unchanged. The
factors are set on the device (`particle_stats.ClusterLabels`); the weights, the parents and
the restored log-weights stay there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core import geometry
from mcl3d.kernels import resample as kr
from mcl3d.kernels.particle_stats import weighted_partials
from mcl3d.kernels.particles import apply_factors, gather, log_inverse_parent_factor
from mcl3d.localization.estimate import kld_sample_count
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


def kld_count(positions: np.ndarray, quats_xyzw: np.ndarray, cfg: ResampleConfig,
              capacity: int) -> int:
    """Particles to draw by KLD-sampling: the bins of x, y, z and yaw occupied by a sample
    of the particles drawn by weight."""
    R = geometry.quat_to_rot(quats_xyzw)
    yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
    keys = np.column_stack([np.floor(positions / cfg.kld_bin_m),
                            np.floor(yaw / cfg.kld_bin_rad)]).astype(np.int64)
    bins = len(np.unique(keys, axis=0))
    lo = min(cfg.min_particles, capacity)
    return kld_sample_count(bins, cfg.kld_epsilon, cfg.kld_delta, lo, capacity)


def resample(p: ParticleSet, n_out: int, weights: Weights, u0: float, floored: bool = False,
             keep_posterior: bool = True) -> None:
    """Draw `n_out` particles (offset `u0` in [0, 1)) by weight, or by weight * `p.factor`
    when `floored` (mode-preserving); `keep_posterior` then gives each copy its parent's
    -log(factor)."""
    n = p.n
    total = _floored_weights(p) if floored else weights.total
    kr.scan_blocks(p.w, n, p.cdf, p.block_sums)
    kr.scan_block_sums(p.block_sums, (n + kr.SCAN_BLOCK - 1) // kr.SCAN_BLOCK)
    kr.add_block_offsets(p.cdf, n, p.block_sums, total)
    kr.systematic_select(p.cdf, n, n_out, u0, p.parent)
    gather(p.pos, p.quat, p.parent, n_out, p.pos_back, p.quat_back, p.log_w)
    p.swap()
    p.n = n_out
    if floored and keep_posterior:
        log_inverse_parent_factor(p.factor, p.parent, n_out, p.log_w)


def _floored_weights(p: ParticleSet) -> float:
    """Resampling weights w * factor (mode-preserving) into p.w; returns their sum."""
    weighted_partials(p.w, p.factor, p.factor, p.n, p.partial_sums)
    kr.sum_partials(p.partial_sums, p.n, p.sums)
    apply_factors(p.w, p.factor, p.n)  # the same f32 products, summed in the same order
    return float(p.sums[0])
