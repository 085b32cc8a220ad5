"""kernels.scan_normals / maps.scan_normals: range-image normals against a NumPy reference and
against the true normals of a box room, whatever the order of the points."""

import numpy as np

ROOM = (np.array([-4.0, -3.0, -1.5]), np.array([5.0, 3.5, 2.0]))  # around the sensor
CORRIDOR = (np.array([-20.0, -1.5, -1.5]), np.array([20.0, 1.5, 2.0]))  # walls at grazing


def _room_scan(rings: int, columns: int, seed: int, drop: float = 0.1, room=ROOM):
    """Points where rays at the columns' azimuth centres hit a box room's walls (the sensor
    inside, at the origin), their rings, their walls' inward normals; a share `drop` lost,
    the rest shuffled."""
    lo, hi = room
    rng = np.random.default_rng(seed)
    az = -np.pi + (np.arange(columns) + 0.5) * 2 * np.pi / columns
    el = np.radians(np.linspace(-15, 15, rings))
    A, E = np.meshgrid(az, el)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, hi / d, lo / d)
    axis = np.argmin(t, axis=1)
    pts = d * t[np.arange(len(d)), axis][:, None]
    normal = np.zeros_like(pts)
    normal[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    ring = np.repeat(np.arange(rings), columns)
    keep = rng.random(len(pts)) > drop
    order = rng.permutation(np.flatnonzero(keep))
    return pts[order].astype(np.float32), ring[order].astype(np.int32), normal[order]


def _reference(pts, rows, width, height, row_reach, n_cols, col_step, gate_per_m, gate_min_m):
    """The kernels' algorithm in NumPy (float64 sums): normals, and per point how it was
    found (0: none, 1: a plane, 2: across a line)."""
    from mcl3d.kernels import scan_normals as k

    az = np.arctan2(pts[:, 1], pts[:, 0]).astype(np.float64)
    col = np.clip(np.floor((az / (2 * np.pi) + 0.5) * width).astype(int), 0, width - 1)
    pixel = rows * width + col
    image = np.full(width * height, -1)
    for i in range(len(pts) - 1, -1, -1):  # the smallest index wins
        image[pixel[i]] = i
    out = np.zeros_like(pts, dtype=np.float64)
    how = np.zeros(len(pts), int)
    half = (n_cols // 2) * col_step

    def window(i, p, gate):
        row, c0 = divmod(pixel[i], width)
        near = []
        for rr in range(row - row_reach, row + row_reach + 1):
            if 0 <= rr < height:
                for kk in range(n_cols):
                    j = image[rr * width + (c0 + kk * col_step - half) % width]
                    if j >= 0 and np.linalg.norm(pts[j] - p) <= gate:
                        near.append(pts[j] - p)
        if len(near) < k.MIN_NEIGHBORS:
            return None, None
        lam, vec = np.linalg.eigh(np.cov(np.array(near).T, bias=True))
        return vec, lam[1] < k.LINE_RATIO * lam[2]

    for i, p in enumerate(pts.astype(np.float64)):
        gate = gate_min_m + gate_per_m * np.linalg.norm(p)
        vec, line = window(i, p, gate)
        if vec is None or line:
            vec, line = window(i, p, k.WIDE_GATE * gate)
        if vec is None:
            continue
        e = vec[:, 0]
        if line:  # across the line t, nearest the vertical (level t) or the ray (steep)
            t = vec[:, 2]
            w = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < k.STEEP_LINE else p / np.linalg.norm(p)
            e = w - (w @ t) * t
            e /= np.linalg.norm(e)
        out[i] = -e if e @ p > 0 else e
        how[i] = 2 if line else 1
    return out, how


def _device(pts, rows, width, height, *window):
    import taichi as ti

    from mcl3d.kernels import scan_normals as k

    n = len(pts)
    image = ti.ndarray(ti.i32, shape=width * height)
    pixel = np.empty(n, np.int32)
    out = np.empty((n, 3), np.float32)
    k.clear_image(image, width * height)
    k.project(pts, rows, n, width, height, pixel, image)
    k.estimate(pts, pixel, n, width, height, image, *window, out)
    return out


def test_range_image_normals_match_numpy_reference(ti_runtime):
    pts, rows, _ = _room_scan(rings=6, columns=180, seed=3, drop=0.2, room=CORRIDOR)
    window = (1, 5, 1, np.radians(2.0), 0.0)  # tight: every case occurs
    got = _device(pts, rows, 180, 6, *window)
    want, how = _reference(pts, rows, 180, 6, *window)
    assert {0, 1, 2} <= set(how)
    has = how > 0
    np.testing.assert_array_equal(np.abs(got).sum(axis=1) > 0, has)
    np.testing.assert_allclose(got[has], want[has], atol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(got[has], axis=1), 1.0, atol=1e-4)


def test_range_image_normals_face_the_sensor_and_fit_the_walls(ti_runtime):
    from mcl3d.maps.scan_normals import RangeImageNormals, layout

    pts, rows, true_normal = _room_scan(rings=16, columns=360, seed=1)
    shape = layout(pts, rows)
    assert shape is not None and shape.height == 16 and 300 <= shape.width <= 400
    normals = RangeImageNormals()(pts, rows, shape)
    has = np.abs(normals).sum(axis=1) > 0
    assert has.mean() > 0.8
    assert (np.einsum("ij,ij->i", normals[has], pts[has]) < 0).all()  # towards the sensor
    # away from the room's edges the window lies on one wall: the wall's normal
    assert np.median(np.einsum("ij,ij->i", normals[has], true_normal[has])) > 0.999


def test_layout_refuses_what_is_no_range_image():
    from mcl3d.maps.scan_normals import layout

    pts, rows, _ = _room_scan(rings=16, columns=360, seed=2)
    assert layout(pts, None) is None
    assert layout(pts, rows % 4) is None  # a Livox's few lines
    assert layout(pts[:1000], rows[:1000]) is None  # too sparse
