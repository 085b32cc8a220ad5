"""Free space a keyframe saw through, as evidence against a particle (docs/slam.md).

Eq. 3 scores only the scan points that land in a keyframe voxel; a point that lands nowhere
costs nothing, so a pose whose points miss the map (a floor that does not exist, a heading
that puts trunks beside the keyframe's trunks) is never charged. Each keyframe keeps a
spherical range image in its lidar frame (`bins_el` × `bins_az` bins of `bin_rad`, the
nearest return per bin, 0 where nothing came back). A scan point taken into a neighbour
keyframe's frame that lies nearer than that keyframe's return in its bin, by more than
max(margin_m, margin_frac × return), is in space the keyframe's beam went through: the pose
that put it there is contradicted.

Rows are (particle, neighbour) pairs `g = 3 i + j` as in kernels/slam.py; each row counts
its own points serially (no atomics), so counts are reproducible.
"""

import math

import taichi as ti

from mcl3d.kernels.se3 import pose_compose, pose_inverse, quat_rotate
from mcl3d.kernels.slam import NEIGHBOURS, load_keyframe

vec3 = ti.math.vec3


@ti.func
def image_bin(p: vec3, bin_rad: ti.f32, bins_el: ti.i32, bins_az: ti.i32):
    """(elevation row, azimuth column) of direction p: azimuth from -π, elevation from -π/2."""
    r_xy = ti.sqrt(p[0] * p[0] + p[1] * p[1])
    az = ti.atan2(p[1], p[0]) + math.pi
    el = ti.atan2(p[2], r_xy) + 0.5 * math.pi
    row = ti.min(ti.max(ti.cast(ti.floor(el / bin_rad), ti.i32), 0), bins_el - 1)
    col = ti.cast(ti.floor(az / bin_rad), ti.i32) % bins_az
    return row, col


@ti.func
def nearer(r: ti.f32, seen: ti.f32, min_range_m: ti.f32, margin_m: ti.f32,
           margin_frac: ti.f32) -> ti.i32:
    """1 when a point at range r (not under `min_range_m`) lies nearer than the return
    `seen` of its bin (0: none) by more than max(margin_m, margin_frac × seen)."""
    return ti.select(r >= min_range_m and seen > 0.0
                     and r + ti.max(margin_m, margin_frac * seen) < seen, 1, 0)


@ti.kernel
def seen_through(n: ti.i32, num_src: ti.i32, stride: ti.i32, points: ti.template(),
                 kf: ti.types.ndarray(ndim=3), q_cur: ti.template(), t_cur: ti.template(),
                 nb: ti.template(), images: ti.types.ndarray(ndim=3), bin_rad: ti.f32,
                 min_range_m: ti.f32, margin_m: ti.f32, margin_frac: ti.f32,
                 counts: ti.template()):
    """counts[3 i + j]: how many of the scan points 0, stride, 2 stride, ... (lidar frame),
    placed at particle i's pose, lie in keyframe nb[i, j]'s seen-through space (0 for a row
    without a keyframe). Points nearer the keyframe than `min_range_m` are not judged."""
    bins_el = images.shape[1]
    bins_az = images.shape[2]
    for i, j in ti.ndrange(n, NEIGHBOURS):
        k = nb[i, j]
        count = 0
        if k >= 0:
            q_kf, t_kf = load_keyframe(kf, i, k)
            q_inv, t_inv = pose_inverse(q_kf, t_kf)
            q, t = pose_compose(q_inv, t_inv, q_cur[i], t_cur[i])
            for s in range((num_src + stride - 1) // stride):
                p = quat_rotate(q, points[s * stride]) + t
                row, col = image_bin(p, bin_rad, bins_el, bins_az)
                count += nearer(p.norm(), images[k, row, col], min_range_m, margin_m,
                                margin_frac)
        counts[i * NEIGHBOURS + j] = count


@ti.kernel
def set_image(slot: ti.i32, image: ti.types.ndarray(ndim=2), images: ti.types.ndarray(ndim=3)):
    """images[slot] = image."""
    for r, c in ti.ndrange(image.shape[0], image.shape[1]):
        images[slot, r, c] = image[r, c]


@ti.kernel
def keyframes_seen_through(n: ti.i32, kf_points: ti.types.ndarray(ndim=3),
                           kf_counts: ti.types.ndarray(ndim=1), kf: ti.types.ndarray(ndim=3),
                           q_cur: ti.template(), t_cur: ti.template(), nb: ti.template(),
                           image: ti.types.ndarray(ndim=2), bin_rad: ti.f32,
                           min_range_m: ti.f32, margin_m: ti.f32, margin_frac: ti.f32,
                           counts: ti.template()):
    """The other way round: counts[3 i + j] += how many of keyframe nb[i, j]'s points
    (`kf_points[k, :kf_counts[k]]`, its lidar frame), placed by particle i's map into the
    particle's current lidar frame, lie nearer than the scan's own return (`image`, the
    scan's range image): the scan saw through a surface that keyframe put there (a ceiling
    under a pose one floor too high)."""
    bins_el = image.shape[0]
    bins_az = image.shape[1]
    for i, j in ti.ndrange(n, NEIGHBOURS):
        k = nb[i, j]
        count = 0
        if k >= 0:
            q_kf, t_kf = load_keyframe(kf, i, k)
            q_inv, t_inv = pose_inverse(q_cur[i], t_cur[i])
            q, t = pose_compose(q_inv, t_inv, q_kf, t_kf)
            for s in range(kf_counts[k]):
                p = quat_rotate(q, vec3(kf_points[k, s, 0], kf_points[k, s, 1],
                                        kf_points[k, s, 2])) + t
                row, col = image_bin(p, bin_rad, bins_el, bins_az)
                count += nearer(p.norm(), image[row, col], min_range_m, margin_m, margin_frac)
        counts[i * NEIGHBOURS + j] += count


@ti.kernel
def set_points(slot: ti.i32, points: ti.types.ndarray(ndim=2), count: ti.i32,
               kf_points: ti.types.ndarray(ndim=3), kf_counts: ti.types.ndarray(ndim=1)):
    """kf_points[slot] = points (the first `count` rows are the keyframe's)."""
    for s, a in ti.ndrange(points.shape[0], 3):
        kf_points[slot, s, a] = points[s, a]
    kf_counts[slot] = count
