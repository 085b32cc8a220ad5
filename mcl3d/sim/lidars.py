"""LiDAR models: beam tables and firing times of real sensors, cast against a world.

Every return is cast from the sensor pose at its own firing time, so scans carry the motion
distortion real drivers deliver (nothing is deskewed). Points are expressed in the `lidar`
frame at their firing time, with range noise, dropouts, range limits that shrink on dark or
grazing surfaces, an intensity from reflectivity and incidence angle, `ring` and time.

- VLP-16: 16 beams -15..+15 deg, 1800 firings per turn at 10 Hz, lasers fired 2.304 us apart;
- OS1-64: 64 beams over 45 deg, 1024 x 10 Hz, all beams of a column at once, organized cloud
  with zeros for "no return" as the Ouster driver publishes it;
- OS0-64: the same with 90 deg vertical field of view and shorter range;
- MID-360: non-repetitive pattern, 4 lasers zig-zagging over -7..52 deg elevation at an
  irrational ratio to the 10 Hz azimuth turn, 200 k points/s, 0.1..40 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError

SENSORS = ("vlp16", "os0-64", "os1-64", "mid360")


class LidarConfig(Section):
    """LiDAR noise and limits; `None` means the sensor's datasheet value."""

    range_sigma_m: float | None = Field(None, ge=0, description="range noise sigma (m)")
    min_range_m: float | None = Field(None, ge=0, description="returns closer are dropped (m)")
    max_range_m: float | None = Field(None, gt=0, description="max range on 80% white (m)")
    dropout_prob: float = Field(0.005, ge=0, le=1, description="random return loss (0..1)")
    azimuth_fov_deg: tuple[float, float] = Field(
        (-180.0, 180.0), description="keep azimuths in [lo, hi] deg of the lidar frame; "
        "[-90, 90] keeps the forward half (the SLAM paper's cropped forest runs)")
    column_stride: int = Field(1, ge=1, description="keep every n-th firing (1: full sensor)")
    rate_hz: float = Field(10.0, gt=0, le=20, description="scan rate (Hz)")


@dataclass
class Firing:
    """One scan's beams: unit directions in the lidar frame, time offsets, ring numbers."""

    directions: np.ndarray  # (N, 3) float64
    times_s: np.ndarray  # (N,) float64, relative to the scan stamp
    ring: np.ndarray  # (N,) uint16
    organized: tuple[int, int] | None  # (height, width) for organized clouds


@dataclass(frozen=True)
class LidarModel:
    name: str
    range_sigma_m: float
    min_range_m: float
    max_range_m: float

    def firing(self, scan_index: int, period_s: float, stride: int) -> Firing:
        raise NotImplementedError


def _directions(azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=-1)


@dataclass(frozen=True)
class SpinningLidar(LidarModel):
    """A rotating multi-beam LiDAR (clockwise from above, starting behind the sensor)."""

    elevations_deg: tuple[float, ...] = ()
    columns: int = 1024
    beam_dt_s: float = 0.0  # time between consecutive beams of one column
    organized: bool = False
    ring_top_first: bool = False

    def firing(self, scan_index: int, period_s: float, stride: int) -> Firing:
        cols = np.arange(0, self.columns, stride)
        elev = np.radians(np.asarray(self.elevations_deg))
        n_beams = len(elev)
        azimuth = np.pi - 2 * np.pi * cols / self.columns
        col_t = cols * (period_s / self.columns)
        order = np.argsort(-elev if self.ring_top_first else elev, kind="stable")
        ring = np.empty(n_beams, dtype=np.uint16)
        ring[order] = np.arange(n_beams)
        # Organized clouds are row-major (ring, column); unorganized follow firing order.
        if self.organized:
            rows = order
            az = np.broadcast_to(azimuth[None, :], (n_beams, len(cols)))
            el = np.broadcast_to(elev[rows][:, None], az.shape)
            t = col_t[None, :] + self.beam_dt_s * rows[:, None]
            r = np.broadcast_to(ring[rows][:, None], az.shape)
            shape = (n_beams, len(cols))
        else:
            az = np.broadcast_to(azimuth[:, None], (len(cols), n_beams))
            el = np.broadcast_to(elev[None, :], az.shape)
            t = col_t[:, None] + self.beam_dt_s * np.arange(n_beams)[None, :]
            r = np.broadcast_to(ring[None, :], az.shape)
            shape = None
        return Firing(_directions(az.ravel(), el.ravel()), t.ravel(), r.ravel().astype(np.uint16),
                      shape)


@dataclass(frozen=True)
class LivoxMid360(LidarModel):
    """Non-repetitive pattern: each laser zig-zags in elevation at a frequency incommensurate
    with the azimuth turn, so successive scans fill different gaps (coverage grows with time)."""

    points_per_s: int = 200_000
    n_lasers: int = 4
    elevation_range_deg: tuple[float, float] = (-7.0, 52.0)
    zigzag_hz: float = 10.0 * 36.0 * (1 + 5 ** 0.5) / 2

    def firing(self, scan_index: int, period_s: float, stride: int) -> Firing:
        per_laser = round(self.points_per_s * period_s / self.n_lasers)
        k = np.arange(0, per_laser, stride)
        t_scan0 = scan_index * period_s
        t_rel = np.repeat((k * (period_s / per_laser))[None, :], self.n_lasers, axis=0)
        t_rel = t_rel + (np.arange(self.n_lasers) * period_s / (per_laser * self.n_lasers))[:, None]
        t_abs = t_scan0 + t_rel
        laser = np.repeat(np.arange(self.n_lasers)[:, None], len(k), axis=1)
        azimuth = 2 * np.pi * (t_abs / period_s + laser / self.n_lasers)
        phase = self.zigzag_hz * t_abs + laser / self.n_lasers + 0.37 * laser
        tri = 2.0 * np.abs(phase - np.floor(phase) - 0.5)  # triangle wave in [0, 1]
        lo, hi = np.radians(self.elevation_range_deg)
        elevation = lo + (hi - lo) * tri
        order = np.argsort(t_rel.ravel(), kind="stable")
        return Firing(_directions(azimuth.ravel()[order], elevation.ravel()[order]),
                      t_rel.ravel()[order], laser.ravel()[order].astype(np.uint16), None)


def make_lidar(name: str) -> LidarModel:
    if name == "vlp16":
        return SpinningLidar("vlp16", 0.015, 0.4, 100.0,
                             elevations_deg=(-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13,
                                             -1, 15),
                             columns=1800, beam_dt_s=2.304e-6)
    if name == "os1-64":
        return SpinningLidar("os1-64", 0.015, 0.5, 120.0,
                             elevations_deg=tuple(np.linspace(22.5, -22.5, 64)), columns=1024,
                             organized=True, ring_top_first=True)
    if name == "os0-64":
        return SpinningLidar("os0-64", 0.02, 0.3, 50.0,
                             elevations_deg=tuple(np.linspace(45.0, -45.0, 64)), columns=1024,
                             organized=True, ring_top_first=True)
    if name == "mid360":
        return LivoxMid360("mid360", 0.02, 0.1, 40.0)
    raise ConfigError(f"unknown sensor {name!r}; choose one of {', '.join(SENSORS)}")
