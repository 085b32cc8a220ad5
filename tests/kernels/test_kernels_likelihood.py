"""The scan-likelihood kernel against its NumPy twin on a tiny hand-made map, including the
unknown, observed-free and outside-the-map cases."""

import numpy as np
import pytest
from support.floor_map import FLOOR_Z, TRUNC, VOX, floor_map

from mcl3d.core import geometry
from mcl3d.localization.sensor_model import (
    NumpyTsdf,
    SensorModelConfig,
    code_table,
    point_log_likelihood_numpy,
    scan_log_likelihood_numpy,
)


def code_map(tsdf, cfg, tiled=False):
    """The kernel's per-voxel codes (i32 words of two 16-bit codes) and coarse-cell slots,
    dense over the bounds (as small maps have them) or `tiled` (as large maps)."""
    import taichi as ti

    from mcl3d.kernels import likelihood as kl

    codes = ti.field(ti.i32, shape=(tsdf.capacity + 2, kl.BLOCK, kl.BLOCK, kl.WORDS_Z))
    shape = (tsdf.tile_capacity + 1, kl.TILE, kl.TILE, kl.TILE) if tiled else tsdf.coarse_dims
    assert tiled or kl.slot_shape(tsdf) == shape
    slots = ti.field(ti.i32, shape=shape)
    kl.build_codes(tsdf, codes, tsdf.n_blocks, cfg.match_dist_m)
    kl.build_slots(tsdf, slots)
    return codes, slots


