"""The sparse coarse search field against the former dense grid over the bounds
(support/dense_coarse_field.py): the same code at every cell of small maps and around them,
for every cell size, with windows small enough that every halo matters, and where the bounds
coarsen the cells; bricks only near the surface; the device layout that takes least memory."""

import numpy as np
import pytest
from support.dense_coarse_field import (
    dense_codes,
    dense_factor,
    dense_with_margin,
    sparse_over_bounds,
)
from support.floor_map import floor_map

from mcl3d.localization.sensor_model import SensorModelConfig

localize_world = pytest.importorskip("support.localize_world")

MARGIN = 3  # cells checked outside the bounds


@pytest.fixture(scope="module")
def room(backend):
    """The localization tests' room at 10 cm voxels."""
    from mcl3d.core import runtime

    runtime.init(backend)
    return localize_world.build_map(0.1)


def field_of(tsdf, cfg):
    from mcl3d.localization.coarse_field import coarse_field

    return coarse_field(tsdf, cfg)


@pytest.mark.parametrize("window_cells", [64, 8])
@pytest.mark.parametrize(("cell_m", "max_dist_m"), [(0.1, 1.5), (0.2, 0.45), (0.4, 1.5),
                                                    (0.8, 0.7)])
def test_same_codes_as_the_dense_field(room, monkeypatch, window_cells, cell_m, max_dist_m):
    """Windows of 8 cells put most surfaces of a window in its halo."""
    from mcl3d.localization import coarse_field

    monkeypatch.setattr(coarse_field, "WINDOW_CELLS", window_cells)
    cfg = SensorModelConfig(coarse_cell_m=cell_m, coarse_max_dist_m=max_dist_m)
    field = field_of(room, cfg)
    codes, cell = dense_codes(room, cfg)
    assert field.cell_m == pytest.approx(cell) == pytest.approx(max(cell_m, 0.1))
    np.testing.assert_array_equal(sparse_over_bounds(field, MARGIN),
                                  dense_with_margin(codes, MARGIN))
    assert len(field.bricks) > 2 and (field.block_slots >= 1).all()


def test_same_codes_on_the_floor_map(ti_runtime):
    """Unknown, FREE and partly observed blocks (support/floor_map.py)."""
    tsdf = floor_map()
    cfg = SensorModelConfig(coarse_cell_m=0.1, coarse_max_dist_m=0.45)
    codes, _ = dense_codes(tsdf, cfg)
    np.testing.assert_array_equal(sparse_over_bounds(field_of(tsdf, cfg), MARGIN),
                                  dense_with_margin(codes, MARGIN))


@pytest.mark.parametrize("cap_share", [4, 600])
def test_large_bounds_coarsen_the_cells_as_before(room, monkeypatch, cap_share):
    """The room inside bounds 6x its own, with a cap on the bounds' cells that the finest
    cells exceed: the cell grows as the dense field's did (0.2 m, or one cell per block under
    a tiny cap), with the same codes, and bricks only next to the room."""
    from mcl3d.localization import coarse_field

    offset = np.array([24, 24, 0])
    padded = localize_world.placed_together([(room, tuple(offset))], 0.1)
    cfg = SensorModelConfig(coarse_cell_m=0.1, coarse_max_dist_m=0.45)
    monkeypatch.setattr(coarse_field, "MAX_COARSE_CELLS",
                        padded.geometry.n_cells * 8**3 // cap_share)
    field = field_of(padded, cfg)
    assert dense_factor(padded, cfg) == {4: 2, 600: 8}[cap_share]
    codes, cell = dense_codes(padded, cfg)
    assert field.cell_m == pytest.approx(cell)
    np.testing.assert_array_equal(sparse_over_bounds(field, MARGIN),
                                  dense_with_margin(codes, MARGIN))
    own = field.block_coords[field.block_slots >= 2]
    assert len(own) and np.all(own >= offset - 1) and np.all(own <= offset + room.coarse_dims)


def test_an_empty_map_is_unknown_everywhere(ti_runtime):
    from mcl3d.localization.coarse_field import COARSE_UNKNOWN
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    tsdf = TsdfMap(MapGeometry(0.1, 0.3, (0.0, 0.0, 0.0), (3, 2, 2)), 4)
    field = field_of(tsdf, SensorModelConfig())
    assert len(field.block_coords) == 0
    assert (sparse_over_bounds(field, 1) == COARSE_UNKNOWN).all()


def test_the_device_layout_is_the_fastest_within_the_dense_budget(room, ti_runtime,
                                                                  monkeypatch):
    """The dense grid of codes (one read a lookup) while it fits likelihood.DENSE_SLOT_BYTES,
    then a dense slot per block (two reads), then tiles; the sparse layouts hold the same
    field in less memory when the map fills little of its bounds."""
    from mcl3d.kernels import likelihood as kl
    from mcl3d.localization.weighing import DeviceCoarseField, coarse_layout

    padded = localize_world.placed_together([(room, (24, 24, 0))], 0.1)
    field = field_of(padded, SensorModelConfig())
    sizes = {layout: sum(DeviceCoarseField(field, layout).nbytes.values())
             for layout in ("codes", "slots", "tiles")}
    assert coarse_layout(field_of(room, SensorModelConfig())) == "codes"
    assert coarse_layout(field) == "codes"
    assert max(sizes["slots"], sizes["tiles"]) < sizes["codes"] / 4, sizes
    blocks = int(np.prod(field.coarse_dims))
    monkeypatch.setattr(kl, "DENSE_SLOT_BYTES", 4 * blocks)
    assert coarse_layout(field) == "slots"
    monkeypatch.setattr(kl, "DENSE_SLOT_BYTES", 4 * blocks - 1)
    assert coarse_layout(field) == "tiles"
