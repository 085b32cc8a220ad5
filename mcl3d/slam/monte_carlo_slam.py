"""Range-based 6-DoF Monte Carlo SLAM with gradient-guided particles (the SLAM paper, §III).

Per scan:
1. the odometry front-end (mcl3d.odometry.lidar_odometry: scan-to-model GICP + IMU
   preintegration) gives the relative motion ΔT and its covariance (inverse Hessian);
2. prediction: every particle moves by ΔT exp(δ), δ ~ N(0, Σ) (eq. 1), plus a vertical
   random walk while the elevator detector holds (median range under a threshold), centred
   on the IMU's vertical motion when the log has an IMU; in the elevator the scan only sees
   the moving cab, so it neither weighs particles nor becomes a keyframe;
3. correction: each particle picks its 3 nearest keyframes in its own map; particles with a
   loop among them (a keyframe more than `loop_min_travel_m` of travel ago, facing within
   half the field of view) take a Gauss-Newton step on the GICP cost against the loop
   keyframes (eq. 5-7), spread over their keyframes since the oldest neighbour in
   proportion to the odometry's drift variance along the path (eq. 8-10 weigh by distance);
4. weighting: the GICP log-likelihood against the 3 neighbours, accumulated (eq. 2-3, 11);
   particles without a loop then take one Gauss-Newton step toward their neighbours with
   the prediction as prior, so the noise does not pile up where the scan pins the pose;
5. keyframes: the scan becomes a keyframe for every particle when its voxel overlap with the
   last keyframe (under the odometry motion) falls below `keyframe_overlap`;
6. pruning: particles with a negligible posterior or frame likelihood are replaced by copies
   of living ones drawn by weight, the weight split between the copies.

Keyframe clouds live once, as Gaussian voxel maps shared by every particle. Choices the
paper leaves open are documented in docs/slam.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import (
    quat_to_rot,
    rotation_angle,
    se3,
    se3_inverse,
    se3_log,
    transform_points,
)
from mcl3d.odometry.lidar_odometry import LOST_COVARIANCE, Odometry, OdometryConfig
from mcl3d.registration.preprocess import ScanGrid, deskew, estimate_covariances, voxel_downsample

STAGES = ("odometry", "preprocess", "predict", "correct", "weigh", "refine", "keyframe",
          "prune", "estimate")


class SlamConfig(Section):
    particles: int = Field(10000, ge=1, description="particles N")
    seed: int = Field(0, ge=0, lt=2**32, description="random seed (reproducible runs)")
    fov_deg: float = Field(360.0, gt=0, le=360, description="keep points within ±fov/2 of "
                           "the lidar's +x axis (the paper crops the backward half: 180)")
    scan_voxel_m: float = Field(0.25, gt=0, description="downsampling of scans and keyframe "
                                "clouds (m)")
    keyframe_voxel_m: float = Field(0.5, gt=0, description="Gaussian voxel size of the "
                                    "keyframe maps used for likelihood and correction (m)")
    keyframe_overlap: float = Field(0.7, gt=0, le=1, description="new keyframe when the "
                                    "scan's voxel overlap with the last keyframe drops below")
    overlap_voxel_m: float = Field(1.0, gt=0, description="voxel size of the overlap test (m)")
    keyframe_points: int = Field(2048, ge=64, description="most points per keyframe map")
    max_keyframes: int = Field(256, ge=2, description="keyframe capacity (voxel maps are "
                               "allocated for this many)")
    correction_points: int = Field(512, ge=16, description="scan points per likelihood and "
                                   "Gauss-Newton evaluation")
    loop_min_travel_m: float = Field(10.0, gt=0, description="a neighbour keyframe this far "
                                     "back along the path is a loop")
    gn_iterations: int = Field(1, ge=0, description="Gauss-Newton steps per loop frame (0: "
                               "no gradient guidance)")
    min_inliers: int = Field(100, ge=6, description="loop correspondences needed for a step "
                             "(of correction_points): a loop keyframe that sees little of the "
                             "scan (the next row of trees, seen from behind) pulls the wrong way")
    max_correction_m: float = Field(1.0, gt=0, description="trust region of one step (m)")
    max_correction_deg: float = Field(5.0, gt=0, description="trust region of one step (deg)")
    refine_without_loop: bool = Field(True, description="particles without a loop take one "
                                      "Gauss-Newton step toward their own newest keyframes "
                                      "per scan, the prediction noise as prior (not in the "
                                      "paper; see docs/slam.md)")
    settled_correction_m: float = Field(0.02, ge=0, description="a step this small means the "
                                        "particle is on the loop: later steps spread from here "
                                        "instead of from the oldest neighbour (m)")
    settled_correction_deg: float = Field(0.2, ge=0, description="the same for rotation (deg)")
    odometry_noise_scale: float = Field(0.25, ge=0, description="× the odometry's σ (its "
                                        "inverse Hessian overstates the per-scan error)")
    noise_trans_per_m: float = Field(0.01, ge=0, description="translation σ per metre moved")
    noise_rot_deg_per_m: float = Field(0.05, ge=0, description="rotation σ (deg) per metre")
    noise_rot_per_rad: float = Field(0.01, ge=0, description="rotation σ per radian turned")
    noise_trans_min_m: float = Field(0.001, ge=0, description="translation σ floor per scan")
    noise_rot_min_deg: float = Field(0.01, ge=0, description="rotation σ floor per scan (deg)")
    max_motion_sigma_m: float = Field(0.0025, gt=0, description="cap on the translation σ per "
                                      "scan (degenerate or lost registration) (m)")
    max_motion_sigma_deg: float = Field(0.025, gt=0, description="the same for rotation (deg)")
    points_weight: float = Field(30.0, gt=0, description="independent points a scan is worth "
                                 "in the likelihood (tempering; see docs/slam.md)")
    outlier_cost: float = Field(0.0, ge=0, description="cost of a scan point with no voxel "
                                "(a matched point costs eᵀΩe; 0 as in the paper)")
    prune_posterior: float = Field(1e-8, ge=0, lt=1, description="dead below this posterior")
    prune_likelihood_ratio: float = Field(1e-16, ge=0, lt=1, description="dead when the "
                                          "frame likelihood is below this times the best "
                                          "particle's")
    elevator_median_range_m: float = Field(1.5, ge=0, description="elevator detected while "
                                           "the median range is below this (0: off)")
    elevator_sigma_z_m: float = Field(0.25, ge=0, description="vertical random walk per scan "
                                      "while in the elevator, without IMU (m)")
    elevator_imu_sigma_z_m: float = Field(0.01, ge=0, description="the same around the IMU's "
                                          "vertical motion (m)")
    neighbour_max_dz_m: float = Field(2.0, gt=0, description="keyframes more than this above "
                                      "or below a particle are not its neighbours (another "
                                      "floor) (m)")
    cluster_cell_m: float = Field(2.0, gt=0, description="grid cell for counting hypotheses")
    odometry: OdometryConfig = OdometryConfig()


@dataclass
class SlamFrame:
    """One scan's result. The pose is the representative particle's (largest weight)."""

    stamp_ns: int
    T_world_lidar: np.ndarray
    T_odom_lidar: np.ndarray  # the odometry front-end's pose
    T_motion_lidar: np.ndarray  # the same plus the elevator motion it could not see
    representative: int
    ess: float
    max_weight: float
    hypotheses: int
    looping: int
    corrected: int
    pruned: int
    keyframe: bool
    num_keyframes: int
    elevator: bool
    travel_m: float
    odometry_warnings: list[str]
    timings_ms: dict[str, float] = field(default_factory=dict)


class _Stopwatch:
    """Per-stage wall times; synchronizes the device so GPU work is charged to its stage."""

    def __init__(self):
        import taichi as ti

        self._sync = ti.sync
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, stage: str) -> None:
        self._sync()
        now = time.perf_counter()
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._t) * 1e3
        self._t = now


def motion_covariance(cfg: SlamConfig, T_prev_curr: np.ndarray, odo_cov: np.ndarray
                      ) -> np.ndarray:
    """Σ of the prediction noise δ (rotation first): the odometry's inverse Hessian, scaled
    and capped (a lost scan reports 1e6), plus a floor growing with the motion."""
    sig_max = np.r_[np.full(3, np.deg2rad(cfg.max_motion_sigma_deg)),
                    np.full(3, cfg.max_motion_sigma_m)]
    cov = np.where(np.isfinite(odo_cov), odo_cov, LOST_COVARIANCE) * cfg.odometry_noise_scale**2
    scaled = cov / np.outer(sig_max, sig_max)
    w, U = np.linalg.eigh(0.5 * (scaled + scaled.T))
    scaled = (U * np.clip(w, 0.0, 1.0)) @ U.T
    cov = scaled * np.outer(sig_max, sig_max)
    dist = float(np.linalg.norm(T_prev_curr[:3, 3]))
    angle = float(rotation_angle(T_prev_curr[:3, :3]))
    sig_t = cfg.noise_trans_min_m + cfg.noise_trans_per_m * dist
    sig_r = (np.deg2rad(cfg.noise_rot_min_deg) + np.deg2rad(cfg.noise_rot_deg_per_m) * dist
             + cfg.noise_rot_per_rad * angle)
    return cov + np.diag(np.r_[np.full(3, sig_r**2), np.full(3, sig_t**2)])


def crop_fov(points: np.ndarray, times: np.ndarray | None, fov_deg: float):
    """Points (and their times) within ±fov/2 of the lidar's +x axis."""
    if fov_deg >= 360.0:
        return points, times
    keep = np.abs(np.arctan2(points[:, 1], points[:, 0])) <= np.deg2rad(fov_deg) / 2
    return points[keep], None if times is None else times[keep]