def pool_slots(tsdf, slots, cells):
    """likelihood.slot_of of each coarse cell (n, 3), as the hot loops read it."""
    import taichi as ti

    from mcl3d.kernels.likelihood import slot_of

    @ti.kernel
    def slots_of(m: ti.template(), slot: ti.template(),
                 c: ti.types.ndarray(dtype=ti.math.ivec3, ndim=1),
                 out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(c.shape[0]):
            out[i] = slot_of(m, slot, c[i])

    out = np.zeros(len(cells), np.int32)
    slots_of(tsdf, slots, np.ascontiguousarray(cells, dtype=np.int32), out)
    return out


def run_kernel(tsdf, positions, quats, points, cfg, cache_block, tiled=False):
    import taichi as ti

    from mcl3d.kernels.likelihood import N_CODES, scan_log_likelihood

    n, m = len(positions), len(points)
    pos = ti.Vector.field(3, ti.f32, shape=n)
    quat = ti.Vector.field(4, ti.f32, shape=n)
    pts = ti.Vector.field(3, ti.f32, shape=m)
    table = ti.field(ti.f32, shape=N_CODES)
    log_w, match, ll_mean = (ti.field(ti.f32, shape=n) for _ in range(3))
    pos.from_numpy(positions.astype(np.float32))
    quat.from_numpy(quats.astype(np.float32))
    pts.from_numpy(points.astype(np.float32))
    table.from_numpy(code_table(cfg, tsdf.truncation_m))
    log_w.from_numpy(np.full(n, 2.0, np.float32))  # the kernel adds to the previous weight
    order = ti.field(ti.i32, shape=n)  # any permutation: results are per particle
    order.from_numpy(np.random.default_rng(n).permutation(n).astype(np.int32))
    codes, slots = code_map(tsdf, cfg, tiled)
    scan_log_likelihood(tsdf, codes, slots, order, pos, quat, n, pts, m, table,
                        cfg.tempering(m), log_w, match, ll_mean, cache_block)
    return log_w.to_numpy() - 2.0, match.to_numpy(), ll_mean.to_numpy()


@pytest.mark.parametrize(("cache_block", "tiled"), [(False, False), (True, False),
                                                    (False, True), (True, True)])
def test_kernel_matches_numpy_twin(ti_runtime, cache_block, tiled):
    tsdf = floor_map()
    host = NumpyTsdf.of(tsdf)
    cfg = SensorModelConfig(sigma_m=0.05, effective_points=4.0)
    rng = np.random.default_rng(0)
    n, m = 37, 23
    positions = rng.uniform([-0.3, -0.3, 0.3], [1.9, 1.9, 1.7], size=(n, 3))
    quats = geometry.rot_to_quat(geometry.random_rotations(rng, n))
    points = rng.normal(scale=0.6, size=(m, 3))
    k_ll, k_match, k_mean = run_kernel(tsdf, positions, quats, points, cfg, cache_block, tiled)
    r_ll, r_match, r_mean = scan_log_likelihood_numpy(host, positions, quats, points, cfg)
    # f32 transforms may put a point on the other side of a voxel face: allow a few
    per_point = np.abs(k_mean - r_mean) * m
    assert np.mean(per_point < 1e-3) > 0.9
    assert np.all(per_point < 4.0)
    np.testing.assert_allclose(k_ll, r_ll, atol=cfg.tempering(m) * 4.0)
    assert np.mean(np.abs(k_match - r_match) < 1e-6) > 0.9


def test_codes_match_the_model_at_every_voxel(ti_runtime):
    """Each voxel's code, decoded through the code table, is the NumPy model's value and
    match flag at that voxel; unallocated cells point at the constant blocks."""
    from mcl3d.kernels.likelihood import MATCH_BIT

    tsdf = floor_map()
    host = NumpyTsdf.of(tsdf)
    cfg = SensorModelConfig(sigma_m=0.05, match_dist_m=0.12)
    codes, slots = code_map(tsdf, cfg)
    words = codes.to_numpy()
    g = np.stack(np.meshgrid(*(np.arange(16),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    p = (g + 0.5) * VOX
    d, w, b = host.lookup(p)
    s = pool_slots(tsdf, slots, g >> 3)
    code = (words[s, g[:, 0] & 7, g[:, 1] & 7, (g[:, 2] & 7) >> 1] >> (16 * (g[:, 2] & 1))
            ) & 0xFFFF
    np.testing.assert_allclose(code_table(cfg, TRUNC)[code],
                               point_log_likelihood_numpy(d, w, b, TRUNC, cfg), atol=1e-6)
    observed = (b >= 0) & ((w > 0) | (d < np.float32(TRUNC * 0.999)))
    np.testing.assert_array_equal((code >> MATCH_BIT) & 1,
                                  observed & (np.abs(d) < cfg.match_dist_m))
    assert set(np.unique(s[b == -3])) == {tsdf.capacity}
    assert set(np.unique(s[b == -1])) == {tsdf.capacity + 1}


def scattered_map():
    """Blocks and FREE cells scattered over 3 x 2 x 2 tiles, some tiles left unclaimed."""
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf = TsdfMap(MapGeometry(VOX, TRUNC, (0.0, 0.0, 0.0), (19, 10, 9)), 128)
    rng = np.random.default_rng(5)
    tsdf.mark_free(rng.integers(0, (19, 10, 9), size=(40, 3)))
    tsdf.allocate(rng.integers(0, (19, 7, 9), size=(100, 3)))
    return tsdf


@pytest.mark.parametrize("tiled", [False, True])
@pytest.mark.parametrize("make_map", [floor_map, scattered_map])
def test_pool_slots_match_the_sparse_index(ti_runtime, make_map, tiled):
    """Every coarse cell, inside and outside the bounds, reads its block through the top
    grid and its tile: its id, `capacity` when FREE, `capacity + 1` when unknown."""
    tsdf = make_map()
    _, values = tsdf.coarse_cells()
    dims = np.asarray(tsdf.coarse_dims)
    g = np.stack(np.meshgrid(*[np.arange(-2, d + 2) for d in dims], indexing="ij"),
                 axis=-1).reshape(-1, 3)
    expected = NumpyTsdf.of(tsdf).coarse(g)
    expected = np.where(expected >= 0, expected,
                        np.where(expected == -3, tsdf.capacity, tsdf.capacity + 1))
    slots = code_map(tsdf, SensorModelConfig(), tiled)[1]
    np.testing.assert_array_equal(pool_slots(tsdf, slots, g), expected)
    assert (values >= 0).sum() == tsdf.n_blocks and (values == -3).any()


def test_locality_keys_match_numpy(ti_runtime):
    """15-bit Morton keys of (x, y, yaw) cells, each axis wrapped to 5 bits."""
    import taichi as ti

    from mcl3d.kernels.likelihood import locality_keys

    rng = np.random.default_rng(2)
    n = 300
    positions = rng.uniform(-3.0, 3.0, size=(n, 3)).astype(np.float32)
    quats = geometry.rot_to_quat(geometry.random_rotations(rng, n)).astype(np.float32)
    pos = ti.Vector.field(3, ti.f32, shape=n)
    quat = ti.Vector.field(4, ti.f32, shape=n)
    keys = ti.field(ti.i32, shape=n)
    pos.from_numpy(positions)
    quat.from_numpy(quats)
    locality_keys(pos, quat, n, 0.1, 0.02, keys)
    yaw = geometry.rot_to_rpy(geometry.quat_to_rot(quats.astype(np.float64)))[:, 2]
    cells = np.floor(np.column_stack([positions[:, :2] / 0.1, yaw / 0.02])).astype(np.int64)
    expected = np.zeros(n, np.int64)
    for bit in range(5):
        for axis in range(3):
            expected |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    # a value on a cell boundary may land on either side in f32
    assert np.mean(keys.to_numpy() == expected) > 0.97
    assert keys.to_numpy().max() < 2**15


def test_point_cases(ti_runtime):
    """One particle at the identity, one point per case, checked against the model."""
    tsdf = floor_map()
    cfg = SensorModelConfig(sigma_m=0.05, effective_points=1.0)
    cases = {
        "surface": ([1.05, 0.45, FLOOR_Z + 0.01], None),
        "behind": ([1.05, 0.45, FLOOR_Z - 0.2], None),
        "observed free": ([0.45, 0.45, 1.5], cfg.log_free),
        "FREE block": ([1.2, 1.2, 1.2], cfg.log_free),
        "unknown block": ([1.2, 1.2, 0.4], cfg.log_unknown),
        "never-observed voxel": ([0.05, 0.45, 0.45], cfg.log_unknown),
        "outside the map": ([5.0, 0.5, 0.5], cfg.log_unknown),
    }
    for name, (p, expected) in cases.items():
        ll, match, mean = run_kernel(tsdf, np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]]),
                                     np.array([p]), cfg, False)
        if expected is None:
            # the voxel centre's distance to the plane, through the exact hit term
            zc = (np.floor(p[2] / VOX) + 0.5) * VOX
            d = zc - FLOOR_Z
            expected = np.log(cfg.z_hit * np.exp(-0.5 * (d / cfg.sigma_m) ** 2) + cfg.z_rand)
            assert mean[0] == pytest.approx(expected, abs=2e-3), name
            assert match[0] == (1.0 if abs(d) < cfg.match_dist_m else 0.0), name
        else:
            assert mean[0] == pytest.approx(expected, abs=1e-6), name
            assert match[0] == 0.0, name
        assert ll[0] == pytest.approx(mean[0] * cfg.tempering(1), abs=1e-5)
    # the ordering the model promises: hit > unknown > random floor > observed free
    assert np.log(cfg.z_hit + cfg.z_rand) > cfg.log_unknown > np.log(cfg.z_rand) > cfg.log_free


def test_table_matches_exact_model():
    cfg = SensorModelConfig(sigma_m=0.05)
    d = np.linspace(-TRUNC + 1e-4, TRUNC * 0.99, 2001).astype(np.float32)
    b = np.zeros_like(d, dtype=np.int64)
    w = np.ones_like(d)
    table = point_log_likelihood_numpy(d, w, b, TRUNC, cfg)
    exact = point_log_likelihood_numpy(d, w, b, TRUNC, cfg, exact=True)
    assert np.max(np.abs(table - exact)) < 0.01


def test_reduce_scan_keeps_the_first_point_of_each_voxel():
    """The one-key-per-cell dedup keeps exactly the points a row-wise np.unique would."""
    from mcl3d.localization.sensor_model import reduce_scan

    rng = np.random.default_rng(5)
    pts = rng.uniform(-20.0, 20.0, size=(5000, 3)).astype(np.float32)
    pts[::7] = pts[::7] * 0.01 + 3.0  # many points share voxels
    cfg = SensorModelConfig(voxel_m=0.5, points=65536, min_range_m=0.5, max_range_m=30.0)
    r = np.linalg.norm(pts, axis=1)
    idx = np.flatnonzero((r >= 0.5) & (r <= 30.0))
    _, first = np.unique(np.floor(pts[idx] / 0.5).astype(np.int64), axis=0, return_index=True)
    np.testing.assert_array_equal(reduce_scan(pts, cfg, rng), pts[idx[np.sort(first)]])


def test_spatial_order_is_a_permutation_along_a_z_curve():
    from mcl3d.localization.sensor_model import spatial_order

    g = np.stack(np.meshgrid(*(np.arange(4),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    order = spatial_order((g[::-1] + 0.5) * 0.4, 0.4)
    np.testing.assert_array_equal(np.sort(order), np.arange(64))
    cells = g[::-1][order]
    assert np.all(np.abs(np.diff(cells[:8], axis=0)).max(axis=1) <= 1)  # the first 2^3 cube
    np.testing.assert_array_equal(cells[0], [0, 0, 0])
    np.testing.assert_array_equal(cells[-1], [3, 3, 3])


def coarse_case(max_dist_m=0.45):
    from mcl3d.localization.coarse_field import coarse_field

    cfg = SensorModelConfig(coarse_cell_m=VOX, coarse_max_dist_m=max_dist_m, match_dist_m=0.12)
    return cfg, coarse_field(floor_map(), cfg)


def test_coarse_field_is_the_distance_to_the_nearest_surface_cell(ti_runtime):
    """Codes against a brute-force distance between cell centres; far cells split into
    observed (far-free code) and unknown (the unknown block, the never-observed voxels)."""
    from mcl3d.localization.coarse_field import COARSE_BINS

    cfg, field = coarse_case()
    assert field.cell_m == pytest.approx(VOX) and field.cells_per_block == 8
    g = np.stack(np.meshgrid(*(np.arange(16),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    surface_k = int(FLOOR_Z / VOX)
    in_free_block = (g[:, 0] >= 8) & (g[:, 1] >= 8) & (g[:, 2] >= 8)
    surf = g[(g[:, 2] == surface_k) & ~in_free_block]
    dist = np.sqrt(((g[:, None, :] - surf[None]) ** 2).sum(-1)).min(1) * VOX
    unknown = ((g[:, 0] >= 8) & (g[:, 1] >= 8) & (g[:, 2] < 8)) | (
        (g[:, 0] == 0) & (g[:, 1] < 8) & (g[:, 2] < 8))
    code = field.codes_at(g)
    near = dist < cfg.coarse_max_dist_m - 1e-6
    np.testing.assert_array_equal(code[near], np.minimum(
        (dist[near] * COARSE_BINS / cfg.coarse_max_dist_m).astype(int), COARSE_BINS - 1))
    np.testing.assert_array_equal(code[~near & ~unknown], COARSE_BINS)
    np.testing.assert_array_equal(code[~near & unknown], COARSE_BINS + 1)


def coarse_particles(rng, n, m, lo, hi, spread_m):
    """n poses uniform in [lo, hi) with uniform rotations, m points around the sensor."""
    positions = rng.uniform(lo, hi, size=(n, 3))
    quats = geometry.rot_to_quat(geometry.random_rotations(rng, n))
    return positions, quats, rng.normal(scale=spread_m, size=(m, 3))


def run_coarse(kernel, field, origin_m, cell_m, positions, quats, points, cfg, sigma_m):
    """(log-weight increment, match, mean ll) of `kernel` (the coarse kernel's signature)
    on the device field `field`."""
    import taichi as ti

    from mcl3d.localization.coarse_field import coarse_match_codes, coarse_table

    n, m = len(positions), len(points)
    pos = ti.Vector.field(3, ti.f32, shape=n)
    quat = ti.Vector.field(4, ti.f32, shape=n)
    pts = ti.Vector.field(3, ti.f32, shape=m)
    table = coarse_table(cfg, sigma_m)
    tab = ti.field(ti.f32, shape=len(table))
    log_w, match, ll_mean = (ti.field(ti.f32, shape=n) for _ in range(3))
    order = ti.field(ti.i32, shape=n)
    pos.from_numpy(positions.astype(np.float32))
    quat.from_numpy(quats.astype(np.float32))
    pts.from_numpy(points.astype(np.float32))
    tab.from_numpy(table)
    log_w.from_numpy(np.full(n, 1.0, np.float32))
    order.from_numpy(np.random.default_rng(n).permutation(n).astype(np.int32))
    kernel(field, ti.math.vec3(*origin_m), 1.0 / cell_m, order, pos, quat, n, pts, m, tab,
           coarse_match_codes(cfg), cfg.tempering(m), log_w, match, ll_mean)
    return log_w.to_numpy() - 1.0, match.to_numpy(), ll_mean.to_numpy()


@pytest.mark.parametrize("layout", ["codes", "slots", "tiles"])
def test_coarse_kernel_matches_numpy_twin(ti_runtime, layout):
    from mcl3d.kernels.likelihood import coarse_scan_log_likelihood
    from mcl3d.localization.coarse_field import (
        COARSE_BINS,
        coarse_log_likelihood_numpy,
        coarse_match_codes,
        coarse_table,
    )
    from mcl3d.localization.weighing import DeviceCoarseField

    cfg, field = coarse_case()
    rng = np.random.default_rng(4)
    positions, quats, points = coarse_particles(rng, 41, 29, [-0.3, -0.3, 0.3], [1.9, 1.9, 1.7],
                                                0.6)
    m = len(points)
    device = DeviceCoarseField(field, layout)
    ll, match, mean = run_coarse(coarse_scan_log_likelihood, device, field.origin_m,
                                 field.cell_m, positions, quats, points, cfg, 0.3)
    table = coarse_table(cfg, 0.3)
    r_ll, r_match, r_mean = coarse_log_likelihood_numpy(
        field, positions, quats, points, table, coarse_match_codes(cfg), cfg.tempering(m))
    per_point = np.abs(mean - r_mean) * m
    assert np.mean(per_point < 1e-3) > 0.9  # f32: a point on a cell face may differ
    np.testing.assert_allclose(ll, r_ll, atol=cfg.tempering(m) * 4.0)
    assert np.mean(np.abs(match - r_match) < 1e-6) > 0.9
    # the table: best on a surface, the random floor far from it, free below, unknown neutral
    assert table[0] > table[COARSE_BINS - 1] > cfg.log_free
    assert table[-1] == pytest.approx(cfg.log_unknown)


def dense_coarse_kernel():
    """The former kernel over a dense (X, Y, Z) grid of codes, as the reference."""
    import taichi as ti

    from mcl3d.kernels.se3 import quat_to_mat

    @ti.kernel
    def kernel(field: ti.template(), origin: ti.math.vec3, inv_cell: ti.f32,
               order: ti.template(), pos: ti.template(), quat: ti.template(), n: ti.i32,
               pts: ti.template(), n_pts: ti.i32, table: ti.template(), match_codes: ti.i32,
               tempering: ti.f32, log_w: ti.template(), match: ti.template(),
               ll_mean: ti.template()):
        dims = ti.static(field.shape)
        ti.loop_config(block_dim=64)
        for k in range(n):
            i = order[k]
            R = quat_to_mat(quat[i])
            t = (pos[i] - origin) * inv_cell
            Rs = R * inv_cell
            total = 0.0
            hits = 0
            for j in range(n_pts):
                g = ti.cast(ti.floor(Rs @ pts[j] + t), ti.i32)
                inside = (g[0] >= 0) & (g[0] < dims[0]) & (g[1] >= 0) & (g[1] < dims[1]) & (
                    g[2] >= 0) & (g[2] < dims[2])
                gc = ti.select(inside, g, 0)
                code = ti.select(inside, field[gc[0], gc[1], gc[2]], 257)
                total += table[code]
                hits += ti.cast(code < match_codes, ti.i32)
            inv_m = 1.0 / ti.max(n_pts, 1)
            log_w[i] += tempering * total
            match[i] = hits * inv_m
            ll_mean[i] = total * inv_m

    return kernel


@pytest.mark.parametrize("layout", ["codes", "slots", "tiles"])
def test_coarse_kernel_gives_the_dense_kernels_results(ti_runtime, layout):
    """On the localization tests' room (0.2 m cells, 4^3 per block), particles inside and
    around it: the sparse field gives the former dense field's results (to float rounding: the
    compiler may fuse the two kernels' sums differently on some CPUs)."""
    import taichi as ti
    from support.dense_coarse_field import dense_codes
    from support.localize_world import build_map

    from mcl3d.kernels.likelihood import coarse_scan_log_likelihood
    from mcl3d.localization.coarse_field import coarse_field
    from mcl3d.localization.weighing import DeviceCoarseField

    tsdf = build_map(0.1)
    cfg = SensorModelConfig(coarse_cell_m=0.2)
    field = coarse_field(tsdf, cfg)
    codes, cell = dense_codes(tsdf, cfg)
    dense = ti.field(ti.i32, shape=codes.shape)
    dense.from_numpy(codes)
    lo, hi = tsdf.geometry.extent_m
    args = (*coarse_particles(np.random.default_rng(6), 300, 96, lo - 1.0, hi + 1.0, 3.0), cfg,
            0.4)
    got = run_coarse(coarse_scan_log_likelihood, DeviceCoarseField(field, layout),
                     field.origin_m, field.cell_m, *args)
    want = run_coarse(dense_coarse_kernel(), dense, field.origin_m, cell, *args)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=0)
    assert np.ptp(want[2]) > 0.5  # particles in and around the room score differently
