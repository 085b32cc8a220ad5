"""TSDF kernels against NumPy references on tiny maps: allocation, one ray, queries, state."""

from functools import partial

import numpy as np
import pytest

from mcl3d.core.errors import MapError


def _map(dims=(4, 3, 2), capacity=64, voxel=0.1, trunc=0.3, origin=(-0.4, -0.4, -0.8)):
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    return TsdfMap(MapGeometry(voxel, trunc, origin, dims), capacity)


def test_allocation_gives_unique_dense_ids(ti_runtime):
    tsdf = _map()
    rng = np.random.default_rng(0)
    coords = rng.integers(-1, 5, size=(200, 3))  # duplicates and out-of-grid cells
    tsdf.allocate(coords)
    inside = coords[np.all((coords >= 0) & (coords < (4, 3, 2)), axis=1)]
    expected = {tuple(c) for c in inside}
    assert tsdf.n_blocks == len(expected)
    cells, ids = tsdf.coarse_cells()
    assert sorted(ids) == list(range(len(expected)))
    data = tsdf.blocks()
    assert {tuple(c) for c in data.coords} == expected
    coarse = dict(zip(map(tuple, cells), ids, strict=True))
    for b, c in enumerate(data.coords):
        assert coarse[tuple(c)] == b
    assert (data.weight == 0).all() and np.allclose(data.sdf, tsdf.truncation_m)


def test_sparse_index_over_many_tiles(ti_runtime):
    """Blocks and FREE cells scattered over a grid of 3 x 2 x 2 tiles: tiles are claimed
    only where a cell is known, and every cell reads back as a dense NumPy grid says."""
    tsdf = _map(dims=(19, 10, 9), capacity=400)
    rng = np.random.default_rng(3)
    dense = np.full((19, 10, 9), -1, np.int64)
    free = rng.integers(0, (19, 10, 9), size=(60, 3))
    alloc = rng.integers(0, (19, 10, 9), size=(300, 3))
    alloc[:, 1] = np.minimum(alloc[:, 1], 7)  # tiles with y >= 8 hold FREE cells at most
    tsdf.mark_free(free)
    tsdf.allocate(alloc)
    dense[tuple(free.T)] = -3
    data = tsdf.blocks()
    dense[tuple(data.coords.T)] = np.arange(len(data.coords))
    assert {tuple(c) for c in data.coords} == {tuple(c) for c in alloc}
    known = np.argwhere(dense != -1)
    assert tsdf.n_tiles == len({tuple(c) for c in known >> 3})
    cells, values = tsdf.coarse_cells()
    got = np.full_like(dense, -1)
    got[tuple(cells.T)] = values
    np.testing.assert_array_equal(got, dense)
    from mcl3d.maps.sparse_cells import CellLookup

    grid = np.argwhere(np.ones((21, 12, 11), bool)) - 1  # one cell past each face
    lookup = CellLookup(cells, values, tsdf.coarse_dims)(grid)
    inside = np.all((grid >= 0) & (grid < (19, 10, 9)), axis=1)
    np.testing.assert_array_equal(lookup[inside], dense[tuple(grid[inside].T)])
    assert (lookup[~inside] == -1).all()


def test_tile_pool_past_capacity_says_how_many_tiles(ti_runtime):
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf = TsdfMap(MapGeometry(0.1, 0.3, (0.0, 0.0, 0.0), (40, 8, 8)), 16, capacity_tiles=2)
    with pytest.raises(MapError, match=r"coarse index needs 5 tiles but its capacity is 2"):
        tsdf.allocate(np.array([[8 * i, 0, 0] for i in range(5)]))
    assert tsdf.n_blocks == 2


def test_allocation_past_capacity_says_how_many_blocks(ti_runtime):
    tsdf = _map(capacity=3)
    coords = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [0, 1, 0]])
    with pytest.raises(MapError, match=r"needs 5 blocks but its capacity is 3"):
        tsdf.allocate(coords)
    assert tsdf.n_blocks == 3
    assert (tsdf.coarse_cells()[1] == -2).sum() == 2  # OVERFLOW cells


def _grid(tsdf):
    o0, v = np.asarray(tsdf.origin_m), tsdf.voxel_size_m
    return lambda x: np.floor((x - o0) / v).astype(int)


