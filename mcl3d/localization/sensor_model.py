"""The LiDAR endpoint model's parameters, scan reduction, and a NumPy twin of the kernel.

The Taichi kernel (mcl3d.kernels.likelihood) is the implementation that runs; the NumPy
version here computes the same quantities vectorised over particles x points and serves as
the reference in tests and the baseline in bench/bench_localize.py. docs/sensor-model.md
explains the model and every parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from mcl3d.core.config import Section
from mcl3d.core.geometry import quat_to_rot
from mcl3d.maps.sparse_cells import CellLookup
from mcl3d.registration.preprocess import deskew

BLOCK = 8
MIN_SCAN_POINTS = 8  # fewer usable points after the range gate: the scan is skipped
FREE = -3  # mcl3d.kernels.tsdf_lookup.FREE (kept here so the NumPy twin needs no Taichi)


class SensorModelConfig(Section):
    """Endpoint likelihood on the TSDF; probabilities are relative to a perfect hit (= 1)."""

    sigma_m: float = Field(0.05, gt=0.0, description="std of the signed distance of a hit")
    search_sigma_m: float = Field(
        0.12, gt=0.0, description="sigma while searching (before the first convergence and "
                                  "after a global re-seed): wider basins of attraction")
    z_hit: float = Field(0.9, gt=0.0, le=1.0, description="weight of the Gaussian hit term")
    z_rand: float = Field(0.1, gt=0.0, le=1.0, description="uniform term: floor near surfaces")
    p_free: float = Field(0.05, gt=0.0, le=1.0,
                          description="a point in observed free space (a penalty, < z_rand)")
    p_unknown: float = Field(0.12, gt=0.0, le=1.0,
                             description="a point in unknown space or outside the map (neutral: "
                                         "about the random floor)")
    match_dist_m: float = Field(0.10, gt=0.0,
                                description="|d| below this counts as a surface match")
    effective_points: float = Field(
        16.0, gt=0.0, description="tempering: the summed log-likelihood is scaled by "
                                  "effective_points / M, as if only this many points were "
                                  "independent")
    points: int = Field(256, ge=MIN_SCAN_POINTS, le=65536, description="M, scan points per update")
    min_range_m: float = Field(1.0, ge=0.0, description="closer points are dropped (the robot)")
    max_range_m: float = Field(60.0, gt=0.0, description="farther points are dropped")
    voxel_m: float = Field(0.25, gt=0.0, description="voxel grid before the random subset")
    coarse_sigma_m: float = Field(
        0.6, ge=0.0, description="global search starts with a coarse model on a distance field "
                                 "with this sigma (0: off), shrinking to search_sigma_m")
    coarse_scans: int = Field(8, ge=1, description="scans of the coarse model after a global "
                                                   "(re-)initialization")
    coarse_cell_m: float = Field(0.1, gt=0.0, description="cell of the coarse distance field "
                                                          "(voxel x power of two)")
    coarse_max_dist_m: float = Field(1.5, gt=0.0, description="distances beyond this count as "
                                                              "far from any surface")
    cache_block: bool | str = Field(
        "auto", description="kernel keeps the last coarse-cell lookup (auto: on GPUs only, "
                            "where it saves memory reads; on cpu it measured slower)")
    model: Literal["tsdf", "paper"] = Field(
        "tsdf", description="tsdf: the model of docs/sensor-model.md (free/unknown cases, "
                            "tempered log-likelihoods); paper: Eisoldt et al. eq. 3, a "
                            "precomputed Gaussian of the TSDF value interpolated trilinearly, "
                            "summed over the points with a z_rand / max_range_m floor, "
                            "untempered (effective_points unused)")

    @model_validator(mode="after")
    def _check(self) -> SensorModelConfig:
        if self.max_range_m <= self.min_range_m:
            raise ValueError("max_range_m must be larger than min_range_m")
        return self

    @property
    def log_free(self) -> float:
        return float(np.log(self.p_free))

    @property
    def log_unknown(self) -> float:
        return float(np.log(self.p_unknown))

    def tempering(self, n_points: int) -> float:
        return self.effective_points / max(n_points, 1)

    def increment_scale(self, n_points: int) -> float:
        """A scan's log-weight increment per unit of the kernel's ll_mean, up to a constant
        per scan (what annealing rescales)."""
        return 1.0 if self.model == "paper" else self.tempering(n_points) * n_points


TABLE_SIZE = 1024  # mcl3d.kernels.likelihood.TABLE_SIZE
MORTON_BITS = 21  # per axis: 2^21 cells of spatial_order's cell size


def hit_table(cfg: SensorModelConfig, truncation_m: float, sigma_m: float | None = None
              ) -> np.ndarray:
    """log(z_hit exp(-d^2 / 2 sigma^2) + z_rand) at the centres of TABLE_SIZE bins of d
    over [-truncation, truncation) (sigma: cfg.sigma_m unless given)."""
    sigma = cfg.sigma_m if sigma_m is None else sigma_m
    d = (np.arange(TABLE_SIZE) + 0.5) * (2.0 * truncation_m / TABLE_SIZE) - truncation_m
    return np.log(cfg.z_hit * np.exp(-0.5 * (d / sigma) ** 2) + cfg.z_rand).astype(np.float32)


def code_table(cfg: SensorModelConfig, truncation_m: float, sigma_m: float | None = None
               ) -> np.ndarray:
    """Log-likelihood per voxel code of mcl3d.kernels.likelihood: codes k and TABLE_SIZE + k
    are hit bin k (without / with a surface match), then observed free, then unknown."""
    hit = hit_table(cfg, truncation_m, sigma_m)
    return np.concatenate([hit, hit, [cfg.log_free, cfg.log_unknown]]).astype(np.float32)


def spatial_order(points: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices sorting points along a Morton (Z-order) curve of `cell_m` cells: consecutive
    points of a scan then fall into nearby map blocks for every particle (fewer cache
    misses); only the order of a sum changes."""
    key = np.floor(points / cell_m).astype(np.int64)
    key = np.clip(key - key.min(axis=0), 0, (1 << MORTON_BITS) - 1)
    code = np.zeros(len(points), np.int64)
    for bit in range(MORTON_BITS):
        for axis in range(3):
            code |= ((key[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def reduce_scan(points: np.ndarray, cfg: SensorModelConfig, rng: np.random.Generator,
                times_s: np.ndarray | None = None, twist: np.ndarray | None = None
                ) -> np.ndarray:
    """Range gate, one point per `voxel_m` cell (the first), a random subset of M, then
    deskewing of the kept points to the scan stamp when per-point times and the lidar's
    twist (rotation-first, per second, in the lidar frame) are known."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    keep = np.isfinite(pts).all(axis=1)
    r = np.linalg.norm(np.where(keep[:, None], pts, 0.0), axis=1)
    keep &= (r >= cfg.min_range_m) & (r <= cfg.max_range_m)
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return np.zeros((0, 3), np.float32)
    keys = np.floor(pts[idx] / cfg.voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if np.prod(span.astype(np.float64)) < 2.0**62:  # one int64 per cell: np.unique is faster
        keys = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, first = np.unique(keys, axis=0 if keys.ndim == 2 else None, return_index=True)
    idx = idx[np.sort(first)]
    if len(idx) > cfg.points:
        idx = idx[np.sort(rng.choice(len(idx), cfg.points, replace=False))]
    out = pts[idx]
    if times_s is not None and twist is not None and len(times_s) == len(pts):
        out = deskew(out, np.asarray(times_s, dtype=np.float64)[idx], twist)
    return np.ascontiguousarray(out, dtype=np.float32)


@dataclass
class NumpyTsdf:
    """The TSDF on the host (sparse coarse cells -> pool indices + pool), for the NumPy
    twin."""

    coarse: CellLookup  # coarse cell (..., 3) -> pool index, FREE or UNKNOWN
    sdf: np.ndarray  # (nb, 8, 8, 8) float32
    weight: np.ndarray  # (nb, 8, 8, 8) float32
    origin_m: np.ndarray
    voxel_size_m: float
    truncation_m: float

    @staticmethod
    def of(tsdf) -> NumpyTsdf:
        data = tsdf.blocks()  # rows in pool order, so coarse ids index them directly
        return NumpyTsdf(CellLookup(*tsdf.coarse_cells(), tsdf.coarse_dims),
                         data.sdf.astype(np.float32), data.weight.astype(np.float32),
                         np.asarray(tsdf.origin_m, np.float32), tsdf.voxel_size_m,
                         tsdf.truncation_m)

    def lookup(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d, w, block id) of the voxel containing each point of p (..., 3)."""
        g = np.floor((p - self.origin_m) / np.float32(self.voxel_size_m)).astype(np.int64)
        b = self.coarse(g >> 3)
        bi = np.maximum(b, 0)
        loc = g & 7
        d = np.where(b >= 0, self.sdf[bi, loc[..., 0], loc[..., 1], loc[..., 2]],
                     self.truncation_m)
        w = np.where(b >= 0, self.weight[bi, loc[..., 0], loc[..., 1], loc[..., 2]], 0.0)
        return d, w, b


def _observed(d, w, b, trunc: float):
    """Voxels of allocated blocks that were observed. Never-observed voxels hold
    d = +truncation (a map invariant), so, like the kernel, w is only needed there."""
    return (b >= 0) & ((w > 0) | (d < np.float32(trunc) * np.float32(0.999)))


def point_log_likelihood_numpy(d, w, b, trunc: float, cfg: SensorModelConfig,
                               exact: bool = False) -> np.ndarray:
    """The kernel's per-point model; `exact` evaluates the hit term instead of the table."""
    observed = _observed(d, w, b, trunc)
    free = (b == FREE) | (observed & (d >= np.float32(trunc) * np.float32(0.999)))
    hit = observed & ~free
    ll = np.full(np.shape(d), cfg.log_unknown, dtype=np.float64)
    ll[free] = cfg.log_free
    dh = d[hit].astype(np.float64)
    if exact:
        ll[hit] = np.log(cfg.z_hit * np.exp(-0.5 * (dh / cfg.sigma_m) ** 2) + cfg.z_rand)
    else:
        k = ((d[hit] + np.float32(trunc)) * np.float32(TABLE_SIZE * 0.5 / trunc)).astype(np.int64)
        ll[hit] = hit_table(cfg, trunc)[np.clip(k, 0, TABLE_SIZE - 1)]
    return ll


def scan_log_likelihood_numpy(host: NumpyTsdf, positions: np.ndarray, quats_xyzw: np.ndarray,
                              points: np.ndarray, cfg: SensorModelConfig, chunk: int = 1000
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tempered log-likelihood increment, match ratio, mean per-point ll) per particle."""
    n, m = len(positions), len(points)
    out_ll = np.empty(n)
    out_match = np.empty(n)
    pts = points.astype(np.float32)
    for s in range(0, n, chunk):
        R = quat_to_rot(quats_xyzw[s:s + chunk].astype(np.float64)).astype(np.float32)
        p = np.einsum("nij,mj->nmi", R, pts) + positions[s:s + chunk, None, :].astype(np.float32)
        d, w, b = host.lookup(p)
        ll = point_log_likelihood_numpy(d, w, b, host.truncation_m, cfg)
        out_ll[s:s + chunk] = ll.sum(axis=1)
        out_match[s:s + chunk] = (_observed(d, w, b, host.truncation_m)
                                  & (np.abs(d) < cfg.match_dist_m)).mean(1)
    return out_ll * cfg.tempering(m), out_match, out_ll / max(m, 1)


# ----------------------------------------------------------------- the paper's model
def paper_value(d: np.ndarray, cfg: SensorModelConfig, truncation_m: float,
                sigma_m: float) -> np.ndarray:
    """Eq. 3 of the paper times z_hit, d clamped to +-truncation: what the map precomputes
    per voxel for `sensor.model: paper` (mcl3d.kernels.paper_likelihood)."""
    d = np.clip(np.asarray(d, np.float64), -truncation_m, truncation_m)
    return cfg.z_hit * np.exp(-0.5 * (d / sigma_m) ** 2) / np.sqrt(2 * np.pi * sigma_m**2)


def paper_log_likelihood_numpy(host: NumpyTsdf, positions: np.ndarray, quats_xyzw: np.ndarray,
                               points: np.ndarray, cfg: SensorModelConfig, sigma_m: float
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy twin of paper_scan_log_likelihood: (log of the summed per-point terms, match
    ratio, log of their mean) per particle; the values of the eight voxel centres around a
    point are interpolated trilinearly (voxels outside the allocated blocks read d = +trunc)."""
    trunc = host.truncation_m
    R = quat_to_rot(quats_xyzw.astype(np.float64))
    p = np.einsum("nij,mj->nmi", R, points.astype(np.float64)) + positions[:, None, :]
    u = (p - host.origin_m) / host.voxel_size_m - 0.5
    base = np.floor(u)
    f = u - base
    score = np.zeros(p.shape[:2])
    for corner in np.ndindex(2, 2, 2):
        c = np.asarray(corner)
        centre = host.origin_m + (base + c + 0.5) * host.voxel_size_m
        d, _, _ = host.lookup(centre.astype(np.float32))
        weight = np.prod(np.where(c == 1, f, 1.0 - f), axis=-1)
        score += weight * paper_value(d, cfg, trunc, sigma_m)
    total = (score + cfg.z_rand / cfg.max_range_m).sum(axis=1)
    hit = score >= paper_value(cfg.match_dist_m, cfg, trunc, sigma_m)
    return np.log(total), hit.mean(axis=1), np.log(total / max(len(points), 1))
