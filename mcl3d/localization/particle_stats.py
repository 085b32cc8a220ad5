"""What the host needs of the particle set, computed on the device, of a size independent of
the particle count N: weighted means (match ratio, log-likelihood), the heaviest particle, a
sample of particles drawn by weight or picked by index, and the ESS of a re-tempered scan.

Copying every particle to the host each update caps a GPU (the copies and the host work on
them grow with N); a sample of `samples` particles drawn by weight (systematic resampling
along the weights' CDF, as the host's `estimate.systematic_sample` draws it) is all that
clustering needs, so only that sample crosses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import taichi as ti

from mcl3d.core import geometry
from mcl3d.kernels import cluster_labels as kc
from mcl3d.kernels import particle_stats as ks
from mcl3d.kernels import resample as kr
from mcl3d.localization.estimate import WeightedParticles
from mcl3d.localization.particle_set import ParticleSet
from mcl3d.localization.resampling import MIN_WEIGHT_SQUARES


@dataclass(frozen=True)
class CloudStats:
    """Weighted statistics of one update's particles (weights in the set's `w`)."""

    match_ratio: float  # weighted mean fraction of scan points on a surface
    mean_log_likelihood: float  # weighted mean per-point log-likelihood
    best_match_ratio: float  # the largest match ratio of any particle
    T_best: np.ndarray  # (4, 4) the heaviest particle (the first of equals)


def cloud_stats(p: ParticleSet, total_weight: float) -> CloudStats:
    """Reductions over the `w` that `resampling.compute_weights` left (sum `total_weight`)."""
    n = p.n
    ks.weighted_partials(p.w, p.match, p.ll_mean, n, p.partial_sums)
    kr.sum_partials(p.partial_sums, n, p.sums)
    sum_match, sum_ll = float(p.sums[0]), float(p.sums[1])
    best = ks.first_index_of(p.w, n, kr.max_log_weight(p.w, n))
    best = min(best, n - 1)
    T_best = geometry.se3_from_tq(p.pos[best].to_numpy().astype(np.float64),
                                  p.quat[best].to_numpy().astype(np.float64))
    return CloudStats(sum_match / total_weight, sum_ll / total_weight,
                      float(kr.max_log_weight(p.match, n)), T_best)


def tempered_ess(p: ParticleSet, coef: float) -> float:
    """ESS of the weights exp(log_w + coef * ll_mean) (annealing's candidate tempering)."""
    n = p.n
    ks.tempered_sums(p.log_w, p.ll_mean, n, coef, p.partial_sums, p.sums)
    s1, s2 = p.sums.to_numpy().astype(np.float64)
    return s1 * s1 / max(s2, MIN_WEIGHT_SQUARES)


class ParticleSampler:
    """Device fields for a sample of at most `capacity` particles and its host copy."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self._idx = ti.field(ti.i32, shape=self.capacity)
        self._pos = ti.Vector.field(3, ti.f32, shape=self.capacity)
        self._quat = ti.Vector.field(4, ti.f32, shape=self.capacity)
        self._w = ti.field(ti.f32, shape=self.capacity)

    def by_weight(self, p: ParticleSet, total_weight: float, k: int, u0: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(positions (k, 3), quaternions (k, 4)) float64 of `k` particles drawn by weight
        with the offset `u0` in [0, 1) (systematic: particle j is drawn for the slots s with
        C_{j-1} <= (s + u0) / k < C_j)."""
        n = p.n
        k = self._check(k)
        kr.scan_blocks(p.w, n, p.cdf, p.block_sums)
        kr.scan_block_sums(p.block_sums, (n + kr.SCAN_BLOCK - 1) // kr.SCAN_BLOCK)
        kr.add_block_offsets(p.cdf, n, p.block_sums, total_weight)
        kr.systematic_select(p.cdf, n, k, u0, self._idx)
        return self._gathered(p, k)

    def at(self, p: ParticleSet, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions, quaternions) float64 of the particles at `indices` (< n)."""
        k = self._check(len(indices))
        idx = np.zeros(self.capacity, np.int32)
        idx[:k] = indices
        self._idx.from_numpy(idx)
        return self._gathered(p, k)

    def shown(self, p: ParticleSet, total_weight: float, indices: np.ndarray
              ) -> WeightedParticles:
        """The particles at `indices` with their weights / `total_weight` (to show)."""
        pos, quat = self.at(p, indices)
        k = len(indices)
        ks.gather_values(p.w, self._idx, k, self._w)
        w = self._w.to_numpy()[:k].astype(np.float64) / total_weight
        return WeightedParticles(pos, quat, w, np.zeros(k), np.zeros(k))

    def _check(self, k: int) -> int:
        if not 0 < k <= self.capacity:
            raise ValueError(f"a sample of {k} particles does not fit {self.capacity}")
        return int(k)

    def _gathered(self, p: ParticleSet, k: int) -> tuple[np.ndarray, np.ndarray]:
        ks.gather_poses(p.pos, p.quat, self._idx, k, self._pos, self._quat)
        return (self._pos.to_numpy()[:k].astype(np.float64),
                self._quat.to_numpy()[:k].astype(np.float64))


def evenly(count: int, keep: int) -> np.ndarray:
    """Indices of at most `keep` of `count` items, evenly spread (deterministic)."""
    if count <= keep:
        return np.arange(count)
    return np.linspace(0, count - 1, keep).astype(np.int64)


class MeanOfAll:
    """The weighted mean pose of every particle and the covariance about it (`estimate.mean:
    all`, the paper's estimate) from device moments: 14 + 27 numbers come back."""

    def __init__(self, capacity: int):
        blocks = (int(capacity) + kr.SCAN_BLOCK - 1) // kr.SCAN_BLOCK
        self._pose = ti.Vector.field(14, ti.f32, shape=blocks)
        self._pose_sum = ti.Vector.field(14, ti.f32, shape=1)
        self._tangent = ti.Vector.field(27, ti.f32, shape=blocks)
        self._tangent_sum = ti.Vector.field(27, ti.f32, shape=1)

    def __call__(self, p: ParticleSet) -> tuple[np.ndarray, np.ndarray]:
        """(T_mean (4, 4), covariance (6, 6) rotation first) of the weights in `p.w`."""
        n = p.n
        ks.pose_moment_partials(p.pos, p.quat, p.w, n, self._pose)
        ks.sum_vector_partials(self._pose, n, self._pose_sum)
        m = self._pose_sum.to_numpy()[0].astype(np.float64)
        t_mean = m[1:4] / m[0]
        qq = geometry.symmetric_from_upper(m[4:], 4)
        q_mean = np.linalg.eigh(qq)[1][:, -1]  # as average_quaternions
        q_mean = q_mean if q_mean[3] >= 0 else -q_mean
        ks.tangent_moment_partials(p.pos, p.quat, p.w, n, ti.math.vec3(*t_mean),
                                   ti.math.vec4(*q_mean), self._tangent)
        ks.sum_vector_partials(self._tangent, n, self._tangent_sum)
        x = self._tangent_sum.to_numpy()[0].astype(np.float64) / m[0]
        covariance = geometry.symmetric_from_upper(x[6:], 6) - np.outer(x[:6], x[:6])
        return geometry.se3_from_tq(t_mean, q_mean), covariance


class ClusterLabels:
    """Every particle's cluster on the device, the clusters' weights, and the resampling
    factors of a mode floor (`search.update_modes`): centres and factors go down, one
    weight per cluster comes back."""

    def __init__(self, capacity: int):
        blocks = (int(capacity) + kr.SCAN_BLOCK - 1) // kr.SCAN_BLOCK
        self._centres = ti.Vector.field(7, ti.f32, shape=kc.MAX_CENTRES)
        self._partial = ti.Vector.field(kc.MAX_CENTRES, ti.f32, shape=blocks)
        self._sum = ti.Vector.field(kc.MAX_CENTRES, ti.f32, shape=1)
        self._table = ti.field(ti.f32, shape=kc.MAX_CENTRES + 1)

    def weights(self, p: ParticleSet, centres: list[np.ndarray], radius_m: float,
                angle_rad: float, total_weight: float) -> np.ndarray:
        """Labels every particle with the first centre (4x4 pose) within `radius_m` and
        `angle_rad` (`estimate.label_particles`) into `p.label`; each centre's share of the
        weights in `p.w` (sum `total_weight`)."""
        c = len(centres)
        if c > kc.MAX_CENTRES:
            raise ValueError(f"{c} cluster centres; the device labels at most {kc.MAX_CENTRES}")
        host = np.zeros((kc.MAX_CENTRES, 7), np.float32)
        for i, T in enumerate(centres):
            host[i, :3], host[i, 3:] = T[:3, 3], geometry.rot_to_quat(T[:3, :3])
        self._centres.from_numpy(host)
        kc.label_by_centres(p.pos, p.quat, p.n, self._centres, c, radius_m,
                            float(np.cos(0.5 * min(angle_rad, np.pi))), p.label)
        kc.label_weight_partials(p.w, p.label, p.n, self._partial)
        ks.sum_vector_partials(self._partial, p.n, self._sum)
        return self._sum.to_numpy()[0, :c].astype(np.float64) / total_weight

    def apply(self, p: ParticleSet, table: np.ndarray, keep_place_factors: bool) -> None:
        """p.factor = table[label + 1] (`estimate.mode_floor_table`), or the larger of that
        and the place factors already in p.factor (`PlaceEvidence.floor`) when
        `keep_place_factors`."""
        padded = np.ones(kc.MAX_CENTRES + 1, np.float32)
        padded[:len(table)] = table
        self._table.from_numpy(padded)
        kc.label_factors(p.label, p.n, self._table, int(keep_place_factors), p.factor)
