"""Keyframe range images and the seen-through count (mcl3d/slam/free_space.py): a pose one
floor too high puts its floor points in the room the keyframe saw through; the true pose
does not."""

from types import SimpleNamespace

import numpy as np

from mcl3d.core import geometry
from mcl3d.slam.free_space import FreeSpace, image_shape, range_image

ROOM_LO = np.array([-4.0, -3.0, -1.2])  # the room around the sensor (m): floor 1.2 m below
ROOM_HI = np.array([5.0, 3.5, 2.3])


def room_scan(rng, n: int, offset=np.zeros(3)) -> np.ndarray:
    """Ray-cast returns of a sensor at `offset` inside the box room (lidar frame)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = ROOM_LO - offset, ROOM_HI - offset
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, hi / d, lo / d)
    return d * np.min(t, axis=1, keepdims=True)


def test_range_image_keeps_the_nearest_return_and_unknown_bins():
    rows, cols = image_shape(2.0)
    assert (rows, cols) == (90, 180)
    pts = np.array([[5.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 9.9], [0.2, 0.0, 0.0]])
    img = range_image(pts, 2.0, 0.5, 100.0)
    row, col = 45, 90  # +x: elevation 0 (row 45), azimuth 0 (column 90)
    assert img[row, col] == np.float32(3.0)  # the nearer of two returns
    assert img[row + 1, col] == 0.0  # no return there: unknown, not free
    assert np.count_nonzero(img) == 2  # the point at 0.2 m is under the minimum range
    # a thin pole in one bin next to a wall: the wall's bins beside it take the pole's range
    wall = np.array([[10.0, np.tan(np.deg2rad(a)) * 10.0, 0.0] for a in (-2.9, -1.0, 1.0)])
    img = range_image(np.r_[wall, [[4.0, np.tan(np.deg2rad(1.0)) * 4.0, 0.0]]], 2.0, 0.5, 100)
    pole_m = 4.0 / np.cos(np.deg2rad(1.0))
    np.testing.assert_allclose(img[45, 89:91], pole_m, rtol=1e-6)
    np.testing.assert_allclose(img[45, 88], 10.0 / np.cos(np.deg2rad(1.0)), rtol=1e-6)  # not
    # beside the pole: its own return or its neighbour's on the wall


def test_a_pose_one_floor_up_is_seen_through(ti_runtime):
    import taichi as ti

    from tests.kernels.test_kernels_slam import pack, pose_fields

    rng = np.random.default_rng(2)
    keyframe_scan = room_scan(rng, 20_000)
    scan = room_scan(rng, 20_000, offset=np.array([0.6, 0.3, 0.0]))  # a little further in
    src = scan[:512]
    free = FreeSpace(2, 2.0, 0.5, 100.0, 256)
    free.store(1, keyframe_scan, keyframe_scan)
    free.set_scan(scan)
    assert free.kf_counts.to_numpy().tolist() == [0, 256]
    T_kf = np.eye(4)
    truth = geometry.se3(np.eye(3), [0.6, 0.3, 0.0])
    ghost = geometry.se3(np.eye(3), [0.6, 0.3, 1.75])  # its ceiling above the room's
    q_cur, t_cur = pose_fields(np.stack([truth, ghost]))
    kf = ti.ndarray(ti.f32, (2, 2, 6))
    kf.from_numpy(pack(np.stack([np.stack([T_kf, T_kf])] * 2)))
    nb = ti.field(ti.i32, (2, 3))
    nb.from_numpy(np.array([[1, -1, -1], [1, -1, -1]], np.int32))
    pts = ti.Vector.field(3, ti.f32, 512)
    pts.from_numpy(src.astype(np.float32))
    counts = ti.field(ti.i32, 6)
    particles = SimpleNamespace(n=2, kf=kf, q_cur=q_cur, t_cur=t_cur, nb=nb)
    free.count(particles, pts, 512, 2, 0.3, 0.05, counts)
    truth_seen, _, _, ghost_seen, _, _ = counts.to_numpy()
    # the ghost's floor points float in the room, and the room's ceiling hangs in the
    # ghost's view under the ceiling the scan saw: about the floor's and the ceiling's share
    # of the 256 scan points and 256 keyframe points judged
    floor_share = float(np.mean(np.isclose(src[:, 2], ROOM_LO[2])))
    ceiling_share = float(np.mean(np.isclose(keyframe_scan[:, 2], ROOM_HI[2])))
    assert truth_seen <= 0.01 * 512
    assert ghost_seen >= 0.5 * (floor_share + ceiling_share) * 256
