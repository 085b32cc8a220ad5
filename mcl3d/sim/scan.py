"""One simulated LiDAR scan: firing pattern -> poses at each firing time -> ray cast -> noise."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.sim.lidars import LidarConfig, LidarModel
from mcl3d.sim.raycast import WorldCaster
from mcl3d.sim.trajectories import SimTrajectory

REFERENCE_REFLECTIVITY = 0.8  # datasheet max range is quoted for an 80% white target


@dataclass
class SimulatedScan:
    points: np.ndarray  # (N, 3) float32, lidar frame at each point's firing time
    times_s: np.ndarray  # (N,) float32 relative to the stamp
    intensity: np.ndarray  # (N,) float32
    ring: np.ndarray  # (N,) uint16
    height: int
    width: int
    n_valid: int


def simulate_scan(model: LidarModel, cfg: LidarConfig, caster: WorldCaster,
                  traj: SimTrajectory, T_base_lidar: np.ndarray, scan_index: int,
                  stamp_s: float, rng: np.random.Generator) -> SimulatedScan:
    """Cast one sweep starting at `stamp_s`; each return uses the pose at its own time."""
    period = 1.0 / cfg.rate_hz
    firing = model.firing(scan_index, period, cfg.column_stride)
    d_lidar = firing.directions
    t_abs = stamp_s + firing.times_s
    uniq, inverse = np.unique(t_abs, return_inverse=True)
    T = traj.T_map_base(uniq) @ T_base_lidar
    origins = T[inverse, :3, 3]
    directions = np.einsum("nij,nj->ni", T[inverse, :3, :3], d_lidar)
    hits = caster.cast(origins, directions, traj.cab_z_m(t_abs), traj.door_closed(t_abs))

    sigma = model.range_sigma_m if cfg.range_sigma_m is None else cfg.range_sigma_m
    min_r = model.min_range_m if cfg.min_range_m is None else cfg.min_range_m
    max_r = model.max_range_m if cfg.max_range_m is None else cfg.max_range_m
    echo = np.clip(hits.reflectivity * hits.cos_incidence / REFERENCE_REFLECTIVITY, 1e-4, 1.0)
    azimuth = np.degrees(np.arctan2(d_lidar[:, 1], d_lidar[:, 0]))
    lo, hi = cfg.azimuth_fov_deg
    valid = (np.isfinite(hits.range_m) & (hits.range_m >= min_r)
             & (hits.range_m <= max_r * np.sqrt(echo))
             & (rng.random(len(t_abs)) >= cfg.dropout_prob)
             & (azimuth >= lo) & (azimuth <= hi))
    noise = rng.standard_normal(len(t_abs))
    r = np.where(valid, hits.range_m + sigma * noise, 0.0)
    intensity = 255.0 * hits.reflectivity * (0.2 + 0.8 * hits.cos_incidence)
    intensity = np.where(valid, intensity * (1.0 + 0.05 * rng.standard_normal(len(t_abs))), 0.0)
    if hits.scatter_depth_m is not None:  # drawn last: worlds of solids keep their scans
        r = np.where(valid, r + _scatter_depth(hits.scatter_depth_m, rng), 0.0)
    points = (d_lidar * r[:, None]).astype(np.float32)
    intensity = np.clip(intensity, 0.0, 255.0).astype(np.float32)
    times = firing.times_s.astype(np.float32)
    ring = firing.ring
    n_valid = int(valid.sum())
    if firing.organized is not None:  # "no return" stays in place as a zero point
        height, width = firing.organized
        return SimulatedScan(points, times, intensity, ring, height, width, n_valid)
    return SimulatedScan(points[valid], times[valid], intensity[valid], ring[valid], 1, n_valid,
                         n_valid)


def _scatter_depth(mean_depth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """How far each pulse went into porous foliage before a leaf returned it: exponential
    (leaves spread at random through the crown: Beer-Lambert), 0 on solid surfaces."""
    return rng.exponential(1.0, len(mean_depth_m)) * mean_depth_m
