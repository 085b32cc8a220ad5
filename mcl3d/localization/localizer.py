"""6-DoF Monte Carlo localization in a TSDF: `Localizer(tsdf, config).step(...)`.

One step = motion update (kernel) -> scan likelihood (kernel) -> weights and ESS (kernels)
-> estimate from the dominant cluster (host, on a weighted subsample) -> recovery check ->
systematic resampling (kernels) when the ESS is low, optionally with a KLD-sampling count
(during a global search mode-preserving: every plausible cluster keeps a share of the
particles, see docs/sensor-model.md), and re-seeding of a fraction of the particles when the
filter has lost track.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from mcl3d.core import geometry
from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError, InputError
from mcl3d.localization.estimate import (
    ClusterParams,
    Hypothesis,
    cluster_hypotheses,
    kld_sample_count,
    label_particles,
    mode_floor,
)
from mcl3d.localization.initialization import FreeCells, InitConfig, free_cells
from mcl3d.localization.particle_set import ParticleSet
from mcl3d.localization.sensor_model import (
    BLOCK,
    SensorModelConfig,
    code_table,
    reduce_scan,
    spatial_order,
)

STATES = ("initializing", "converged", "ambiguous", "lost")
COARSE_MIN_WEIGHT = 1e-12  # the coarse phase's mode floor protects any cluster it finds
STAGES = ("motion", "likelihood", "weights", "estimate", "resample", "recovery")


class MotionNoiseConfig(Section):
    """Per-update noise std, growing with the motion: std = alpha * |motion| + floor."""

    trans_per_m: float = Field(0.10, ge=0.0, description="m of translation noise per m moved")
    trans_per_rad: float = Field(0.05, ge=0.0, description="m of translation noise per rad")
    rot_per_rad: float = Field(0.10, ge=0.0, description="rad of rotation noise per rad turned")
    rot_per_m: float = Field(0.02, ge=0.0, description="rad of rotation noise per m moved")
    trans_floor_m: float = Field(0.02, ge=0.0, description="translation noise every update")
    rot_floor_rad: float = Field(0.01, ge=0.0, description="rotation noise every update")
    explore_trans_m: float = Field(0.05, ge=0.0, description="extra translation noise until "
                                                             "the filter first converges")
    explore_rot_rad: float = Field(0.03, ge=0.0, description="extra rotation noise until "
                                                             "the filter first converges")


class ResampleConfig(Section):
    ess_threshold: float = Field(0.5, gt=0.0, le=1.0,
                                 description="resample when ESS < threshold * N")
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
    kld: bool = Field(False, description="adapt the particle count with KLD-sampling")
    min_particles: int = Field(2000, ge=1)
    kld_epsilon: float = Field(0.05, gt=0.0, description="KL error bound")
    kld_delta: float = Field(0.01, gt=0.0, lt=1.0, description="1 - confidence (z = 2.33)")
    kld_bin_m: float = Field(0.25, gt=0.0, description="KLD bin size in x, y, z")
    kld_bin_rad: float = Field(0.1, gt=0.0, description="KLD bin size in yaw")


class EstimateConfig(Section):
    cluster_radius_m: float = Field(1.0, gt=0.0)
    cluster_angle_rad: float = Field(0.5, gt=0.0)
    max_hypotheses: int = Field(3, ge=1)
    samples: int = Field(5000, ge=100, description="weighted subsample used for clustering")
    converged_weight: float = Field(0.8, gt=0.0, le=1.0,
                                    description="dominant cluster weight to be converged")
    converged_std_m: float = Field(0.25, gt=0.0, description="... and its worst-axis std")
    converged_std_rad: float = Field(0.1, gt=0.0)
    hypothesis_min_weight: float = Field(0.1, gt=0.0, le=1.0,
                                         description="clusters reported as hypotheses")
    converged_scans: int = Field(
        5, ge=1, description="global search: the dominant cluster must pass the test this many "
                             "scans in a row (after the coarse phase) to be converged")
    converge_min_motion_m: float = Field(
        1.0, ge=0.0, description="global search: ... and the sensor must have moved this far "
                                 "since the (re-)initialization (or turned as below): scans "
                                 "from one place are not independent evidence")
    converge_min_rotation_rad: float = Field(1.0, ge=0.0)


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
    expansion_std_rad: float = Field(0.3, gt=0.0)
    expansion_attempts: int = Field(1, ge=0, description="then re-seed globally (one: a "
                                                          "slip is found at once, a kidnap "
                                                          "needs the global search early)")
    attempt_scans: int = Field(5, ge=1, description="scans to wait for an attempt to work")


class LocalizerConfig(Section):
    particles: int = Field(100_000, ge=1, description="N (the maximum with KLD)")
    seed: int = Field(0, ge=0, lt=2**32)
    sensor: SensorModelConfig = SensorModelConfig()
    motion: MotionNoiseConfig = MotionNoiseConfig()
    resample: ResampleConfig = ResampleConfig()
    estimate: EstimateConfig = EstimateConfig()
    recovery: RecoveryConfig = RecoveryConfig()
    init: InitConfig = InitConfig()


@dataclass
class LocalizationResult:
    stamp_s: float
    T_map_lidar: np.ndarray  # (4, 4) mean of the dominant cluster
    T_best: np.ndarray  # (4, 4) the heaviest particle
    covariance: np.ndarray  # (6, 6) rotation-first [rad^2, m^2]
    state: str
    hypotheses: list[Hypothesis]
    ess: float
    n_particles: int
    match_ratio: float  # weighted mean fraction of scan points on a surface
    mean_log_likelihood: float  # weighted mean per-point log-likelihood
    n_points: int
    resampled: bool
    reseeded: str  # "", "expansion" or "global"
    timings_ms: dict[str, float] = field(default_factory=dict)


class EmptyScan(InputError):
    """A scan with too few points left after the range gate (skipped by the pipeline)."""


class _Timer:
    def __init__(self) -> None:
        self.ms: dict[str, float] = dict.fromkeys(STAGES, 0.0)

    def lap(self, stage: str, t0: float) -> float:
        import taichi as ti

        ti.sync()
        now = time.perf_counter()
        self.ms[stage] += 1e3 * (now - t0)
        return now


def _systematic(weights: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    cdf = np.cumsum(weights)
    cdf /= cdf[-1]
    return np.minimum(np.searchsorted(cdf, (np.arange(k) + rng.random()) / k), len(cdf) - 1)


class Localizer:
    """Particle filter over T_map_lidar; see the module docstring."""

    def __init__(self, tsdf, config: LocalizerConfig, imu_roll_pitch: tuple | None = None):
        self.tsdf = tsdf
        self.cfg = config
        capacity = config.particles
        self.particles = ParticleSet(capacity)
        self.imu_roll_pitch = imu_roll_pitch
        self.step_index = 0
        self.ever_converged = False
        self._points = None
        self._free: FreeCells | None = None
        self._fast = self._slow = None
        self._lost_run = 0
        self._healthy = False  # converged since the last reset
        self._attempt = 0
        self._since_attempt = 0
        self._last: LocalizationResult | None = None
        self.last_sample_positions = np.zeros((0, 3), np.float32)  # for visualization
        self.anneal_beta = 1.0
        self.sigma_m = config.sensor.sigma_m  # the hit term's sigma in the last update
        self._searching = False  # global search since the last global (re-)initialization
        self._search_scans = 0
        self._moved = np.zeros(2)  # m, rad since the search began
        self._dominant_run = 0
        self._init_step = 0
        self._coarse = None  # the coarse search field, built at the first global init
        self._mode_factors: np.ndarray | None = None  # mode-preserving resampling factors
        self.rivals = 0  # protected clusters besides the dominant one (global search)
        self._exploring = False  # the last update was a coarse or grace scan (see _modes)
        self._upright: tuple[float, float] | None = None  # roll, pitch when last converged
        self._rng = np.random.default_rng(config.seed)
        import taichi as ti

        from mcl3d.kernels import likelihood as kl

        self._points = ti.Vector.field(3, ti.f32, shape=config.sensor.points)
        self._points_host = np.zeros((config.sensor.points, 3), np.float32)
        self._keys = ti.field(ti.i32, shape=capacity)
        self._order = ti.field(ti.i32, shape=capacity)
        self._order_host = np.zeros(capacity, np.int32)
        self.cache_block = config.sensor.cache_block
        if self.cache_block == "auto":
            from mcl3d.core import runtime

            info = runtime.current()
            self.cache_block = info is not None and info.backend != "cpu"
        self.cache_block = bool(self.cache_block)
        self._table = ti.field(ti.f32, shape=kl.N_CODES)
        self._coarse_table = ti.field(ti.f32, shape=kl.COARSE_BINS + 2)
        self._table_sigma = None
        # the sensor model per voxel, evaluated once (the map is read-only from here on):
        # 1 KiB per map block, a quarter of an f32 map
        self._codes = ti.field(ti.i32, shape=(tsdf.capacity + 2, kl.BLOCK, kl.BLOCK,
                                              kl.WORDS_Z))
        self._slots = ti.field(ti.i32, shape=tsdf.coarse_dims)
        kl.build_codes(tsdf, self._codes, tsdf.n_blocks, config.sensor.match_dist_m)
        kl.build_slots(tsdf, self._slots)

    # ------------------------------------------------------------------ initialization
    @property
    def seed(self) -> int:
        return self.cfg.seed

    def free_space(self) -> FreeCells:
        if self._free is None:
            self._free = free_cells(self.tsdf, self.cfg.init)
        return self._free

    def init_global(self, fraction: float = 1.0) -> None:
        """Uniform over the map's free space; roll/pitch from gravity when known (the IMU's,
        else, for a re-seed, the last converged estimate's: a kidnapped robot is still
        upright, and uniform rotations on SO(3) would waste most particles on tilted poses)."""
        from mcl3d.kernels import particles as kp

        cells = self.free_space()
        if fraction >= 1.0:
            self._start_search()
        p = self.particles
        roll_pitch = self.imu_roll_pitch or self._upright
        gravity = roll_pitch is not None
        roll, pitch = roll_pitch if gravity else (0.0, 0.0)
        kp.init_cells(p.pos, p.quat, p.log_w, p.n, cells.corners_m, len(cells.corners_m),
                      cells.cell_m, int(gravity), roll, pitch, self.cfg.init.gravity_std_rad,
                      fraction, self.seed, self._counter(1))

    def init_particles(self, positions: np.ndarray, quats_xyzw: np.ndarray,
                       search: bool = False) -> None:
        """A given particle set (tests, restarts). search=True: it is the state of a global
        search (convergence only after motion, modes kept), without a coarse phase."""
        self.particles.set_host(positions, quats_xyzw)
        if search:
            self._start_search()
            self._search_scans = self.cfg.sensor.coarse_scans

    def _start_search(self) -> None:
        """A fresh global search: coarse model first, convergence only after motion."""
        self._searching = True
        self._init_step = self.step_index
        self._search_scans = 0
        self._moved[:] = 0.0
        self._dominant_run = 0
        self.ever_converged = False
        if self.cfg.sensor.coarse_sigma_m > 0 and self._coarse is None:
            import taichi as ti

            from mcl3d.localization.sensor_model import coarse_field

            host = coarse_field(self.tsdf, self.cfg.sensor)
            self._coarse = ti.field(ti.i32, shape=host.codes.shape)
            self._coarse.from_numpy(host.codes)
            self._coarse_host = host

    def search_sigma(self) -> float | None:
        """The coarse model's sigma for the next scan, None outside the coarse phase."""
        s = self.cfg.sensor
        if not self._searching or self._coarse is None or self._search_scans >= s.coarse_scans:
            return None
        frac = self._search_scans / s.coarse_scans
        return s.coarse_sigma_m * (min(s.search_sigma_m, s.coarse_sigma_m)
                                   / s.coarse_sigma_m) ** frac

    def init_pose(self, T_map_lidar: np.ndarray, std: list[float], fraction: float = 1.0
                  ) -> None:
        """Gaussian around a pose: std = (x, y, z [m], roll, pitch, yaw [rad])."""
        import taichi as ti

        from mcl3d.kernels import particles as kp

        T = np.asarray(T_map_lidar, dtype=np.float64)
        self._check_in_map(T[:3, 3])
        t, q = geometry.tq_from_se3(T)
        p = self.particles
        kp.init_gaussian(p.pos, p.quat, p.log_w, p.n, ti.math.vec3(*t), ti.math.vec4(*q),
                         ti.math.vec3(*std[:3]), ti.math.vec3(*std[3:6]), fraction,
                         self.seed, self._counter(2))

    def _check_in_map(self, t: np.ndarray) -> None:
        lo, hi = self.tsdf.geometry.extent_m
        if np.any(t < lo) or np.any(t > hi):
            raise InputError(
                f"the initial pose {np.round(t, 2).tolist()} m lies outside the map "
                f"({np.round(lo, 1).tolist()} .. {np.round(hi, 1).tolist()} m): the map and "
                f"the log are in different frames or places; check --map and --init")

    def _counter(self, salt: int) -> int:
        return (self.step_index * 8 + salt) & 0xFFFFFFFF

    # ----------------------------------------------------------------------- the step
    def motion_std(self, T_prev_curr: np.ndarray, extra_rot: float = 0.0,
                   extra_trans: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        m = self.cfg.motion
        d = float(np.linalg.norm(T_prev_curr[:3, 3]))
        a = float(geometry.rotation_angle(T_prev_curr[:3, :3]))
        std_t = m.trans_per_m * d + m.trans_per_rad * a + m.trans_floor_m + extra_trans
        std_r = m.rot_per_rad * a + m.rot_per_m * d + m.rot_floor_rad + extra_rot
        return np.full(3, std_r), np.full(3, std_t)

    def step(self, scan_points: np.ndarray, T_prev_curr: np.ndarray | None, stamp_s: float,
             extra_std: tuple[float, float] = (0.0, 0.0), point_times_s: np.ndarray | None = None,
             twist: np.ndarray | None = None) -> LocalizationResult:
        """One filter update with a scan (lidar frame) and the motion since the last scan.

        `T_prev_curr` None: no motion update (the first scan). `extra_std` (rad, m) widens
        the motion noise when the motion is a guess (constant velocity). With per-point times
        (s after the stamp) and the lidar twist (rotation first, per s) the points are
        deskewed to the stamp.
        """
        import taichi as ti

        from mcl3d.kernels import motion, resample

        cfg = self.cfg
        p = self.particles
        timer = _Timer()
        t0 = time.perf_counter()
        self.step_index += 1
        step = self._counter(0)
        coarse_sigma = self.search_sigma()
        self._exploring = self._searching and self._search_scans < (
            cfg.sensor.coarse_scans + cfg.resample.mode_grace_scans)
        if T_prev_curr is not None:
            extra_r, extra_t = extra_std
            if not self.ever_converged:  # the exploration grows with the coarse sigma
                scale = max(1.0, (coarse_sigma or 0.0) / cfg.sensor.search_sigma_m)
                extra_r += cfg.motion.explore_rot_rad * scale
                extra_t += cfg.motion.explore_trans_m * scale
            if self._searching:
                self._moved += [np.linalg.norm(T_prev_curr[:3, 3]),
                                geometry.rotation_angle(np.asarray(T_prev_curr)[:3, :3])]
            std_r, std_t = self.motion_std(T_prev_curr, extra_r, extra_t)
            t, q = geometry.tq_from_se3(np.asarray(T_prev_curr, dtype=np.float64))
            motion.propagate(p.pos, p.quat, p.n, ti.math.vec4(*q), ti.math.vec3(*t),
                             ti.math.vec3(*std_r), ti.math.vec3(*std_t), self.seed, step)
        t0 = timer.lap("motion", t0)

        pts = reduce_scan(scan_points, cfg.sensor, np.random.default_rng([self.seed, step]),
                          point_times_s, twist)
        if len(pts) < 8:
            raise EmptyScan(f"the scan at {stamp_s:.3f} s has {len(pts)} points after the "
                             f"range gate [{cfg.sensor.min_range_m}, {cfg.sensor.max_range_m}] "
                             f"m (at least 8 are needed)")
        sigma = cfg.sensor.sigma_m if self.ever_converged else max(cfg.sensor.search_sigma_m,
                                                                   cfg.sensor.sigma_m)
        if sigma != self._table_sigma:
            self._table.from_numpy(code_table(cfg.sensor, self.tsdf.truncation_m, sigma))
            self._table_sigma = sigma
            self._fast = self._slow = None  # log-likelihoods change scale with sigma
            self._healthy = False
        self.upload_scan(pts)
        if coarse_sigma is None:
            self.sigma_m = sigma
            self.scan_likelihood(len(pts), self.cache_block)
        else:
            self.sigma_m = coarse_sigma
            self.coarse_likelihood(len(pts), coarse_sigma)
        if self._searching:
            self._search_scans += 1
        s = cfg.sensor
        n = p.n
        self.anneal_beta = 1.0  # the extra tempering of this scan (1: none)
        if cfg.resample.anneal_min_ess > 0 and not self.ever_converged:
            self.anneal_beta = self._anneal(n, s.tempering(len(pts)) * len(pts))
        t0 = timer.lap("likelihood", t0)

        shift = resample.max_log_weight(p.log_w, n)
        resample.shifted_weights(p.log_w, n, shift, p.w, p.partial_sums)
        resample.sum_partials(p.partial_sums, n, p.sums)
        s1, s2 = float(p.sums[0]), float(p.sums[1])
        ess = s1 * s1 / max(s2, 1e-30)
        t0 = timer.lap("weights", t0)

        pos, quat, w, match, ll = self._host(n, s1)
        result_parts = self._estimate(pos, quat, w, match, ll)
        t0 = timer.lap("estimate", t0)

        lost = self._monitor(result_parts["match_ratio"], result_parts["mean_ll"],
                             result_parts["state"])
        reseed = self._recovery_action(lost)
        state = "lost" if lost else result_parts["state"]
        if state == "converged":
            roll, pitch, _ = geometry.rot_to_rpy(result_parts["T_map_lidar"][:3, :3])
            self._upright = (float(roll), float(pitch))
        t0 = timer.lap("recovery", t0)

        resampled = bool(reseed) or ess < cfg.resample.ess_threshold * n
        if resampled:
            n_out = self._kld_count(pos, quat, w) if cfg.resample.kld else n
            factors = None if reseed else self._mode_factors
            total = s1 if factors is None else self._upload_floored_weights(w, factors)
            resample.scan_blocks(p.w, n, p.cdf, p.block_sums)
            resample.scan_block_sums(p.block_sums, (n + resample.SCAN_BLOCK - 1)
                                     // resample.SCAN_BLOCK)
            resample.add_block_offsets(p.cdf, n, p.block_sums, total)
            u0 = float(np.random.default_rng([self.seed, step, 7]).random())
            resample.systematic_select(p.cdf, n, n_out, u0, p.parent)
            from mcl3d.kernels.particles import gather

            gather(p.pos, p.quat, p.parent, n_out, p.pos_back, p.quat_back, p.log_w)
            p.swap()
            p.n = n_out
            if factors is not None and not self._exploring:
                self._restore_posterior(factors, n_out)
        t0 = timer.lap("resample", t0)
        if reseed:
            self._reseed(reseed, result_parts["T_map_lidar"])
            timer.lap("recovery", t0)

        result = LocalizationResult(
            stamp_s=float(stamp_s), T_map_lidar=result_parts["T_map_lidar"],
            T_best=result_parts["T_best"], covariance=result_parts["covariance"], state=state,
            hypotheses=result_parts["hypotheses"], ess=float(ess), n_particles=n,
            match_ratio=result_parts["match_ratio"],
            mean_log_likelihood=result_parts["mean_ll"], n_points=len(pts),
            resampled=resampled, reseeded=reseed, timings_ms=timer.ms)
        self._last = result
        return result

    # ------------------------------------------------------------------------ helpers
    def upload_scan(self, pts: np.ndarray) -> None:
        """The reduced scan to the device, in Morton order of map blocks."""
        m = len(pts)
        self._points_host[:m] = pts[spatial_order(pts, self.tsdf.voxel_size_m * BLOCK)]
        self._points_host[m:] = 0.0
        self._points.from_numpy(self._points_host)

    def scan_likelihood(self, n_points: int, cache_block: bool) -> None:
        """Adds the tempered scan log-likelihood of the uploaded scan to every log-weight,
        visiting the particles sorted by pose cell (a point 5 m away moves about a voxel
        from one cell to the next) so that consecutive ones read the same map blocks."""
        from mcl3d.kernels.likelihood import locality_keys, scan_log_likelihood

        p = self.particles
        vox = self.tsdf.voxel_size_m
        locality_keys(p.pos, p.quat, p.n, vox, vox / 5.0, self._keys)
        keys = self._keys.to_numpy()[:p.n].astype(np.uint16)
        self._order_host[:p.n] = np.argsort(keys, kind="stable")
        self._order.from_numpy(self._order_host)
        scan_log_likelihood(self.tsdf, self._codes, self._slots, self._order, p.pos, p.quat,
                            p.n, self._points, n_points, self._table,
                            self.cfg.sensor.tempering(n_points), p.log_w, p.match, p.ll_mean,
                            cache_block)

    def coarse_likelihood(self, n_points: int, sigma_m: float) -> None:
        """Like scan_likelihood, with the coarse search model at `sigma_m`."""
        import taichi as ti

        from mcl3d.kernels.likelihood import coarse_scan_log_likelihood, locality_keys
        from mcl3d.localization.sensor_model import coarse_match_codes, coarse_table

        p = self.particles
        s = self.cfg.sensor
        field = self._coarse_host
        self._coarse_table.from_numpy(coarse_table(s, sigma_m))
        cell = field.cell_m
        locality_keys(p.pos, p.quat, p.n, cell, cell / 5.0, self._keys)
        keys = self._keys.to_numpy()[:p.n].astype(np.uint16)
        self._order_host[:p.n] = np.argsort(keys, kind="stable")
        self._order.from_numpy(self._order_host)
        coarse_scan_log_likelihood(self._coarse, ti.math.vec3(*field.origin_m), 1.0 / cell,
                                   self._order, p.pos, p.quat, p.n, self._points, n_points,
                                   self._coarse_table, coarse_match_codes(s),
                                   s.tempering(n_points), p.log_w, p.match, p.ll_mean)

    def _upload_floored_weights(self, w: np.ndarray, factors: np.ndarray) -> float:
        """Resampling weights w * factor (mode-preserving) into p.w; returns their sum."""
        p = self.particles
        host = np.zeros(p.capacity, np.float32)
        host[:len(w)] = w * factors
        p.w.from_numpy(host)
        return float(host.sum(dtype=np.float64))

    def _restore_posterior(self, factors: np.ndarray, n_out: int) -> None:
        """Each copy carries log(weight / resampling weight) of its parent: the floored
        modes keep their particles but not more than their share of the posterior."""
        p = self.particles
        parent = p.parent.to_numpy()[:n_out]
        log_w = np.zeros(p.capacity, np.float32)
        log_w[:n_out] = -np.log(factors[parent])
        p.log_w.from_numpy(log_w)

    def _modes(self, pos, quat, w, hyps: list[Hypothesis]) -> None:
        """Mode-preserving resampling factors during a global search (`mode_floor`): the
        clusters are those of the weighted sample plus those of a uniform sample of the
        particles (a mode that holds many particles but little weight), merged when closer
        than two cluster radii. During the coarse phase the model is a deliberately blurred
        search heuristic, not evidence to accumulate: the heaviest clusters keep their floor
        whatever their weight, and the copies start with equal weights (tempering), so the
        accurate model decides between the modes from the end of the coarse phase on."""
        e, r = self.cfg.estimate, self.cfg.resample
        self._mode_factors, self.rivals = None, 0
        if not self._searching or r.mode_share <= 0:
            return
        k = min(len(w), e.samples)
        idx = np.random.default_rng([self.seed, self.step_index, 4]).choice(len(w), k,
                                                                             replace=False)
        params = ClusterParams(e.cluster_radius_m, e.cluster_angle_rad, e.max_hypotheses)
        populous = cluster_hypotheses(pos[idx], quat[idx], np.full(k, 1.0 / k), params)
        centres: list[np.ndarray] = []
        for h in hyps + populous:
            T = h.T_map_lidar
            if all(np.linalg.norm(T[:3, 3] - C[:3, 3]) > 2 * e.cluster_radius_m
                   or geometry.rotation_angle(C[:3, :3].T @ T[:3, :3])
                   > 2 * e.cluster_angle_rad for C in centres):
                centres.append(T)
        labels = label_particles(pos, quat, centres, e.cluster_radius_m, e.cluster_angle_rad)
        floor = mode_floor(labels, w, r.mode_share,
                           COARSE_MIN_WEIGHT if self._exploring else r.mode_min_weight,
                           e.max_hypotheses)
        self.rivals = floor.rivals
        if floor.rivals:
            self._mode_factors = floor.factors

    def _anneal(self, n: int, scale: float) -> float:
        """Largest beta <= 1 with ESS(log_w_prev + beta * increment) >= anneal_min_ess * N;
        the increment already added is scaled down to beta times itself."""
        from mcl3d.kernels.particles import add_scaled

        p = self.particles
        log_w = p.log_w.to_numpy()[:n].astype(np.float64)
        inc = scale * p.ll_mean.to_numpy()[:n].astype(np.float64)
        prev = log_w - inc
        target = self.cfg.resample.anneal_min_ess * n

        def ess(beta: float) -> float:
            x = prev + beta * inc
            w = np.exp(x - x.max())
            return w.sum() ** 2 / (w @ w)

        if ess(1.0) >= target:
            return 1.0
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ess(mid) >= target else (lo, mid)
        add_scaled(p.log_w, p.ll_mean, n, float((lo - 1.0) * scale))
        return lo

    def _host(self, n: int, s1: float):
        p = self.particles
        pos = p.pos.to_numpy()[:n].astype(np.float64)
        quat = p.quat.to_numpy()[:n].astype(np.float64)
        w = p.w.to_numpy()[:n].astype(np.float64) / s1
        match = p.match.to_numpy()[:n].astype(np.float64)
        ll = p.ll_mean.to_numpy()[:n].astype(np.float64)
        return pos, quat, w, match, ll

    def _estimate(self, pos, quat, w, match, ll) -> dict:
        e = self.cfg.estimate
        best = int(np.argmax(w))
        T_best = geometry.se3_from_tq(pos[best], quat[best])
        k = min(len(w), e.samples)
        idx = _systematic(w, k, np.random.default_rng([self.seed, self.step_index, 3]))
        self.last_sample_positions = pos[idx].astype(np.float32)
        hyps = cluster_hypotheses(pos[idx], quat[idx], np.full(k, 1.0 / k),
                                  ClusterParams(e.cluster_radius_m, e.cluster_angle_rad,
                                                e.max_hypotheses))
        h0 = hyps[0]
        compact = (h0.position_std_m <= e.converged_std_m
                   and h0.rotation_std_rad <= e.converged_std_rad)
        strong = [h for h in hyps if h.weight >= e.hypothesis_min_weight]
        dominant = h0.weight >= e.converged_weight and compact
        self._modes(pos, quat, w, hyps)
        if self._searching:  # global search: dominant for a while, after the coarse phase
            self._dominant_run = self._dominant_run + 1 if (
                dominant and self.search_sigma() is None and not self.rivals) else 0
            moved = (self._moved[0] >= e.converge_min_motion_m
                     or self._moved[1] >= e.converge_min_rotation_rad)
            dominant = self._dominant_run >= e.converged_scans and moved
        if dominant:
            state = "converged"
            self.ever_converged = True
            self._searching = False
        elif len(strong) >= 2 or self.ever_converged:
            state = "ambiguous"
        else:
            state = "initializing"
        return {"T_map_lidar": h0.T_map_lidar, "T_best": T_best, "covariance": h0.covariance,
                "hypotheses": strong or hyps[:1], "state": state,
                "match_ratio": float(w @ match), "mean_ll": float(w @ ll)}

    def _monitor(self, match_ratio: float, mean_ll: float, state: str) -> bool:
        r = self.cfg.recovery
        x = np.array([match_ratio, mean_ll])
        if self._fast is None:
            self._fast, self._slow = x.copy(), x.copy()
        self._fast += r.alpha_fast * (x - self._fast)
        active = r.enabled and (self.ever_converged or (
            not self._searching and self.step_index - self._init_step > r.grace_scans))
        lost = active and bool(self._fast[0] < r.lost_match_ratio
                               or self._fast[0] < r.drop_ratio * self._slow[0]
                               or self._fast[1] < self._slow[1] - r.ll_drop)
        if not lost:  # while lost, the slow average keeps the healthy reference level
            self._slow += r.alpha_slow * (x - self._slow)
        if state == "converged" and not lost:
            if self._attempt or not self._healthy:
                self._slow = self._fast.copy()  # the reference level: a converged filter
            self._healthy = True
            self._attempt = 0
        self._lost_run = self._lost_run + 1 if lost else 0
        return lost

    def _recovery_action(self, lost: bool) -> str:
        r = self.cfg.recovery
        self._since_attempt += 1
        if not lost or self._lost_run < r.patience or self._since_attempt < r.attempt_scans:
            return ""
        self._since_attempt = 0
        self._attempt += 1
        return "expansion" if self._attempt <= r.expansion_attempts else "global"

    def _reseed(self, how: str, T_estimate: np.ndarray) -> None:
        r = self.cfg.recovery
        if how == "expansion":
            k = self._attempt
            std = [r.expansion_std_m * k] * 2 + [0.25 * r.expansion_std_m * k] + \
                  [0.3 * r.expansion_std_rad * k] * 2 + [r.expansion_std_rad * k]
            t = np.clip(T_estimate[:3, 3], *self.tsdf.geometry.extent_m)
            T = T_estimate.copy()
            T[:3, 3] = t
            self.init_pose(T, std, r.fraction)
        else:
            self.init_global(r.global_fraction)
            self.ever_converged = False  # global localization again: search mode
            if r.global_fraction < 1.0:
                self._searching = False  # part of the cloud stays: no coarse phase

    def _kld_count(self, pos, quat, w) -> int:
        r = self.cfg.resample
        k = min(len(w), self.cfg.estimate.samples)
        idx = _systematic(w, k, np.random.default_rng([self.seed, self.step_index, 5]))
        R = geometry.quat_to_rot(quat[idx])
        yaw = np.arctan2(R[:, 1, 0], R[:, 0, 0])
        keys = np.column_stack([np.floor(pos[idx] / r.kld_bin_m),
                                np.floor(yaw / r.kld_bin_rad)]).astype(np.int64)
        bins = len(np.unique(keys, axis=0))
        lo = min(r.min_particles, self.particles.capacity)
        return kld_sample_count(bins, r.kld_epsilon, r.kld_delta, lo, self.particles.capacity)


def check_config(cfg: LocalizerConfig) -> None:
    if cfg.resample.kld and cfg.resample.min_particles > cfg.particles:
        raise ConfigError(f"--min-particles {cfg.resample.min_particles} exceeds "
                          f"--max-particles {cfg.particles}")
