"""Global-initialization candidates from the map's known blocks, column by column: the same
cells as the former dense grid over the bounds (kept here as the NumPy reference), and a
global start in a map whose bounds span kilometres but whose surface is two rooms."""

import numpy as np
import pytest

from mcl3d.core import geometry

localize_world = pytest.importorskip("support.localize_world")
LIDAR_Z_M = localize_world.LIDAR_Z_M

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
FAR_BLOCKS = (2500, 2500, 250)  # the room's offset in blocks: 1 km x 1 km x 100 m at 10 cm


def dense_candidates(tsdf, cfg) -> np.ndarray:
    """The former implementation: a dense (X, Y, Z) grid of cell states over the bounds,
    the height band by cumulative sums along z, covered cells by a reversed cumsum."""
    f = 1
    while f < 8 and tsdf.voxel_size_m * f * 2 <= cfg.cell_m + 1e-9:
        f *= 2
    k, cell, trunc = 8 // f, tsdf.voxel_size_m * f, tsdf.truncation_m
    data = tsdf.blocks()
    grid = np.zeros(np.asarray(tsdf.coarse_dims) * k, np.uint8)
    for c in data.free_coords:
        grid[c[0] * k:(c[0] + 1) * k, c[1] * k:(c[1] + 1) * k, c[2] * k:(c[2] + 1) * k] = FREE
    shape = (len(data.coords), k, f, k, f, k, f)
    observed = (data.weight > 0).reshape(shape)
    near = observed & (data.sdf < trunc * 0.999).reshape(shape)
    state = np.where(near.any(axis=(2, 4, 6)), OCCUPIED,
                     np.where((observed & ~near).all(axis=(2, 4, 6)), FREE, UNKNOWN))
    for (x, y, z), s in zip(data.coords, state, strict=True):
        grid[x * k:(x + 1) * k, y * k:(y + 1) * k, z * k:(z + 1) * k] = s
    ok = grid == FREE
    occupied = grid == OCCUPIED
    band = cfg.default_band_m if cfg.height_band_m == "auto" else cfg.height_band_m
    if band is not None and band != "none":
        lo, hi = band
        nz = grid.shape[2]
        counts = np.concatenate([np.zeros((*grid.shape[:2], 1), np.int32),
                                 np.cumsum(occupied, axis=2, dtype=np.int32)], axis=2)
        z = np.arange(nz)
        first = np.clip(np.ceil(z - 0.5 - (hi - trunc) / cell).astype(np.int64), 0, nz)
        last = np.clip(np.floor(z - 0.5 - (lo - trunc) / cell).astype(np.int64), -1, nz - 1)
        ok &= (counts[:, :, np.maximum(last + 1, first)] - counts[:, :, first]) > 0
    if cfg.covered is not False:
        def anything_above(mask):
            above = np.flip(np.cumsum(np.flip(mask, axis=2), axis=2), axis=2) > 0
            return np.concatenate([above[:, :, 1:], np.zeros_like(above[:, :, :1])], 2)

        covered = ok & anything_above(occupied)
        if not (cfg.covered == "auto" and covered.sum() < cfg.covered_share * max(ok.sum(), 1)):
            ok &= anything_above(grid != FREE)  # not under open sky
    return (np.asarray(tsdf.origin_m) + np.argwhere(ok) * cell).astype(np.float32)


@pytest.fixture(scope="module")
def maps(backend):
    """A mesh-built room (5 cm), the hall (10 cm) and a room fused from six scans (unknown
    voxels inside allocated blocks, carved free space)."""
    from mcl3d.core import runtime
    from mcl3d.maps.build import BuildConfig, MapGeometry, ScanFuser, new_map

    runtime.init(backend)
    room = localize_world.build_map()
    hall = localize_world.build_map(0.1, localize_world.hall_mesh())
    cfg = BuildConfig(voxel_size_m=0.1)
    mesh = localize_world.room_mesh()
    g = MapGeometry.around(mesh.vertices.min(0), mesh.vertices.max(0), 0.1, cfg.trunc_m,
                           margin_m=cfg.trunc_m)
    fused = new_map(g, cfg)
    scanner, fuser = localize_world.Scanner(seed=1), ScanFuser(fused, cfg)
    for T in localize_world.path(12)[::2]:
        fuser.fuse(scanner.scan(T), T)
    fused.finalize()
    return {"room": room, "hall": hall, "fused": fused}


