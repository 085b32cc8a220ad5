"""Simulated wheel/visual odometry: integrated noisy increments, so it drifts like the real thing.

Each increment between two samples is corrupted by a per-run scale error and turn bias
(systematic: wheel radius, track width) and by white noise whose variance grows with the
distance and angle travelled (so the drift is independent of the rate), optionally plus
white noise on the velocities themselves (the MCL paper's sweep: its odometry is ground
truth with noise of sigma on the velocity and angular velocity). The reported pose
covariance is propagated through the same increments. Odometry sees neither a kidnap nor
the elevator cab's motion (it measures motion relative to the floor it stands on).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.geometry import se3_adjoint, se3_exp, se3_inverse, se3_log
from mcl3d.sim.trajectories import SimTrajectory


class WheelOdometryConfig(Section):
    rate_hz: float = Field(50.0, gt=0, le=1000, description="sample rate (Hz)")
    trans_noise: float = Field(0.01, ge=0, description="translation random walk (m/sqrt(m))")
    rot_noise_per_m: float = Field(0.002, ge=0,
                                   description="rotation random walk per distance (rad/sqrt(m))")
    rot_noise_per_rad: float = Field(0.01, ge=0,
                                     description="rotation random walk per turn (rad/sqrt(rad))")
    scale_error_sigma: float = Field(0.01, ge=0,
                                     description="sigma of the per-run distance scale error (-)")
    turn_bias_sigma: float = Field(0.002, ge=0,
                                   description="sigma of the per-run yaw bias per metre (rad/m)")
    twist_noise: tuple[float, float] = Field((0.02, 0.01),
                                             description="reported twist noise sigma (m/s, rad/s)")
    velocity_noise: tuple[float, float] = Field(
        (0.0, 0.0), description="white noise sigma on the integrated velocity and angular "
        "velocity (m/s, rad/s): the MCL paper's odometry, ground truth plus noise of sigma")


class WheelOdometrySimulator:
    """Stateful odometry; call `measure` on consecutive, increasing time chunks."""

    def __init__(self, traj: SimTrajectory, cfg: WheelOdometryConfig,
                 rng: np.random.Generator) -> None:
        self.traj, self.cfg, self.rng = traj, cfg, rng
        self.scale = 1.0 + cfg.scale_error_sigma * rng.standard_normal()
        self.turn_bias = cfg.turn_bias_sigma * rng.standard_normal()
        self._T_true, self._t_prev = None, 0.0
        self._T_est = np.eye(4)
        self._cov = np.zeros((6, 6))  # rotation-first, right-perturbation (body frame)

    def measure(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses T_odom_base (N, 4, 4), twists (N, 6) [v; w] in base_link and ROS-ordered
        pose covariances (N, 6, 6) in the odom frame at times t_s."""
        cfg = self.cfg
        truth = self.traj.T_odom_base(t_s)
        kin = self.traj.kinematics(t_s)
        v_map = kin.v_map.copy()
        if self.traj.carrier is not None:
            v_map[:, 2] -= self.traj.carrier(t_s, 1)[:, 0]
        v_body = np.einsum("nji,nj->ni", kin.R_map_base, v_map)
        poses, covs = np.empty((len(t_s), 4, 4)), np.empty((len(t_s), 6, 6))
        for i, T_true in enumerate(truth):
            if self._T_true is not None:
                self._step(se3_inverse(self._T_true) @ T_true, float(t_s[i]) - self._t_prev)
            self._T_true, self._t_prev = T_true, float(t_s[i])
            poses[i] = self._T_est
            R = self._T_est[:3, :3]
            J = np.zeros((6, 6))  # body rot-first -> ROS odom-frame (x y z rx ry rz)
            J[:3, 3:], J[3:, :3] = R, R
            covs[i] = J @ self._cov @ J.T
        twist = np.hstack([self.scale * v_body, kin.w_base])
        twist[:, :3] += cfg.twist_noise[0] * self.rng.standard_normal((len(t_s), 3))
        twist[:, 3:] += cfg.twist_noise[1] * self.rng.standard_normal((len(t_s), 3))
        return poses, twist, covs

    def _step(self, delta: np.ndarray, dt_s: float) -> None:
        cfg = self.cfg
        xi = se3_log(delta)
        dist, angle = float(np.linalg.norm(xi[3:])), float(np.linalg.norm(xi[:3]))
        xi_meas = xi.copy()
        xi_meas[3:] *= self.scale
        xi_meas[2] += self.turn_bias * dist
        var_rot = cfg.rot_noise_per_m ** 2 * dist + cfg.rot_noise_per_rad ** 2 * angle
        var_trans = cfg.trans_noise ** 2 * dist
        var_rot += (cfg.velocity_noise[1] * dt_s) ** 2
        var_trans += (cfg.velocity_noise[0] * dt_s) ** 2
        Q = np.diag([var_rot] * 3 + [var_trans] * 3)
        noise = np.sqrt(np.diag(Q)) * self.rng.standard_normal(6)
        step = se3_exp(xi_meas) @ se3_exp(noise)
        Ad = se3_adjoint(se3_inverse(step))
        self._cov = Ad @ self._cov @ Ad.T + Q
        self._T_est = self._T_est @ step
