"""The Monte Carlo SLAM particle set on the device: current poses, per-particle keyframe
poses, cumulative log weights, and the batched GICP that scores them against the shared
keyframe voxel maps (kernels/slam.py does the arithmetic).

Keyframes live in `max_keyframes` slots. A keyframe is known by its number (the order
keyframes were made in, `seq`); until the slots are full number and slot agree, after that a
new keyframe takes the slot its caller frees (`add_keyframe(..., slot=)`), so a slot's age is
`seq[slot]`, and every per-slot value (poses of every particle, travel, drift sums, number)
is rewritten together.

Host side stays O(N) and small: log weights come back once per frame for pruning and the
representative particle; keyframe poses only come back for one particle at a time.
"""

from __future__ import annotations

import math

import numpy as np
import taichi as ti

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import quat_to_rot, rot_to_quat, se3
from mcl3d.kernels import slam as slam_kernels
from mcl3d.kernels import slam_posterior
from mcl3d.kernels.slam import NEIGHBOURS
from mcl3d.slam.free_space import FreeSpace
from mcl3d.slam.slam_config import CorrectionConfig, LikelihoodConfig

DRIFT_SUMS = 5  # W, Σ w p (3), V: see SlamParticles.correct
BYTES_PER_KEYFRAME_POSE = 24  # translation + quaternion vector part, f32
COVARIANCE_JITTER = 1e-12  # added to a covariance's diagonal before factorizing it
F32_MAX = 3e38  # "no limit" for a float32 kernel argument


