"""Global search: from a uniform cloud to one pose, without losing the true mode on the way.

A fresh search (global initialization or a global re-seed) first scores scans with a coarse
model whose sigma shrinks scan by scan (a blurred search heuristic with wide basins), then
with the accurate model. Until the first convergence each scan is tempered further
(annealing) so that it cannot collapse the cloud at once. Mode-preserving resampling keeps
every plausible cluster alive with a share of the particles, and the search is converged
only when one cluster dominated for several scans after the sensor moved (docs/sensor-model.md).
"""

from __future__ import annotations

import numpy as np

from mcl3d.core import geometry
from mcl3d.kernels.particles import add_scaled
from mcl3d.localization.estimate import (
    ClusterParams,
    Hypothesis,
    cluster_hypotheses,
    mode_floor_table,
)
from mcl3d.localization.evidence import PlaceEvidence
from mcl3d.localization.localization_config import LocalizerConfig
from mcl3d.localization.particle_set import ParticleSet
from mcl3d.localization.particle_stats import ClusterLabels, ParticleSampler, tempered_ess

COARSE_MIN_WEIGHT = 1e-12  # the coarse phase's mode floor protects any cluster it finds
ANNEAL_BISECTIONS = 12  # steps of the search for the tempering factor beta


class GlobalSearch:
    """The state of a global search since the last global (re-)initialization."""

    def __init__(self, cfg: LocalizerConfig, sampler: ParticleSampler):
        self.cfg = cfg
        self.sampler = sampler  # device sample fields shared with the estimate
        self.labels = ClusterLabels(cfg.particles)
        self.active = False
        self.scans = 0  # scans scored since the search began
        self.moved = np.zeros(2)  # m, rad since the search began
        self.dominant_run = 0  # scans in a row with one dominant cluster
        self.exploring = False  # this update is a coarse or grace scan (see update_modes)
        self.floored = False  # the particle set's `factor` holds mode-preserving factors
        self.rivals = 0  # protected clusters besides the dominant one
        self.live_places = 0  # places whose evidence the scans have not ruled out

    def start(self, scans_done: int = 0) -> None:
        """A fresh search; `scans_done` = coarse_scans skips the coarse phase."""
        self.active = True
        self.scans = scans_done
        self.moved[:] = 0.0
        self.dominant_run = 0

    def coarse_sigma(self) -> float | None:
        """The coarse model's sigma for the next scan, None outside the coarse phase."""
        s = self.cfg.sensor
        if not self.active or s.coarse_sigma_m <= 0 or self.scans >= s.coarse_scans:
            return None
        frac = self.scans / s.coarse_scans
        return s.coarse_sigma_m * (min(s.search_sigma_m, s.coarse_sigma_m)
                                   / s.coarse_sigma_m) ** frac

    def begin_update(self) -> None:
        self.exploring = self.active and self.scans < (
            self.cfg.sensor.coarse_scans + self.cfg.resample.mode_grace_scans)

    def add_motion(self, T_prev_curr: np.ndarray) -> None:
        if self.active:
            self.moved += [np.linalg.norm(T_prev_curr[:3, 3]),
                           geometry.rotation_angle(np.asarray(T_prev_curr)[:3, :3])]

    def count_scan(self) -> None:
        if self.active:
            self.scans += 1

    def update_modes(self, p: ParticleSet, total_weight: float, hyps: list[Hypothesis],
                     rng: np.random.Generator,
                     evidence: PlaceEvidence | None = None) -> None:
        """Mode-preserving resampling factors (`mode_floor`) into `p.factor`: the clusters
        are those of the weighted sample plus those of a uniform sample of the particles (a
        mode that holds many particles but little weight), merged when closer than two
        cluster radii; every particle is labelled on the device. During the coarse phase the
        model is a deliberately blurred search heuristic, not evidence to accumulate: the
        heaviest clusters keep their floor whatever their weight, and the copies start with
        equal weights (tempering), so the accurate model decides between the modes from the
        end of the coarse phase on. With `evidence` (added this update), every place the scans
        have not ruled out also keeps a floor of particles (`PlaceEvidence.floor`, on the
        device), however many look-alike places there are."""
        e, r = self.cfg.estimate, self.cfg.resample
        self.floored, self.rivals, self.live_places = False, 0, 0
        if not self.active or r.mode_share <= 0:
            return
        k = min(p.n, e.samples)
        pos, quat = self.sampler.at(p, rng.choice(p.n, k, replace=False))
        params = ClusterParams(e.cluster_radius_m, e.cluster_angle_rad, e.max_hypotheses)
        populous = cluster_hypotheses(pos, quat, np.full(k, 1.0 / k), params)
        centres: list[np.ndarray] = []
        for h in hyps + populous:
            T = h.T_map_lidar
            if all(np.linalg.norm(T[:3, 3] - C[:3, 3]) > 2 * e.cluster_radius_m
                   or geometry.rotation_angle(C[:3, :3].T @ T[:3, :3])
                   > 2 * e.cluster_angle_rad for C in centres):
                centres.append(T)
        cluster_w = self.labels.weights(p, centres, e.cluster_radius_m, e.cluster_angle_rad,
                                        total_weight)
        table, self.rivals = mode_floor_table(
            cluster_w, r.mode_share, COARSE_MIN_WEIGHT if self.exploring else r.mode_min_weight,
            e.max_hypotheses)
        place_floored = False
        if evidence is not None and r.place_min_particles > 0:
            margin = max(r.place_margin_nats, evidence.noise_margin(evidence.places))
            self.live_places = evidence.floor(p, margin, r.place_min_particles)
            place_floored = self.live_places >= 2
        if self.rivals or place_floored:
            self.labels.apply(p, table, place_floored)
            self.floored = True

    def converged(self, dominant: bool) -> bool:
        """Whether one cluster dominated long enough, after the coarse phase, with no rival
        and after enough motion: scans from one place are not independent evidence."""
        e = self.cfg.estimate
        self.dominant_run = self.dominant_run + 1 if (
            dominant and self.coarse_sigma() is None and not self.rivals) else 0
        moved = (self.moved[0] >= e.converge_min_motion_m
                 or self.moved[1] >= e.converge_min_rotation_rad)
        return self.dominant_run >= e.converged_scans and moved


def anneal(p: ParticleSet, scale: float, min_ess_share: float) -> float:
    """Largest beta <= 1 with ESS(log_w_prev + beta * increment) >= min_ess_share * N; the
    increment (scale * per-point mean ll) already added is scaled down to beta times itself.
    Each candidate's ESS is a reduction on the device (two numbers come back)."""
    n = p.n
    target = min_ess_share * n
    if tempered_ess(p, 0.0) >= target:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(ANNEAL_BISECTIONS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if tempered_ess(p, (mid - 1.0) * scale) >= target else (lo, mid)
    add_scaled(p.log_w, p.ll_mean, n, float((lo - 1.0) * scale))
    return lo
