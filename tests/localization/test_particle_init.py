"""Global initialization: the floor seen in the first scan (the candidates:
test_global_candidates.py)."""

import numpy as np

from mcl3d.localization.initialization import floor_height


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