def _column(origin, point, tsdf, behind, n=None):
    """The band samples of a one-column point along its normal n (projective without one:
    along the reversed ray)."""
    v, trunc = tsdf.voxel_size_m, tsdf.truncation_m
    if n is None:
        n = -(point - origin) / np.linalg.norm(point - origin)
    samples = int(np.ceil((behind + trunc) / v)) + 1
    return [point + min(-behind + j * v, trunc) * n for j in range(samples)], n


def _carve_reference(origin, point, tsdf, blocks, s_voxels=0.0):
    """Free-space hits {voxel: 1} in allocated `blocks` and blocks made FREE by one ray,
    walked from its band back toward the sensor: voxels counted from range s_voxels on,
    unallocated blocks walked from range 2 * s_voxels on."""
    v, trunc = tsdf.voxel_size_m, tsdf.truncation_m
    o0, grid = np.asarray(tsdf.origin_m), _grid(tsdf)
    r = np.linalg.norm(point - origin)
    s_free = r - trunc
    a, w = origin + s_free * (point - origin) / r, -(point - origin) / r
    length, stop_after = s_free - s_voxels, s_free - 2 * s_voxels
    free_hits, free_blocks, last = {}, set(), None
    s = 0.0
    while s < length:
        g = grid(a + s * w)
        b = tuple(g >> 3)
        if b in blocks:
            if tuple(g) != last:
                free_hits[tuple(g)] = 1
                last = tuple(g)
            s += v
        elif s > stop_after:
            break
        else:
            free_blocks.add(b)
            lo = o0 + np.array(b) * 8 * v
            hi = lo + 8 * v
            ex = [((hi if w[k] > 0 else lo)[k] - a[k]) / w[k] for k in range(3)
                  if abs(w[k]) > 1e-9]
            s = max(min(ex), s) + 1e-4
    return free_hits, free_blocks


def _lowest_bit(i):
    return min(i & -i, 1 << 20) if i > 0 else 1 << 20


def _band_reference(origin, point, tsdf, behind, sigma, n=None, count=1):
    """{voxel: (d, w)} of one point's one-column band (a bundle's: its mean point and
    normal, its count times the weight)."""
    v, trunc = tsdf.voxel_size_m, tsdf.truncation_m
    o0, grid = np.asarray(tsdf.origin_m), _grid(tsdf)
    column, n = _column(origin, point, tsdf, behind, n)
    band, last = {}, None
    for x in column:
        g = grid(x)
        if last is None or tuple(g) != last:
            last = tuple(g)
            c = o0 + (g + 0.5) * v
            d = np.dot(c - point, n)
            if -behind <= d <= trunc:
                band[tuple(g)] = d, count * np.exp(-0.5 * np.dot(c - point, c - point)
                                                   / sigma**2)
    return band


def _bundles(origin, points, tsdf, spacing):
    """(mean point, unit mean normal, count, index of its first point) of each bundle of
    projective one-column points: consecutive points in one voxel whose normals agree
    within BUNDLE_COS (scan_fuse)."""
    from mcl3d.kernels.tsdf_fusion import BUNDLE_COS

    grid = _grid(tsdf)
    groups, firsts = [], []
    for i, p in enumerate(points):
        r = np.linalg.norm(p - origin)
        assert int(r * spacing / tsdf.voxel_size_m) == 0  # a one-column band
        n = -(p - origin) / r
        last = groups[-1][-1] if groups else None
        if last is not None and (grid(p) == grid(last[0])).all() and n @ last[1] >= BUNDLE_COS:
            groups[-1].append((p, n))
        else:
            groups.append([(p, n)])
            firsts.append(i)
    out = []
    for g, first in zip(groups, firsts, strict=True):
        n = np.sum([n for _, n in g], axis=0)
        out.append((np.mean([p for p, _ in g], axis=0), n / np.linalg.norm(n), len(g), first))
    return out


