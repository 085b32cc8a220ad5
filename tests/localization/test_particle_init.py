"""Global-initialization candidates: the height band and the floor seen in the first scan."""

import numpy as np

from mcl3d.localization.initialization import _in_height_band, floor_height


def test_height_band_counts_every_surface_below():
    """Brute force over random columns: a cell is in the band when any occupied cell below
    it (not only the nearest) is lo..hi below, heights measured as the map does."""
    rng = np.random.default_rng(0)
    occupied = rng.random((3, 4, 30)) < 0.08
    cell, trunc, lo, hi = 0.2, 0.15, 0.9, 1.5
    ok = _in_height_band(occupied, cell, trunc, lo, hi)
    ref = np.zeros_like(occupied)
    for x, y, z in np.ndindex(occupied.shape):
        heights = [(z - z0 - 0.5) * cell + trunc for z0 in range(z) if occupied[x, y, z0]]
        ref[x, y, z] = any(lo <= h <= hi for h in heights)
    np.testing.assert_array_equal(ok, ref)
    assert ok.any() and not ok.all()


def test_a_drone_over_a_crate_stays_in_the_band():
    """Floor at z = 0, a crate top at z = 1.5 m: the cell 3.4 m above the floor is 1.9 m
    above the crate, and the band around 3.4 m must still hold it."""
    cell, trunc = 0.2, 0.13  # no height exactly on a band edge
    occupied = np.zeros((1, 1, 30), bool)
    occupied[0, 0, [0, 8]] = True  # floor cell and crate-top cell
    ok = _in_height_band(occupied, cell, trunc, 3.2, 3.6)
    above_floor = (np.arange(30) - 0.5) * cell + trunc
    above_crate = above_floor - 8 * cell
    np.testing.assert_array_equal(ok[0, 0], ((above_floor >= 3.2) & (above_floor <= 3.6))
                                  | ((above_crate >= 3.2) & (above_crate <= 3.6)))
    assert ok[0, 0, 17]  # 3.53 m above the floor, 1.93 m above the crate


def test_floor_height_of_a_drone_among_walls():
    """A drone 3.4 m up in a hall: most returns below the sensor are on the walls, spread
    over every height, and the floor level holds fewer than a tenth of them; it still
    stands out from the walls (three times the mean level), so it is found."""
    rng = np.random.default_rng(1)
    angle = rng.uniform(0, 2 * np.pi, 12000)
    walls = np.column_stack([10 * np.cos(angle), 10 * np.sin(angle),
                             rng.uniform(-3.4, 2.0, 12000)])
    r = rng.uniform(5, 9, 700)
    a = rng.uniform(0, 2 * np.pi, 700)
    floor = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(-3.4, 0.01, 700)])
    pts = np.vstack([walls, floor])
    assert 0.1 * np.sum(pts[:, 2] < -0.1) > 700
    assert abs(floor_height(pts, 0.0, 0.0) - 3.4) < 0.05
    assert floor_height(walls, 0.0, 0.0) is None  # walls alone: no floor
