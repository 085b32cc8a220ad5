"""The particle filter's parameters (`LocalizerConfig` and its sections), with units.

Angles are degrees in these sections (as in every config file); each section converts them
to radians once, in the `*_rad` properties the filter reads. The degree defaults are the
floats whose conversion gives the radian values the filter was tuned with, exactly.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError
from mcl3d.localization.initialization import InitConfig
from mcl3d.localization.sensor_model import SensorModelConfig


class MotionNoiseConfig(Section):
    """Per-update noise std, growing with the motion: std = alpha * |motion| + floor."""

    trans_per_m: float = Field(0.10, ge=0.0, description="m of translation noise per m moved")
    trans_per_deg: float = Field(0.0008726646259971648, ge=0.0,
                                 description="m of translation noise per deg turned")
    rot_per_deg: float = Field(0.10, ge=0.0,
                               description="deg of rotation noise per deg turned (a ratio)")
    rot_deg_per_m: float = Field(1.1459155902616465, ge=0.0,
                                 description="deg of rotation noise per m moved")
    trans_floor_m: float = Field(0.02, ge=0.0, description="translation noise every update")
    rot_floor_deg: float = Field(0.5729577951308232, ge=0.0,
                                 description="rotation noise every update, deg")
    explore_trans_m: float = Field(0.05, ge=0.0, description="extra translation noise until "
                                                             "the filter first converges")
    explore_rot_deg: float = Field(1.7188733853924696, ge=0.0,
                                   description="extra rotation noise until the filter first "
                                               "converges, deg")

    @property
    def trans_per_rad(self) -> float:
        return math.degrees(self.trans_per_deg)

    @property
    def rot_rad_per_m(self) -> float:
        return math.radians(self.rot_deg_per_m)

    @property
    def rot_floor_rad(self) -> float:
        return math.radians(self.rot_floor_deg)

    @property
    def explore_rot_rad(self) -> float:
        return math.radians(self.explore_rot_deg)


class ResampleConfig(Section):
    ess_threshold: float = Field(0.5, gt=0.0, le=1.0,
                                 description="resample when ESS < threshold * N (1: every "
                                             "scan, as the paper; equal weights, the only "
                                             "case skipped, resample to the same set)")
    anneal_min_ess: float = Field(
        0.05, ge=0.0, lt=1.0, description="until the first convergence, temper each scan "
                                          "further so that ESS >= this * N (0: off)")
    mode_share: float = Field(
        0.1, ge=0.0, lt=0.5, description="global search: every cluster with at least "
                                         "mode_min_weight of the weight keeps at least this "
                                         "share of the particles at resampling (0: off)")
    mode_min_weight: float = Field(
        0.01, gt=0.0, lt=1.0, description="... and a global search is not converged while "
                                          "a second cluster holds this much weight")
    mode_grace_scans: int = Field(
        12, ge=0, description="global search: after the coarse phase, this many scans of the "
                             "accurate model keep every cluster found, with equal weights "
                             "after each resampling, so that a mode the coarse model left "
                             "misaligned aligns before it is judged")
    place_min_particles: int = Field(
        32, ge=0, description="global search: every place (cell of place_cell_m and "
                              "place_yaw_deg) whose best lineage is within place_margin_nats "
                              "of the best keeps at least this many particles at resampling, "
                              "so a look-alike place dies only when the scans rule it out "
                              "(0: off)")
    place_margin_nats: float = Field(10.0, gt=0.0, description="... the evidence margin")
    place_cell_m: float = Field(1.0, gt=0.0, description="... the place cell in x, y, z")
    place_yaw_deg: float = Field(30.0, gt=0.0, le=360.0, description="... and in yaw")
    kld: bool = Field(False, description="adapt the particle count with KLD-sampling")
    min_particles: int = Field(2000, ge=1)
    kld_epsilon: float = Field(0.05, gt=0.0, description="KL error bound")
    kld_delta: float = Field(0.01, gt=0.0, lt=1.0, description="1 - confidence (z = 2.33)")
    kld_bin_m: float = Field(0.25, gt=0.0, description="KLD bin size in x, y, z")
    kld_bin_deg: float = Field(5.729577951308232, gt=0.0, description="KLD bin size in yaw, deg")

    @property
    def kld_bin_rad(self) -> float:
        return math.radians(self.kld_bin_deg)


class EstimateConfig(Section):
    cluster_radius_m: float = Field(1.0, gt=0.0)
    cluster_angle_deg: float = Field(28.64788975654116, gt=0.0)
    max_hypotheses: int = Field(3, ge=1, le=8, description="clusters reported; a global "
                                "search protects up to twice as many (16 on the device)")
    samples: int = Field(5000, ge=100, description="weighted subsample used for clustering")
    converged_weight: float = Field(0.8, gt=0.0, le=1.0,
                                    description="dominant cluster weight to be converged")
    converged_std_m: float = Field(0.25, gt=0.0, description="... and its worst-axis std")
    converged_std_deg: float = Field(5.729577951308232, gt=0.0)
    hypothesis_min_weight: float = Field(0.1, gt=0.0, le=1.0,
                                         description="clusters reported as hypotheses")
    converged_scans: int = Field(
        5, ge=1, description="global search: the dominant cluster must pass the test this many "
                             "scans in a row (after the coarse phase) to be converged")
    converge_min_motion_m: float = Field(
        1.0, ge=0.0, description="global search: ... and the sensor must have moved this far "
                                 "since the (re-)initialization (or turned as below): scans "
                                 "from one place are not independent evidence")
    converge_min_rotation_deg: float = Field(57.29577951308232, ge=0.0)
    rival_margin_nats: float = Field(
        4.6, ge=0.0, description="not converged while a particle away from the dominant "
                                 "cluster has a lineage whose evidence since the "
                                 "initialization is within this many nats of the dominant's "
                                 "best (a look-alike place; 4.6 = a likelihood ratio of 1%; "
                                 "0: off)")
    mean: Literal["cluster", "all"] = Field(
        "cluster", description="the reported pose: cluster = the weighted mean of the heaviest "
                               "cluster; all = the weighted mean of every particle, as the "
                               "paper (across modes while the filter is multi-modal)")

    @property
    def cluster_angle_rad(self) -> float:
        return math.radians(self.cluster_angle_deg)

    @property
    def converged_std_rad(self) -> float:
        return math.radians(self.converged_std_deg)

    @property
    def converge_min_rotation_rad(self) -> float:
        return math.radians(self.converge_min_rotation_deg)


class CheckConfig(Section):
    """The check of a global search's convergence claim against the whole map
    (mcl3d.localization.claim_check): the claim stands only when no other place, with or
    without particles, explains the recent scans about as well."""

    enabled: bool = Field(True, description="check every claim of a global search")
    grid_m: float = Field(0.5, gt=0.0, description="test positions: one per cell of this "
                                                   "size holding a global candidate")
    yaw_deg: float = Field(10.0, gt=0.0, le=90.0, description="... times yaws this far apart")
    coarse_sigma_m: float = Field(0.4, gt=0.0, description="the coarse model's sigma for the "
                                                           "test poses (wide: grid error)")
    coarse_scans: int = Field(1, ge=1, description="scans of the window, from the one the "
                                                   "test poses are placed at, they are "
                                                   "scored on")
    anchor_scans: int = Field(2, ge=1, description="the test poses are placed at each of this "
                                                   "many newest scans of the window (the "
                                                   "robot may stand off the candidates at one)")
    place_m: float = Field(2.0, gt=0.0, description="one best test pose per cell of this size")
    place_yaw_deg: float = Field(30.0, gt=0.0, le=360.0, description="... and yaw bin")
    candidates: int = Field(15, ge=1, le=63, description="best places per anchor scan refined "
                                                         "and compared (63 in all at most)")
    window_scans: int = Field(8, ge=1, description="scans, spread over the search so far, "
                                                   "that the refined places are compared on")
    history_scans: int = Field(300, ge=1, description="the window spans at most this many "
                                                      "scans back")
    refine_poses: int = Field(256, ge=8, description="poses around each place per round")
    margin_nats: float = Field(
        4.6, ge=0.0, description="a place within this many nats of the claim's (summed "
                                 "tempered log-likelihood over the window) explains the scans "
                                 "about as well: the claim is withheld")
    inject_share: float = Field(0.05, gt=0.0, lt=0.5,
                                description="share of the particles re-seeded at each such "
                                            "place that holds none")


class RecoveryConfig(Section):
    """Loss detection on the weighted match ratio (AMCL-style fast/slow averages)."""

    enabled: bool = True
    alpha_fast: float = Field(0.3, gt=0.0, le=1.0)
    alpha_slow: float = Field(0.02, gt=0.0, le=1.0)
    lost_match_ratio: float = Field(0.35, ge=0.0, le=1.0,
                                    description="lost when the fast average falls below")
    drop_ratio: float = Field(0.5, gt=0.0, le=1.0,
                              description="... or below this fraction of the slow average")
    ll_drop: float = Field(0.15, gt=0.0, description="... or when the fast average of the mean "
                                                    "per-point log-likelihood falls this many "
                                                    "nats below its slow average")
    patience: int = Field(2, ge=1, description="lost scans in a row before re-seeding")
    grace_scans: int = Field(20, ge=0, description="tracking: no recovery before this many "
                                                   "scans after the initialization, unless "
                                                   "converged (a global search: not before "
                                                   "its first convergence)")
    fraction: float = Field(0.5, gt=0.0, le=1.0,
                            description="share of particles re-seeded by expansion")
    global_fraction: float = Field(1.0, gt=0.0, le=1.0,
                                   description="share re-seeded over the whole free space")
    expansion_std_m: float = Field(1.0, gt=0.0, description="expansion resetting, per attempt")
    expansion_std_deg: float = Field(17.188733853924695, gt=0.0)
    expansion_attempts: int = Field(1, ge=0, description="then re-seed globally (one: a "
                                                          "slip is found at once, a kidnap "
                                                          "needs the global search early)")
    attempt_scans: int = Field(5, ge=1, description="scans to wait for an attempt to work")

    @property
    def expansion_std_rad(self) -> float:
        return math.radians(self.expansion_std_deg)


class LocalizerConfig(Section):
    particles: int = Field(100_000, ge=1, description="N (the maximum with KLD)")
    seed: int = Field(0, ge=0, lt=2**32)
    sensor: SensorModelConfig = SensorModelConfig()
    motion: MotionNoiseConfig = MotionNoiseConfig()
    resample: ResampleConfig = ResampleConfig()
    estimate: EstimateConfig = EstimateConfig()
    recovery: RecoveryConfig = RecoveryConfig()
    init: InitConfig = InitConfig()
    check: CheckConfig = CheckConfig()


def check_config(cfg: LocalizerConfig) -> None:
    """ConfigError for settings that are valid one by one but not together."""
    if cfg.resample.kld and cfg.resample.min_particles > cfg.particles:
        raise ConfigError(f"the KLD-sampling minimum of {cfg.resample.min_particles} particles "
                          f"exceeds the maximum of {cfg.particles}", setting="min_particles")
