"""Range-based 6-DoF Monte Carlo SLAM with gradient-guided particles (the SLAM paper, §III).

Per scan:
1. the odometry front-end (mcl3d.odometry.lidar_odometry: scan-to-model GICP + IMU
   preintegration) gives the relative motion ΔT and its covariance (inverse Hessian);
2. prediction: every particle moves by ΔT exp(δ), δ ~ N(0, Σ) (eq. 1), plus a vertical
   random walk while the elevator detector holds (the scan closed in every direction), centred
   on the IMU's vertical motion when the log has an IMU; in the elevator the scan only sees
   the moving cab, so it neither weighs particles nor becomes a keyframe;
3. correction: each particle picks its 3 nearest keyframes in its own map; particles with a
   loop among them (a keyframe more than `loop_closure.min_travel_m` of travel ago, facing within
   half the field of view) take a Gauss-Newton step on the GICP cost against the loop
   keyframes (eq. 5-7), spread over their keyframes since the oldest neighbour in
   proportion to the odometry's drift variance along the path (eq. 8-10 weigh by distance);
4. weighting: the GICP log-likelihood against the 3 neighbours, accumulated (eq. 2-3, 11);
   a neighbour that is not a loop costs the cloud's median such row (`likelihood.local_weight`
   0): the odometry already matched the scan to the recent map, so only loops tell particles
   apart; a scan point without a voxel costs a typical matched point's cost (no evidence);
   optionally (`correction.refine_without_loop`) particles without a loop then take
   one Gauss-Newton step toward their neighbours with the prediction as prior;
5. keyframes: the scan becomes a keyframe for every particle when its voxel overlap with the
   last keyframe (under the odometry motion) falls below `keyframes.overlap`; once
   `keyframes.capacity` keyframes are kept, it replaces the most redundant one
   (mcl3d.slam.keyframe_store), so a run of any length keeps a bounded store;
6. pruning: particles with a negligible posterior or frame likelihood are replaced by copies
   of living ones drawn by weight, the weight split between the copies; after an elevator
   ride each height stratum is pruned on its own until one floor's evidence dominates
   (mcl3d.slam.floor_guard).

Keyframe clouds live once, as Gaussian voxel maps shared by every particle. Choices the
paper leaves open are documented in docs/slam.md.
"""

from __future__ import annotations

import time

import numpy as np
import taichi as ti

from mcl3d.core.geometry import (
    quat_to_rot,
    rotation_angle,
    se3,
    se3_inverse,
    se3_log,
    transform_points,
)
from mcl3d.kernels.scan_grid import MAX_K
from mcl3d.kernels.slam import NEIGHBOURS, UNSCORED
from mcl3d.maps.sparse_cells import unique_keys
from mcl3d.odometry.lidar_odometry import LOST_COVARIANCE, LidarOdometry, OdometryFrame
from mcl3d.registration.batch_gicp import BatchGicp
from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
from mcl3d.registration.gicp_state import SourcePool
from mcl3d.registration.preprocess import (
    ScanGrid,
    deskew,
    download_rows,
    estimate_covariances,
    plane_rows_to_covs,
    voxel_downsample,
)
from mcl3d.slam.cloud_mean import CloudMean
from mcl3d.slam.elevator import ElevatorRide, in_elevator, open_sectors
from mcl3d.slam.floor_guard import FloorGuard, stratified_prune_plan
from mcl3d.slam.frame_store import SlamFrame, SlamFrames
from mcl3d.slam.free_space import FreeSpace
from mcl3d.slam.keyframe_store import KeyframeBook, slot_to_reuse
from mcl3d.slam.loop_bridge import anchored_keyframes, bridge_between_anchors, step_covariances
from mcl3d.slam.loop_graph import LoopEdge, LoopEdges, agreeing_edges, solve_pose_graph
from mcl3d.slam.slam_config import PredictionNoiseConfig, PruningConfig, SlamConfig
from mcl3d.slam.slam_particles import DRIFT_SUMS, SlamParticles
from mcl3d.slam.structure_up import KeyframeUps

HYPOTHESIS_MIN_SHARE = 0.01  # a grid cell holding this share of the weight is a hypothesis
BINCOUNT_CELLS_PER_POSITION = 4  # count_hypotheses bins directly when the cloud's box has
# at most this many cells per particle (else it sorts the cells)
KEYFRAME_BUCKETS_PER_POINT = 2  # hash slots per keyframe point (rounded up to a power of 2)


