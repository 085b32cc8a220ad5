"""What each keyframe saw through: a spherical range image per keyframe slot, and the count
of a particle's scan points that fall in that free space (kernels/slam_free_space.py).

Eq. 3 only scores scan points that land in a keyframe voxel, so structure *missing* from a
wrong hypothesis' map costs nothing: a particle one floor too high matches the walls and the
ceiling of the floor below, and its own floor points, floating in that floor's room, go
unscored. The keyframe's beams went through that room; the count here lets the likelihood
charge such points (`likelihood.free_space_cost`).
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from mcl3d.kernels import slam_free_space


def image_shape(bin_deg: float) -> tuple[int, int]:
    """(elevation rows, azimuth columns) of a whole-sphere image of `bin_deg` bins."""
    return int(np.ceil(180.0 / bin_deg)), int(np.ceil(360.0 / bin_deg))


def range_image(points: np.ndarray, bin_deg: float, min_range_m: float,
                max_range_m: float) -> np.ndarray:
    """(rows, cols) f32: the nearest return of each bin of a scan (lidar frame), 0 where
    nothing came back; then, in bins with a return, the nearest return of the 3 × 3 bins
    around it (azimuth wraps), so a beam that missed a thin object between its neighbours
    does not claim the object's place was free. Bins without a return stay 0 (unknown: out
    of the field of view, sky)."""
    rows, cols = image_shape(bin_deg)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    r = np.linalg.norm(pts, axis=1)
    keep = (r >= min_range_m) & (r <= max_range_m)
    pts, r = pts[keep], r[keep]
    bin_rad = np.deg2rad(bin_deg)
    az = np.arctan2(pts[:, 1], pts[:, 0]) + np.pi
    el = np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])) + 0.5 * np.pi
    row = np.clip(np.floor(el / bin_rad).astype(np.int64), 0, rows - 1)
    col = np.floor(az / bin_rad).astype(np.int64) % cols
    image = np.full((rows, cols), np.inf)
    np.minimum.at(image, (row, col), r)
    padded = np.pad(image, ((1, 1), (0, 0)), constant_values=np.inf)
    near = np.full_like(image, np.inf)
    for dr in (0, 1, 2):
        band = padded[dr:dr + rows]
        for dc in (-1, 0, 1):
            near = np.minimum(near, np.roll(band, dc, axis=1))
    out = np.where(np.isfinite(image), near, 0.0)
    return out.astype(np.float32)


class FreeSpace:
    """What every keyframe slot saw through (its range image) and `points_per_keyframe` of
    its points, on the device, allocated for every slot at start (4 bytes per bin: 64.8 kB
    per keyframe at 2° bins), plus the current scan's range image; `count` charges a
    particle's rows both ways: scan points in a keyframe's seen-through space, and keyframe
    points in the scan's."""

    def __init__(self, slots: int, bin_deg: float, min_range_m: float, max_range_m: float,
                 points_per_keyframe: int):
        self.bin_deg, self.min_range_m, self.max_range_m = bin_deg, min_range_m, max_range_m
        rows, cols = image_shape(bin_deg)
        self.images = ti.ndarray(ti.f32, (slots, rows, cols))
        self.images.fill(0.0)
        self.scan_image = ti.ndarray(ti.f32, (rows, cols))
        self.scan_image.fill(0.0)
        self.points_per_keyframe = points_per_keyframe
        self.kf_points = ti.ndarray(ti.f32, (slots, points_per_keyframe, 3))
        self.kf_counts = ti.ndarray(ti.i32, slots)
        self.kf_counts.fill(0)

    @property
    def nbytes(self) -> int:
        return 4 * (int(np.prod(self.images.shape)) + int(np.prod(self.scan_image.shape))
                    + int(np.prod(self.kf_points.shape)) + int(self.kf_counts.shape[0]))

    def _image(self, points_lidar: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(range_image(points_lidar, self.bin_deg, self.min_range_m,
                                                self.max_range_m))

    def store(self, slot: int, points_lidar: np.ndarray, cloud: np.ndarray) -> None:
        """The keyframe in `slot` is the scan `points_lidar` (its own lidar frame), `cloud`
        its downsampled points (thinned evenly to `points_per_keyframe`)."""
        slam_free_space.set_image(slot, self._image(points_lidar), self.images)
        cloud = np.asarray(cloud, np.float32).reshape(-1, 3)
        if len(cloud) > self.points_per_keyframe:
            cloud = cloud[np.linspace(0, len(cloud) - 1, self.points_per_keyframe).astype(int)]
        rows = np.zeros((self.points_per_keyframe, 3), np.float32)
        rows[:len(cloud)] = cloud
        slam_free_space.set_points(slot, rows, len(cloud), self.kf_points, self.kf_counts)

    def set_scan(self, points_lidar: np.ndarray) -> None:
        """The scan being weighed (its lidar frame)."""
        self.scan_image.from_numpy(self._image(points_lidar))

    def count(self, particles, points_field, num_src: int, stride: int, margin_m: float,
              margin_frac: float, counts) -> None:
        """counts[3 i + j]: particle i's scan points (every `stride`-th of the `num_src` in
        `points_field`) in neighbour j's seen-through space, plus neighbour j's points in
        the scan's seen-through space."""
        p = particles
        args = (np.deg2rad(self.bin_deg), self.min_range_m, margin_m, margin_frac, counts)
        slam_free_space.seen_through(p.n, num_src, stride, points_field, p.kf, p.q_cur,
                                     p.t_cur, p.nb, self.images, *args)
        slam_free_space.keyframes_seen_through(p.n, self.kf_points, self.kf_counts, p.kf,
                                               p.q_cur, p.t_cur, p.nb, self.scan_image, *args)