CONFIGS = [{"height_band_m": None, "covered": False}, {}, {"covered": True},
           {"height_band_m": [0.5, 1.4], "covered": False}, {"cell_m": 0.1},
           {"cell_m": 0.4, "height_band_m": [0.0, 3.0]}, {"cell_m": 0.05, "covered": True}]


@pytest.mark.parametrize("name", ["room", "hall", "fused"])
def test_candidates_equal_the_dense_grid(maps, name, ti_runtime, monkeypatch):
    """Same cells in the same order for every option, also when the columns come in many
    small chunks."""
    from mcl3d.localization import initialization
    from mcl3d.localization.initialization import InitConfig, free_cells

    tsdf = maps[name]
    for i, overrides in enumerate(CONFIGS):
        cfg = InitConfig(**overrides)
        monkeypatch.setattr(initialization, "CHUNK_CELLS", 1 << 22 if i % 2 else 64)
        got = free_cells(tsdf, cfg)
        want = dense_candidates(tsdf, cfg)
        assert len(want) > 0
        np.testing.assert_array_equal(got.corners_m, want, err_msg=str(overrides))


def test_height_band_counts_every_surface_below():
    """Brute force over random columns: a free cell is in the band when any occupied cell
    below it (not only the nearest) is lo..hi below, heights measured as the map does."""
    from mcl3d.localization.initialization import _chunk_candidates

    rng = np.random.default_rng(0)
    dims = np.array([3, 4, 30])
    draw = rng.random(dims)
    states = np.where(draw < 0.08, OCCUPIED, np.where(draw < 0.1, UNKNOWN, FREE)).astype(np.uint8)
    cells = np.argwhere(np.ones(dims, bool))
    cell, trunc, lo, hi = 0.2, 0.15, 0.9, 1.5
    keys, covered, open_sky = _chunk_candidates(cells, states.reshape(-1), dims, (lo, hi),
                                                cell, trunc)
    ref, ref_covered, ref_open = [], [], []
    for x, y, z in np.ndindex(*dims):
        if states[x, y, z] != FREE:
            continue
        heights = [(z - z0 - 0.5) * cell + trunc for z0 in range(z) if states[x, y, z0] == 2]
        if any(lo <= h <= hi for h in heights):
            ref.append((x * dims[1] + y) * dims[2] + z)
            ref_covered.append(bool((states[x, y, z + 1:] == OCCUPIED).any()))
            ref_open.append(bool((states[x, y, z + 1:] == FREE).all()))
    np.testing.assert_array_equal(keys, ref)
    np.testing.assert_array_equal(covered, ref_covered)
    np.testing.assert_array_equal(open_sky, ref_open)
    assert 0 < len(ref) < (states == FREE).sum() and 0 < sum(ref_covered) < len(ref)
    assert 0 < sum(ref_open) < len(ref) - sum(ref_covered)  # also unknown above, no surface


