"""Gaussian voxel maps on the device: the registration target shared by every pose.

`GaussianVoxelMaps` is one fixed-capacity hash table (kernels/voxel_hash.py) holding up to
`max_maps` maps (keyframes, resolution levels), each built and updated incrementally on the
device from points with covariances. A voxel keeps the mean of its points and the average of
their covariances; a registration looks up exactly one voxel per point.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from mcl3d.core import runtime
from mcl3d.core.errors import ConfigError, MapError, PointCloudError
from mcl3d.core.geometry import rot_to_quat
from mcl3d.kernels import upload, voxel_hash

GPU_LAUNCH_POINTS = 16384  # points per ordered launch off the cpu: one GPU thread takes them
# in order, and Mesa's lavapipe stops any loop of one thread after 65,535 iterations
SERIAL_LOOKUPS = 1 << 16  # fewer voxel lookups: on the calling thread on cpu (~1 ms)
MAX_PROBES = 128  # slots a voxel may sit past its home: at half load a run past 32 came once
# in ~45 SLAM keyframe maps of 2,048 points and ended the run; lookups stop at an empty slot


def ensure_runtime():
    """The running Taichi runtime, starting `auto` when the caller has not chosen one."""
    return runtime.current() or runtime.init("auto")


def check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """(N, 3) finite float64 array, or a PointCloudError naming `name`."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise PointCloudError(f"{name} must be an (N, 3) array of x, y, z; got shape {arr.shape}")
    arr = arr[:, :3]
    if not np.isfinite(arr).all():
        raise PointCloudError(f"{name} contains NaN or inf coordinates; drop them first")
    return arr