def _scan_reference(origin, points, tsdf, behind, sigma, spacing=0.0):
    """Float64 re-implementation of scan_allocate + scan_fuse for one-column points.

    Band: per voxel the sums of w*d and w over all bundles; free-space hits: per voxel the
    number of rays that cross it, a bundle's all along its first ray (near the sensor only
    a subset of them: see scan_fuse).
    """
    grid = _grid(tsdf)
    bundles = _bundles(origin, points, tsdf, spacing)
    blocks = {tuple(grid(x) >> 3) for p, n, *_ in bundles
              for x in _column(origin, p, tsdf, behind, n)[0]}
    s_dense = 0.5 * tsdf.voxel_size_m / spacing if spacing > 0 else 0.0
    sums, free_hits, free_blocks = {}, {}, set()
    for p, n, count, first in bundles:
        for g, (d, w) in _band_reference(origin, p, tsdf, behind, sigma, n, count).items():
            wd0, w0 = sums.get(g, (0.0, 0.0))
            sums[g] = wd0 + w * d, w0 + w
        hits, free = _carve_reference(origin, points[first], tsdf, blocks,
                                      s_dense / _lowest_bit(first))
        for g in hits:
            free_hits[g] = free_hits.get(g, 0) + count
        free_blocks |= free
    return sums, free_hits, blocks, free_blocks - blocks


def _ray_reference(origin, point, tsdf, behind, sigma):
    sums, free_hits, blocks, free_blocks = _scan_reference(origin, [point], tsdf, behind, sigma)
    return {g: (wd / w, w) for g, (wd, w) in sums.items()}, free_hits, blocks, free_blocks


def _pool_sums(tsdf):
    """{voxel: (sum w*d, sum w)} of every voxel with band weight, read from the pool."""
    data = tsdf.blocks()
    got = {}
    for b, c in enumerate(data.coords):
        for idx in zip(*np.nonzero(data.weight[b] > 0), strict=True):
            got[tuple(np.asarray(c) * 8 + np.asarray(idx))] = (data.sdf[b][idx],
                                                               data.weight[b][idx])
    return data, got


def _ray_buffers(n):
    """The per-point rays scan_allocate sets up for scan_fuse."""
    import taichi as ti

    return ti.ndarray(ti.math.vec4, shape=n), ti.ndarray(ti.math.vec4, shape=n)


def test_fusion_of_a_ray_and_a_scan_line_matches_numpy(ti_runtime):
    """One ray in full (band, carving, finalize), then a scan line on the same map (the
    kernels compile once per map)."""
    import taichi as ti

    from mcl3d.kernels import tsdf_fusion
    from mcl3d.maps.free_space import HostMap

    tsdf = _map(dims=(6, 4, 3), capacity=64, voxel=0.1, trunc=0.3, origin=(-0.8, -0.8, -0.8))
    tsdf.as_sums = True
    origin = np.array([0.013, -0.021, 0.017])
    point = np.array([3.31, 1.17, 0.53])
    behind, sigma = 0.2, 0.1
    pts = (point - origin).astype(np.float32)[None]
    q = ti.math.vec4(0, 0, 0, 1)
    t = ti.math.vec3(*origin)
    alpha = np.zeros(1, np.float32)
    rays = _ray_buffers(1)
    tsdf_fusion.scan_allocate(tsdf, pts, np.zeros_like(pts), alpha, 1, q, t, q, t, 0.1, 100.0,
                              0.0, behind, False, *rays, 64, 1, True)
    tsdf.init_new_blocks(0, tsdf.requested_blocks)
    tsdf_fusion.scan_fuse(tsdf, *rays, alpha, 1, t, t, 0.0, behind, True, sigma, 64, 1)
    band, free_hits, blocks, free_blocks = _ray_reference(origin, point, tsdf, behind, sigma)
    data, got = _pool_sums(tsdf)
    assert {tuple(c) for c in data.coords} == blocks
    assert {tuple(c) for c in data.free_coords} == free_blocks
    assert set(got) == set(band)
    for g, (d, w) in band.items():
        assert got[g][1] == pytest.approx(w, abs=1e-5)
        assert got[g][0] / got[g][1] == pytest.approx(d, abs=1e-5)
    tsdf.finalize()
    host = HostMap(tsdf)
    for g, (d, _) in band.items():
        assert float(host.voxel_dw(np.array(g))[0]) == pytest.approx(d, abs=1e-5)
    assert len(free_hits) > 5
    for g in free_hits:
        if g not in band:  # free-only voxel: observed, distance bounded via band voxels
            d, w = host.voxel_dw(np.array(g))
            assert w == free_hits[g]
            assert 0 < d <= tsdf.truncation_m + 1e-6
    _check_scan_line(tsdf)


