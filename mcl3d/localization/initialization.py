"""Where the particles start: free-space cells of the map for global localization, the
sensor's roll/pitch from the IMU's gravity, and the typed initialization choices.

Global candidates are cells observed free (every voxel at least the truncation distance
from a surface, or a whole FREE block), optionally only those within a height band above
the nearest surface below (ground robots: the lidar rides 0.2-2.5 m above the floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError, MapError
from mcl3d.core.geometry import rpy_to_rot

MAX_DENSE_CELLS = 20_000_000  # the host grid for candidate cells stays under ~20 MB
UNKNOWN_CELL, FREE_CELL, OCCUPIED_CELL = 0, 1, 2


class InitConfig(Section):
    """How particles are initialized: globally, around a given pose or around the first
    ground-truth pose. Angles in degrees; the `*_rad` properties convert them once."""

    mode: str = Field("global", description="global | pose | gt")
    pose: list[float] | None = Field(None, description="x y z roll pitch yaw [m, deg]")
    std: list[float] = Field([0.5, 0.5, 0.1, 2.864788975654116, 2.864788975654116,
                              17.188733853924695],
                             description="std of x y z [m] and roll pitch yaw [deg] around "
                                         "the given pose")
    height_band_m: list[float] | str | None = Field(
        "auto", description="global: lidar height above the surface below [lo, hi] m; "
                            "'auto': the floor seen in the first scan, levelled by the IMU's "
                            "gravity, +- auto_band_m (else the default band); null or 'none' "
                            "samples all free space")
    default_band_m: list[float] = Field([0.2, 2.5], description="band when auto finds no floor")
    covered: bool | str = Field(
        "auto", description="keep only cells with a surface somewhere above them (inside a "
                            "building, not on its roof or around it); auto: when at least "
                            "covered_share of the candidates are covered (indoor maps)")
    covered_share: float = Field(0.3, ge=0.0, le=1.0)
    auto_band_m: float = Field(0.2, gt=0.0, description="half-width of the auto band")
    cell_m: float = Field(0.2, gt=0.0, description="resolution of the free-space candidates "
                                                   "(rounded to voxel x power of two)")
    gravity_std_deg: float = Field(1.7188733853924696, ge=0.0,
                                   description="roll/pitch noise when taken from the IMU, deg")
    imu_samples: int = Field(20, ge=1, description="accelerometer samples averaged for gravity")
    uniform_rotation: bool = Field(
        False, description="global: rotations uniform on SO(3) even when gravity is known "
                           "(the paper's 6-DoF uniform initialization); false: roll/pitch from "
                           "the IMU's gravity (or the last converged estimate) when known")
    stratified: bool = Field(
        True, description="global: particle i takes a cell of the i-th of N equal runs of the "
                          "candidates and a golden-ratio yaw (no holes); false: independent "
                          "uniform draws, as the paper")

    @property
    def pose_m_rad(self) -> list[float] | None:
        """The given pose as x y z [m], roll pitch yaw [rad]."""
        return None if self.pose is None else _m_deg_to_m_rad(self.pose)

    @property
    def std_m_rad(self) -> list[float]:
        """The std around the pose as x y z [m], roll pitch yaw [rad]."""
        return _m_deg_to_m_rad(self.std)

    @property
    def gravity_std_rad(self) -> float:
        return math.radians(self.gravity_std_deg)


def _m_deg_to_m_rad(values: list[float]) -> list[float]:
    return [*values[:3], *(math.radians(v) for v in values[3:])]


@dataclass
class FreeCells:
    corners_m: np.ndarray  # (k, 3) float32 lower corners
    cell_m: float


def _cell_factor(tsdf, cell_m: float) -> int:
    f = 1
    while f < 8 and tsdf.voxel_size_m * f * 2 <= cell_m + 1e-9:
        f *= 2
    while f < 8 and tsdf.geometry.n_cells * (8 // f) ** 3 > MAX_DENSE_CELLS:
        f *= 2
    return f


def cell_states(tsdf, factor: int) -> np.ndarray:
    """Dense (X, Y, Z) uint8 grid of cells of `factor` voxels: unknown / free / occupied."""
    data = tsdf.blocks()
    k = 8 // factor
    dims = np.asarray(tsdf.coarse_dims) * k
    if np.prod(dims) > 8 * MAX_DENSE_CELLS:
        raise MapError(f"the map's grid {tsdf.coarse_dims} blocks is too large for global "
                       f"initialization candidates; crop the map or start from a given pose",
                       setting="init")
    grid = np.zeros(dims, np.uint8)
    for c in data.free_coords:
        grid[c[0] * k:(c[0] + 1) * k, c[1] * k:(c[1] + 1) * k, c[2] * k:(c[2] + 1) * k] = FREE_CELL
    if len(data.coords):
        nb = len(data.coords)
        shape = (nb, k, factor, k, factor, k, factor)
        observed = (data.weight > 0).reshape(shape)
        near = (observed & (data.sdf < tsdf.truncation_m * 0.999).reshape(shape))
        occ = near.any(axis=(2, 4, 6))
        free = (observed & ~near).all(axis=(2, 4, 6))
        state = np.where(occ, OCCUPIED_CELL, np.where(free, FREE_CELL, UNKNOWN_CELL))
        base = data.coords * k
        ii, jj, hh = np.meshgrid(np.arange(k), np.arange(k), np.arange(k), indexing="ij")
        gx = base[:, 0, None, None, None] + ii
        gy = base[:, 1, None, None, None] + jj
        gz = base[:, 2, None, None, None] + hh
        grid[gx, gy, gz] = state.astype(np.uint8)
    return grid


def _keep_covered(grid: np.ndarray, ok: np.ndarray, cfg: InitConfig) -> np.ndarray:
    """Candidates under a surface (a ceiling, a roof, a canopy), when asked or when they are
    a sizeable share (an indoor map: mesh-built maps also mark the space above the roof and
    around the walls free, which would take half the particles)."""
    if cfg.covered is False or cfg.covered == "false":
        return ok
    occupied = grid == OCCUPIED_CELL
    above = np.flip(np.cumsum(np.flip(occupied, axis=2), axis=2), axis=2) > 0
    covered = ok & np.concatenate([above[:, :, 1:], np.zeros_like(above[:, :, :1])], axis=2)
    if cfg.covered == "auto" and covered.sum() < cfg.covered_share * max(ok.sum(), 1):
        return ok
    return covered


def _in_height_band(occupied: np.ndarray, cell_m: float, truncation_m: float, lo: float,
                    hi: float) -> np.ndarray:
    """Cells with a surface somewhere below them at a height in [lo, hi], not only the
    nearest surface: a drone over a crate is 3.4 m above the floor but 1.9 m above the
    crate, and the band from the floor its first scan sees must still hold its pose.
    A cell z above an occupied cell z0 is (z - z0 - 0.5) * cell + truncation high."""
    nz = occupied.shape[2]
    counts = np.concatenate([np.zeros((*occupied.shape[:2], 1), np.int32),
                             np.cumsum(occupied, axis=2, dtype=np.int32)], axis=2)
    z = np.arange(nz)
    first = np.clip(np.ceil(z - 0.5 - (hi - truncation_m) / cell_m).astype(np.int64), 0, nz)
    last = np.clip(np.floor(z - 0.5 - (lo - truncation_m) / cell_m).astype(np.int64), -1,
                   nz - 1)
    below = counts[:, :, np.maximum(last + 1, first)] - counts[:, :, first]
    return below > 0


def free_cells(tsdf, cfg: InitConfig) -> FreeCells:
    """Candidate cells for global initialization; MapError when there are none."""
    factor = _cell_factor(tsdf, cfg.cell_m)
    cell = tsdf.voxel_size_m * factor
    grid = cell_states(tsdf, factor)
    ok = grid == FREE_CELL
    band = cfg.default_band_m if cfg.height_band_m == "auto" else cfg.height_band_m
    if band == "none":
        band = None
    if band is not None:
        if isinstance(band, str) or len(band) != 2:
            raise ConfigError(f"height band {band!r}: give [lo, hi] in m, 'auto' or null")
        lo, hi = band
        if hi < lo:
            raise ConfigError(f"height band {band}: hi must be >= lo")
        ok &= _in_height_band(grid == OCCUPIED_CELL, cell, tsdf.truncation_m, lo, hi)
    ok = _keep_covered(grid, ok, cfg)
    idx = np.argwhere(ok)
    if len(idx) == 0:
        where = f" within the height band {band} m above a surface" if band is not None else ""
        raise MapError(f"the map has no observed free space{where} to place particles in; "
                       f"drop the height band, or start from a given pose",
                       setting="height_band")
    corners = np.asarray(tsdf.origin_m) + idx * cell
    return FreeCells(corners.astype(np.float32), float(cell))


def floor_height(points_lidar: np.ndarray, roll: float, pitch: float,
                 bin_m: float = 0.05) -> float | None:
    """Height of the lidar above the floor it sees: the densest level of returns below the
    sensor once the scan is levelled with the gravity's roll/pitch, if it holds a tenth of
    them or three times the mean level (a drone 3.4 m up sees as many wall returns below as
    floor ones); None without a floor."""
    p = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)] @ rpy_to_rot(roll, pitch, 0.0).T
    below = p[(p[:, 2] < -0.1) & (np.hypot(p[:, 0], p[:, 1]) > 0.5), 2]
    if len(below) < 50:
        return None
    counts, edges = np.histogram(below, bins=np.arange(below.min(), 0.0 + bin_m, bin_m))
    k = int(np.argmax(counts))
    if counts[k] < max(20, min(0.1 * len(below), 3.0 * counts.mean())):
        return None  # no level stands out: walls and clutter only
    return float(-(edges[k] + edges[k + 1]) / 2)


def auto_band(cfg: InitConfig, first_scan: np.ndarray | None, roll_pitch) -> list[float] | None:
    """The height band to use: explicit, or from the floor seen in the first scan."""
    if cfg.height_band_m != "auto":
        return cfg.height_band_m
    if first_scan is None or roll_pitch is None:
        return cfg.default_band_m
    h = floor_height(first_scan, *roll_pitch)
    if h is None:
        return cfg.default_band_m
    return [max(h - cfg.auto_band_m, 0.0), h + cfg.auto_band_m]


def gravity_roll_pitch(accels_lidar: np.ndarray) -> tuple[float, float]:
    """Roll and pitch of T_map_lidar (z up) from mean specific force in the lidar frame."""
    a = np.asarray(accels_lidar, dtype=np.float64).reshape(-1, 3).mean(axis=0)
    if not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1.0:
        raise ConfigError("the IMU's accelerometer does not show gravity (mean |a| < 1 m/s^2); "
                          "cannot take roll/pitch from it")
    roll = float(np.arctan2(a[1], a[2]))
    pitch = float(np.arctan2(-a[0], np.hypot(a[1], a[2])))
    return roll, pitch


def parse_floats(text: str, n: int, what: str) -> list[float]:
    """'1 2 3' or '1,2,3' -> n floats, or ConfigError naming the option."""
    parts = text.replace(",", " ").split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"{what} must be {n} numbers, got {text!r}") from None
    if len(values) != n or not np.all(np.isfinite(values)):
        raise ConfigError(f"{what} must be {n} finite numbers, got {text!r}")
    return values
