"""The seen-through count (kernels/slam_free_space.py) against NumPy on tiny inputs."""

import numpy as np

from mcl3d.core import geometry
from tests.kernels.test_kernels_slam import pack, pose_fields, random_poses


def seen_through_numpy(points, stride, T_cur, T_kf, nb, images, bin_rad, min_range_m,
                       margin_m, margin_frac):
    rows, cols = images.shape[1:]
    n = len(T_cur)
    counts = np.zeros(3 * n, np.int64)
    pts = points[::stride].astype(np.float64)
    for i in range(n):
        for j in range(3):
            k = nb[i, j]
            if k < 0:
                continue
            p = geometry.transform_points(geometry.se3_inverse(T_kf[i, k]) @ T_cur[i], pts)
            r = np.linalg.norm(p, axis=1)
            az = np.arctan2(p[:, 1], p[:, 0]) + np.pi
            el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])) + 0.5 * np.pi
            row = np.clip(np.floor(el / bin_rad).astype(int), 0, rows - 1)
            col = np.floor(az / bin_rad).astype(int) % cols
            seen = images[k, row, col]
            hit = (r >= min_range_m) & (seen > 0) & (r + np.maximum(margin_m, margin_frac * seen)
                                                     < seen)
            counts[3 * i + j] = int(hit.sum())
    return counts


def test_seen_through_matches_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam_free_space

    rng = np.random.default_rng(4)
    n, K, M, stride = 4, 3, 37, 2
    bin_deg = 30.0
    rows, cols = 6, 12
    T_cur = random_poses(rng, n, spread=1.0)
    T_kf = np.stack([random_poses(rng, K, spread=1.0) for _ in range(n)])
    points = rng.uniform(-6, 6, (M, 3)).astype(np.float32)
    images = rng.uniform(0.5, 9.0, (K, rows, cols)).astype(np.float32)
    images[rng.random((K, rows, cols)) < 0.2] = 0.0  # bins without a return
    nb_np = np.array([[0, 1, 2], [2, -1, 0], [-1, -1, -1], [1, 0, -1]], np.int32)

    pts = ti.Vector.field(3, ti.f32, M)
    pts.from_numpy(points)
    kf = ti.ndarray(ti.f32, (n, K, 6))
    kf.from_numpy(pack(T_kf))
    q_cur, t_cur = pose_fields(T_cur)
    nb = ti.field(ti.i32, (n, 3))
    nb.from_numpy(nb_np)
    img = ti.ndarray(ti.f32, (K, rows, cols))
    for k in range(K):
        slam_free_space.set_image(k, images[k], img)
    counts = ti.field(ti.i32, 3 * n)
    args = (np.deg2rad(bin_deg), 0.5, 0.3, 0.05)
    slam_free_space.seen_through(n, M, stride, pts, kf, q_cur, t_cur, nb, img, *args, counts)
    # the kernel's f32 poses: compare with NumPy on the same rounded poses
    want = seen_through_numpy(points, stride, read_back(T_cur), read_back(T_kf), nb_np, images,
                              *args)
    got = counts.to_numpy()
    assert got.sum() > 0 and got[6:9].sum() == 0  # something is seen through; no keyframe: 0
    assert np.abs(got - want).max() <= 1  # a point exactly on a bin edge may round either way
    assert (got == want).mean() >= 0.9


def read_back(T):
    """Poses as the kernels hold them (f32 translation, quaternion vector part)."""
    from mcl3d.slam.slam_particles import unpack_poses

    rows = pack(T)
    return unpack_poses(rows.reshape(-1, 6)).reshape(T.shape)


def test_keyframes_seen_through_matches_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import slam_free_space

    rng = np.random.default_rng(5)
    n, K, P = 3, 2, 29
    rows, cols = 6, 12
    T_cur = random_poses(rng, n, spread=1.0)
    T_kf = np.stack([random_poses(rng, K, spread=1.0) for _ in range(n)])
    kf_points = rng.uniform(-6, 6, (K, P, 3)).astype(np.float32)
    kf_counts = np.array([P, 17], np.int32)  # keyframe 1 keeps fewer points
    image = rng.uniform(0.5, 9.0, (rows, cols)).astype(np.float32)
    image[rng.random((rows, cols)) < 0.2] = 0.0
    nb_np = np.array([[0, 1, -1], [1, -1, 0], [-1, -1, -1]], np.int32)

    kf = ti.ndarray(ti.f32, (n, K, 6))
    kf.from_numpy(pack(T_kf))
    q_cur, t_cur = pose_fields(T_cur)
    nb = ti.field(ti.i32, (n, 3))
    nb.from_numpy(nb_np)
    pts = ti.ndarray(ti.f32, (K, P, 3))
    cnt = ti.ndarray(ti.i32, K)
    for k in range(K):
        slam_free_space.set_points(k, kf_points[k], int(kf_counts[k]), pts, cnt)
    img = ti.ndarray(ti.f32, (rows, cols))
    img.from_numpy(image)
    counts = ti.field(ti.i32, 3 * n)
    counts.from_numpy(np.arange(3 * n, dtype=np.int32))  # the kernel adds to what is there
    args = (np.deg2rad(30.0), 0.5, 0.3, 0.05)
    slam_free_space.keyframes_seen_through(n, pts, cnt, kf, q_cur, t_cur, nb, img, *args,
                                           counts)
    Tc, Tk = read_back(T_cur), read_back(T_kf)
    want = np.arange(3 * n)
    for i in range(n):
        for j in range(3):
            k = nb_np[i, j]
            if k < 0:
                continue
            # the keyframe's points seen from the particle: the scan's image is "keyframe 0"
            one = seen_through_numpy(kf_points[k, :kf_counts[k]], 1, Tk[i, k][None],
                                     Tc[i][None, None], np.array([[0, -1, -1]]),
                                     image[None], *args)
            want[3 * i + j] += one[0]
    got = counts.to_numpy()
    assert (got - np.arange(3 * n)).sum() > 0
    assert np.abs(got - want).max() <= 1
    assert (got == want).mean() >= 0.9