def _band_bound(g, band, voxel_m, trunc_m):
    """refine_free_voxels in NumPy: the least k * |e| * voxel + |d(n)| over band voxels n at
    k = 1..ceil(trunc / voxel) steps along the 26 grid directions e, at most trunc."""
    radius = int(trunc_m / voxel_m + 0.999)
    bound = trunc_m
    for e in np.array(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij")).reshape(3, -1).T:
        if e.any():
            for k in range(1, radius + 1):
                n = tuple(np.asarray(g) + k * e)
                if n in band:
                    bound = min(bound, k * np.linalg.norm(e) * voxel_m + abs(band[n][0]))
    return bound


def test_free_voxels_are_bounded_through_band_neighbours(ti_runtime):
    """finalize's refine_free_voxels against NumPy: a floor seen at grazing angles, whose
    rays cross voxels just above the band."""
    import taichi as ti

    from mcl3d.kernels import tsdf_fusion
    from mcl3d.maps.free_space import HostMap

    tsdf = _map(dims=(10, 4, 3), capacity=128, voxel=0.1, trunc=0.3, origin=(-0.8, -0.8, -0.8))
    tsdf.as_sums = True
    x, y = np.meshgrid(np.linspace(0.6, 3.5, 30), np.linspace(-0.5, 0.5, 9))
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, -0.47)], axis=1).astype(np.float32)
    n, q, t = len(pts), ti.math.vec4(0, 0, 0, 1), ti.math.vec3(0.013, -0.021, 0.017)
    alpha = np.zeros(n, np.float32)
    rays = _ray_buffers(n)
    tsdf.relaunch_until_placed(partial(
        tsdf_fusion.scan_allocate, tsdf, pts, np.zeros_like(pts), alpha, n, q, t, q, t, 0.1,
        100.0, 0.0, 0.2, False, *rays, 64, 1, True))
    tsdf.init_new_blocks(0, tsdf.requested_blocks)
    tsdf_fusion.scan_fuse(tsdf, *rays, alpha, n, t, t, 0.0, 0.2, True, 0.1, 64, 1)
    data, sums = _pool_sums(tsdf)
    band = {g: (np.clip(wd / w, -0.3, 0.3),) for g, (wd, w) in sums.items()}
    hits, counts = set(), tsdf.free_hits.to_numpy()
    for b, cb in enumerate(data.coords):
        hits |= {tuple(np.asarray(cb) * 8 + i) for i in np.argwhere(counts[b])}
    tsdf.finalize()
    host = HostMap(tsdf)
    bounds = {g: _band_bound(g, band, 0.1, 0.3) for g in hits - set(band)}
    assert sum(bound < 0.3 for bound in bounds.values()) > 20
    for g, bound in bounds.items():
        assert float(host.voxel_dw(np.array(g))[0]) == pytest.approx(bound, abs=1e-5)


def test_carving_claims_the_tiles_it_crosses(ti_runtime):
    """A 21 m ray over a map four tiles long: the allocation pass claims the tiles of the
    band and of every block the carving walk crosses, so carving marks the same FREE
    blocks as the NumPy walk, and no other tile exists."""
    import taichi as ti

    from mcl3d.kernels import tsdf_fusion

    tsdf = _map(dims=(30, 4, 3), capacity=64, voxel=0.1, trunc=0.3, origin=(-0.8, -0.8, -0.8))
    tsdf.as_sums = True
    origin = np.array([0.013, -0.021, 0.017])
    point = np.array([20.31, 1.17, 0.53])
    pts = (point - origin).astype(np.float32)[None]
    q, t = ti.math.vec4(0, 0, 0, 1), ti.math.vec3(*origin)
    alpha = np.zeros(1, np.float32)
    rays = _ray_buffers(1)
    tsdf.relaunch_until_placed(lambda: tsdf_fusion.scan_allocate(
        tsdf, pts, np.zeros_like(pts), alpha, 1, q, t, q, t, 0.1, 100.0, 0.0, 0.2, False,
        *rays, 64, 1, True))
    tsdf.init_new_blocks(0, tsdf.requested_blocks)
    tsdf_fusion.scan_fuse(tsdf, *rays, alpha, 1, t, t, 0.0, 0.2, True, 0.1, 64, 1)
    _, _, blocks, free_blocks = _ray_reference(origin, point, tsdf, 0.2, 0.1)
    data = tsdf.blocks()
    assert {tuple(c) for c in data.coords} == blocks
    assert {tuple(c) for c in data.free_coords} == free_blocks
    assert {c[0] >> 3 for c in free_blocks} == {0, 1, 2, 3}
    assert tsdf.n_tiles == len({tuple(np.asarray(c) >> 3) for c in blocks | free_blocks})