def check_pose(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ConfigError(f"{name} must be a finite 4x4 pose matrix; got shape {T.shape}")
    if np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-3:
        raise ConfigError(f"{name} does not hold a rotation matrix (R R^T != I)")
    return T


class GaussianVoxelMaps:
    """Up to `max_maps` Gaussian voxel maps in one device hash table of fixed capacity.

    Each map has `buckets_per_map` slots (a power of two; keep the voxel count under about
    half of it) and its own voxel size. Points are staged `max_points` at a time. Kernels
    take the maps as one `ti.template()` and read the table `vox` and the voxel sizes `res`.
    """

    _data_oriented = True  # passed to kernels as one ti.template() (see gicp_state)

    def __init__(self, max_maps: int = 8, buckets_per_map: int = 1 << 16,
                 max_points: int = 131072, max_probes: int = MAX_PROBES):
        if max_maps < 1 or max_points < 1 or max_probes < 1:
            raise ConfigError("max_maps, max_points and max_probes must be >= 1")
        if buckets_per_map < 16 or buckets_per_map & (buckets_per_map - 1):
            raise ConfigError(
                f"buckets_per_map must be a power of two >= 16, got {buckets_per_map}")
        if max_maps * buckets_per_map > 1 << 26:
            raise ConfigError("max_maps * buckets_per_map must stay under 2^26 slots")
        self.runtime = ensure_runtime()
        self.max_maps, self.buckets, self.max_points = max_maps, buckets_per_map, max_points
        self.max_probes = max_probes
        slots = max_maps * buckets_per_map
        self.vox = voxel_hash.Voxel.field(shape=slots, layout=ti.Layout.AOS)
        self.vsum = ti.Vector.field(3, ti.f32, slots)
        self.vsumcov = ti.Matrix.field(3, 3, ti.f32, slots)
        self.res = ti.field(ti.f32, max_maps)
        self.pts = ti.Vector.field(3, ti.f32, max_points)
        self.covs = ti.Matrix.field(3, 3, ti.f32, max_points)
        self.coord = ti.Vector.field(3, ti.i32, max_points)
        self.probe = ti.field(ti.i32, max_points)
        self.slot = ti.field(ti.i32, max_points)
        self.counter = ti.field(ti.i32, ())
        self._voxel_size = [0.0] * max_maps  # 0: not usable until clear() gives a size
        self._num_voxels = [0] * max_maps
        voxel_hash.clear_region(self.vox, self.vsum, self.vsumcov, 0, slots)

    def _region(self, map_id: int) -> tuple[int, int]:
        if not 0 <= map_id < self.max_maps:
            raise ConfigError(f"map id {map_id} is outside 0..{self.max_maps - 1} (max_maps)")
        return map_id * self.buckets, (map_id + 1) * self.buckets

    def voxel_size(self, map_id: int) -> float:
        self._region(map_id)
        return self._voxel_size[map_id]

    def num_voxels(self, map_id: int) -> int:
        self._region(map_id)
        return self._num_voxels[map_id]

    def clear(self, map_id: int, voxel_size_m: float) -> None:
        """Empty map `map_id` and give it a voxel size."""
        begin, end = self._region(map_id)
        if not np.isfinite(voxel_size_m) or voxel_size_m <= 0:
            raise ConfigError(f"voxel_size_m must be > 0, got {voxel_size_m}")
        voxel_hash.clear_region(self.vox, self.vsum, self.vsumcov, begin, end)
        self.res[map_id] = voxel_size_m
        self._voxel_size[map_id] = float(voxel_size_m)
        self._num_voxels[map_id] = 0

    def insert(self, map_id: int, points: np.ndarray, covs: np.ndarray,
               T_map_points: np.ndarray | None = None) -> int:
        """Add points (N, 3) with covariances (N, 3, 3), given in a frame placed in the map by
        `T_map_points`, to map `map_id`; returns the map's voxel count afterwards."""
        self._region(map_id)
        if self._voxel_size[map_id] <= 0:
            raise MapError(f"map {map_id} has no voxel size: call clear(map_id, voxel_size_m)")
        pts = check_points(points)
        covs = np.asarray(covs, dtype=np.float64)
        if covs.shape != (len(pts), 3, 3):
            raise PointCloudError(f"covs must have shape ({len(pts)}, 3, 3), got {covs.shape}")
        T = check_pose(np.eye(4) if T_map_points is None else T_map_points, "T_map_points")
        for start in range(0, len(pts), self.max_points):
            chunk = slice(start, start + self.max_points)
            n = len(pts[chunk])
            upload.vector_rows(np.ascontiguousarray(pts[chunk], np.float32), n, self.pts)
            upload.matrix_rows(np.ascontiguousarray(covs[chunk], np.float32), n, self.covs)
            self._add_staged(map_id, n, T)
        return self._finalize(map_id)

    def insert_rows(self, map_id: int, pts, rows, n: int, plane: bool,
                    T_map_points: np.ndarray | None = None) -> int:
        """`insert` for points already on the device: the first `n` of the vec3 field `pts`
        with covariance rows `rows` (upper triangles xx xy xz yy yz zz, or (n, α, β, 0) for
        αI + βnnᵀ when `plane`), e.g. a BatchGicp's source pool: no host round trip."""
        self._region(map_id)
        if self._voxel_size[map_id] <= 0:
            raise MapError(f"map {map_id} has no voxel size: call clear(map_id, voxel_size_m)")
        if not 0 <= n <= self.max_points:
            raise ConfigError(f"insert_rows takes at most {self.max_points} points, got {n}")
        T = check_pose(np.eye(4) if T_map_points is None else T_map_points, "T_map_points")
        if n:
            voxel_hash.stage_rows(pts, rows, n, bool(plane), self.pts, self.covs)
            self._add_staged(map_id, n, T)
        return self._finalize(map_id)

    def _add_staged(self, map_id: int, n: int, T: np.ndarray) -> None:
        """Add the `n` staged points (their frame placed in the map by T) to map `map_id`."""
        res = self._voxel_size[map_id]
        voxel_hash.begin_insert(self.pts, self.covs, n, T.astype(np.float32), res,
                                self.coord, self.probe, self.slot)
        self._settle(map_id, n)
        step = max(n, 1) if self.runtime.backend == "cpu" else GPU_LAUNCH_POINTS
        lost = sum(voxel_hash.accumulate(self.pts, self.covs, self.slot, begin,
                                         min(begin + step, n), res, self.vox, self.vsum,
                                         self.vsumcov) for begin in range(0, n, step))
        if lost:
            raise MapError(
                f"voxel map {map_id}: {lost} points found no free slot within "
                f"{self.max_probes} probes (raise buckets_per_map, now {self.buckets}, or the "
                f"voxel size) or lie over 2^20 voxels from the map's origin")

    def _finalize(self, map_id: int) -> int:
        begin, end = self._region(map_id)
        self._num_voxels[map_id] = voxel_hash.finalize(
            self.vox, self.vsum, self.vsumcov, self._voxel_size[map_id], begin, end)
        return self._num_voxels[map_id]

    def _settle(self, map_id: int, n: int) -> None:
        args = (self.coord, self.probe, self.slot, n, map_id, self.buckets, self.vox)
        for _ in range(self.max_probes + 1):
            voxel_hash.claim_slots(*args)
            voxel_hash.commit_slots(*args)
            if voxel_hash.resolve_slots(*args, self.max_probes) == 0:
                return

    def voxels(self, map_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(means (V, 3), covariances (V, 3, 3)) of map `map_id`, in no particular order."""
        begin, end = self._region(map_id)
        v = self._num_voxels[map_id]
        means = np.zeros((max(v, 1), 3), np.float32)
        covs = np.zeros((max(v, 1), 3, 3), np.float32)
        self.counter[None] = 0
        voxel_hash.gather_voxels(self.vox, begin, end, means, covs, self.counter)
        return means[:v].astype(np.float64), covs[:v].astype(np.float64)

    def overlap(self, points: np.ndarray, map_ids: list[int],
                T_map_points: list[np.ndarray]) -> float:
        """Fraction of `points` that land in an occupied voxel of at least one of `map_ids`,
        point set placed in map k by T_map_points[k] (the keyframe-insertion test)."""
        pts = check_points(points)
        if len(map_ids) != len(T_map_points) or not 1 <= len(map_ids) <= self.max_maps:
            raise ConfigError("overlap needs one pose per map id and 1..max_maps maps")
        if len(pts) == 0:
            return 0.0
        queries = self._queries(map_ids, T_map_points)
        hits = 0
        for start in range(0, len(pts), self.max_points):
            chunk = np.ascontiguousarray(pts[start:start + self.max_points], np.float32)
            upload.vector_rows(chunk, len(chunk), self.pts)
            hits += voxel_hash.count_hits(self.pts, len(chunk), queries, len(map_ids), self.res,
                                          self.buckets, self.max_probes, self.vox)
        return hits / len(pts)

    def overlap_of(self, pts, n: int, map_ids: list[int],
                   T_map_points: list[np.ndarray]) -> float:
        """`overlap` of the first `n` points of a device vec3 field (a BatchGicp's source
        pool): no upload."""
        if len(map_ids) != len(T_map_points) or not 1 <= len(map_ids) <= self.max_maps:
            raise ConfigError("overlap needs one pose per map id and 1..max_maps maps")
        if n <= 0:
            return 0.0
        hits = voxel_hash.count_hits(pts, n, self._queries(map_ids, T_map_points),
                                     len(map_ids), self.res, self.buckets, self.max_probes,
                                     self.vox)
        return hits / n

    def overlaps_of(self, pts, n: int, map_ids: list[int], T_map_points: list[np.ndarray],
                    stride: int = 1) -> np.ndarray:
        """Each map's own overlap (`overlap_of` with that map alone) of the first `n` points of
        a device vec3 field, estimated from every `stride`-th point; one launch for all."""
        if len(map_ids) != len(T_map_points) or not 1 <= len(map_ids) <= self.max_maps:
            raise ConfigError("overlap needs one pose per map id and 1..max_maps maps")
        if stride < 1:
            raise ConfigError(f"stride must be >= 1, got {stride}")
        hits = np.zeros(len(map_ids), np.int32)
        if n <= 0:
            return hits.astype(np.float64)
        samples = (n + stride - 1) // stride
        serial = self.runtime.backend == "cpu" and samples * len(map_ids) <= SERIAL_LOOKUPS
        voxel_hash.count_hits_each(pts, n, stride, self._queries(map_ids, T_map_points),
                                   len(map_ids), self.res, self.buckets, self.max_probes,
                                   self.vox, hits, serial)
        return hits / samples

    def _queries(self, map_ids: list[int], T_map_points: list[np.ndarray]) -> np.ndarray:
        """Rows (map id, qx, qy, qz, qw, tx, ty, tz) for count_hits, checked."""
        for m in set(map_ids):
            self._region(m)
            if self._voxel_size[m] <= 0:
                raise MapError(f"map {m} was never cleared/filled: it has no voxel size")
        T = np.stack([check_pose(T, "T_map_points") for T in T_map_points])
        return np.c_[map_ids, rot_to_quat(T[:, :3, :3]), T[:, :3, 3]].astype(np.float32)
