"""Simulated IMU: specific force and angular rate of the `imu` frame plus MEMS noise.

The noise model is the continuous-time one of Kalibr / Allan-variance datasheets: white noise
with density sigma (per sqrt(Hz)), discretized as sigma / sqrt(dt), and a bias random walk
with density sigma_b, discretized as sigma_b * sqrt(dt). Defaults are a consumer MEMS part
(BMI088 / ICM-42688 class, as in the Livox MID-360).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.sim.trajectories import GRAVITY_MPS2, SimTrajectory


class ImuConfig(Section):
    rate_hz: float = Field(200.0, gt=0, le=2000, description="sample rate (Hz)")
    gyro_noise_density: float = Field(2.4e-4, ge=0, description="gyro white noise (rad/s/sqrt(Hz))")
    accel_noise_density: float = Field(1.9e-3, ge=0,
                                       description="accelerometer white noise (m/s^2/sqrt(Hz))")
    gyro_bias_random_walk: float = Field(2.0e-5, ge=0,
                                         description="gyro bias random walk (rad/s^2/sqrt(Hz))")
    accel_bias_random_walk: float = Field(3.0e-4, ge=0,
                                          description="accel bias random walk (m/s^3/sqrt(Hz))")
    gyro_bias_initial: float = Field(1.7e-3, ge=0, description="sigma of the turn-on gyro bias "
                                     "(rad/s)")
    accel_bias_initial: float = Field(0.02, ge=0, description="sigma of the turn-on accel bias "
                                      "(m/s^2)")


def true_imu(traj: SimTrajectory, T_base_imu: np.ndarray, t_s: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free angular velocity (rad/s) and specific force (m/s^2) in the imu frame."""
    k = traj.kinematics(t_s)
    R_bi, r_b = T_base_imu[:3, :3], T_base_imu[:3, 3]
    w, dw = k.w_base, k.dw_base
    lever = np.cross(dw, r_b) + np.cross(w, np.cross(w, r_b))
    a_map = k.a_map + np.einsum("nij,nj->ni", k.R_map_base, lever)
    a_map[:, 2] += GRAVITY_MPS2
    f_base = np.einsum("nji,nj->ni", k.R_map_base, a_map)
    return w @ R_bi, f_base @ R_bi


class ImuSimulator:
    """Stateful (bias) IMU; call `measure` on consecutive, increasing time chunks."""

    def __init__(self, traj: SimTrajectory, T_base_imu: np.ndarray, cfg: ImuConfig,
                 rng: np.random.Generator) -> None:
        self.traj, self.T_base_imu, self.cfg, self.rng = traj, T_base_imu, cfg, rng
        self.gyro_bias = cfg.gyro_bias_initial * rng.standard_normal(3)
        self.accel_bias = cfg.accel_bias_initial * rng.standard_normal(3)

    def measure(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured angular velocity and specific force (N, 3) at times t_s."""
        cfg, n = self.cfg, len(t_s)
        dt = 1.0 / cfg.rate_hz
        w, f = true_imu(self.traj, self.T_base_imu, t_s)
        steps = self.rng.standard_normal((2, n, 3)) * np.sqrt(dt)
        gyro_bias = self.gyro_bias + cfg.gyro_bias_random_walk * np.cumsum(steps[0], axis=0)
        accel_bias = self.accel_bias + cfg.accel_bias_random_walk * np.cumsum(steps[1], axis=0)
        if n:
            self.gyro_bias, self.accel_bias = gyro_bias[-1], accel_bias[-1]
        white = self.rng.standard_normal((2, n, 3)) / np.sqrt(dt)
        return (w + gyro_bias + cfg.gyro_noise_density * white[0],
                f + accel_bias + cfg.accel_noise_density * white[1])