def _check_scan_line(tsdf):
    """Several points, four in one voxel in a row: one bundle (its band at their mean, four
    times the weight; it carves along its first ray, four hits a voxel), in runs of any
    length (3: a run starts inside the bundle, which the first run takes), band sums
    merged in registers, with the same result, however the runs are spread over threads
    (kernels.spread). With a ray spacing that puts rays half a voxel apart at 10 m, only a
    subset carves near the sensor (rays 5, 6 not at all, ray 4 from 2.5 m on): fewer hits,
    the same band."""
    import taichi as ti

    from mcl3d.kernels import tsdf_fusion

    origin = np.array([0.013, -0.021, 0.017])
    c = np.array([2.05, 0.55, 0.35])  # a voxel centre
    near_c = c + np.array([[0.02, 0.01, -0.02], [-0.03, 0.02, 0.0], [0.0, -0.02, 0.03],
                           [0.03, 0.03, 0.01], [-0.01, -0.03, -0.02]])
    points = [*near_c[:4], np.array([3.31, 1.17, 0.53]), np.array([1.2, 1.9, -0.35]),
              near_c[4]]
    behind, sigma = 0.2, 0.1
    pts = np.array([p - origin for p in points], np.float32)
    q = ti.math.vec4(0, 0, 0, 1)
    t = ti.math.vec3(*origin)
    alpha = np.zeros(len(pts), np.float32)
    rays = _ray_buffers(len(pts))
    args = (pts, np.zeros_like(pts), alpha, len(pts), q, t, q, t, 0.1, 100.0)
    all_hits = None
    assert [b[2] for b in _bundles(origin, points, tsdf, 0.0)] == [4, 1, 1, 1]
    for run_length, spacing, threads in ((1, 0.0, 2), (3, 0.0, 3), (64, 0.0, 1),
                                         (64, 0.005, 1)):
        sums, free_hits, blocks, free_blocks = _scan_reference(origin, points, tsdf, behind,
                                                               sigma, spacing)
        assert len(sums) > 12 and len(free_hits) > (0 if spacing else 10) and free_blocks
        if spacing:  # the subset near the sensor skips some voxels and counts less
            assert sum(free_hits.values()) < sum(all_hits.values())
        all_hits = free_hits
        tsdf.clear()
        tsdf.as_sums = True
        tsdf.relaunch_until_placed(partial(tsdf_fusion.scan_allocate, tsdf, *args, spacing,
                                           behind, False, *rays, run_length, threads, True))
        tsdf.init_new_blocks(0, tsdf.requested_blocks)
        tsdf_fusion.scan_fuse(tsdf, *rays, alpha, len(pts), t, t, spacing, behind, True,
                              sigma, run_length, threads)
        data, got = _pool_sums(tsdf)
        assert {tuple(b) for b in data.coords} == blocks
        assert {tuple(b) for b in data.free_coords} == free_blocks
        assert set(got) == set(sums)
        for g, (wd, w) in sums.items():
            assert got[g][1] == pytest.approx(w, abs=1e-5)
            assert got[g][0] == pytest.approx(wd, abs=1e-5)
        hits, counts = {}, tsdf.free_hits.to_numpy()
        for b, cb in enumerate(data.coords):
            for idx in zip(*np.nonzero(counts[b] > 0), strict=True):
                hits[tuple(np.asarray(cb) * 8 + np.asarray(idx))] = counts[b][idx]
        assert hits == free_hits


def _query_map():
    tsdf = _map(dims=(3, 3, 2), capacity=16, voxel=0.1, trunc=0.3, origin=(0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    coords = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 1, 1]])
    tsdf.allocate(coords)
    sdf = rng.uniform(-0.3, 0.3, size=(len(coords), 8, 8, 8)).astype(np.float32)
    weight = (rng.random((len(coords), 8, 8, 8)) > 0.1).astype(np.float32)
    tsdf.write_blocks(coords, sdf, weight)
    tsdf.mark_free(np.array([[2, 0, 0], [2, 2, 1]]))
    return tsdf


