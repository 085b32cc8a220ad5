"""kernels.point_fusion: point-cloud maps' normals with spacing, and their bands, against
NumPy references on tiny inputs."""

import numpy as np
from scipy.spatial import cKDTree

from mcl3d.maps.build import BuildConfig

VOXEL_M = 0.1
BEHIND_M = 0.1


def test_spacing_is_the_k_nearest_disc_per_point(ti_runtime):
    """On a jittered plane 2 cm apart the k nearest lie in the cells searched, so the
    spacing is sqrt(pi d_k^2 / k) with d_k from a brute-force k-d tree, and the normals are
    the plane's."""
    from mcl3d.maps.point_normals import sorted_normals

    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.arange(40) * 0.02, np.arange(40) * 0.02)
    pts = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    pts[:, :2] += rng.uniform(-0.004, 0.004, (len(pts), 2))
    pts = (pts @ np.linalg.qr(rng.normal(size=(3, 3)))[0].T + [3.0, -2.0, 1.0]).astype(np.float32)
    k = 12
    order, normals, spacing = sorted_normals(pts, k)
    d_k = cKDTree(pts[order].astype(np.float64)).query(pts[order], k=k)[0][:, -1]
    np.testing.assert_allclose(spacing, np.sqrt(np.pi * d_k**2 / k), rtol=1e-4)
    plane = np.linalg.svd(pts - pts.mean(axis=0))[2][2]
    assert np.abs(normals @ plane).min() > 0.999
    assert 0.018 < np.median(spacing) < 0.024


def _band_reference(geometry, pts, nrm, steps, trunc_m):
    """{voxel: (sum w d, sum w)} of the points' bands and the blocks of every sample (those
    allocated), as the kernel samples them: columns a
    voxel apart over +-steps/2 voxels of the tangent plane, depths from -behind to +trunc,
    each voxel once per point, f32 like the kernel."""
    f = np.float32
    origin, inv = np.asarray(geometry.origin_m, f), f(1.0 / VOXEL_M)
    n_s = int(np.ceil((BEHIND_M + trunc_m) / VOXEL_M)) + 1
    sums, blocks = {}, set()
    for p, n, k in zip(pts, nrm, steps, strict=True):
        a_axis = np.array([0, 1, 0] if abs(n[0]) > 0.9 else [1, 0, 0], f)
        e1 = np.cross(n, a_axis)
        e1 = (e1 / np.sqrt(e1 @ e1)).astype(f)
        e2 = np.cross(n, e1).astype(f)
        pg, nv = (p - origin) * inv, n * inv
        seen = set()
        for a in range(k + 1):
            for b in range(k + 1):
                base = pg + f(a - 0.5 * k) * e1 + f(b - 0.5 * k) * e2
                for j in range(n_s):
                    s = f(min(-BEHIND_M + j * VOXEL_M, trunc_m))
                    g = tuple(np.floor(base + s * nv).astype(int))
                    if g in seen:
                        continue
                    seen.add(g)
                    blocks.add(tuple(np.array(g) >> 3))
                    v = origin + (np.array(g, f) + f(0.5)) * f(VOXEL_M) - p
                    d = f(v @ n)
                    if -BEHIND_M <= d <= trunc_m:
                        w = np.exp(-0.5 * (v @ v) / VOXEL_M**2)
                        wd0, w0 = sums.get(g, (0.0, 0.0))
                        sums[g] = (wd0 + w * d, w0 + w)
    return sums, blocks


def test_band_fusion_matches_numpy(ti_runtime):
    """Random points, normals and footprints 0..2 in a small map: the allocated blocks are
    those the samples fall in, and every voxel's sums are the reference's."""
    from mcl3d.kernels import point_fusion
    from mcl3d.kernels.tsdf_lookup import BLOCK
    from mcl3d.maps.build import new_map
    from mcl3d.maps.tsdf import MapGeometry

    rng = np.random.default_rng(7)
    n = 40
    pts = rng.uniform(0.5, 2.5, (n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3))
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    steps = rng.integers(0, 3, n).astype(np.int32)
    cfg = BuildConfig(voxel_size_m=VOXEL_M)
    geometry = MapGeometry.around(np.zeros(3), np.full(3, 3.0), VOXEL_M, cfg.trunc_m,
                                  margin_m=cfg.trunc_m)
    tsdf = new_map(geometry, cfg, 2000)
    tsdf.relaunch_until_placed(lambda: point_fusion.points_allocate_band(
        tsdf, pts, nrm, steps, n, BEHIND_M))
    tsdf.init_new_blocks(0, tsdf.n_blocks)
    point_fusion.points_fuse_band(tsdf, pts, nrm, steps, n, VOXEL_M, BEHIND_M, 8)
    want, want_blocks = _band_reference(geometry, pts, nrm, steps, cfg.trunc_m)
    data = tsdf.blocks()  # the running sums (w d, w) while building
    got = {}
    for c, wd, w in zip(data.coords, data.sdf, data.weight, strict=True):
        for idx in zip(*np.nonzero(w), strict=True):
            got[tuple(c * BLOCK + np.array(idx))] = (wd[idx], w[idx])
    assert want_blocks == set(map(tuple, data.coords.tolist()))
    assert set(got) == set(want)
    keys = sorted(want)
    np.testing.assert_allclose([got[g] for g in keys], [want[g] for g in keys],
                               rtol=1e-4, atol=1e-6)
