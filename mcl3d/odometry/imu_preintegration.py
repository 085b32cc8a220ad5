"""IMU preintegration (Forster et al.): relative rotation, velocity and position between two
times from gyro and accelerometer samples, for the odometry's motion prediction.

Between t_i and t_j, with biases removed and samples held constant until the next one (the
last partial interval uses the last sample before t_j, as GLIM integrates it):
  ΔR ← ΔR Exp((ω − b_g) dt),  Δp ← Δp + Δv dt + ½ ΔR (a − b_a) dt²,  Δv ← Δv + ΔR (a − b_a) dt
and the state of the IMU in the world frame moves as
  R_j = R_i ΔR,  v_j = v_i + g Δt + R_i Δv,  p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core.errors import InputError
from mcl3d.core.geometry import se3, so3_exp

GRAVITY_MPS2 = 9.80665


@dataclass
class Preintegrated:
    """Relative motion of the IMU frame over `dt_s`, in the frame at the start."""

    dt_s: float
    delta_rot: np.ndarray  # (3, 3)
    delta_v: np.ndarray  # (3,) m/s
    delta_p: np.ndarray  # (3,) m

    def predict(self, T_world_imu: np.ndarray, v_world: np.ndarray, g_world: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """(T_world_imu, v_world) at the end of the interval from the state at its start."""
        R, p = T_world_imu[:3, :3], T_world_imu[:3, 3]
        dt = self.dt_s
        p_new = p + v_world * dt + 0.5 * g_world * dt * dt + R @ self.delta_p
        v_new = v_world + g_world * dt + R @ self.delta_v
        return se3(R @ self.delta_rot, p_new), v_new

    def velocity_at_start(self, T_world_imu_i: np.ndarray, T_world_imu_j: np.ndarray,
                          g_world: np.ndarray) -> np.ndarray:
        """The start velocity that makes the interval end at the registered position p_j
        (inverts the position equation): how LiDAR poses give the IMU its velocity."""
        R, p_i, p_j = T_world_imu_i[:3, :3], T_world_imu_i[:3, 3], T_world_imu_j[:3, 3]
        dt = max(self.dt_s, 1e-6)
        return (p_j - p_i - 0.5 * g_world * dt * dt - R @ self.delta_p) / dt


def preintegrate(stamps_s: np.ndarray, gyro: np.ndarray, accel: np.ndarray, t0_s: float,
                 t1_s: float, gyro_bias: np.ndarray | None = None,
                 accel_bias: np.ndarray | None = None) -> Preintegrated:
    """Integrate samples (stamps (N,), gyro (N, 3) rad/s, accel (N, 3) m/s² specific force)
    over [t0_s, t1_s]; sample k holds from its stamp to the next (the first also before)."""
    stamps = np.asarray(stamps_s, dtype=np.float64).ravel()
    gyro = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
    accel = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
    if len(stamps) == 0 or gyro.shape != (len(stamps), 3) or accel.shape != gyro.shape:
        raise InputError("preintegration needs N stamps and N gyro and accelerometer samples")
    if t1_s < t0_s or not (np.isfinite(gyro).all() and np.isfinite(accel).all()):
        raise InputError("IMU samples must be finite and the interval must not run backwards")
    bg = np.zeros(3) if gyro_bias is None else np.asarray(gyro_bias, dtype=np.float64)
    ba = np.zeros(3) if accel_bias is None else np.asarray(accel_bias, dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    stamps, gyro, accel = stamps[order], gyro[order], accel[order]
    # interval boundaries: t0, every sample stamp inside (t0, t1), t1
    inside = (stamps > t0_s) & (stamps < t1_s)
    bounds = np.concatenate([[t0_s], stamps[inside], [t1_s]])
    held = np.clip(np.searchsorted(stamps, bounds[:-1], side="right") - 1, 0, len(stamps) - 1)
    dt = np.diff(bounds)[:, None]
    steps = so3_exp((gyro[held] - bg) * dt)  # every interval's rotation at once
    rots = np.empty((len(dt), 3, 3))  # ΔR at the start of each interval
    rot = np.eye(3)
    for k, step in enumerate(steps):
        rots[k] = rot
        rot = rot @ step
    a = np.einsum("kij,kj->ki", rots, accel[held] - ba)  # ΔR (a - b_a), frame at t0
    dv = a * dt
    v_before = np.zeros_like(dv)  # Δv at the start of each interval
    np.cumsum(dv[:-1], axis=0, out=v_before[1:])
    delta_p = (v_before * dt + 0.5 * a * dt * dt).sum(axis=0)
    return Preintegrated(float(t1_s - t0_s), rot, dv.sum(axis=0), delta_p)


def gravity_from_static(accel: np.ndarray, R_world_imu: np.ndarray) -> np.ndarray:
    """Gravity in the world frame from accelerometer samples taken at rest (the specific force
    at rest is -g), scaled to 9.80665 m/s²."""
    f = np.asarray(accel, dtype=np.float64).reshape(-1, 3).mean(axis=0)
    norm = np.linalg.norm(f)
    if not np.isfinite(norm) or norm < 1.0:
        raise InputError("cannot find gravity: the accelerometer mean is not ~9.8 m/s² "
                         f"(got {norm:.2f}); is linear_acceleration in m/s²?")
    return -R_world_imu @ (f / norm) * GRAVITY_MPS2