def test_a_ceiling_never_seen_keeps_its_room_and_open_sky_goes():
    """Three columns of 0.2 m cells: a room whose ceiling the map saw, a room whose ceiling
    it never saw (a lidar inside it: unknown above 2.8 m) and a roof with free space above
    it to the map's top (a mesh-built map). Only the roof's cells are dropped."""
    from mcl3d.localization.initialization import InitConfig, _chunk_candidates, _without_open_sky

    nz = 30
    seen = np.full(nz, FREE, np.uint8)
    seen[[0, 15]] = OCCUPIED  # floor and ceiling (3 m)
    unseen = seen.copy()
    unseen[15:] = UNKNOWN
    roof = np.full(nz, FREE, np.uint8)
    roof[:16] = UNKNOWN  # inside the building below, as seen from above
    roof[16] = OCCUPIED
    states = np.concatenate([seen, unseen, roof])
    cells = np.stack([np.repeat([0, 1, 2], nz), np.zeros(3 * nz, int), np.tile(np.arange(nz), 3)],
                     axis=1)
    keys, covered, open_sky = _chunk_candidates(cells, states, np.array([3, 1, nz]), (0.2, 2.5),
                                                0.2, 0.15)
    kept = _without_open_sky(keys, covered, open_sky, InitConfig(covered=True))
    column = kept // nz
    assert set(column) == {0, 1} and (column == 0).sum() == (column == 1).sum() > 5
    assert (keys // nz == 2).sum() > 5 and covered[keys // nz == 1].sum() == 0


def test_a_drone_over_a_crate_stays_in_the_band():
    """Floor at z = 0, a crate top at z = 1.5 m: the cell 3.4 m above the floor is 1.9 m
    above the crate, and the band around 3.4 m must still hold it."""
    from mcl3d.localization.initialization import _chunk_candidates

    cell, trunc = 0.2, 0.13  # no height exactly on a band edge
    states = np.full(30, FREE, np.uint8)
    states[[0, 8]] = OCCUPIED  # floor cell and crate-top cell
    cells = np.stack([np.zeros(30, int), np.zeros(30, int), np.arange(30)], axis=1)
    keys, _, _ = _chunk_candidates(cells, states, np.array([1, 1, 30]), (3.2, 3.6), cell,
                                   trunc)
    above_floor = (np.arange(30) - 0.5) * cell + trunc
    above_crate = above_floor - 8 * cell
    want = (((above_floor >= 3.2) & (above_floor <= 3.6))
            | ((above_crate >= 3.2) & (above_crate <= 3.6))) & (states == FREE)
    np.testing.assert_array_equal(keys, np.flatnonzero(want))
    assert 17 in keys  # 3.53 m above the floor, 1.93 m above the crate


@pytest.fixture(scope="module")
def far_apart(maps):
    """The hall and the room (both at 10 cm) 1 km apart in x and y and 100 m in z: 1.6
    billion coarse cells of bounds (the dense grid refused anything over 160 million)."""
    room = localize_world.build_map(0.1)
    hall = maps["hall"]
    assert room.origin_m == hall.origin_m
    return room, hall, localize_world.placed_together([(hall, (0, 0, 0)), (room, FAR_BLOCKS)], 0.1)


def test_candidates_of_rooms_a_kilometre_apart(far_apart, ti_runtime):
    """The candidates of the joint map are those of each room, the far one's moved by its
    offset; they never touch the kilometre between them. (Open sky is free space up to the
    map's top, which the joint map raises by 100 m: the rooms' roofs are compared with
    `covered` off.)"""
    from mcl3d.localization.initialization import InitConfig, free_cells

    room, hall, joint = far_apart
    assert joint.geometry.n_cells > 1_500_000_000
    shift = np.asarray(FAR_BLOCKS) * joint.geometry.block_size_m
    for overrides in ({"covered": False}, {"height_band_m": None, "covered": False}):
        cfg = InitConfig(**overrides)
        got = free_cells(joint, cfg)
        want = np.concatenate([free_cells(hall, cfg).corners_m,
                               free_cells(room, cfg).corners_m + shift.astype(np.float32)])
        assert got.cell_m == pytest.approx(0.2)
        np.testing.assert_allclose(got.corners_m, want, atol=1e-3)


def test_coarse_field_of_rooms_a_kilometre_apart(far_apart, ti_runtime):
    """The coarse search field of the joint map holds each room's bricks (the same codes at
    every cell of each room's bounds) and nothing between them."""
    from mcl3d.localization.coarse_field import coarse_field
    from mcl3d.localization.sensor_model import SensorModelConfig

    room, hall, joint = far_apart
    cfg = SensorModelConfig(coarse_cell_m=0.8)  # the joint bounds' cell: one per block
    field = coarse_field(joint, cfg)
    k = field.cells_per_block
    assert coarse_field(joint, SensorModelConfig()).cell_m == pytest.approx(0.8) and k == 1
    bricked = field.block_coords[field.block_slots >= 2]
    by_a_room = np.zeros(len(bricked), bool)
    for part, offset in ((hall, (0, 0, 0)), (room, FAR_BLOCKS)):
        own = coarse_field(part, cfg)
        g = np.stack(np.meshgrid(*[np.arange(d * k) for d in part.coarse_dims], indexing="ij"),
                     axis=-1).reshape(-1, 3)
        np.testing.assert_array_equal(field.codes_at(g + np.asarray(offset) * k),
                                      own.codes_at(g))
        by_a_room |= np.all((bricked >= np.asarray(offset) - 2)
                            & (bricked < np.asarray(offset) + part.coarse_dims + 2), axis=1)
    assert by_a_room.all()  # within reach (1.5 m, 2 blocks) of a room's bounds
    assert len(bricked) > 100
    assert field.bricks.nbytes < 64 << 20


def test_global_start_in_rooms_a_kilometre_apart(far_apart, ti_runtime):
    """Particles start in both rooms; scans of the room bring the filter to its pose 1 km
    away, with the default coarse search phase (its field holds bricks near the rooms
    only, indexed through tiles: a few MiB where a dense grid would take terabytes)."""
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer

    _, _, joint = far_apart
    shift = geometry.se3(np.eye(3), np.asarray(FAR_BLOCKS) * joint.geometry.block_size_m)
    scanner = localize_world.Scanner(seed=2)
    path = localize_world.path(30)
    cfg = LocalizerConfig.model_validate({"particles": 20000, "seed": 3})
    loc = Localizer(joint, cfg, imu_roll_pitch=(0.0, 0.0))
    loc.init_global()
    pos, _, _ = loc.particles.host()
    assert (pos[:, 0] < 100).mean() > 0.3 and (pos[:, 0] > 900).mean() > 0.1  # both rooms
    T_prev = None
    for k, T in enumerate(path):
        dT = None if T_prev is None else geometry.relative_se3(T_prev, T)
        r = loc.step(scanner.scan(T), dT, 0.1 * k)
        T_prev = T
    err = np.linalg.norm(r.T_map_lidar[:3, 3] - (shift @ path[-1])[:3, 3])
    assert r.state == "converged" and err < 0.2, (r.state, err)
    field = loc.weigher.coarse_summary
    assert field["layout"] == "tiles" and field["index_bytes"] + field["brick_bytes"] < 64 << 20


def test_a_room_fused_from_its_scans_keeps_candidates_under_its_unseen_ceiling(maps, ti_runtime):
    """The fused room's lidar (0.8 m up, beams within 15 deg) sees the 3 m ceiling only near
    the far walls: most of its candidates have no surface observed above them, and keeping
    only those with one would drop them. Unknown above is no open sky: all of them stay."""
    from mcl3d.localization import initialization
    from mcl3d.localization.initialization import InitConfig, free_cells

    fused = maps["fused"]
    band = (LIDAR_Z_M - 0.3, LIDAR_Z_M + 0.3)
    kept = free_cells(fused, InitConfig(covered=True, height_band_m=list(band)))
    every = free_cells(fused, InitConfig(covered=False, height_band_m=list(band)))
    np.testing.assert_array_equal(kept.corners_m, every.corners_m)
    cells, values = fused.coarse_cells()
    columns = initialization._Columns.of(fused, 2, cells[values == initialization.FREE_BLOCK])
    dims = np.asarray(fused.coarse_dims, np.int64) * 4
    flags = [initialization._chunk_candidates(*columns.cells(part), dims, band, 0.2,
                                              fused.truncation_m)[1:]
             for part in columns.chunks()]
    covered, open_sky = (np.concatenate(f) for f in zip(*flags, strict=True))
    assert len(covered) == len(every.corners_m) > 50
    assert covered.mean() < 0.5 and not open_sky.any()
