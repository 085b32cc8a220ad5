"""kernels.scan_normals.share_columns / copy_shared against a NumPy reference: which points
take the normal of their range-image neighbour in the middle of three columns, and that
they get it facing the sensor."""

import numpy as np


def _image(pts, rows, width, height):
    """Each point's pixel and, per pixel, the smallest index of its points (-1: none)."""
    az = np.arctan2(pts[:, 1], pts[:, 0]).astype(np.float64)
    col = np.clip(np.floor((az / (2 * np.pi) + 0.5) * width).astype(int), 0, width - 1)
    pixel = rows * width + col
    image = np.full(width * height, -1)
    for i in range(len(pts) - 1, -1, -1):
        image[pixel[i]] = i
    return pixel, image


def _share_reference(pts, pixel, image, width, share_m):
    """source[i]: the point in the middle column of point i's three (columns 3k..3k+2)
    when that is another column and within share_m of point i, else -1."""
    source = np.full(len(pts), -1)
    for i, px in enumerate(pixel):
        row, col = divmod(px, width)
        mid = col // 3 * 3 + 1
        if mid != col and mid < width:
            j = image[row * width + mid]
            if j >= 0 and np.linalg.norm(pts[j] - pts[i]) <= share_m:
                source[i] = j
    return source


def test_shared_normals_match_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import scan_normals as k

    rng = np.random.default_rng(4)
    width, height = 25, 3  # the last three columns: one
    az = -np.pi + (np.arange(width) + 0.5) * 2 * np.pi / width
    A, ring = np.meshgrid(az, np.arange(height))
    r = rng.uniform(1.0, 1.3, A.shape)  # neighbours 0.25..0.33 m apart along a ring
    pts = np.stack([r * np.cos(A), r * np.sin(A), 0.05 * ring - 0.05], -1).reshape(-1, 3)
    rows = ring.ravel()
    keep = rng.random(len(pts)) > 0.15  # empty pixels
    extra = [3, 10]  # two pixels with a second point
    pts = np.concatenate([pts[keep], pts[extra] * 1.001]).astype(np.float32)
    rows = np.concatenate([rows[keep], rows[extra]]).astype(np.int32)
    order = rng.permutation(len(pts))
    pts, rows = pts[order], rows[order]
    n, share_m = len(pts), 0.3
    pixel_ref, image_ref = _image(pts, rows, width, height)
    want_source = _share_reference(pts, pixel_ref, image_ref, width, share_m)
    assert 0 < (want_source >= 0).sum() < (pixel_ref % width % 3 != 1).sum()

    image = ti.ndarray(ti.i32, shape=width * height)
    pixel = np.empty(n, np.int32)
    source = np.empty(n, np.int32)
    k.clear_image(image, width * height)
    k.project(pts, rows, n, width, height, pixel, image)
    np.testing.assert_array_equal(pixel, pixel_ref)
    k.share_columns(pts, pixel, n, width, image, share_m, source)
    np.testing.assert_array_equal(source, want_source)
    np.testing.assert_array_equal(pixel, np.where(want_source >= 0, -1, pixel_ref))

    normals = rng.normal(size=(n, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[want_source[want_source >= 0][:1]] = 0.0  # a source without a normal
    want = normals.copy()
    for i, j in enumerate(want_source):
        if j >= 0:
            want[i] = -normals[j] if normals[j] @ pts[i] > 0 else normals[j]
    k.copy_shared(pts, source, n, normals)
    np.testing.assert_array_equal(normals, want)