class _Stopwatch:
    """Per-stage wall times; synchronizes the device so GPU work is charged to its stage."""

    def __init__(self):
        self._sync = ti.sync
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, stage: str) -> None:
        self._sync()
        now = time.perf_counter()
        self.ms[stage] = self.ms.get(stage, 0.0) + (now - self._t) * 1e3
        self._t = now


def motion_covariance(noise: PredictionNoiseConfig, T_prev_curr: np.ndarray,
                      odo_cov: np.ndarray) -> np.ndarray:
    """Σ of the prediction noise δ (rotation first): the odometry's inverse Hessian, scaled
    and capped (a lost scan reports 1e6), plus a floor growing with the motion."""
    sig_max = np.r_[np.full(3, np.deg2rad(noise.max_odometry_sigma_deg)),
                    np.full(3, noise.max_odometry_sigma_m)]
    cov = np.where(np.isfinite(odo_cov), odo_cov, LOST_COVARIANCE) * noise.odometry_scale**2
    scaled = cov / np.outer(sig_max, sig_max)
    w, U = np.linalg.eigh(0.5 * (scaled + scaled.T))
    scaled = (U * np.clip(w, 0.0, 1.0)) @ U.T
    cov = scaled * np.outer(sig_max, sig_max)
    dist = float(np.linalg.norm(T_prev_curr[:3, 3]))
    angle = float(rotation_angle(T_prev_curr[:3, :3]))
    sig_t = noise.trans_min_m + noise.trans_per_m * dist
    sig_r = (np.deg2rad(noise.rot_min_deg) + np.deg2rad(noise.rot_deg_per_m) * dist
             + noise.rot_deg_per_deg * angle)  # deg per deg: the same ratio in radians
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