def _trilinear_reference(host, p):
    g = host.to_grid(p) - 0.5
    i0 = np.floor(g).astype(int)
    f = g - i0
    d, w, grad = 0.0, np.inf, np.zeros(3)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                dv, wv = map(float, host.voxel_dw(i0 + np.array([dx, dy, dz])))
                wx = f[0] if dx else 1 - f[0]
                wy = f[1] if dy else 1 - f[1]
                wz = f[2] if dz else 1 - f[2]
                d += wx * wy * wz * dv
                w = min(w, wv)
                grad += dv * np.array([(1 if dx else -1) * wy * wz, wx * (1 if dy else -1) * wz,
                                       wx * wy * (1 if dz else -1)])
    return d, w, grad / host.geometry.voxel_size_m


def test_queries_match_numpy(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import tsdf_lookup as k
    from mcl3d.maps.free_space import HostMap

    tsdf = _query_map()
    host = HostMap(tsdf)

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              near: ti.types.ndarray(dtype=ti.math.vec2, ndim=1),
              tri: ti.types.ndarray(dtype=ti.math.vec2, ndim=1),
              grad: ti.types.ndarray(dtype=ti.math.vec4, ndim=1),
              state: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(p.shape[0]):
            near[i] = k.sdf_nearest(m, p[i])
            tri[i] = k.sdf_trilinear(m, p[i])
            grad[i] = k.sdf_trilinear_grad(m, p[i])
            state[i] = k.state_at(m, p[i])

    rng = np.random.default_rng(4)
    p = rng.uniform(-0.1, 2.5, size=(500, 3)).astype(np.float32)
    p[:, 2] = rng.uniform(-0.1, 1.7, size=500)
    near = np.zeros((500, 2), np.float32)
    tri = np.zeros((500, 2), np.float32)
    grad = np.zeros((500, 4), np.float32)
    state = np.zeros(500, np.int32)
    query(tsdf, p, near, tri, grad, state)
    for i in range(500):
        d, w = host.voxel_dw(np.floor(host.to_grid(p[i].astype(np.float64))).astype(int))
        d, w = float(d), float(w)
        assert near[i] == pytest.approx([d, w], abs=1e-6)
        expected_state = 0 if w <= 0 else (2 if d >= tsdf.truncation_m * 0.999 else 1)
        assert state[i] == expected_state
        dt, wt, gt = _trilinear_reference(host, p[i].astype(np.float64))
        assert tri[i] == pytest.approx([dt, wt], abs=2e-5)
        assert grad[i] == pytest.approx([dt, *gt], abs=2e-4)


def test_gradient_is_the_derivative_of_trilinear(ti_runtime):
    import taichi as ti

    from mcl3d.kernels import tsdf_lookup as k

    tsdf = _query_map()

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              out: ti.types.ndarray(dtype=ti.math.vec4, ndim=1)):
        for i in range(p.shape[0]):
            out[i] = k.sdf_trilinear_grad(m, p[i])

    rng = np.random.default_rng(5)
    p = rng.uniform(0.1, 1.5, size=(50, 3))
    h = 1e-3
    probes = [p] + [p + h * e for e in np.eye(3)] + [p - h * e for e in np.eye(3)]
    outs = []
    for q in probes:
        out = np.zeros((len(p), 4), np.float32)
        query(tsdf, q.astype(np.float32), out)
        outs.append(out[:, 0].astype(np.float64))
    numeric = np.stack([(outs[1 + a] - outs[4 + a]) / (2 * h) for a in range(3)], axis=1)
    out = np.zeros((len(p), 4), np.float32)
    query(tsdf, p.astype(np.float32), out)
    # skip probes that straddle a voxel-centre plane (the interpolant has kinks there)
    g = (p - np.asarray(tsdf.origin_m)) / tsdf.voxel_size_m - 0.5
    smooth = np.all(np.abs(g - np.round(g)) > 0.05, axis=1)
    assert smooth.sum() > 20
    np.testing.assert_allclose(out[smooth, 1:], numeric[smooth], atol=0.05)


