"""kernels.voxel_normals / maps.voxel_normals: normals of a scan without a range image against
a NumPy reference of the same search, and against the true normals of a box room."""

import numpy as np
import pytest


def _room_scan(n: int, seed: int, far: float = 1.0):
    """n points where random rays from the origin hit a box room's walls (scaled by `far`),
    with range noise, and the walls' inward normals."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-4.0, -3.0, -1.5]) * far, np.array([5.0, 3.5, 2.0]) * far
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, hi / d, lo / d)
    axis = np.argmin(t, axis=1)
    r = t[np.arange(n), axis] + rng.normal(0.0, 0.005, n)
    normal = np.zeros((n, 3))
    normal[np.arange(n), axis] = -np.sign(d[np.arange(n), axis])
    return (d * r[:, None]).astype(np.float32), normal


def _reference(pts: np.ndarray, k: int) -> np.ndarray:
    """The kernel's search in NumPy (float64 scatter, numpy's eigh): level, 27 cells in the
    kernel's order, the k nearest (ties: the earlier), plane, or across a line, facing."""
    from mcl3d.kernels import scan_normals as sn
    from mcl3d.kernels import voxel_normals as kv
    from mcl3d.maps import voxel_normals as vn

    order, cells, codes = vn.sorted_cells(pts.astype(np.float64))
    keys, starts, ends, offsets = vn.cell_tables(codes)
    p_sorted = pts[order]
    out = np.zeros((len(pts), 3))
    table = [dict(zip(keys[offsets[lv]:offsets[lv + 1]].tolist(),
                      range(offsets[lv], offsets[lv + 1]), strict=True))
             for lv in range(kv.LEVELS)]
    for i in range(len(pts)):
        level = kv.LEVELS - 1
        for lv in range(kv.LEVELS - 1):
            c = table[lv][int(codes[i] >> (3 * kv.LEVEL_SHIFT * lv))]
            if ends[c] - starts[c] >= vn.min_own(k):
                level = lv
                break
        own = cells[i] >> (kv.LEVEL_SHIFT * level)
        cand = []
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    code = int(vn.morton_codes((own + np.array([dx, dy, dz]))[None])[0])
                    c = table[level].get(code)
                    if c is not None:
                        cand.extend(range(starts[c], ends[c]))
        cand = np.asarray(cand)
        d2 = ((p_sorted[cand] - p_sorted[i]) ** 2).sum(axis=1)
        nbr = cand[np.argsort(d2, kind="stable")[:k]]
        if len(nbr) < sn.MIN_NEIGHBORS:
            continue
        q = p_sorted[nbr].astype(np.float64)
        lam, vec = np.linalg.eigh(np.cov(q.T, bias=True))
        normal = vec[:, 0]
        if lam[1] < sn.LINE_RATIO * lam[2]:  # across the line: vertical if level, else ray
            t, p = vec[:, 2], p_sorted[i].astype(np.float64)
            w = np.array([0.0, 0.0, 1.0]) if abs(t[2]) < sn.STEEP_LINE else p / np.linalg.norm(p)
            normal = (w - (w @ t) * t) / np.linalg.norm(w - (w @ t) * t)
        out[i] = -normal if normal @ p_sorted[i] > 0 else normal
    normals = np.empty_like(out)
    normals[order] = out
    return normals


def test_morton_codes_interleave_the_bits():
    from mcl3d.maps.voxel_normals import morton_codes

    cells = np.random.default_rng(0).integers(0, 1 << 21, (500, 3))
    want = np.zeros(500, np.int64)
    for b in range(21):
        for a in range(3):
            want |= ((cells[:, a] >> b) & 1) << (3 * b + a)
    np.testing.assert_array_equal(morton_codes(cells), want)


@pytest.mark.parametrize("far", [1.0, 6.0])  # dense: fine cells; sparse: coarse ones
def test_voxel_normals_match_numpy_reference(ti_runtime, far):
    from mcl3d.maps.voxel_normals import voxel_normals_of

    pts, _ = _room_scan(1500, seed=int(far), far=far)
    got = voxel_normals_of(pts, 8)
    want = _reference(pts, 8)
    has = np.abs(want).sum(axis=1) > 0
    assert has.mean() > 0.9
    agree = (np.abs(got).sum(axis=1) > 0) == has
    assert agree.mean() > 0.995  # the line test's threshold in float32 against float64
    both = has & agree
    cos = np.einsum("ij,ij->i", got[both], want[both])
    assert np.percentile(cos, 1) > 0.9999


def test_voxel_normals_face_the_sensor_and_fit_the_walls(ti_runtime):
    from mcl3d.maps.voxel_normals import voxel_normals_of

    pts, true_normal = _room_scan(20000, seed=5)
    normals = voxel_normals_of(pts, 12)
    has = np.abs(normals).sum(axis=1) > 0
    assert has.mean() > 0.95
    assert (np.einsum("ij,ij->i", normals[has], pts[has]) < 0).all()
    assert np.median(np.einsum("ij,ij->i", normals[has], true_normal[has])) > 0.999


def test_build_map_takes_voxel_normals_for_scans_without_rings(ti_runtime):
    from mcl3d.maps.build import BuildConfig, ScanFuser
    from mcl3d.maps.voxel_normals import voxel_normals_of

    pts, _ = _room_scan(3000, seed=7)
    fuser = ScanFuser.__new__(ScanFuser)
    fuser.config = BuildConfig()
    np.testing.assert_array_equal(fuser.normals(pts, None), voxel_normals_of(pts, 12))
    fuser.config = BuildConfig(normals="knn")
    host = fuser.normals(pts, None)
    assert np.median(np.abs(np.einsum("ij,ij->i", host, voxel_normals_of(pts, 12)))) > 0.999


def test_voxel_normals_of_sparse_rings_on_the_ground_face_up(ti_runtime):
    """A VLP-16's rings on flat ground 1.8 m below: the k nearest of a point all lie on its
    own ring's arc (the next ring is metres away), a line: the normal across it is the
    vertical (before, such points got none and fused along their grazing rays)."""
    from mcl3d.maps.voxel_normals import voxel_normals_of

    rng = np.random.default_rng(3)
    elevation = np.radians(np.arange(-15.0, -1.0, 2.0))  # the rings that reach the ground
    azimuth = np.radians(np.arange(0.0, 360.0, 0.4))
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    d = d.reshape(-1, 3)
    r = 1.8 / -d[:, 2] + rng.normal(0.0, 0.015, len(d))
    pts = (d * r[:, None]).astype(np.float32)
    normals = voxel_normals_of(pts, 12)
    assert (np.abs(normals).sum(axis=1) > 0).all()
    assert np.percentile(normals[:, 2], 5) > 0.99
