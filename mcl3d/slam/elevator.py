"""The elevator: while the scan sees only the cab, the particles move by the IMU's vertical
motion (or a vertical random walk without IMU); this module integrates that motion."""

from __future__ import annotations

import numpy as np


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


def in_elevator(ranges_m: np.ndarray, median_range_m: float) -> bool:
    """The detector: the scan's median range is under `median_range_m` (0: off)."""
    return bool(len(ranges_m) and median_range_m > 0 and np.median(ranges_m) < median_range_m)
