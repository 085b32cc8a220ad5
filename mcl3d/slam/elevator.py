"""The elevator: detecting that the scan sees only a closed cab, and the vertical motion
the particles take while it does (the IMU's, or a vertical random walk without IMU).

The paper detects the cab by the median range of the scan. A median says how close the
nearest surfaces are, not whether the sensor is shut in: it is as short in a 2 m aisle, or
for a handheld sensor beside a wall, as in a cab. A closed cab is the one place where every
direction ends on a nearby surface, so the default detector (`enclosure`) asks exactly that:
the scan is split into equal azimuth sectors across the field of view, and it is enclosed
when in every sector the `percentile` of the ranges is under `enclosure_range_m`. One open
direction (an aisle's far end, a door, a window onto the corridor, an empty sector where
nothing came back) is enough to say "not in a cab"."""

from __future__ import annotations

import numpy as np

from mcl3d.slam.slam_config import ElevatorConfig


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


def sector_ranges(points: np.ndarray, sectors: int, percentile: float, fov_deg: float = 360.0,
                  min_points: int = 1) -> np.ndarray:
    """The `percentile` of the range in each of `sectors` equal azimuth sectors spanning
    ±fov/2 around the lidar's +x axis (linear interpolation, as np.percentile); inf where a
    sector holds fewer than `min_points` returns (nothing within the sensor's reach: open)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ranges = np.sqrt(np.einsum("ij,ij->i", points, points))
    half = np.deg2rad(fov_deg) / 2
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    keep = (ranges > 0) & (np.abs(azimuth) <= half)  # a zero point is "no return"
    index = np.minimum(((azimuth[keep] + half) / (2 * half) * sectors).astype(np.int64),
                       sectors - 1)
    ranges = ranges[keep]
    span = float(ranges.max()) + 1.0 if len(ranges) else 1.0
    ordered = np.sort(index * span + ranges)  # by sector, then by range
    count = np.bincount(index, minlength=sectors)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    pos = np.maximum(count - 1, 0) * (percentile / 100.0)
    lo, hi = np.floor(pos).astype(np.int64), np.ceil(pos).astype(np.int64)
    out = np.full(sectors, np.inf)
    ok = count >= max(min_points, 1)
    base = np.arange(sectors) * span
    r_lo = ordered[start[ok] + lo[ok]] - base[ok]
    r_hi = ordered[start[ok] + hi[ok]] - base[ok]
    out[ok] = r_lo + (r_hi - r_lo) * (pos[ok] - lo[ok])
    return out


def in_elevator(points: np.ndarray, cfg: ElevatorConfig, fov_deg: float = 360.0) -> bool:
    """Whether the scan (lidar frame, cropped to `fov_deg`) is taken inside a closed cab,
    by `cfg.detector`: `enclosure` (every azimuth sector closed, module docstring), `median`
    (the paper's: the median range under `cfg.median_range_m`) or `off`."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if cfg.detector == "off" or len(points) == 0:
        return False
    if cfg.detector == "median":
        ranges = np.linalg.norm(points, axis=1)
        ranges = ranges[ranges > 0]
        return bool(len(ranges) and np.median(ranges) < cfg.median_range_m)
    per_sector = sector_ranges(points, cfg.sectors, cfg.percentile, fov_deg,
                               cfg.min_sector_points)
    return bool(np.all(per_sector < cfg.enclosure_range_m))


def open_sectors(points: np.ndarray, cfg: ElevatorConfig, fov_deg: float = 360.0) -> int:
    """How many of the scan's `cfg.sectors` azimuth sectors are open (their percentile range
    at or beyond `cfg.enclosure_range_m`, or too few returns): a cab with its doors open
    leaves one or two, a corridor or a room more."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    per_sector = sector_ranges(points, cfg.sectors, cfg.percentile, fov_deg,
                               cfg.min_sector_points)
    return int(np.sum(per_sector >= cfg.enclosure_range_m))