def thin(points: np.ndarray, covs: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """At most `count` points, picked evenly (deterministic)."""
    if len(points) <= count:
        return points, covs
    pick = np.linspace(0, len(points) - 1, count).astype(np.int64)
    return points[pick], covs[pick]


def prune_plan(log_w: np.ndarray, frame_ll: np.ndarray, cfg: SlamConfig,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dead, sources, new log weights): particles with a posterior under
    `prune_posterior` or a frame likelihood under `prune_likelihood_ratio` times the best
    particle's (the paper's thresholds are absolute; ours are relative because the tempered
    likelihood has no absolute scale) are dead and
    become copies of living particles drawn by weight (systematic sampling); a particle
    copied c times shares its weight with its copies (each keeps 1/(c+1)). Weights are
    returned normalized (log, max 0 before the split)."""
    lw = log_w.astype(np.float64) - float(np.max(log_w))
    post = np.exp(lw)
    post /= post.sum()
    ratio = np.log(cfg.prune_likelihood_ratio) if cfg.prune_likelihood_ratio > 0 else -np.inf
    dead = (post < cfg.prune_posterior) | (frame_ll - np.max(frame_ll) < ratio)
    if dead.all():
        dead[int(np.argmax(lw))] = False
    dead_idx = np.flatnonzero(dead)
    living = np.flatnonzero(~dead)
    if len(dead_idx) == 0:
        return dead_idx, dead_idx, lw
    p = post[living] / post[living].sum()
    cdf = np.cumsum(p)
    u = (rng.random() + np.arange(len(dead_idx))) / len(dead_idx)
    sources = living[np.minimum(np.searchsorted(cdf, u * cdf[-1]), len(living) - 1)]
    copies = np.bincount(sources, minlength=len(lw))
    share = np.log1p(copies)
    lw = lw.copy()
    lw[dead_idx] = lw[sources] - share[sources]
    lw[living] -= share[living]
    return dead_idx, sources, lw


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 per point naming its voxel (21 bits per axis)."""
    c = np.floor(points / voxel_m).astype(np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def count_hypotheses(positions: np.ndarray, weights: np.ndarray, cell_m: float,
                     min_share: float = 0.01) -> int:
    """Grid cells of `cell_m` holding at least `min_share` of the weight."""
    cells = np.floor(positions / cell_m).astype(np.int64)
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    mass = np.bincount(inverse.ravel(), weights=weights)
    return int(np.sum(mass >= min_share))


class ElevatorRide:
    """Vertical motion while the elevator detector holds, from the IMU: specific force
    rotated into the world plus gravity, integrated twice. The cab stands still when the
    detector releases, so the velocity left then is the integrated accelerometer bias; the
    ride is corrected for it (the bias's ½ b T² is ½ v_end T)."""

    def __init__(self, start_s: float):
        self.start_s = start_s
        self.v_mps = 0.0
        self.z_m = 0.0
        self.last_s: float | None = None

    def integrate(self, imu: np.ndarray, R_world_imu: np.ndarray, g_world: np.ndarray,
                  up: np.ndarray) -> None:
        for k in range(len(imu)):
            t = float(imu[k, 0])
            if self.last_s is not None and t > self.last_s:
                a_up = float((R_world_imu @ imu[k, 4:7] + g_world) @ up)
                dt = t - self.last_s
                self.z_m += self.v_mps * dt + 0.5 * a_up * dt * dt
                self.v_mps += a_up * dt
            self.last_s = t

    def bias_correction_m(self) -> float:
        duration = (self.last_s - self.start_s) if self.last_s is not None else 0.0
        return -0.5 * self.v_mps * max(duration, 0.0)


class MonteCarloSlam:
    """`step(points, times, stamp, imu)` per scan in stamp order; `trajectory()` and
    `map_points()` at any time give the representative particle's result."""

    def __init__(self, config: SlamConfig | None = None,
                 T_lidar_imu: np.ndarray | None = None):
        import taichi as ti

        from mcl3d.kernels.slam import NEIGHBOURS
        from mcl3d.registration.batch_gicp import BatchGicp
        from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
        from mcl3d.slam.particles import DRIFT_SUMS, SlamParticles

        self.cfg = cfg = config or SlamConfig()
        if cfg.keyframe_voxel_m < cfg.scan_voxel_m:
            raise ConfigError("slam.keyframe_voxel_m must be >= slam.scan_voxel_m")
        self.odometry = Odometry(cfg.odometry, T_lidar_imu)
        buckets = 1 << int(np.ceil(np.log2(2 * cfg.keyframe_points)))
        self.maps = GaussianVoxelMaps(max_maps=cfg.max_keyframes, buckets_per_map=buckets,
                                      max_points=cfg.keyframe_points)
        groups = cfg.particles * NEIGHBOURS
        self.gicp = BatchGicp(self.maps, max_groups=groups, max_rows=groups,
                              max_source_points=cfg.correction_points)
        self.particles = SlamParticles(cfg.particles, cfg.max_keyframes, self.gicp, cfg.seed)
        self.grid = ScanGrid(max_voxels=cfg.odometry.max_points)
        self._grid_pts = ti.Vector.field(3, ti.f32, cfg.odometry.max_points)
        self._grid_rows = ti.Vector.field(6, ti.f32, cfg.odometry.max_points)
        self.frames: list[SlamFrame] = []
        self.keyframe_clouds: list[np.ndarray] = []  # lidar frame, scan_voxel_m
        self.keyframe_frames: list[int] = []  # frame index of every keyframe
        self.travel_m = 0.0
        # the prediction's variance summed along the path: rotational W, Σ w_j p_j (p_j the
        # odometry's position), translational V; loop corrections are spread by them
        self.drift = np.zeros(DRIFT_SUMS)
        self._rep = 0
        self._last_keys = np.zeros(0, np.int64)  # overlap voxels of the last keyframe
        self._ride: ElevatorRide | None = None
        self._ride_applied_m = 0.0
        self.vertical_offset = np.zeros(3)  # elevator motion the odometry did not see

    # ---- one scan ----

    def step(self, points: np.ndarray, times_s: np.ndarray | None, stamp_ns: int,
             imu: np.ndarray | None = None) -> SlamFrame:
        cfg = self.cfg
        watch = _Stopwatch()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        times = None if times_s is None else np.asarray(times_s, np.float64).ravel()
        points, times = crop_fov(points, times, cfg.fov_deg)
        odo = self.odometry.step(points, times, stamp_ns, imu)
        watch.lap("odometry")
        first = len(self.frames) == 0
        ranges = np.linalg.norm(points, axis=1)
        elevator = bool(len(ranges) and cfg.elevator_median_range_m > 0
                        and np.median(ranges) < cfg.elevator_median_range_m)
        lift = self._elevator_shift(elevator, odo, imu, stamp_ns)
        down, covs = self._preprocess(points, times, odo, first)
        watch.lap("preprocess")
        step = len(self.frames)
        self.travel_m += float(np.linalg.norm(odo.T_prev_curr[:3, 3]))
        T_odom = self._with_offset(odo.T_world_lidar)
        p = self.particles
        looping = corrected = 0
        if not first:
            cov = motion_covariance(cfg, odo.T_prev_curr, odo.covariance)
            w = float(np.trace(cov[:3, :3]))
            self.drift += np.r_[w, w * T_odom[:3, 3], np.trace(cov[3:, 3:])]
            p.predict(odo.T_prev_curr, cov, 2 * step)
            if lift is not None:
                p.shift_vertical(*lift, 2 * step + 1)
                self.drift[4] += lift[2] ** 2  # the elevator's random walk
        watch.lap("predict")
        src_pts, src_covs = thin(down, covs, cfg.correction_points)
        can_score = (p.num_keyframes > 0 and len(src_pts) >= cfg.min_inliers
                     and not elevator)
        if can_score:
            self.gicp.set_source(src_pts, src_covs)
            gate = (self.travel_m, cfg.loop_min_travel_m, self._up(), cfg.neighbour_max_dz_m,
                    np.deg2rad(cfg.fov_deg / 2))
            looping = p.select_neighbours(*gate)
            for _ in range(cfg.gn_iterations if looping else 0):
                corrected = p.correct(self.travel_m, self.drift, T_odom[:3, 3], len(src_pts),
                                      cfg.min_inliers,
                                      np.deg2rad(cfg.max_correction_deg), cfg.max_correction_m,
                                      np.deg2rad(cfg.settled_correction_deg),
                                      cfg.settled_correction_m)
                p.select_neighbours(*gate)
        watch.lap("correct")
        if can_score:
            p.weigh(len(src_pts), cfg.outlier_cost, cfg.points_weight)
        watch.lap("weigh")
        if can_score and cfg.refine_without_loop and not first:
            p.refine(cov, cfg.min_inliers, np.deg2rad(cfg.max_correction_deg),
                     cfg.max_correction_m)
        watch.lap("refine")
        keyframe = not elevator and self._keyframe_due(down, T_odom)
        if keyframe:
            self._add_keyframe(down, covs, T_odom[:3, 3])
        watch.lap("keyframe")
        pruned, post = self._prune(step, can_score)
        watch.lap("prune")
        self._rep = int(np.argmax(post))
        positions = p.positions()
        T_rep = se3(quat_to_rot(p.quaternion(self._rep)), positions[self._rep])
        hyp = count_hypotheses(positions, post, cfg.cluster_cell_m)
        watch.lap("estimate")
        frame = SlamFrame(stamp_ns, T_rep, odo.T_world_lidar, T_odom, self._rep,
                          float(1.0 / np.sum(post**2)), float(post.max()), hyp, looping,
                          corrected, pruned, keyframe, p.num_keyframes, elevator,
                          self.travel_m, list(odo.warnings), watch.ms)
        self.frames.append(frame)
        if keyframe:
            self.keyframe_frames.append(len(self.frames) - 1)
        return frame

    def _with_offset(self, T: np.ndarray) -> np.ndarray:
        out = T.copy()
        out[:3, 3] += self.vertical_offset
        return out

    def _up(self) -> np.ndarray:
        """World up: against the IMU's gravity, else the first scan's +z."""
        g = self.odometry.g_world
        return np.array([0.0, 0.0, 1.0]) if g is None else -g / np.linalg.norm(g)

    def _elevator_shift(self, elevator: bool, odo, imu, stamp_ns: int):
        """(shift, up, sigma) for the particles this scan, or None outside the elevator."""
        cfg = self.cfg
        g = self.odometry.g_world
        up = self._up()
        has_imu = g is not None and imu is not None and len(imu) > 0
        shift = 0.0
        if elevator and self._ride is None:
            self._ride = ElevatorRide(stamp_ns * 1e-9)
            self._ride_applied_m = 0.0
        if self._ride is not None and has_imu:
            R_world_imu = (odo.T_world_lidar @ self.odometry.T_lidar_imu)[:3, :3]
            self._ride.integrate(imu, R_world_imu, g, up)
            target = self._ride.z_m if elevator else (self._ride.z_m
                                                      + self._ride.bias_correction_m())
            shift = target - self._ride_applied_m
            self._ride_applied_m = target
        if not elevator:
            self._ride = None
            if shift == 0.0:
                return None
        self.vertical_offset += shift * up
        sigma = 0.0
        if elevator:
            sigma = cfg.elevator_imu_sigma_z_m if has_imu else cfg.elevator_sigma_z_m
        return shift * up, up, sigma

    def _preprocess(self, points, times, odo, first: bool) -> tuple[np.ndarray, np.ndarray]:
        """Deskewed to the stamp with the odometry's motion, downsampled, covariances: on
        the device (ScanGrid, as the odometry does), on the host when the scan has more
        voxels than the grid holds or the odometry asks for more neighbours than it finds."""
        from mcl3d.kernels.scan_grid import MAX_K
        from mcl3d.registration.preprocess import download_rows, plane_rows_to_covs

        cfg, oc = self.cfg, self.cfg.odometry
        twist = None
        if times is not None and not first and len(points) and self.frames:
            dt = (odo.stamp_ns - self.frames[-1].stamp_ns) * 1e-9
            if dt > 0:
                twist = se3_log(odo.T_prev_curr) / dt
        if oc.k_neighbors <= MAX_K:
            n = self.grid.downsample(points, cfg.scan_voxel_m, self._grid_pts,
                                     None if twist is None else times, twist, oc.min_range_m,
                                     oc.max_range_m, self._grid_rows, oc.k_neighbors)
            if n is not None:
                down, rows = download_rows(self._grid_pts, self._grid_rows, n)
                return down, plane_rows_to_covs(rows)
        if twist is not None:
            points = deskew(points, times, twist)
        r = np.linalg.norm(points, axis=1)
        points = points[(r >= oc.min_range_m) & (r <= oc.max_range_m)]
        down = voxel_downsample(points, cfg.scan_voxel_m) if len(points) else points
        return down, estimate_covariances(down, oc.k_neighbors)

    def _keyframe_due(self, down: np.ndarray, T_motion_lidar: np.ndarray) -> bool:
        if len(down) < self.cfg.min_inliers:
            return False
        if self.particles.num_keyframes == 0:
            return True
        last = self.frames[self.keyframe_frames[-1]].T_motion_lidar
        in_last = transform_points(se3_inverse(last) @ T_motion_lidar, down)
        keys = voxel_keys(in_last, self.cfg.overlap_voxel_m)
        overlap = float(np.isin(keys, self._last_keys).mean())
        return overlap < self.cfg.keyframe_overlap

    def _add_keyframe(self, down: np.ndarray, covs: np.ndarray, odom_position: np.ndarray
                      ) -> None:
        k = self.particles.add_keyframe(self.travel_m, self.drift, odom_position)
        pts, cv = thin(down, covs, self.cfg.keyframe_points)
        self.maps.clear(k, self.cfg.keyframe_voxel_m)
        self.maps.insert(k, pts, cv)
        self.keyframe_clouds.append(down.astype(np.float32))
        self._last_keys = np.unique(voxel_keys(down, self.cfg.overlap_voxel_m))

    def _prune(self, step: int, scored: bool) -> tuple[int, np.ndarray]:
        """Prune; particles without a neighbour keyframe (unmapped space, another floor) get
        the median likelihood of the scored ones: no evidence for or against them."""
        from mcl3d.kernels.slam import UNSCORED

        p = self.particles
        log_w = p.log_w.to_numpy().astype(np.float64)
        frame_ll = np.zeros_like(log_w)
        if scored:
            frame_ll = p.frame_ll.to_numpy().astype(np.float64)
            unscored = frame_ll <= UNSCORED
            typical = float(np.median(frame_ll[~unscored])) if (~unscored).any() else 0.0
            frame_ll[unscored] = typical
            log_w[unscored] += typical
        rng = np.random.default_rng([self.cfg.seed, step])
        dead, sources, lw = prune_plan(log_w, frame_ll, self.cfg, rng)
        p.respawn(dead, sources, lw)
        post = np.exp(lw - lw.max())
        return len(dead), post / post.sum()

    # ---- results of the representative particle ----

    def representative_keyframes(self) -> np.ndarray:
        return self.particles.keyframe_poses(self._rep)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, poses) of every scan as the representative particle's map places it:
        each scan hangs off the keyframe before it by the odometry motion since then, so
        the trajectory follows the loop corrections of its keyframes."""
        kf_poses = self.representative_keyframes()
        stamps = np.array([f.stamp_ns for f in self.frames], dtype=np.int64)
        poses = np.empty((len(self.frames), 4, 4))
        anchor = -1
        for i, f in enumerate(self.frames):
            if anchor + 1 < len(self.keyframe_frames) and self.keyframe_frames[anchor + 1] <= i:
                anchor += 1
            if anchor < 0:
                poses[i] = f.T_world_lidar
                continue
            kf_frame = self.frames[self.keyframe_frames[anchor]]
            poses[i] = (kf_poses[anchor] @ se3_inverse(kf_frame.T_motion_lidar)
                        @ f.T_motion_lidar)
        return stamps, poses

    def map_points(self) -> np.ndarray:
        """The union of the keyframe clouds under the representative's keyframe poses."""
        kf_poses = self.representative_keyframes()
        clouds = [transform_points(T, c.astype(np.float64))
                  for T, c in zip(kf_poses, self.keyframe_clouds, strict=True)]
        return np.concatenate(clouds) if clouds else np.zeros((0, 3))
