"""Scan preprocessing for GICP: deskewing, voxel-grid downsampling, per-point covariances.

Neighbour search runs on the host (scipy's cKDTree): it is done once per scan, not per pose,
so it is not the hot loop; everything per pose runs in the Taichi kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.errors import ConfigError, PointCloudError
from mcl3d.gaussian_voxels import check_points

PLANE_EIGENVALUES = (1e-3, 1.0, 1.0)  # normal first, as small_gicp/gtsam_points (kernel: n, 1, 1)
MIN_NEIGHBORS = 5  # fewer neighbours than this: identity covariance


@dataclass
class Scan:
    """A preprocessed point cloud: points (N, 3) and their covariances (N, 3, 3), float64."""

    points: np.ndarray
    covs: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def __repr__(self) -> str:
        if len(self) == 0:
            return "Scan(0 points)"
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        return (f"Scan({len(self)} points, extent x {lo[0]:.1f}..{hi[0]:.1f} "
                f"y {lo[1]:.1f}..{hi[1]:.1f} z {lo[2]:.1f}..{hi[2]:.1f} m)")


def voxel_ids(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One int64 per point naming its voxel (a 1D key sorts ~10x faster than (N, 3) rows);
    (N, 3) integer rows when the cloud spans too many voxels to pack."""
    keys = np.floor(points / voxel_size_m).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        return keys
    return (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]


def voxel_downsample(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One point per occupied voxel of edge `voxel_size_m`: the mean of its points."""
    pts = check_points(points)
    if not np.isfinite(voxel_size_m) or voxel_size_m <= 0:
        raise ConfigError(f"voxel_size_m must be > 0, got {voxel_size_m}")
    if len(pts) == 0:
        return pts.reshape(0, 3)
    _, inverse, counts = np.unique(voxel_ids(pts, voxel_size_m), axis=0, return_inverse=True,
                                   return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 3))
    for a in range(3):
        sums[:, a] = np.bincount(inverse, weights=pts[:, a], minlength=len(counts))
    return sums / counts[:, None]


def estimate_covariances(points: np.ndarray, k_neighbors: int = 10,
                         max_neighbor_dist_m: float = np.inf) -> np.ndarray:
    """Plane-regularized covariance of each point's k nearest neighbours (itself included).

    Eigenvalues are replaced by (1e-3, 1, 1): a thin disc along the local surface. A point
    with fewer than 5 neighbours (within `max_neighbor_dist_m`) gets the identity.
    """
    from scipy.spatial import cKDTree

    pts = check_points(points)
    if k_neighbors < MIN_NEIGHBORS:
        raise ConfigError(f"k_neighbors must be >= {MIN_NEIGHBORS}, got {k_neighbors}")
    if len(pts) < MIN_NEIGHBORS:
        return np.tile(np.eye(3), (len(pts), 1, 1))
    k = min(k_neighbors, len(pts))
    dist, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=max_neighbor_dist_m,
                                   workers=-1)
    found = np.isfinite(dist)
    counts = found.sum(axis=1).astype(np.int32)
    # found neighbours come first in each row (sorted by distance); the rest are never read
    neighbors = np.where(found, idx, 0).astype(np.int32)
    from mcl3d.gaussian_voxels import ensure_runtime
    from mcl3d.kernels.covariance import plane_covariances

    ensure_runtime()
    out = np.empty((len(pts), 3, 3), np.float32)
    plane_covariances(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(neighbors),
                      counts, len(pts), MIN_NEIGHBORS, PLANE_EIGENVALUES[0], out)
    return out.astype(np.float64)


def deskew(points: np.ndarray, point_times_s: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Undo the sensor's motion during a sweep.

    `point_times_s` are each point's time relative to the scan stamp (the header stamp, the
    reference time of every pose mcl3d outputs; negative before it). `twist` is the sensor's
    velocity (wx, wy, wz, vx, vy, vz) in its own frame (rad/s, m/s), assumed constant over the
    sweep. Each point is moved into the sensor frame at the stamp: p' = exp(t twist) p
    (a Taichi kernel, f32: ~1e-5 m at 100 m).
    """
    pts = check_points(points)
    times = np.asarray(point_times_s, dtype=np.float64).ravel()
    twist = np.asarray(twist, dtype=np.float64).ravel()
    if times.shape != (len(pts),):
        raise PointCloudError(f"need one time per point: {len(times)} times for "
                              f"{len(pts)} points")
    if not np.isfinite(times).all() or twist.shape != (6,) or not np.isfinite(twist).all():
        raise PointCloudError("point times and the twist must be finite (twist has 6 values)")
    if len(pts) == 0:
        return pts
    from mcl3d.gaussian_voxels import ensure_runtime
    from mcl3d.kernels.deskew import deskew_points

    ensure_runtime()
    out = np.empty((len(pts), 3), np.float32)
    deskew_points(np.ascontiguousarray(pts, np.float32), np.ascontiguousarray(times, np.float32),
                  len(pts), twist[:3].astype(np.float32), twist[3:].astype(np.float32), out)
    return out.astype(np.float64)


def preprocess(points: np.ndarray, voxel_size_m: float = 0.25, k_neighbors: int = 10,
               max_range_m: float = np.inf, min_range_m: float = 0.0) -> Scan:
    """Range crop, voxel-grid downsampling and per-point covariances: a scan ready for GICP."""
    pts = check_points(points)
    if not 0 <= min_range_m < max_range_m:
        raise ConfigError(f"need 0 <= min_range_m < max_range_m, got {min_range_m}, "
                          f"{max_range_m}")
    r = np.linalg.norm(pts, axis=1)
    pts = pts[(r >= min_range_m) & (r <= max_range_m)]
    down = voxel_downsample(pts, voxel_size_m)
    return Scan(down, estimate_covariances(down, k_neighbors))