def unpack_poses(rows: np.ndarray) -> np.ndarray:
    """(K, 6) device rows (t, quaternion vector part) -> (K, 4, 4)."""
    v = rows[:, 3:6].astype(np.float64)
    w = np.sqrt(np.clip(1.0 - np.sum(v * v, axis=1), 0.0, None))
    q = np.concatenate([v, w[:, None]], axis=1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return se3(quat_to_rot(q), rows[:, :3].astype(np.float64))


def prior_information(covariance: np.ndarray) -> np.ndarray:
    """The prediction's covariance as the Gauss-Newton steps' prior: its inverse, f32."""
    return np.linalg.inv(covariance + COVARIANCE_JITTER * np.eye(6)).astype(np.float32)


class SlamParticles:
    """N particles x up to `max_keyframes` keyframes, scored by `gicp` (a BatchGicp over the
    keyframe voxel maps, sized for 3 N groups)."""

    def __init__(self, n: int, max_keyframes: int, gicp, seed: int):
        if n < 1:
            raise ConfigError(f"particles must be >= 1, got {n}", setting="particles")
        self.n, self.max_keyframes, self.gicp, self.seed = n, max_keyframes, gicp, seed
        self.q_cur = ti.Vector.field(4, ti.f32, n)
        self.t_cur = ti.Vector.field(3, ti.f32, n)
        self.log_w = ti.field(ti.f32, n)
        self.frame_ll = ti.field(ti.f32, n)
        self.nb = ti.field(ti.i32, (n, NEIGHBOURS))
        self.nb_loop = ti.field(ti.i32, (n, NEIGHBOURS))
        self.shift = ti.Vector.field(6, ti.f32, n)
        self.seen = ti.field(ti.i32, n * NEIGHBOURS)  # points in seen-through space, per row
        self.corrected = ti.field(ti.i32, n)
        self.fixed_travel = ti.field(ti.f32, n)  # travel (m) at the particle's last correction
        self.fixed_drift = ti.Vector.field(DRIFT_SUMS, ti.f32, n)  # drift sums there
        # every particle's pose of every keyframe, allocated (and touched) for the whole
        # capacity now, so a run's memory does not grow as keyframes come
        self.kf = ti.ndarray(ti.f32, (n, max_keyframes, 6))
        self.kf.fill(0.0)
        self.kf_travel = ti.ndarray(ti.f32, max_keyframes)
        self.kf_drift = ti.ndarray(ti.f32, (max_keyframes, DRIFT_SUMS + 3))
        self.kf_seq = ti.ndarray(ti.i32, max_keyframes)
        self.kf_seq.fill(-1)
        self.seq = np.full(max_keyframes, -1, np.int64)  # host copy of kf_seq
        self.next_seq = 0  # the number the next keyframe gets
        self.num_keyframes = 0  # slots in use
        self.q_cur.from_numpy(np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (n, 1)))

    # ---- memory ----

    def state_bytes(self) -> int:
        """Bytes of particle state: keyframe poses (allocated for the whole capacity),
        current poses, weights."""
        per_particle = 28 + 8 + 2 * 4 * 3 + 24 + 8 + 4 * DRIFT_SUMS  # pose, weights,
        # neighbours, shift, flags, drift sums at the last settled correction
        return self.n * (self.max_keyframes * BYTES_PER_KEYFRAME_POSE + per_particle)

    # ---- filter steps ----

    def predict(self, T_prev_curr: np.ndarray, covariance: np.ndarray, step: int) -> None:
        chol = np.linalg.cholesky(covariance + COVARIANCE_JITTER * np.eye(6)).astype(np.float32)
        slam_kernels.predict(self.n, rot_to_quat(T_prev_curr[:3, :3]).astype(np.float32),
                             T_prev_curr[:3, 3].astype(np.float32), chol, self.seed, step,
                             self.q_cur, self.t_cur)

    def shift_vertical(self, shift: np.ndarray, up: np.ndarray, sigma_m: float,
                       step: int) -> None:
        slam_kernels.shift_vertical(self.n, np.asarray(shift, np.float32),
                                    np.asarray(up, np.float32), sigma_m, self.seed, step,
                                    self.t_cur)

    @property
    def full(self) -> bool:
        return self.num_keyframes >= self.max_keyframes

    def add_keyframe(self, travel_m: float, drift: np.ndarray, odom_position: np.ndarray,
                     slot: int | None = None) -> int:
        """Every particle's current pose becomes the pose of a new keyframe, in the next
        free slot or, once all are used, in `slot` (the keyframe there is dropped); returns
        the slot. `drift` are the odometry's drift sums at this scan (see `correct`),
        `odom_position` its position."""
        k = self.num_keyframes if slot is None else int(slot)
        if not 0 <= k < self.max_keyframes or (slot is not None and not self.full):
            raise ConfigError(f"keyframe slot {k} is not free (keyframes: "
                              f"{self.num_keyframes} of {self.max_keyframes}); a slot is "
                              "reused only once all are used")
        slam_kernels.insert_keyframe(self.n, k, self.q_cur, self.t_cur, self.kf)
        self.kf_travel[k] = travel_m
        for a, v in enumerate(np.r_[drift, odom_position]):
            self.kf_drift[k, a] = float(v)
        self.kf_seq[k] = self.next_seq
        self.seq[k] = self.next_seq
        self.next_seq += 1
        self.num_keyframes = max(self.num_keyframes, k + 1)
        return k

    def slots_in_order(self) -> np.ndarray:
        """The used slots, oldest keyframe first."""
        return np.argsort(self.seq[:self.num_keyframes], kind="stable")

    def select_neighbours(self, travel_m: float, loop_min_travel_m: float,
                          up: np.ndarray | None = None, max_dz_m: float = np.inf,
                          max_facing_rad: float = np.pi, facing_neighbours: bool = False
                          ) -> int:
        """Neighbour keyframes of every particle (none more than `max_dz_m` along `up`);
        returns how many particles see a loop (a keyframe facing more than `max_facing_rad`
        away is not a loop; with `facing_neighbours` it is not a neighbour either unless it
        is one of the newest)."""
        up = np.array([0.0, 0.0, 1.0]) if up is None else up
        return int(slam_kernels.select_neighbours(
            self.n, self.num_keyframes, self.kf, self.q_cur, self.t_cur, self.kf_travel,
            self.kf_seq, self.next_seq - NEIGHBOURS, travel_m, loop_min_travel_m,
            float(np.cos(max_facing_rad)),
            np.asarray(up, np.float32), min(max_dz_m, F32_MAX), int(facing_neighbours),
            self.nb, self.nb_loop))

    def _linearize(self, num_src: int, loop_only: bool, cost_cap: float = math.inf) -> None:
        """One GICP linearization of every (particle, neighbour) row at the current poses (no
        point adds more than `cost_cap` to a row's ½ Σ eᵀΩe)."""
        g = self.gicp
        slam_kernels.build_rows(self.n, self.kf, self.q_cur, self.t_cur, self.nb, self.nb_loop,
                                int(loop_only), num_src, g.rows.group, g.rows.map, g.rows.q,
                                g.rows.t, g.rows.start, g.rows.count, g.poses.q_cand,
                                g.poses.t_cand)
        groups = self.n * NEIGHBOURS
        g.start(groups, groups, num_src, one_row_per_group=True)
        g.iterate(use_lm=False, chunk=num_src, cost_cap=cost_cap)  # whole rows: reproducible

    def correct(self, travel_m: float, drift: np.ndarray, odom_position: np.ndarray,
                num_src: int, cfg: CorrectionConfig) -> int:
        """One gradient-guided update of the looping particles and their keyframes (eq. 5-10);
        returns how many particles moved. `drift` are the odometry's drift sums now (W: the
        prediction's cumulative rotational variance, Σ w_j p_j, V: the translational one),
        by which the correction is spread over the keyframes."""
        self._linearize(num_src, loop_only=True)
        best = self.gicp.poses.best
        slam_kernels.correct(self.n, self.nb_loop, best.H, best.b, best.n,
                             cfg.min_inliers, np.deg2rad(cfg.max_step_deg), cfg.max_step_m,
                             self.q_cur, self.t_cur, self.shift, self.corrected)
        d = ti.types.vector(DRIFT_SUMS, ti.f32)(*np.asarray(drift, np.float32))
        slam_kernels.propagate(self.n, self.num_keyframes, self.kf, self.nb, self.kf_travel,
                               self.kf_drift, d,
                               ti.math.vec3(*np.asarray(odom_position, np.float32)),
                               self.shift, self.corrected, self.fixed_travel, self.fixed_drift)
        slam_kernels.mark_fixed(self.n, travel_m, d, self.corrected, self.shift,
                                np.deg2rad(cfg.settled_step_deg), cfg.settled_step_m,
                                self.fixed_travel, self.fixed_drift)
        return int(self.corrected.to_numpy().sum())

    def loop_keyframes(self) -> dict[int, tuple[int, ...]]:
        """The loop keyframes each particle that `correct` just moved was corrected toward
        (read before the neighbours are selected again)."""
        moved = np.flatnonzero(self.corrected.to_numpy())
        if len(moved) == 0:
            return {}
        nb = self.nb.to_numpy()[moved]
        loop = self.nb_loop.to_numpy()[moved] == 1
        return {int(i): tuple(int(k) for k in row[m]) for i, row, m in zip(moved, nb, loop,
                                                                           strict=True)}

    def weigh(self, num_src: int, cfg: LikelihoodConfig,
              free_space: FreeSpace | None = None, free_space_cost: float = 0.0,
              local_weight: float | None = None) -> None:
        """Frame log-likelihood of every particle, added to its cumulative log weight;
        with `free_space`, scan points in a neighbour's seen-through space and the
        neighbour's points in the scan's (FreeSpace.count) cost `free_space_cost` each;
        a neighbour that is not a loop costs as `local_weight` says (default
        `cfg.local_weight`)."""
        self._linearize(num_src, loop_only=False,
                        cost_cap=0.5 * cfg.outlier_cost if cfg.truncated else math.inf)
        best = self.gicp.poses.best
        seen_cost = 0.0
        if free_space is not None and free_space_cost > 0:
            stride = max(1, num_src // cfg.free_space_points)
            judged = (num_src + stride - 1) // stride
            free_space.count(self, self.gicp.pool.points, num_src, stride,
                             cfg.free_space_margin_m, cfg.free_space_margin_frac, self.seen)
            seen_cost = free_space_cost * num_src / judged
        local_weight = cfg.local_weight if local_weight is None else local_weight
        unmatched_cost = cfg.outlier_cost + (self._typical_point_cost()
                                             if cfg.unmatched_as_typical else 0.0)
        reference = 0.0 if local_weight >= 1.0 else self._local_reference(
            num_src, unmatched_cost, seen_cost)
        slam_kernels.likelihood(self.n, num_src, self.nb, self.nb_loop, best.e, best.n,
                                unmatched_cost, self.seen, seen_cost, cfg.points_weight,
                                local_weight, reference, self.frame_ll, self.log_w)

    def _typical_point_cost(self) -> float:
        """The median over the particles' non-loop rows of a matched point's mean cost: what
        a scan point costs against the map the odometry just matched it to (0 without)."""
        best = self.gicp.poses.best
        costs = np.empty(self.n * NEIGHBOURS, np.float32)
        slam_kernels.local_point_costs(self.n, self.nb, self.nb_loop, best.e, best.n, costs)
        return _median_of_filled(costs)

    def _local_reference(self, num_src: int, unmatched_cost: float, seen_cost: float) -> float:
        """The median cost of the particles' neighbour rows that are not loops: what a scan
        costs against the map the odometry just matched it to (0 without such rows)."""
        best = self.gicp.poses.best
        costs = np.empty(self.n * NEIGHBOURS, np.float32)
        slam_kernels.local_row_costs(self.n, num_src, self.nb, self.nb_loop, best.e, best.n,
                                     unmatched_cost, self.seen, seen_cost, costs)
        return _median_of_filled(costs)

    def refine(self, covariance: np.ndarray, cfg: CorrectionConfig) -> int:
        """One Gauss-Newton step of every particle without a loop toward its own neighbour
        keyframes, from the terms `weigh` linearized, with the prediction's `covariance` as
        the prior; returns how many moved."""
        best = self.gicp.poses.best
        return int(slam_kernels.refine(self.n, self.nb, self.nb_loop, best.H, best.b,
                                       best.n, cfg.min_inliers, prior_information(covariance),
                                       np.deg2rad(cfg.max_step_deg), cfg.max_step_m,
                                       self.q_cur, self.t_cur))

    def spread(self, covariance: np.ndarray, num_src: int, points_weight: float,
               min_inliers: int, refined: bool, corrected: bool, step: int) -> int:
        """Give the particles a Gauss-Newton step moved (loop correction or refinement) back
        the spread the step took: each draws δ ~ N(0, P) with P = (Σ⁻¹ + k H)⁻¹ the
        Gaussian posterior of its step, Σ the prediction's `covariance` as prior and k H the
        curvature of the tempered likelihood (k = points_weight / (rows · num_src), H the
        GICP Hessian `weigh` just linearized against its neighbours), and moves by exp(δ)
        (kernels/slam_posterior.py, random numbers from the run's seed and `step`).
        A step lands every particle on the likelihood's mode; without this the cloud
        collapses there and stops covering the truth. `refined` / `corrected`: whether
        `refine` / `correct` ran on this scan. Returns how many particles drew."""
        best = self.gicp.poses.best
        return int(slam_posterior.draw_posterior(
            self.n, self.nb, self.nb_loop, best.H, best.n, self.corrected,
            prior_information(covariance),
            points_weight / num_src, min_inliers, int(refined), int(corrected), self.seed,
            step, self.q_cur, self.t_cur))

    def respawn(self, dead: np.ndarray, source: np.ndarray, log_w: np.ndarray) -> None:
        """Replace particles `dead` by copies of `source` and upload the new log weights."""
        if len(dead):
            slam_kernels.respawn(len(dead), np.ascontiguousarray(dead, np.int32),
                                 np.ascontiguousarray(source, np.int32), self.num_keyframes,
                                 self.q_cur, self.t_cur, self.fixed_travel, self.fixed_drift,
                                 self.kf)
        self.log_w.from_numpy(np.ascontiguousarray(log_w, np.float32))

    # ---- read back ----

    def current_poses(self) -> np.ndarray:
        q = self.q_cur.to_numpy().astype(np.float64)
        return se3(quat_to_rot(q / np.linalg.norm(q, axis=1, keepdims=True)),
                   self.t_cur.to_numpy().astype(np.float64))

    def quaternion(self, i: int) -> np.ndarray:
        q = np.array([self.q_cur[i][a] for a in range(4)], np.float64)
        return q / np.linalg.norm(q)

    def positions(self) -> np.ndarray:
        return self.t_cur.to_numpy().astype(np.float64)

    def keyframe_poses(self, i: int) -> np.ndarray:
        """(K, 4, 4) keyframe poses of particle i, by slot."""
        K = self.num_keyframes
        out = np.zeros((max(K, 1), 6), np.float32)
        if K:
            slam_kernels.gather_keyframes(i, K, self.kf, out)
        return unpack_poses(out[:K])


def _median_of_filled(rows: np.ndarray) -> float:
    """The median of the rows a kernel filled (it leaves -1 in the others); 0 without any."""
    filled = rows[rows >= 0]
    return float(np.median(filled)) if len(filled) else 0.0
