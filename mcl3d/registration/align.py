"""Pairwise registration in small_gicp's spirit: `preprocess(points) -> Scan`, then
`align(target, source, init_T_target_source) -> RegistrationResult`.

The target becomes a Gaussian voxel map per resolution; the source is registered coarse to
fine (each level starts where the previous one converged), all on the device.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mcl3d.core import runtime
from mcl3d.core.errors import ConfigError, PointCloudError
from mcl3d.core.geometry import rot_to_rpy
from mcl3d.registration.batch_gicp import BatchGicp
from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps, check_pose, ensure_runtime
from mcl3d.registration.preprocess import Scan, preprocess

__all__ = ["RegistrationResult", "Scan", "align", "preprocess"]

DEFAULT_RESOLUTIONS_M = (1.0, 0.25)


@dataclass
class RegistrationResult:
    """Outcome of `align`; H, b and error are evaluated at T_target_source."""

    T_target_source: np.ndarray
    converged: bool
    iterations: int
    num_inliers: int
    H: np.ndarray  # 6x6, rotation first: inv(H) approximates the pose covariance
    b: np.ndarray
    error: float  # 0.5 * sum of e^T (C_B + R C_A R^T)^-1 e over the inliers

    def __repr__(self) -> str:
        t = self.T_target_source[:3, 3]
        rpy = np.degrees(rot_to_rpy(self.T_target_source[:3, :3]))
        return (f"RegistrationResult(converged={self.converged}, iterations={self.iterations}, "
                f"num_inliers={self.num_inliers}, error={self.error:.4g},\n"
                f"  t=[{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m, "
                f"rpy=[{rpy[0]:.3f}, {rpy[1]:.3f}, {rpy[2]:.3f}] deg)")


class _Engine:
    """Device fields for pairwise alignment, kept between calls and regrown when too small."""

    def __init__(self, levels: int, target_points: int, source_points: int):
        self.runtime = ensure_runtime()
        buckets = 1 << max(14, int(np.ceil(np.log2(max(target_points, 1) * 2))))
        self.levels, self.target_points = levels, buckets // 2
        self.maps = GaussianVoxelMaps(max_maps=levels, buckets_per_map=buckets,
                                      max_points=min(buckets // 2, 131072))
        self.source_points = 1 << max(12, int(np.ceil(np.log2(max(source_points, 1)))))
        self.gicp = BatchGicp(self.maps, max_groups=1, max_rows=1,
                              max_source_points=self.source_points)

    def fits(self, levels: int, target_points: int, source_points: int) -> bool:
        return (runtime.current() is self.runtime and levels <= self.levels
                and target_points <= self.target_points and source_points <= self.source_points)


_engine: _Engine | None = None


def _get_engine(levels: int, target_points: int, source_points: int) -> _Engine:
    global _engine
    if _engine is None or not _engine.fits(levels, target_points, source_points):
        _engine = _Engine(levels, target_points, source_points)
    return _engine


def _as_scan(cloud: Scan | np.ndarray, voxel_size_m: float) -> Scan:
    if isinstance(cloud, Scan):
        return cloud
    return preprocess(cloud, voxel_size_m=voxel_size_m)


def align(target: Scan | np.ndarray, source: Scan | np.ndarray,
          init_T_target_source: np.ndarray | None = None,
          voxel_resolution_m: float | Sequence[float] = DEFAULT_RESOLUTIONS_M,
          max_iterations: int = 30, use_lm: bool = False,
          rotation_epsilon_rad: float = np.radians(0.1), translation_epsilon_m: float = 1e-3,
          downsampling_resolution_m: float = 0.1) -> RegistrationResult:
    """VGICP of `source` onto `target` (Scans, or raw (N, 3) points which are preprocessed
    with `downsampling_resolution_m`), coarse to fine over `voxel_resolution_m`."""
    init = check_pose(np.eye(4) if init_T_target_source is None else init_T_target_source,
                      "init_T_target_source")
    levels = [float(voxel_resolution_m)] if np.isscalar(voxel_resolution_m) \
        else [float(r) for r in voxel_resolution_m]
    if not levels or min(levels) <= 0:
        raise ConfigError(f"voxel_resolution_m must be > 0, got {voxel_resolution_m}")
    target = _as_scan(target, downsampling_resolution_m)
    source = _as_scan(source, downsampling_resolution_m)
    for name, scan in (("target", target), ("source", source)):
        if len(scan) == 0:
            raise PointCloudError(f"the {name} point cloud is empty: nothing to register")
    engine = _get_engine(len(levels), len(target), len(source))
    for level, res in enumerate(levels):
        engine.maps.clear(level, res)
        engine.maps.insert(level, target.points, target.covs)
    engine.gicp.set_source(source.points, source.covs)
    T = init
    iterations = 0
    for level in range(len(levels)):
        engine.gicp.set_problem(T[None], row_group=[0], row_map=[level])
        out = engine.gicp.optimize(max_iterations, use_lm, rotation_epsilon_rad,
                                   translation_epsilon_m)
        T = out.T[0]
        iterations += int(out.iterations[0])
    return RegistrationResult(T_target_source=T, converged=bool(out.status[0] == 1),
                              iterations=iterations, num_inliers=int(out.num_inliers[0]),
                              H=out.H[0], b=out.b[0], error=float(out.error[0]))