def prune_plan(log_w: np.ndarray, frame_ll: np.ndarray, cfg: PruningConfig,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dead, sources, new log weights): particles with a posterior under
    `cfg.posterior` or a frame likelihood under `cfg.likelihood_ratio` times the best
    particle's (the paper's thresholds are absolute; ours are relative because the tempered
    likelihood has no absolute scale) are dead and
    become copies of living particles drawn by weight (systematic sampling); a particle
    copied c times shares its weight with its copies (each keeps 1/(c+1)). Weights are
    returned normalized (log, max 0 before the split). The floor guard's rule with every
    particle in one group."""
    return stratified_prune_plan(log_w, frame_ll, np.zeros(len(log_w), np.int64), cfg, rng)


def resample_all(log_w: np.ndarray, rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dead, sources, new log weights) of a systematic resampling of every particle by
    weight: a particle drawn c times stays and gives c - 1 copies to particles drawn never
    (the dead); all weights become equal."""
    lw = np.asarray(log_w, np.float64)
    post = np.exp(lw - lw.max())
    cdf = np.cumsum(post / post.sum())
    n = len(lw)
    drawn = np.minimum(np.searchsorted(cdf, (rng.random() + np.arange(n)) / n * cdf[-1]), n - 1)
    counts = np.bincount(drawn, minlength=n)
    dead = np.flatnonzero(counts == 0)
    sources = np.repeat(np.arange(n), np.maximum(counts - 1, 0))
    return dead, sources, np.zeros(n)


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 per point naming its voxel (21 bits per axis)."""
    c = np.floor(points / voxel_m).astype(np.int64) + (1 << 20)
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def count_hypotheses(positions: np.ndarray, weights: np.ndarray, cell_m: float,
                     min_share: float = HYPOTHESIS_MIN_SHARE) -> int:
    """Grid cells of `cell_m` holding at least `min_share` of the weight."""
    cells = np.floor(positions / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    volume = float(np.prod(span.astype(np.float64)))
    if volume <= BINCOUNT_CELLS_PER_POSITION * len(cells):  # a compact cloud: no sort
        flat = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
        mass = np.bincount(flat, weights=np.asarray(weights, np.float64))
    elif volume < 2.0**62:  # one sortable int64 per cell
        cells = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
        order = np.argsort(cells, kind="stable")
        starts = np.flatnonzero(np.r_[True, cells[order][1:] != cells[order][:-1]])
        mass = np.add.reduceat(np.asarray(weights, np.float64)[order], starts)
    else:
        _, inverse = np.unique(cells, axis=0, return_inverse=True)
        mass = np.bincount(inverse.ravel(), weights=weights)
    return int(np.sum(mass >= min_share))


class MonteCarloSlam:
    """`step(points, times, stamp, imu)` per scan in stamp order; `trajectory()` and
    `map_points()` at any time give the representative particle's result."""

    def __init__(self, config: SlamConfig | None = None,
                 T_lidar_imu: np.ndarray | None = None, scans: int | None = None):
        """`scans`: how many scans the run expects, if known (the per-scan records are
        allocated for them)."""
        self.cfg = cfg = config or SlamConfig()
        self.odometry = LidarOdometry(cfg.odometry, T_lidar_imu)
        kf = cfg.keyframes
        buckets = 1 << int(np.ceil(np.log2(KEYFRAME_BUCKETS_PER_POINT * kf.max_points)))
        self.maps = GaussianVoxelMaps(max_maps=kf.capacity, buckets_per_map=buckets,
                                      max_points=kf.max_points)
        groups = cfg.particles * NEIGHBOURS
        self.gicp = BatchGicp(self.maps, max_groups=groups, max_rows=groups,
                              max_source_points=cfg.correction.points)
        self.particles = SlamParticles(cfg.particles, kf.capacity, self.gicp, cfg.seed)
        self.cloud_mean = CloudMean(cfg.particles)
        lk = cfg.likelihood
        self.free_space = None if max(lk.free_space_cost, cfg.elevator.free_space_cost) <= 0 \
            else FreeSpace(
            kf.capacity, lk.free_space_bin_deg, cfg.odometry.min_range_m,
            cfg.odometry.max_range_m, lk.free_space_points)
        self._keyframes_full = False  # said once when keyframes.capacity is reached
        self.grid = ScanGrid(max_voxels=cfg.odometry.max_points)
        self._scan_pool = SourcePool(cfg.odometry.max_points)  # the downsampled scan
        self.frames = SlamFrames(scans)  # every scan's record, as columns
        self.keyframes = KeyframeBook()  # scans, clouds (front_end.scan_voxel_m), dropped
        self.travel_m = 0.0
        # the prediction's variance summed along the path: rotational W, Σ w_j p_j (p_j the
        # odometry's position), translational V; loop corrections are spread by them
        self.drift = np.zeros(DRIFT_SUMS)
        self._rep = 0
        self._last_keys = np.zeros(0, np.int64)  # overlap voxels of the last keyframe
        self._ride: ElevatorRide | None = None
        self._ride_applied_m = 0.0
        self._after_ride = False  # the scans after a ride until the sensor leaves the cab
        self.floor_guard = FloorGuard(cfg.elevator, cfg.pruning,  # floors kept after a ride
                                      cfg.loop_closure.neighbour_max_dz_m)
        self.vertical_offset = np.zeros(3)  # elevator motion the odometry did not see
        self._ride_variance_m2 = 0.0  # the elevator's vertical random walk, summed
        self._written_keyframes = None  # ((scans, bridged, graph, ups), poses) last asked
        self.loop_edges = LoopEdges()  # each loop the representative took, registered
        self.keyframe_ups = KeyframeUps(cfg.odometry.k_neighbors)  # (structure_up)

    # ---- one scan ----

    def step(self, points: np.ndarray, times_s: np.ndarray | None, stamp_ns: int,
             imu: np.ndarray | None = None) -> SlamFrame:
        """Odometry, predict, correct and weigh, keyframe, prune, estimate (module docstring);
        arguments as `LidarOdometry.step`'s."""
        cfg = self.cfg
        watch = _Stopwatch()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        times = None if times_s is None else np.asarray(times_s, np.float64).ravel()
        points, times = crop_fov(points, times, cfg.front_end.fov_deg)
        odo = self.odometry.step(points, times, stamp_ns, imu)
        watch.lap("odometry")
        first = len(self.frames) == 0
        elevator = in_elevator(points, cfg.elevator, cfg.front_end.fov_deg)
        if elevator and self._ride is None and cfg.elevator.resample_on_entry and not first:
            self.particles.respawn(*resample_all(self.particles.log_w.to_numpy(),
                                                 np.random.default_rng([cfg.seed, len(self.frames),
                                                                        1])))
        riding = self._ride is not None
        lift = self._elevator_shift(elevator, odo, imu, stamp_ns)
        if riding and self._ride is None and cfg.elevator.floor_guard:
            self.floor_guard.start()
        in_cab = self._leaving_cab(points) or elevator  # (called on every scan)
        down, covs = self._preprocess(points, times, odo, first)
        watch.lap("preprocess")
        step = len(self.frames)
        self.travel_m += float(np.linalg.norm(odo.T_prev_curr[:3, 3]))
        T_odom = self._with_offset(odo.T_world_lidar)
        cov = None if first else self._predict(odo, T_odom, lift, step)
        watch.lap("predict")
        looping, corrected, scored, loops = self._correct_and_weigh(down, covs, in_cab, cov,
                                                                    T_odom, watch, points)
        keyframe = not in_cab and self._keyframe_due(down, T_odom)
        warnings = list(odo.warnings)
        if keyframe and self.particles.full and not self._keyframes_full:
            warnings.append(f"all {self.particles.max_keyframes} keyframes are used: each new "
                            "keyframe now replaces the most redundant one (raise "
                            "keyframes.capacity to keep more)")
            self._keyframes_full = True
        if keyframe:
            self._add_keyframe(down, covs, T_odom, loops, points)
        watch.lap("keyframe")
        pruned, post, origin = self._prune(step, scored)
        watch.lap("prune")
        p = self.particles
        self._rep = int(np.argmax(post))
        positions = p.positions()
        T_rep = se3(quat_to_rot(p.quaternion(self._rep)), positions[self._rep])
        hyp = count_hypotheses(positions, post, cfg.pruning.hypothesis_cell_m)
        T_mean, cloud_cov = self.cloud_mean(p.q_cur, p.t_cur, post,
                                            se3(T_rep[:3, :3], post @ positions))
        loop_slots = list(loops.get(int(origin[self._rep]), ()))
        kf_poses = p.keyframe_poses(self._rep)[loop_slots] if loop_slots else []
        if cfg.trajectory.loop_graph and loop_slots:
            self._register_loops(loop_slots, kf_poses, T_rep, T_odom, down)
        watch.lap("estimate")
        frame = SlamFrame(stamp_ns, T_rep, odo.T_world_lidar, T_odom, self._rep,
                          float(1.0 / np.sum(post**2)), float(post.max()), hyp, looping,
                          corrected, pruned, keyframe, p.num_keyframes, elevator,
                          self.travel_m, warnings, watch.ms, T_mean, cloud_cov,
                          tuple(int(p.seq[k]) for k in loop_slots),
                          tuple(se3_inverse(T) @ T_rep for T in kf_poses))
        self.frames.append(frame)
        return frame

    @property
    def keyframe_frames(self) -> list[int]:
        """The scan index of every keyframe made, by keyframe number."""
        return self.keyframes.frames

    def _predict(self, odo: OdometryFrame, T_odom: np.ndarray, lift, step: int) -> np.ndarray:
        """Move every particle by the odometry's motion plus noise (and the elevator's lift);
        returns the noise covariance."""
        p = self.particles
        cov = motion_covariance(self.cfg.prediction_noise, odo.T_prev_curr, odo.covariance)
        w = float(np.trace(cov[:3, :3]))
        self.drift += np.r_[w, w * T_odom[:3, 3], np.trace(cov[3:, 3:])]
        p.predict(odo.T_prev_curr, cov, 2 * step)
        if lift is not None:
            p.shift_vertical(*lift, 2 * step + 1)
            self.drift[4] += lift[2] ** 2  # the elevator's random walk
            self._ride_variance_m2 += lift[2] ** 2
        return cov

    def _free_space_cost(self) -> float:
        """The free-space term's cost on this scan: `likelihood.free_space_cost` on every
        scan, else `elevator.free_space_cost` while the floor guard holds the floors."""
        if self.cfg.likelihood.free_space_cost > 0:
            return self.cfg.likelihood.free_space_cost
        return self.cfg.elevator.free_space_cost if self.floor_guard.active else 0.0

    def _correct_and_weigh(self, down: np.ndarray, covs: np.ndarray, in_cab: bool,
                           cov: np.ndarray | None, T_odom: np.ndarray, watch: _Stopwatch,
                           points: np.ndarray
                           ) -> tuple[int, int, bool, dict[int, tuple[int, ...]]]:
        """Loop correction, likelihood and refinement against each particle's neighbour
        keyframes; returns (particles looping, particles corrected, whether the scan was
        scored, the loop keyframes of each corrected particle). Nothing is scored without
        keyframes, in the elevator's cab or on a tiny scan. `points`: the whole scan
        (lidar frame), for the free space it saw."""
        cfg, corr = self.cfg, self.cfg.correction
        p = self.particles
        looping = corrected = 0
        loops: dict[int, tuple[int, ...]] = {}
        src_pts, src_covs = thin(down, covs, corr.points)
        scored = p.num_keyframes > 0 and len(src_pts) >= corr.min_inliers and not in_cab
        if scored:
            free_space_cost = self._free_space_cost()
            if free_space_cost > 0:
                self.free_space.set_scan(points)
            self.gicp.set_source(src_pts, src_covs)
            loop = cfg.loop_closure
            facing_rad = np.deg2rad(cfg.front_end.fov_deg / 2) if loop.facing_gate else np.pi
            gate = (self.travel_m, loop.min_travel_m, self._up(), loop.neighbour_max_dz_m,
                    facing_rad, loop.facing_gate and loop.facing_neighbours)
            looping = p.select_neighbours(*gate)
            for _ in range(corr.gn_iterations if looping else 0):
                corrected = p.correct(self.travel_m, self.drift, T_odom[:3, 3], len(src_pts),
                                      corr)
                loops = loops or p.loop_keyframes()
                p.select_neighbours(*gate)
        watch.lap("correct")
        if scored:
            # after a ride the particles' heights are not the odometry's: every neighbour
            # weighs until the floor guard lets go
            p.weigh(len(src_pts), cfg.likelihood, self.free_space, free_space_cost,
                    local_weight=1.0 if self.floor_guard.active else None)
        watch.lap("weigh")
        if scored and corr.refine_without_loop and cov is not None:
            p.refine(cov, corr)
        if scored and corr.spread_after_step and cov is not None:
            p.spread(cov, len(src_pts), cfg.likelihood.points_weight, corr.min_inliers,
                     corr.refine_without_loop, corrected > 0,
                     len(self.frames))
        watch.lap("refine")
        return looping, corrected, scored, loops

    def _with_offset(self, T: np.ndarray) -> np.ndarray:
        out = T.copy()
        out[:3, 3] += self.vertical_offset
        return out

    def _up(self) -> np.ndarray:
        """World up: against the IMU's gravity, else the first scan's +z."""
        g = self.odometry.g_world
        return np.array([0.0, 0.0, 1.0]) if g is None else -g / np.linalg.norm(g)

    def _leaving_cab(self, points: np.ndarray) -> bool:
        """Whether the scan is still in the cab after a ride (its doors open): until
        `elevator.exit_open_sectors` sectors are open. A scan of the cab matches the cab
        wherever a keyframe saw it, on any floor, and where a keyframe saw the shaft empty
        the cab contradicts the right floor's map: such scans do not decide the floor."""
        if self._ride is not None or not self._after_ride:
            self._after_ride = self._ride is not None
            return False
        ecfg = self.cfg.elevator
        self._after_ride = open_sectors(points, ecfg, self.cfg.front_end.fov_deg) < \
            ecfg.exit_open_sectors
        return self._after_ride

    def _elevator_shift(self, elevator: bool, odo: OdometryFrame, imu: np.ndarray | None,
                        stamp_ns: int):
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
            sigma = cfg.elevator.imu_sigma_z_m if has_imu else cfg.elevator.sigma_z_m
        return shift * up, up, sigma

    def _preprocess(self, points: np.ndarray, times: np.ndarray | None, odo: OdometryFrame,
                    first: bool) -> tuple[np.ndarray, np.ndarray]:
        """Deskewed to the stamp with the odometry's motion, downsampled, covariances: on
        the device (ScanGrid, as the odometry does), on the host when the scan has more
        voxels than the grid holds or the odometry asks for more neighbours than it finds."""
        voxel_m, oc = self.cfg.front_end.scan_voxel_m, self.cfg.odometry
        twist = None
        if times is not None and not first and len(points) and self.frames:
            dt = (odo.stamp_ns - int(self.frames.stamp_ns[-1])) * 1e-9
            if dt > 0:
                twist = se3_log(odo.T_prev_curr) / dt
        if oc.k_neighbors <= MAX_K:
            n = self.grid.downsample(points, voxel_m, self._scan_pool,
                                     None if twist is None else times, twist, oc.min_range_m,
                                     oc.max_range_m, oc.k_neighbors)
            if n is not None:
                down, rows = download_rows(self._scan_pool, n)
                return down, plane_rows_to_covs(rows)
        if twist is not None:
            points = deskew(points, times, twist)
        r = np.linalg.norm(points, axis=1)
        points = points[(r >= oc.min_range_m) & (r <= oc.max_range_m)]
        down = voxel_downsample(points, voxel_m) if len(points) else points
        return down, estimate_covariances(down, oc.k_neighbors)

    def _keyframe_due(self, down: np.ndarray, T_motion_lidar: np.ndarray) -> bool:
        if len(down) < self.cfg.correction.min_inliers:
            return False
        if self.particles.num_keyframes == 0:
            return True
        last = self.frames.pose("T_motion_lidar", self.keyframe_frames[-1])
        in_last = transform_points(se3_inverse(last) @ T_motion_lidar, down)
        keys = voxel_keys(in_last, self.cfg.keyframes.overlap_voxel_m)
        at = np.minimum(np.searchsorted(self._last_keys, keys), len(self._last_keys) - 1)
        overlap = float((self._last_keys[at] == keys).mean())
        return overlap < self.cfg.keyframes.overlap

    def _add_keyframe(self, down: np.ndarray, covs: np.ndarray, T_odom: np.ndarray,
                      loops: dict[int, tuple[int, ...]], points: np.ndarray) -> None:
        """The scan becomes a keyframe, in a free slot or, when all are used, in the one
        `_slot_to_reuse` frees. `loops`: the slots the particles were corrected toward on this
        scan (kept, so the scan's record names them); `points`: the whole scan (lidar
        frame), whose range image says what the keyframe saw through."""
        p = self.particles
        slot = self._slot_to_reuse(loops) if p.full else None
        k = p.add_keyframe(self.travel_m, self.drift, T_odom[:3, 3], slot)
        pts, cv = thin(down, covs, self.cfg.keyframes.max_points)
        self.maps.clear(k, self.cfg.keyframes.voxel_m)
        self.maps.insert(k, pts, cv)
        if self.free_space is not None:
            self.free_space.store(k, points, down)
        self.keyframes.add(k, len(self.frames), down.astype(np.float32),
                           (float(self.drift[0]), float(self.drift[4]) - self._ride_variance_m2,
                            self._ride_variance_m2))
        self._last_keys = unique_keys(voxel_keys(down, self.cfg.keyframes.overlap_voxel_m))
        if self.cfg.trajectory.structure_up:
            self.keyframe_ups.measure(len(self.keyframes) - 1, down, T_odom[:3, :3], self._up())

    def _slot_to_reuse(self, loops: dict[int, tuple[int, ...]]) -> int:
        """The slot of the most redundant keyframe in the representative's map (see
        keyframe_store), keeping the newest keyframes (the local map), the representative's
        neighbours and this scan's loop keyframes; the dropped keyframe's pose is frozen."""
        p, rep = self.particles, self._rep
        T_slots = p.keyframe_poses(rep)
        newest = p.slots_in_order()[-min(NEIGHBOURS, p.max_keyframes - 1):]
        protected = {int(k) for k in newest}
        protected.update(int(k) for k in p.nb.to_numpy()[rep] if k >= 0)
        protected.update(k for kfs in loops.values() for k in kfs)
        facing = self.cfg.front_end.fov_deg / 2 if self.cfg.loop_closure.facing_gate else 180
        slot = slot_to_reuse(T_slots, p.seq[:p.num_keyframes], protected,
                             float(np.cos(np.deg2rad(facing))))
        self.keyframes.retire(int(p.seq[slot]), T_slots[slot])
        return slot

    def _register_loops(self, loop_slots: list[int], T_loop_keyframes: list[np.ndarray],
                        T_rep: np.ndarray, T_odom: np.ndarray, down: np.ndarray) -> None:
        """Register the scan (`down`, lidar frame) onto each loop keyframe the representative
        just took, from its relative pose, as an edge from the newest keyframe (the odometry
        since it); once per pair, again from a scan much nearer (loop_graph)."""
        p = self.particles
        source = len(self.keyframes) - 1
        source_scan = self.keyframe_frames[source]
        T_source_scan = np.eye(4) if source_scan == len(self.frames) else \
            se3_inverse(self.frames.pose("T_motion_lidar", source_scan)) @ T_odom
        for slot, T_target in zip(loop_slots, T_loop_keyframes, strict=True):
            self.loop_edges.take(source, int(p.seq[slot]), down, self.keyframes.clouds[slot],
                                 se3_inverse(T_target) @ T_rep, T_source_scan)

    def _prune(self, step: int, scored: bool) -> tuple[int, np.ndarray, np.ndarray]:
        """Prune; particles without a neighbour keyframe (unmapped space, another floor) get
        the median likelihood of the scored ones: no evidence for or against them. Returns
        (particles pruned, posteriors, the particle each one was before pruning)."""
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
        if scored and self.floor_guard.active:  # after a ride: every floor kept
            dead, sources, lw = self.floor_guard.prune_plan(log_w, frame_ll, ~unscored,
                                                            p.positions() @ self._up(), rng)
        else:
            dead, sources, lw = prune_plan(log_w, frame_ll, self.cfg.pruning, rng)
        p.respawn(dead, sources, lw)
        post = np.exp(lw - lw.max())
        origin = np.arange(len(lw))
        origin[dead] = sources
        return len(dead), post / post.sum(), origin

    # ---- results of the representative particle ----

    def representative_keyframes(self) -> np.ndarray:
        """The representative's poses of the keyframes kept, oldest first, as the filter holds
        them (the written trajectory and map bridge them between loops)."""
        return self.particles.keyframe_poses(self._rep)[self.particles.slots_in_order()]

    def _keyframe_poses_by_number(self) -> np.ndarray:
        """(keyframes made, 4, 4): the representative's pose of every keyframe, solved as the
        loop graph or bridged between the keyframes where it took a loop correction when so
        configured (kept until the next scan: the trajectory and the map both ask at the end
        of a run)."""
        written = self.cfg.trajectory
        key = (len(self.frames), written.bridge_between_loops, written.loop_graph,
               written.structure_up)
        if self._written_keyframes is not None and self._written_keyframes[0] == key:
            return self._written_keyframes[1]
        p = self.particles
        T = self.keyframes.poses_by_number(p.keyframe_poses(self._rep), p.seq)
        kf_frames = np.asarray(self.keyframe_frames, dtype=np.int64)
        motion = self.frames.poses("T_motion_lidar")[kf_frames]
        drift = np.asarray(self.keyframes.drift_variance)
        if written.loop_graph and len(T):
            ups = self.keyframe_ups.by_number if written.structure_up else None
            imu_up = None if self.odometry.g_world is None else self._up()
            T = solve_pose_graph(T, motion, step_covariances(motion, drift, self._up()),
                                 self.map_loop_edges(), ups, self.keyframe_ups.up_world(T, imu_up))
        elif written.bridge_between_loops and len(T):
            loop_scans = np.flatnonzero((self.frames.loop_keyframes >= 0).any(axis=1))
            T = bridge_between_anchors(T, motion, drift,
                                       anchored_keyframes(loop_scans, kf_frames), self._up())
        self._written_keyframes = (key, T)
        return T

    def map_loop_edges(self) -> list[LoopEdge]:
        """The registered loop edges the representative's own keyframes agree with (the loop
        graph's; the others were taken by hypotheses that died)."""
        p = self.particles
        return agreeing_edges(self.keyframes.poses_by_number(p.keyframe_poses(self._rep), p.seq),
                              self.loop_edges.registered())

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, poses) of every scan as the representative particle's map places it:
        each scan hangs off the keyframe before it by the odometry motion since then, so
        the trajectory follows the loop corrections of its keyframes (a keyframe dropped
        from a full store keeps the pose it had then)."""
        poses = self.frames.hung_off(self._keyframe_poses_by_number(), self.keyframe_frames)
        return self.frames.stamp_ns.copy(), poses

    def map_points(self) -> np.ndarray:
        """The union of the kept keyframes' clouds under the representative's poses."""
        p = self.particles
        kf_poses = self._keyframe_poses_by_number()[p.seq[:p.num_keyframes]]  # by slot
        clouds = [transform_points(T, c.astype(np.float64))
                  for T, c in zip(kf_poses, self.keyframes.clouds, strict=True)]
        return np.concatenate(clouds) if clouds else np.zeros((0, 3))
