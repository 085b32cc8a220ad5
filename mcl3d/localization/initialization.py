"""Where the particles start: free-space cells of the map for global localization, the
sensor's roll/pitch from the IMU's gravity, and the typed initialization choices.

Global candidates are cells observed free (every voxel at least the truncation distance
from a surface, or a whole FREE block), optionally only those within a height band above
the nearest surface below (ground robots: the lidar rides 0.2-2.5 m above the floor).
They are found column by column among the map's known blocks (allocated or FREE), so their
time and memory grow with the map's surface and observed space, not with its bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError, MapError
from mcl3d.core.geometry import rpy_to_rot

MAX_KNOWN_CELLS = 20_000_000  # cells of the known blocks at the candidates' resolution
CHUNK_CELLS = 1 << 20  # cells of whole block columns handled at once (~80 MB of temporaries)
UNKNOWN_CELL, FREE_CELL, OCCUPIED_CELL = 0, 1, 2
FREE_BLOCK = -3  # a FREE coarse cell's value (mcl3d.kernels.tsdf_lookup.FREE)


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
        "auto", description="drop the cells under open sky (observed free up to the map's "
                            "top: on a building's roof or around it; a ceiling never seen "
                            "keeps its cells); auto: when at least covered_share of the "
                            "candidates have a surface above them (indoor maps)")
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


def _cell_factor(tsdf, cell_m: float, known_blocks: int) -> int:
    """Voxels per cell edge: cell_m rounded down to voxel x power of two, coarser while the
    known blocks (allocated or FREE: the map's surface and observed space, not its bounds)
    hold more than MAX_KNOWN_CELLS cells."""
    f = 1
    while f < 8 and tsdf.voxel_size_m * f * 2 <= cell_m + 1e-9:
        f *= 2
    while f < 8 and known_blocks * (8 // f) ** 3 > MAX_KNOWN_CELLS:
        f *= 2
    return f


def block_cell_states(tsdf, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Allocated blocks' coordinates (n, 3) and the states of their cells of `factor` voxels
    (n, k, k, k) uint8, k = 8 // factor: occupied when a voxel is observed within the
    truncation, free when every voxel is observed farther, else unknown. Read from the pool a
    chunk at a time: one byte per cell stays, not the voxels."""
    k = 8 // factor
    coords, states = [np.zeros((0, 3), np.int32)], [np.zeros((0, k, k, k), np.uint8)]
    trunc = tsdf.truncation_m * 0.999
    for c, sdf, weight in tsdf.block_chunks():
        shape = (len(c), k, factor, k, factor, k, factor)
        observed = (weight > 0).reshape(shape)
        near = observed & (sdf < trunc).reshape(shape)
        occ = near.any(axis=(2, 4, 6))
        free = (observed & ~near).all(axis=(2, 4, 6))
        coords.append(c)
        states.append(np.where(occ, OCCUPIED_CELL,
                               np.where(free, FREE_CELL, UNKNOWN_CELL)).astype(np.uint8))
    return np.concatenate(coords), np.concatenate(states)


@dataclass
class _Columns:
    """The known blocks sorted by block column (x, y), then z; a block's cells' states are
    its row of `states`, or all FREE for a FREE block (state index -1)."""

    coords: np.ndarray  # (n, 3) int64 block coordinates
    state_of: np.ndarray  # (n,) row of states, -1 for a FREE block
    states: np.ndarray  # (m, k, k, k) uint8
    k: int

    @classmethod
    def of(cls, tsdf, factor: int, free: np.ndarray) -> _Columns:
        """Of the map's allocated blocks and its FREE blocks `free` (n, 3)."""
        coords, states = block_cell_states(tsdf, factor)
        all_coords = np.concatenate([coords, free]).astype(np.int64)
        state_of = np.concatenate([np.arange(len(coords)), np.full(len(free), -1)])
        order = np.lexsort(all_coords.T[::-1])
        return cls(all_coords[order], state_of[order], states, 8 // factor)

    def chunks(self):
        """Slices of whole block columns holding about CHUNK_CELLS cells each."""
        n = len(self.coords)
        column = self.coords[:, 0] * (self.coords[:, 1].max(initial=0) + 1) + self.coords[:, 1]
        starts = np.r_[0, np.flatnonzero(np.diff(column)) + 1, n]
        per = max(1, CHUNK_CELLS // self.k**3)
        s = 0
        while s < n:
            e = starts[np.searchsorted(starts, s + per, side="right") - 1]
            e = e if e > s else starts[np.searchsorted(starts, s, side="right")]
            yield slice(s, int(e))
            s = int(e)

    def cells(self, part: slice) -> tuple[np.ndarray, np.ndarray]:
        """Cell coordinates (c, 3) int64 and states (c,) of the blocks in `part`."""
        k = self.k
        rows = self.state_of[part]
        st = np.full((len(rows), k, k, k), FREE_CELL, np.uint8)
        st[rows >= 0] = self.states[rows[rows >= 0]]
        local = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), axis=-1)
        c = self.coords[part][:, None, None, None, :] * k + local
        return c.reshape(-1, 3), st.reshape(-1)


def _count_in(sorted_keys: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """How many sorted keys lie in [lo, hi) (elementwise)."""
    return np.searchsorted(sorted_keys, hi) - np.searchsorted(sorted_keys, lo)


def _chunk_candidates(cells: np.ndarray, states: np.ndarray, dims: np.ndarray,
                      band: tuple[float, float] | None, cell_m: float, truncation_m: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keys of the free cells of whole columns in the height band (all of them without a
    band), whether each is covered (a surface somewhere above it in its column) and whether
    it is under open sky (every cell above it in its column observed free, to the map's top).

    A cell z above an occupied cell z0 is (z - z0 - 0.5) * cell + truncation high: it is in
    the band when some occupied cell of its column lies at z0 in [first, last] below it (any
    surface below, not only the nearest: a drone over a crate is 3.4 m above the floor but
    1.9 m above the crate, and the band from the floor its first scan sees must hold it)."""
    nz = int(dims[2])
    column = (cells[:, 0] * dims[1] + cells[:, 1]) * nz
    keys = column + cells[:, 2]
    occupied = np.sort(keys[states == OCCUPIED_CELL])
    free = states == FREE_CELL
    free_keys = np.sort(keys[free])
    column, z = column[free], cells[free, 2]
    ok = np.ones(len(z), bool)
    if band is not None:
        lo, hi = band
        first = np.clip(np.ceil(z - 0.5 - (hi - truncation_m) / cell_m).astype(np.int64), 0, nz)
        last = np.clip(np.floor(z - 0.5 - (lo - truncation_m) / cell_m).astype(np.int64), -1,
                       nz - 1)
        ok = _count_in(occupied, column + first, column + np.maximum(last + 1, first)) > 0
    above = column[ok] + z[ok] + 1, column[ok] + nz
    covered = _count_in(occupied, *above) > 0
    open_sky = _count_in(free_keys, *above) == nz - 1 - z[ok]
    return keys[free][ok], covered, open_sky


def _height_band(cfg: InitConfig) -> tuple[float, float] | None:
    band = cfg.default_band_m if cfg.height_band_m == "auto" else cfg.height_band_m
    if band is None or band == "none":
        return None
    if isinstance(band, str) or len(band) != 2:
        raise ConfigError(f"height band {band!r}: give [lo, hi] in m, 'auto' or null")
    lo, hi = band
    if hi < lo:
        raise ConfigError(f"height band {band}: hi must be >= lo")
    return float(lo), float(hi)


def _without_open_sky(keys: np.ndarray, covered: np.ndarray, open_sky: np.ndarray,
                  cfg: InitConfig) -> np.ndarray:
    """Without the candidates under open sky, when asked or when the covered ones (under a
    ceiling, a roof, a canopy) are a sizeable share (an indoor map: mesh-built maps also
    mark the space above the roof and around the walls free, which would take half the
    particles). A ceiling the sensor never saw (a room's, from a lidar whose beams rise 15°:
    a map built from a log) leaves unknown space above its cells, not open sky: they stay."""
    if cfg.covered is False or cfg.covered == "false":
        return keys
    if cfg.covered == "auto" and covered.sum() < cfg.covered_share * max(len(keys), 1):
        return keys
    return keys[~open_sky]


def free_cells(tsdf, cfg: InitConfig) -> FreeCells:
    """Candidate cells for global initialization, in the order of their (x, y, z) cell
    coordinates; MapError when there are none. Built from the known blocks column by
    column: time and memory grow with the map's surface and observed space, not with its
    bounds (a kilometre-scale map's empty sky and unseen ground cost nothing)."""
    band = _height_band(cfg)
    cells, values = tsdf.coarse_cells()
    free = cells[values == FREE_BLOCK]
    factor = _cell_factor(tsdf, cfg.cell_m, tsdf.n_blocks + len(free))
    del cells, values
    cell = tsdf.voxel_size_m * factor
    dims = np.asarray(tsdf.coarse_dims, np.int64) * (8 // factor)
    columns = _Columns.of(tsdf, factor, free)
    keys, covered, open_sky = [np.zeros(0, np.int64)], [np.zeros(0, bool)], [np.zeros(0, bool)]
    for part in columns.chunks():
        k, c, o = _chunk_candidates(*columns.cells(part), dims, band, cell, tsdf.truncation_m)
        keys.append(k)
        covered.append(c)
        open_sky.append(o)
    keys = np.sort(_without_open_sky(*map(np.concatenate, (keys, covered, open_sky)), cfg))
    if len(keys) == 0:
        where = f" within the height band {list(band)} m above a surface" if band else ""
        raise MapError(f"the map has no observed free space{where} to place particles in; "
                       f"drop the height band, or start from a given pose",
                       setting="height_band")
    idx = np.stack([keys // (dims[1] * dims[2]), (keys // dims[2]) % dims[1], keys % dims[2]],
                   axis=1)
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
