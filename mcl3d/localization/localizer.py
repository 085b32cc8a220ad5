"""6-DoF Monte Carlo localization in a TSDF: `Localizer(tsdf, config).step(...)`.

One step reads as the algorithm: predict (motion update, kernel) -> weigh (scan likelihood
and weights, kernels) -> estimate (the dominant cluster of a weighted subsample drawn on the
device, host; a global search's place evidence on the device, see `evidence`; its claims
checked against the whole map, see `claim_check`; no per-particle array leaves the device,
see `particle_stats`) -> loss check -> resample
(systematic, kernels, when the ESS is low; optionally KLD-sampling; mode-preserving during a
global search, see `search`) -> recover (re-seed part of the cloud when the filter has lost
track, see `recovery`; places a check found get a share of the particles).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import taichi as ti

from mcl3d.core import geometry
from mcl3d.core.errors import InputError, MapError
from mcl3d.kernels import claim_check as kcc
from mcl3d.kernels import motion
from mcl3d.kernels import particles as kp
from mcl3d.localization.claim_check import INJECT_STD, ClaimCheck, Rival
from mcl3d.localization.estimate import PoseEstimate, WeightedParticles, estimate_from_sample
from mcl3d.localization.evidence import PlaceEvidence
from mcl3d.localization.initialization import FreeCells, free_cells
from mcl3d.localization.localization_config import LocalizerConfig
from mcl3d.localization.particle_set import ParticleSet
from mcl3d.localization.particle_stats import (
    CloudStats,
    MeanOfAll,
    ParticleSampler,
    cloud_stats,
    evenly,
)
from mcl3d.localization.random_streams import (
    CHECK_COUNTER,
    ESTIMATE_SAMPLE_STREAM,
    EVIDENCE_COUNTER,
    INIT_GLOBAL_COUNTER,
    INIT_POSE_COUNTER,
    KLD_SAMPLE_STREAM,
    MODE_SAMPLE_STREAM,
    MOTION_COUNTER,
    RESAMPLE_OFFSET_STREAM,
    host_rng,
    kernel_counter,
)
from mcl3d.localization.recovery import Recovery
from mcl3d.localization.resampling import Weights, compute_weights, kld_count, resample
from mcl3d.localization.search import GlobalSearch, anneal
from mcl3d.localization.sensor_model import MIN_SCAN_POINTS, reduce_scan
from mcl3d.localization.state import (
    STAGES,
    EmptyScan,
    FilterState,
    LocalizationResult,
    Reseed,
)
from mcl3d.localization.weighing import ScanWeigher


class StageTimer:
    """Wall ms per stage of one update (each lap waits for the device)."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self._t0 = time.perf_counter()

    def lap(self, stage: str) -> None:
        ti.sync()
        now = time.perf_counter()
        self.ms[stage] += 1e3 * (now - self._t0)
        self._t0 = now


