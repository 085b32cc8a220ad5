"""GICP for a batch of poses against Gaussian voxel maps, on the device.

`BatchGicp` owns fixed-capacity containers (gicp_state: the source pool, rows, per-pose
optimizer state) and drives kernels/gicp.py: one `iterate` launch (linearize, reduce, step)
per Gauss-Newton/LM iteration for the whole batch. One pose (pairwise registration), a scan
against several keyframe maps, and 10,000 particles x 3 keyframes all go through the same
kernel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import taichi as ti

from mcl3d.core.errors import ConfigError, PointCloudError
from mcl3d.core.geometry import quat_to_rot, se3
from mcl3d.kernels import gicp
from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps, check_points
from mcl3d.registration.gicp_state import GicpPoses, GicpRows, GicpSums, SourcePool
from mcl3d.registration.preprocess import download_rows, plane_rows_to_covs

STATUS_NAMES = ("running", "converged", "no correspondences", "stalled")
SERIAL_GROUPS = 64  # fewer poses: reset and read them back on the calling thread
SERIAL_CORRESPONDENCES = 1 << 15  # fewer: iterate on the calling thread (~0.25 ms on cpu)
SURFACE_VALIDATION_COS = 0.174  # cos 80°: GLIM's threshold (kernels/gicp.faces_map)
PLANE_FORM_RTOL = 1e-6  # what plane_form may change of a covariance, relative to its largest entry


def plane_form(covs: np.ndarray) -> np.ndarray | None:
    """(N, 6) rows (n, α, β, 0) with covs[i] = α I + β n nᵀ (unit n), or None when some
    covariance is not of that form (three distinct eigenvalues).

    Plane-regularized covariances (eigenvalues ε, 1, 1) and identities are, and the GICP kernel
    rotates them for less than half the cost of a general one. Closed-form eigenvalues on the
    six unique entries keep this cheap enough for every scan (numpy's eigh is ~1 µs a matrix).
    """
    xx, yy, zz = covs[:, 0, 0], covs[:, 1, 1], covs[:, 2, 2]
    xy = 0.5 * (covs[:, 0, 1] + covs[:, 1, 0])
    xz = 0.5 * (covs[:, 0, 2] + covs[:, 2, 0])
    yz = 0.5 * (covs[:, 1, 2] + covs[:, 2, 1])
    q = (xx + yy + zz) / 3.0
    dx, dy, dz = xx - q, yy - q, zz - q
    p = np.sqrt((dx * dx + dy * dy + dz * dz + 2 * (xy * xy + xz * xz + yz * yz)) / 6.0)
    det = dx * (dy * dz - yz * yz) - xy * (xy * dz - yz * xz) + xz * (xy * yz - dy * xz)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(p > 0, det / (2 * p ** 3), 1.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    hi = q + 2 * p * np.cos(phi)
    lo = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    mid = 3 * q - hi - lo
    low_pair = mid - lo < hi - mid  # the two equal eigenvalues are (lo, mid), else (mid, hi)
    alpha = np.where(low_pair, 0.5 * (lo + mid), 0.5 * (mid + hi))
    beta = np.where(low_pair, hi, lo) - alpha
    # C - αI = β n nᵀ: n from its column with the largest diagonal entry
    dxx, dyy, dzz = xx - alpha, yy - alpha, zz - alpha
    pick_x = (np.abs(dxx) >= np.abs(dyy)) & (np.abs(dxx) >= np.abs(dzz))
    pick_y = ~pick_x & (np.abs(dyy) >= np.abs(dzz))
    n = np.where(pick_x[:, None], np.stack([dxx, xy, xz], 1),
                 np.where(pick_y[:, None], np.stack([xy, dyy, yz], 1), np.stack([xz, yz, dzz], 1)))
    norm = np.sqrt((n * n).sum(axis=1))
    n = np.where(norm[:, None] > 0, n / np.where(norm > 0, norm, 1.0)[:, None], [1.0, 0.0, 0.0])
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    entries = ((xx, alpha + beta * nx * nx), (yy, alpha + beta * ny * ny),
               (zz, alpha + beta * nz * nz), (xy, beta * nx * ny), (xz, beta * nx * nz),
               (yz, beta * ny * nz))
    scale = np.maximum.reduce([np.abs(c) for c, _ in entries])
    worst = np.maximum.reduce([np.abs(c - r) for c, r in entries])
    if not (worst <= PLANE_FORM_RTOL * scale).all():
        return None
    return np.c_[n, alpha, beta, np.zeros(len(covs))]


def pose_rows(T: np.ndarray, n: int) -> np.ndarray:
    """(n, 12) f32 rows (R row-major, t) of 4x4 poses (one pose is repeated) for the kernels,
    which turn them into quaternions: cheaper than converting on the host per scan."""
    T = np.asarray(T, np.float64).reshape(-1, 4, 4)
    if len(T) not in (1, n) or not np.isfinite(T).all():
        raise ConfigError(f"expected {n} finite 4x4 poses, got shape {T.shape}")
    out = np.empty((n, 12), np.float32)
    out[:, :9] = T[:, :3, :3].reshape(-1, 9)
    out[:, 9:] = T[:, :3, 3]
    return out


@dataclass
class BatchResult:
    """Per pose: the optimized pose, and H, b, error, inliers at that pose (see kernels/gicp)."""

    T: np.ndarray  # (G, 4, 4) T_frame_source
    H: np.ndarray  # (G, 6, 6) Gauss-Newton Hessian, rotation first
    b: np.ndarray  # (G, 6)
    error: np.ndarray  # (G,) 0.5 * sum e^T M e
    num_inliers: np.ndarray  # (G,)
    iterations: np.ndarray  # (G,) linearizations used
    status: np.ndarray  # (G,) 0 running (out of iterations), 1 converged, 2 lost, 3 stalled
    overlap: np.ndarray | None = None  # (G,) when asked for: see BatchGicp.result

    @property
    def converged(self) -> np.ndarray:
        return self.status == 1


class BatchGicp:
    """Containers sized once: `poses` (`max_groups` poses), `rows` (`max_rows` (pose, map)
    terms), and `pool` (`max_source_points` source points with covariances shared by all
    rows)."""

    def __init__(self, maps: GaussianVoxelMaps, max_groups: int = 1, max_rows: int | None = None,
                 max_source_points: int = 65536):
        max_rows = max_groups if max_rows is None else max_rows
        if min(max_groups, max_rows, max_source_points) < 1:
            raise ConfigError("max_groups, max_rows and max_source_points must be >= 1")
        self.maps = maps
        self.max_groups, self.max_rows, self.max_source_points = max_groups, max_rows, \
            max_source_points
        # padded: a block of lookups may read up to LOOKAHEAD - 1 points past a row's end;
        # structure of arrays, so that a block loads them as whole vectors
        self.pool = SourcePool(max_source_points, padding=gicp.LOOKAHEAD, layout=ti.Layout.SOA)
        self.rows = GicpRows(max_rows)
        self.poses = GicpPoses(max_groups)
        self.num_source = 0
        self.plane_covs = False  # pool.cov_rows hold (n, α, β, 0), see plane_form
        self._tasks: GicpSums | None = None  # per-task sums of a split linearization
        self.serial_correspondences = SERIAL_CORRESPONDENCES if maps.runtime.backend == "cpu" \
            else 0

    def set_source(self, points: np.ndarray, covs: np.ndarray) -> None:
        """Upload the source pool (points in the source frame, covariances (N, 3, 3)).
        Covariances of the form αI + βnnᵀ (all plane-regularized ones) take the faster path."""
        pts = check_points(points, "source points")
        covs = np.asarray(covs, dtype=np.float64)
        if covs.shape != (len(pts), 3, 3):
            raise PointCloudError(f"source covs must have shape ({len(pts)}, 3, 3), "
                                  f"got {covs.shape}")
        if len(pts) > self.max_source_points:
            raise ConfigError(f"source has {len(pts)} points; this GICP holds at most "
                              f"{self.max_source_points} (downsample more or raise the capacity)")
        rows = plane_form(covs)
        self.plane_covs = rows is not None
        if rows is None:
            iu, ju = np.triu_indices(3)
            rows = 0.5 * (covs[:, iu, ju] + covs[:, ju, iu])
        if len(pts):
            gicp.upload_source(np.ascontiguousarray(np.c_[pts, rows], np.float32), len(pts),
                               self.pool, self.maps.runtime.backend == "cpu")
        self.num_source = len(pts)

    def use_device_source(self, num_points: int, plane_covs: bool) -> None:
        """Take the first `num_points` of `pool` as the source, written there on the device
        (preprocess.ScanGrid): rows (n, α, β, 0) when `plane_covs`, else upper triangles
        (xx xy xz yy yz zz)."""
        if not 0 <= num_points <= self.max_source_points:
            raise ConfigError(f"source has {num_points} points; this GICP holds at most "
                              f"{self.max_source_points}")
        self.num_source = int(num_points)
        self.plane_covs = bool(plane_covs)

    def source(self) -> tuple[np.ndarray, np.ndarray]:
        """The source pool back on the host: points (N, 3) and covariances (N, 3, 3)."""
        pts, rows = download_rows(self.pool, self.num_source)
        if self.plane_covs:
            return pts, plane_rows_to_covs(rows)
        iu, ju = np.triu_indices(3)
        covs = np.zeros((len(pts), 3, 3))
        covs[:, iu, ju] = rows
        covs[:, ju, iu] = rows
        return pts, covs

    def set_problem(self, T_init: np.ndarray, row_group: np.ndarray, row_map: np.ndarray,
                    T_left: np.ndarray | None = None, row_start: np.ndarray | None = None,
                    row_count: np.ndarray | None = None, lm_lambda: float = 1e-3) -> int:
        """Upload initial poses (G, 4, 4) and rows; row r registers source points
        [row_start, row_start + row_count) into map row_map[r] at pose T_left[r] @ T[group]."""
        T_init = np.asarray(T_init, dtype=np.float64).reshape(-1, 4, 4)
        G = len(T_init)
        row_group = np.asarray(row_group, dtype=np.int32).ravel()
        row_map = np.asarray(row_map, dtype=np.int32).ravel()
        R = len(row_group)
        if not 1 <= G <= self.max_groups or not 1 <= R <= self.max_rows:
            raise ConfigError(f"{G} poses and {R} rows do not fit this GICP "
                              f"(max {self.max_groups} poses, {self.max_rows} rows)")
        if row_map.shape != (R,) or row_group.min() < 0 or row_group.max() >= G:
            raise ConfigError("row_group must index the poses and row_map must match it")
        if row_map.min() < 0 or row_map.max() >= self.maps.max_maps:
            raise ConfigError(f"row_map holds a map id outside 0..{self.maps.max_maps - 1}")
        if min(self.maps.voxel_size(int(m)) for m in set(row_map.tolist())) <= 0:
            raise ConfigError("a row refers to a map that was never filled")
        if not np.isfinite(T_init).all():
            raise ConfigError("initial poses contain NaN or inf")
        start = np.zeros(R, np.int32) if row_start is None else np.asarray(row_start, np.int32)
        count = (np.full(R, self.num_source, np.int32) if row_count is None
                 else np.asarray(row_count, np.int32))
        if (start < 0).any() or (start + count > self.num_source).any():
            raise ConfigError(f"row point ranges exceed the {self.num_source} source points")
        rows_i = np.empty((R, 4), np.int32)
        rows_i[:, 0], rows_i[:, 1], rows_i[:, 2], rows_i[:, 3] = row_group, row_map, start, count
        rows_f = pose_rows(np.eye(4)[None] if T_left is None else T_left, R)
        gicp.upload_problem(rows_i, rows_f, R, pose_rows(T_init, G), G, lm_lambda, self.rows,
                            self.poses, self._serial_groups(G))
        self._started(G, R, int(count.max()), one_row_per_group=len(np.unique(row_group)) == R)
        return G

    def start(self, num_groups: int, num_rows: int, max_row_points: int,
              lm_lambda: float = 1e-3, one_row_per_group: bool = False) -> None:
        """Begin an optimization of the first `num_groups` poses in poses (q_cand, t_cand) over
        the first `num_rows` rows. `set_problem` calls it; a caller that fills those fields on the
        device (particles, keyframe poses) calls it directly and skips the host round trip.
        `one_row_per_group` (no two rows share a pose) lets whole-row tasks skip atomics."""
        if not (1 <= num_groups <= self.max_groups and 1 <= num_rows <= self.max_rows):
            raise ConfigError(f"{num_groups} poses and {num_rows} rows do not fit this GICP")
        gicp.reset_groups(num_groups, lm_lambda, self.poses, self._serial_groups(num_groups))
        self._started(num_groups, num_rows, max_row_points, one_row_per_group)

    def _started(self, num_groups: int, num_rows: int, max_row_points: int,
                 one_row_per_group: bool) -> None:
        self._rows, self._groups, self._max_count = num_rows, num_groups, max_row_points
        self._one_row_per_group = one_row_per_group

    def default_chunk(self) -> int:
        """Points per task: whole rows when the batch alone fills the threads (few atomics on
        cpu) or runs on one thread anyway (`serial_correspondences`), smaller chunks so that
        one pose still spreads over every thread or GPU lane."""
        if self._serial():
            return self._max_count
        tasks = 256 if self.maps.runtime.backend == "cpu" else 65536
        work = self._rows * self._max_count
        return int(min(self._max_count, max(64, -(-work // tasks))))

    def iterate(self, use_lm: bool = False, rotation_eps_rad: float = 1e-3 * np.pi / 180,
                translation_eps_m: float = 1e-4, chunk: int | None = None,
                validate_surfaces: bool = False, cost_cap: float = math.inf) -> int:
        """One linearization of every running pose plus one solve; returns how many run on.
        `validate_surfaces` drops plane points whose surface faces away from the sensor of the
        map they are matched in (the map's origin; keyframe maps in their lidar frame).
        `cost_cap`: no point adds more than this to the error ½ Σ eᵀMe (a truncated cost)."""
        maps = self.maps
        if chunk is None:
            chunk = self.default_chunk()
        num_chunks = (self._max_count + chunk - 1) // chunk
        exclusive = self._one_row_per_group and num_chunks == 1
        tasks = self.poses.acc if exclusive else self._task_sums(self._rows * num_chunks)
        return gicp.iterate(self.pool, self.rows, self._rows, chunk, num_chunks, maps,
                            maps.buckets, maps.max_probes, tasks, self.poses, self._groups,
                            int(use_lm), rotation_eps_rad, translation_eps_m,
                            SURFACE_VALIDATION_COS if validate_surfaces else 2.0, cost_cap,
                            exclusive, self.plane_covs, self._one_row_per_group, self._serial())

    def _serial_groups(self, num_groups: int) -> bool:
        """Few poses on cpu: their per-pose loops on the calling thread. Never on a GPU, where
        one thread is slow, and where lavapipe's loop limiter cut a long serial overlap count
        short."""
        return num_groups < SERIAL_GROUPS and self.maps.runtime.backend == "cpu"

    def _serial(self) -> bool:
        """Few correspondences: the whole iteration on the calling thread (see gicp.linearize)."""
        return self._rows * self._max_count <= self.serial_correspondences

    def _task_sums(self, tasks: int) -> GicpSums:
        """Per-task sums for a split linearization (grown on demand, never shrunk)."""
        if self._tasks is None or self._tasks.n.shape[0] < tasks:
            self._tasks = GicpSums(1 << max(6, (tasks - 1).bit_length()))
        return self._tasks

    def optimize(self, max_iterations: int = 20, use_lm: bool = False,
                 rotation_eps_rad: float = 1e-3 * np.pi / 180,
                 translation_eps_m: float = 1e-4, overlap_maps: list[int] | None = None,
                 overlap_T_left: np.ndarray | None = None,
                 validate_surfaces: bool = False) -> BatchResult:
        """Iterate until every pose converged or `max_iterations` linearizations were used,
        then `result` (with the overlap when `overlap_maps` are given).
        With max_iterations=1 this only evaluates H, b, error at the initial poses."""
        if max_iterations < 1:
            raise ConfigError(f"max_iterations must be >= 1, got {max_iterations}")
        for _ in range(max_iterations):
            if self.iterate(use_lm, rotation_eps_rad, translation_eps_m,
                            validate_surfaces=validate_surfaces) == 0:
                break
        return self.result(overlap_maps, overlap_T_left)

    def result(self, overlap_maps: list[int] | None = None,
               overlap_T_left: np.ndarray | None = None) -> BatchResult:
        """The current state of every pose. With `overlap_maps`, also each pose's overlap: the
        fraction of the source pool that lands in an occupied voxel of at least one of those
        maps, the pool placed in map k at `overlap_T_left[k] @ T` (list the likeliest first).
        One launch either way."""
        G = self._groups
        maps = self.maps
        queries = np.zeros((1, 13), np.float32)
        num_queries = 0
        if overlap_maps is not None:
            ids = np.asarray(overlap_maps, np.int64).ravel()
            T_left = np.asarray(overlap_T_left, np.float64).reshape(-1, 4, 4)
            if len(ids) != len(T_left) or len(ids) == 0:
                raise ConfigError("overlap needs one left pose per map and at least one map")
            if ids.min() < 0 or ids.max() >= maps.max_maps or \
                    min(maps.voxel_size(int(m)) for m in ids) <= 0:
                raise ConfigError("overlap lists a map that does not exist or was never filled")
            queries = np.empty((len(ids), 13), np.float32)
            queries[:, 0] = ids
            queries[:, 1:] = pose_rows(T_left, len(ids))
            num_queries = len(ids)
        out = np.empty((G, gicp.RESULT_COLUMNS), np.float32)
        gicp.download_results(G, self.poses, self.pool, self.num_source if num_queries else 0,
                              queries, num_queries, maps, maps.buckets, maps.max_probes, out,
                              self._serial_groups(G), num_queries > 0)
        out = out.astype(np.float64)
        return BatchResult(
            T=se3(quat_to_rot(out[:, :4]), out[:, 4:7]),
            H=out[:, 7:43].reshape(G, 6, 6),
            b=out[:, 43:49],
            error=out[:, 49],
            num_inliers=out[:, 50].astype(np.int64),
            iterations=out[:, 51].astype(np.int64),
            status=out[:, 52].astype(np.int64),
            overlap=out[:, 53] / max(self.num_source, 1) if num_queries else None,
        )