def test_band_weight_exp_matches_numpy(ti_runtime):
    """exp_nonpositive (the band weights' exp) against np.exp over the whole f32 range it
    takes: absolute error under 3e-7 (weights are at most 1), relative under 5e-6 down to
    -87, flushed to tiny values below."""
    import taichi as ti

    from mcl3d.kernels.tsdf_band import exp_nonpositive

    @ti.kernel
    def run(x: ti.types.ndarray(dtype=ti.f32, ndim=1), out: ti.types.ndarray(dtype=ti.f32,
                                                                              ndim=1)):
        for i in range(x.shape[0]):
            out[i] = exp_nonpositive(x[i])

    x = np.concatenate([-np.geomspace(1e-8, 87.0, 4000), [0.0, -0.5 * np.log(2), -1e-30],
                        -np.linspace(0, 20, 4001)]).astype(np.float32)
    out = np.zeros_like(x)
    run(x, out)
    ref = np.exp(x.astype(np.float64))
    assert np.max(np.abs(out - ref)) < 3e-7
    assert np.max(np.abs(out / ref - 1)) < 5e-6
    assert out[x == 0][0] == 1.0
    big = np.array([-88.0, -200.0, -1e30], np.float32)
    tiny = np.zeros_like(big)
    run(big, tiny)
    assert np.all((tiny >= 0) & (tiny < 2e-38))


def test_scan_quat_exp_matches_scipy(ti_runtime):
    """The deskew's rotation exp (polynomial below half a radian of half angle, sin/cos
    above) against scipy's rotation vectors, small to large and exactly zero."""
    import taichi as ti
    from scipy.spatial.transform import Rotation

    from mcl3d.kernels.tsdf_fusion import scan_quat_exp

    @ti.kernel
    def run(w: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
            out: ti.types.ndarray(dtype=ti.math.vec4, ndim=1)):
        for i in range(w.shape[0]):
            out[i] = scan_quat_exp(w[i])

    rng = np.random.default_rng(5)
    axes = rng.normal(size=(400, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([np.geomspace(1e-7, 3.0, 399), [0.0]])
    w = (axes * angles[:, None]).astype(np.float32)
    out = np.zeros((len(w), 4), np.float32)
    run(w, out)
    ref = Rotation.from_rotvec(w.astype(np.float64)).as_quat()  # (x, y, z, w), w >= 0
    np.testing.assert_allclose(out, ref, atol=2e-7)
    assert (out[-1] == [0, 0, 0, 1]).all()


def test_a_wide_ray_that_closes_a_bundle_adds_both_bands(ti_runtime):
    """A ray with a patch (footprint_steps > 0) right after a bundle closes it and fuses
    in the same step of the walk: the same band sums as the wide ray first and the bundle
    after it, for runs of any length and thread counts."""
    import taichi as ti

    from mcl3d.kernels import tsdf_fusion

    origin = np.array([0.013, -0.021, 0.017])
    c = np.array([2.05, 0.55, 0.35])  # a voxel centre, 2.1 m away: one column at 0.04 rad
    near = c + np.array([[0.02, 0.01, -0.02], [-0.03, 0.02, 0.0], [0.0, -0.02, 0.03]])
    far = np.array([3.31, 1.17, 0.53])  # 3.5 m: a patch of half-width 1
    spacing, behind, sigma = 0.04, 0.2, 0.1
    q = ti.math.vec4(0, 0, 0, 1)
    t = ti.math.vec3(*origin)

    tsdf = _map(dims=(6, 4, 3), capacity=128, origin=(-0.4, -1.2, -1.2))

    def fused(points, run_length, threads):
        tsdf.clear()  # one map: its kernels compile once
        tsdf.as_sums = True
        pts = np.array([p - origin for p in points], np.float32)
        alpha = np.zeros(len(pts), np.float32)
        rays = _ray_buffers(len(pts))
        args = (pts, np.zeros_like(pts), alpha, len(pts), q, t, q, t, 0.1, 100.0)
        tsdf.relaunch_until_placed(partial(tsdf_fusion.scan_allocate, tsdf, *args, spacing,
                                           behind, False, *rays, run_length, threads, False))
        tsdf.init_new_blocks(0, tsdf.requested_blocks)
        tsdf_fusion.scan_fuse(tsdf, *rays, alpha, len(pts), t, t, spacing, behind, False,
                              sigma, run_length, threads)
        return _pool_sums(tsdf)[1]

    expected = fused([far, *near], 64, 1)
    patch, column = fused([far], 64, 1), fused(near, 64, 1)
    assert len(patch) > len(column) > 3 and set(expected) == set(patch) | set(column)
    for run_length, threads in ((64, 1), (1, 2), (2, 3)):
        got = fused([*near, far], run_length, threads)
        assert set(got) == set(expected)
        for g, (wd, w) in expected.items():
            assert got[g][1] == pytest.approx(w, abs=1e-5)
            assert got[g][0] == pytest.approx(wd, abs=1e-5)