class Localizer:
    """Particle filter over T_map_lidar; see the module docstring."""

    def __init__(self, tsdf, config: LocalizerConfig, imu_roll_pitch: tuple | None = None):
        self.tsdf = tsdf
        self.cfg = config
        self.particles = ParticleSet(config.particles)
        self.imu_roll_pitch = imu_roll_pitch
        self.step_index = 0
        self.ever_converged = False
        self.shown_particles = 0  # particles of each update to keep in last_cloud (a view)
        self.last_cloud: WeightedParticles | None = None  # the last update's, to show
        self.mean_of_all = MeanOfAll(config.particles)
        self.sampler = ParticleSampler(config.estimate.samples)
        self.search = GlobalSearch(config, self.sampler)
        self.recovery = Recovery(config.recovery)
        self.evidence = PlaceEvidence(config.particles)
        self.claim_check = ClaimCheck(config)
        self._rivals: list[Rival] = []  # places the check found, re-seeded after resampling
        self._places = False  # whether this update added to the places' evidence
        self.weigher = ScanWeigher(tsdf, config.sensor, config.particles)
        self._free: FreeCells | bool | None = None  # False: the map has no candidates
        self._init_step = 0  # step_index of the last (re-)initialization
        self._upright: tuple[float, float] | None = None  # roll, pitch when last converged

    @property
    def seed(self) -> int:
        return self.cfg.seed

    # ------------------------------------------------------------------ initialization
    def free_space(self) -> FreeCells:
        if self._free is None:
            self._free = free_cells(self.tsdf, self.cfg.init)
        return self._free

    def _can_seed_globally(self) -> bool:
        """Whether the map has global candidates: one too large for them (a city-sized map)
        or without observed free space is re-seeded around the estimate instead, and the run
        goes on (the same MapError stops a run that starts globally, before any work)."""
        if self._free is None:
            try:
                self.free_space()
            except MapError:
                self._free = False
        return self._free is not False

    def init_global(self, fraction: float = 1.0) -> None:
        """Uniform over the map's free space; roll/pitch from gravity when known (the IMU's,
        else, for a re-seed, the last converged estimate's: a kidnapped robot is still
        upright, and uniform rotations on SO(3) would waste most particles on tilted poses)."""
        cells = self.free_space()
        if fraction >= 1.0:
            self._start_search()
        self.evidence.reset(self.particles.n)
        p = self.particles
        roll_pitch = None if self.cfg.init.uniform_rotation else (
            self.imu_roll_pitch or self._upright)
        gravity = roll_pitch is not None
        roll, pitch = roll_pitch if gravity else (0.0, 0.0)
        kp.init_cells(p.pos, p.quat, p.log_w, p.n, cells.corners_m, len(cells.corners_m),
                      cells.cell_m, int(gravity), roll, pitch, self.cfg.init.gravity_std_rad,
                      int(self.cfg.init.stratified), fraction, self.seed,
                      kernel_counter(self.step_index, INIT_GLOBAL_COUNTER))

    def init_pose(self, T_map_lidar: np.ndarray, std: list[float], fraction: float = 1.0
                  ) -> None:
        """Gaussian around a pose: std = (x, y, z [m], roll, pitch, yaw [rad])."""
        T = np.asarray(T_map_lidar, dtype=np.float64)
        self._check_in_map(T[:3, 3])
        t, q = geometry.tq_from_se3(T)
        p = self.particles
        self.evidence.reset(p.n)
        kp.init_gaussian(p.pos, p.quat, p.log_w, p.n, ti.math.vec3(*t), ti.math.vec4(*q),
                         ti.math.vec3(*std[:3]), ti.math.vec3(*std[3:6]), fraction,
                         self.seed, kernel_counter(self.step_index, INIT_POSE_COUNTER))

    def init_particles(self, positions: np.ndarray, quats_xyzw: np.ndarray,
                       search: bool = False) -> None:
        """A given particle set (tests, restarts). search=True: it is the state of a global
        search (convergence only after motion, modes kept), without a coarse phase."""
        self.particles.set_host(positions, quats_xyzw)
        self.evidence.reset(self.particles.n)
        if search:
            self._start_search(scans_done=self.cfg.sensor.coarse_scans)

    def _start_search(self, scans_done: int = 0) -> None:
        """A fresh global search: coarse model first, convergence only after motion."""
        self.search.start(scans_done)
        self.claim_check.reset()
        self._init_step = self.step_index
        self.ever_converged = False
        if self.cfg.sensor.coarse_sigma_m > 0:
            self.weigher.build_coarse()

    def _check_in_map(self, t: np.ndarray) -> None:
        lo, hi = self.tsdf.geometry.extent_m
        if np.any(t < lo) or np.any(t > hi):
            raise InputError(
                f"the initial pose {np.round(t, 2).tolist()} m lies outside the map "
                f"({np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()} m): the map and "
                f"the log are in different frames or places; check the map and the initial "
                f"pose", setting="init")

    # ----------------------------------------------------------------------- the step
    def step(self, scan_points: np.ndarray, T_prev_curr: np.ndarray | None, stamp_s: float,
             extra_std: tuple[float, float] = (0.0, 0.0), point_times_s: np.ndarray | None = None,
             twist: np.ndarray | None = None) -> LocalizationResult:
        """One filter update with a scan (lidar frame) and the motion since the last scan.

        `T_prev_curr` None: no motion update (the first scan). `extra_std` (rad, m) widens
        the motion noise when the motion is a guess (constant velocity). With per-point times
        (s after the stamp) and the lidar twist (rotation first, per s) the points are
        deskewed to the stamp.
        """
        timer = StageTimer()
        self.step_index += 1
        counter = kernel_counter(self.step_index, MOTION_COUNTER)
        coarse_sigma = self.search.coarse_sigma()
        self.search.begin_update()
        if T_prev_curr is not None:
            self._predict(T_prev_curr, extra_std, coarse_sigma, counter)
        timer.lap("motion")
        pts = reduce_scan(scan_points, self.cfg.sensor, host_rng(self.seed, counter),
                          point_times_s, twist)
        self._weigh(pts, stamp_s, coarse_sigma)
        if self.search.active and self.cfg.check.enabled:
            self.claim_check.add_scan(pts, T_prev_curr)
        timer.lap("likelihood")
        n = self.particles.n
        weights = compute_weights(self.particles)
        stats = cloud_stats(self.particles, weights.total)
        timer.lap("weights")
        self._gather_evidence(len(pts), coarse_sigma)
        estimate, state = self._estimate(stats, weights)
        timer.lap("estimate")
        state, reseed = self._check_loss(estimate, state)
        if reseed == "global" and not self._can_seed_globally():
            reseed = "expansion"
        timer.lap("recovery")
        resampled = (bool(reseed) or bool(self._rivals)
                     or weights.ess < self.cfg.resample.ess_threshold * n)
        if resampled:
            self._resample(weights, reseed, counter)
            if self._rivals and not reseed:
                self._reseed_rivals(estimate.T_map_lidar)
            self._rivals = []
        timer.lap("resample")
        if reseed:
            self._recover(reseed, estimate.T_map_lidar)
            timer.lap("recovery")
        return LocalizationResult(
            stamp_s=float(stamp_s), T_map_lidar=estimate.T_map_lidar, T_best=estimate.T_best,
            covariance=estimate.covariance, state=state, hypotheses=estimate.hypotheses,
            ess=float(weights.ess), n_particles=n, match_ratio=estimate.match_ratio,
            mean_log_likelihood=estimate.mean_log_likelihood, n_points=len(pts),
            resampled=resampled, reseeded=reseed, places=self.search.live_places,
            best_match_ratio=stats.best_match_ratio,
            timings_ms=timer.ms)

    def motion_std(self, T_prev_curr: np.ndarray, extra_rot: float = 0.0,
                   extra_trans: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(rotation std [rad], translation std [m]) per axis for this motion."""
        m = self.cfg.motion
        d = float(np.linalg.norm(T_prev_curr[:3, 3]))
        a = float(geometry.rotation_angle(T_prev_curr[:3, :3]))
        std_t = m.trans_per_m * d + m.trans_per_rad * a + m.trans_floor_m + extra_trans
        std_r = m.rot_per_deg * a + m.rot_rad_per_m * d + m.rot_floor_rad + extra_rot
        return np.full(3, std_r), np.full(3, std_t)

    def _predict(self, T_prev_curr: np.ndarray, extra_std: tuple[float, float],
                 coarse_sigma: float | None, counter: int) -> None:
        """Move every particle by the motion plus noise; until the first convergence the
        noise also explores, more while the coarse model is wide."""
        cfg = self.cfg
        extra_r, extra_t = extra_std
        if not self.ever_converged:
            scale = max(1.0, (coarse_sigma or 0.0) / cfg.sensor.search_sigma_m)
            extra_r += cfg.motion.explore_rot_rad * scale
            extra_t += cfg.motion.explore_trans_m * scale
        self.search.add_motion(T_prev_curr)
        std_r, std_t = self.motion_std(T_prev_curr, extra_r, extra_t)
        t, q = geometry.tq_from_se3(np.asarray(T_prev_curr, dtype=np.float64))
        p = self.particles
        motion.propagate(p.pos, p.quat, p.n, ti.math.vec4(*q), ti.math.vec3(*t),
                         ti.math.vec3(*std_r), ti.math.vec3(*std_t), self.seed, counter)

    def _weigh(self, pts: np.ndarray, stamp_s: float, coarse_sigma: float | None) -> None:
        """Add the reduced scan's tempered log-likelihood to every particle's log-weight."""
        s = self.cfg.sensor
        if len(pts) < MIN_SCAN_POINTS:
            raise EmptyScan(f"the scan at {stamp_s:.3f} s has {len(pts)} points after the "
                            f"range gate [{s.min_range_m}, {s.max_range_m}] m (at least "
                            f"{MIN_SCAN_POINTS} are needed)")
        sigma = s.sigma_m if self.ever_converged else max(s.search_sigma_m, s.sigma_m)
        if self.weigher.set_sigma(sigma):
            self.recovery.reset_reference()
        self.weigher.upload_scan(pts)
        if coarse_sigma is None:
            self.weigher.scan_likelihood(self.particles, len(pts), self.weigher.cache_block)
        else:
            self.weigher.coarse_likelihood(self.particles, len(pts), coarse_sigma)
        self.search.count_scan()
        min_ess = self.cfg.resample.anneal_min_ess
        if min_ess > 0 and not self.ever_converged:
            anneal(self.particles, s.increment_scale(len(pts)), min_ess)

    def _gather_evidence(self, n_points: int, coarse_sigma: float | None) -> None:
        """Each place's evidence, while searching (see `evidence`, on the device); the
        coarse model is a search heuristic, not evidence."""
        r = self.cfg.resample
        self._places = not self.ever_converged and coarse_sigma is None
        if not self._places:
            return
        self.evidence.add(self.particles, self.cfg.sensor.increment_scale(n_points),
                          r.place_cell_m, round(360.0 / r.place_yaw_deg),
                          max(r.place_min_particles, 1), self.seed,
                          kernel_counter(self.step_index, EVIDENCE_COUNTER), r.place_margin_nats)

    def _estimate(self, stats: CloudStats, weights: Weights
                  ) -> tuple[PoseEstimate, FilterState]:
        """The dominant cluster and the filter's state (a global search converges only
        after the coarse phase, with no rival mode, after motion)."""
        e, p = self.cfg.estimate, self.particles
        u0 = host_rng(self.seed, self.step_index, ESTIMATE_SAMPLE_STREAM).random()
        pos, quat = self.sampler.by_weight(p, weights.total, min(p.n, e.samples), u0)
        estimate = estimate_from_sample(pos, quat, stats.T_best, stats.match_ratio,
                                        stats.mean_log_likelihood, e)
        if self.shown_particles > 0:
            shown = min(self.shown_particles, self.sampler.capacity)
            self.last_cloud = self.sampler.shown(p, weights.total, evenly(p.n, shown))
        if self.cfg.estimate.mean == "all":  # the clusters (convergence test) stay
            T_mean, covariance = self.mean_of_all(p)
            estimate = replace(estimate, T_map_lidar=T_mean, covariance=covariance)
        self.search.update_modes(p, weights.total, estimate.clusters,
                                 host_rng(self.seed, self.step_index, MODE_SAMPLE_STREAM),
                                 self.evidence if self._places else None)
        rival = self._rival_explains_scans(estimate)
        converged = estimate.dominant and not rival
        if self.search.active:
            converged = self.search.converged(converged)
            if converged and self._claim_withheld(estimate.T_map_lidar):
                converged, rival = False, True
        if converged:
            self.ever_converged = True
            self.search.active = False
            return estimate, FilterState.CONVERGED
        if len(estimate.hypotheses) >= 2 or self.ever_converged or rival:
            return estimate, FilterState.AMBIGUOUS
        return estimate, FilterState.INITIALIZING

    def _rival_explains_scans(self, estimate: PoseEstimate) -> bool:
        """Whether a place away from the dominant cluster explains the scans within the
        sampling noise (or `rival_margin_nats`) of the dominant's best (see `evidence`)."""
        e = self.cfg.estimate
        if e.rival_margin_nats <= 0 or not self._places:
            return False
        gap = self.evidence.rival_gap(self.particles, estimate.T_map_lidar,
                                      2 * e.cluster_radius_m, 2 * e.cluster_angle_rad)
        live = max(self.search.live_places, 2)
        return gap > -max(e.rival_margin_nats, self.evidence.noise_margin(live))

    def _claim_withheld(self, T_claim: np.ndarray) -> bool:
        """Whether the convergence check (see `claim_check`) found a place without particles
        that explains the scans about as well as the claim: then the claim is withheld and
        those places are re-seeded after this update's resampling."""
        if not self.cfg.check.enabled or not self._can_seed_globally():
            return False
        self._rivals = self.claim_check.rivals(
            self.weigher, self.particles, T_claim, self.free_space(), self.seed,
            kernel_counter(self.step_index, CHECK_COUNTER))
        if self._rivals:
            self.claim_check.withheld += 1
            self.search.dominant_run = 0
        return bool(self._rivals)

    def _reseed_rivals(self, T_claim: np.ndarray) -> None:
        """A share of the particles (a stride: a like share of every place) around each
        rival, with the average log-weight and the claim's best evidence plus the rival's
        window gap: the filter's evidence then decides between the places."""
        c, e, p = self.cfg.check, self.cfg.estimate, self.particles
        k = len(self._rivals)
        count = min(max(1, int(c.inject_share * p.n)), p.n // (2 * k))
        stride = p.n // (count * k)
        base = self.evidence.best_near(p, T_claim, 2 * e.cluster_radius_m,
                                       2 * e.cluster_angle_rad)
        std_t, std_r = INJECT_STD
        for i, r in enumerate(self._rivals):
            t, q = geometry.tq_from_se3(r.T_map_lidar)
            kcc.inject(p.pos, p.quat, p.log_w, self.evidence.log_l, i * stride, stride * k,
                       count, ti.math.vec3(*t), ti.math.vec4(*q), ti.math.vec3(*std_t),
                       ti.math.vec3(*std_r), 0.0, base + r.gap_nats, self.seed,
                       kernel_counter(self.step_index, CHECK_COUNTER) ^ 0x5EED)
            self.claim_check.tried(r.T_map_lidar)
        self.claim_check.reseeded_particles += count * k

    def _check_loss(self, estimate: PoseEstimate, state: FilterState
                    ) -> tuple[FilterState, Reseed]:
        """Lost or not, and the re-seeding to do now; remembers the upright attitude."""
        r = self.cfg.recovery
        active = r.enabled and (self.ever_converged or (
            not self.search.active and self.step_index - self._init_step > r.grace_scans))
        lost = self.recovery.is_lost(estimate.match_ratio, estimate.mean_log_likelihood,
                                     state == FilterState.CONVERGED, active)
        reseed = self.recovery.action(lost)
        if lost or (state == FilterState.CONVERGED and self.recovery.scan_disagrees(
                estimate.match_ratio, estimate.mean_log_likelihood)):
            state = FilterState.LOST
        if state == FilterState.CONVERGED:
            roll, pitch, _ = geometry.rot_to_rpy(estimate.T_map_lidar[:3, :3])
            self._upright = (float(roll), float(pitch))
        return state, reseed

    def _resample(self, weights: Weights, reseed: Reseed, counter: int) -> None:
        """Systematic resampling, KLD-sized when asked, mode-preserving during a search.
        The places' evidence follows the parents only while it is still to be read (it is
        all zeros before the first accurate scan, and unused once converged until the next
        initialization resets it)."""
        cfg, p = self.cfg, self.particles
        n_out = p.n
        if cfg.resample.kld:
            u0 = host_rng(self.seed, self.step_index, KLD_SAMPLE_STREAM).random()
            pos, quat = self.sampler.by_weight(p, weights.total,
                                               min(p.n, cfg.estimate.samples), u0)
            n_out = kld_count(pos, quat, cfg.resample, p.capacity)
        floored = self.search.floored and not reseed
        u0 = float(host_rng(self.seed, counter, RESAMPLE_OFFSET_STREAM).random())
        resample(p, n_out, weights, u0, floored, keep_posterior=not self.search.exploring)
        if self.evidence.scans and not self.ever_converged:
            self.evidence.inherit(p.parent, n_out)

    def _recover(self, how: Reseed, T_estimate: np.ndarray) -> None:
        """Re-seed: around the estimate (clipped into the map), or over the free space."""
        r = self.cfg.recovery
        if how == "expansion":
            T = T_estimate.copy()
            T[:3, 3] = np.clip(T_estimate[:3, 3], *self.tsdf.geometry.extent_m)
            self.init_pose(T, self.recovery.expansion_std(), r.fraction)
        else:
            self.init_global(r.global_fraction)
            self.ever_converged = False  # global localization again: search mode
            if r.global_fraction < 1.0:
                self.search.active = False  # part of the cloud stays: no coarse phase
