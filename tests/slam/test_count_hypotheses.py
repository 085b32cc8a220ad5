"""count_hypotheses (grid cells holding >= 1% of the weight) against a dictionary count, for
a compact cloud (binned directly) and one spread over kilometres (sorted)."""

from collections import defaultdict

import numpy as np
import pytest

from mcl3d.slam.monte_carlo_slam import HYPOTHESIS_MIN_SHARE, count_hypotheses


def by_dictionary(positions, weights, cell_m):
    mass = defaultdict(float)
    for p, w in zip(np.floor(positions / cell_m).astype(np.int64), weights, strict=True):
        mass[tuple(p)] += w
    return sum(m >= HYPOTHESIS_MIN_SHARE for m in mass.values())


@pytest.mark.parametrize("spread_m", [0.5, 3.0, 2000.0])
def test_matches_a_dictionary_count(spread_m):
    rng = np.random.default_rng(int(spread_m))
    centres = rng.uniform(-spread_m, spread_m, (12, 3))
    positions = centres[rng.integers(0, 12, 5000)] + rng.normal(0.0, 0.3, (5000, 3))
    weights = rng.random(5000) ** 4
    weights /= weights.sum()
    expected = by_dictionary(positions, weights, 1.0)
    assert expected > 1
    assert count_hypotheses(positions, weights, 1.0) == expected
