"""Place evidence (mcl3d.localization.evidence) against direct NumPy computations."""

import itertools

import numpy as np

from mcl3d.core import geometry
from mcl3d.localization.evidence import (
    PlaceEvidence,
    place_floor,
    place_labels,
    rival_gap,
)


def yaw_quats(yaw_rad):
    return np.array([geometry.rot_to_quat(geometry.rpy_to_rot(0.0, 0.0, y)) for y in yaw_rad])


def test_places_split_position_and_heading():
    pos = np.array([[0.1, 0.1, 0.0], [0.9, 0.8, 0.5], [1.1, 0.1, 0.0], [0.2, 0.2, 0.1]])
    quats = yaw_quats(np.radians([0.0, 10.0, 0.0, 180.0]))
    labels = place_labels(pos, quats, cell_m=1.0, yaw_bins=12)
    assert labels[0] == labels[1]  # same cell, same 30-degree bin
    assert len({labels[0], labels[2], labels[3]}) == 3  # next cell; turned around
    assert labels.min() == 0 and labels.max() == len(np.unique(labels)) - 1


def test_each_place_continues_from_its_best_and_adds_its_best_drawn_increment():
    ev = PlaceEvidence()
    ev.reset(5)
    ev.log_l = np.array([-1.0, -3.0, -2.0, -5.0, -4.0])
    places = np.array([0, 0, 1, 1, 1])
    inc = np.array([0.5, 2.0, -1.0, 1.0, 0.0])
    ev.add(inc, places, sample=10, rng=np.random.default_rng(0))
    expected = np.array([-1.0 + 2.0] * 2 + [-2.0 + 1.0] * 3)
    np.testing.assert_allclose(ev.log_l, expected)
    assert ev.scans == 1
    ev.inherit(np.array([4, 4, 0, 1, 2]))
    np.testing.assert_allclose(ev.log_l, expected[[4, 4, 0, 1, 2]])


def test_the_increment_is_judged_on_the_same_number_of_particles_per_place():
    """A place with 1000 particles must not beat a place with 10 on the maximum of noise."""
    rng = np.random.default_rng(1)
    places = np.repeat([0, 1], [1000, 10])
    wins = 0
    for _ in range(200):
        ev = PlaceEvidence()
        ev.add(rng.normal(size=1010), places, sample=10, rng=rng)
        wins += ev.log_l[0] > ev.log_l[-1]
    assert 70 < wins < 130  # a fair coin, not the 1000-particle place every time


def test_noise_margin_grows_with_scans_and_places():
    ev = PlaceEvidence()
    rng = np.random.default_rng(2)
    places = np.repeat(np.arange(50), 40)
    margins = []
    for _ in range(4):
        ev.add(rng.normal(0.0, 1.0, len(places)), places, sample=8, rng=rng)
        margins.append(ev.noise_margin(50))
    assert all(b > a for a, b in itertools.pairwise(margins))
    assert ev.noise_margin(500) > ev.noise_margin(5) > 0
    ev.reset(10)
    assert ev.noise_margin(50) == 0.0


def test_the_noise_is_the_sampling_noise_not_the_places_real_differences():
    """Places that differ by a constant but whose particles all score alike add no noise."""
    ev = PlaceEvidence()
    places = np.repeat(np.arange(20), 64)
    for _ in range(3):
        ev.add(places * 0.5, places, sample=16, rng=np.random.default_rng(3), leaders_nats=100)
    assert ev.noise_margin(20) == 0.0
    np.testing.assert_allclose(ev.log_l, 3 * places * 0.5)


def test_rival_gap_compares_the_best_away_with_the_best_at_the_dominant_pose():
    pos = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    quats = yaw_quats(np.radians([0.0, 5.0, 0.0, 180.0]))
    log_l = np.array([-2.0, -1.0, -4.0, -3.0])
    T = np.eye(4)
    gap = rival_gap(pos, quats, log_l, T, radius_m=2.0, angle_rad=1.0)
    assert gap == -3.0 - (-1.0)  # the best away (turned around) minus the best inside
    assert rival_gap(pos[:2], quats[:2], log_l[:2], T, 2.0, 1.0) == -np.inf
    T_far = geometry.se3(np.eye(3), [20.0, 0.0, 0.0])
    assert rival_gap(pos, quats, log_l, T_far, 2.0, 1.0) == np.inf


def test_live_places_keep_their_floor_and_ruled_out_places_do_not():
    labels = np.repeat([0, 1, 2], [9000, 10, 10])
    weights = np.concatenate([np.full(9000, 1.0), np.full(20, 1e-6)])
    log_l = np.concatenate([np.zeros(9010), np.full(10, -50.0)])  # place 2 ruled out
    factors, live = place_floor(labels, weights, log_l, margin_nats=10.0, min_particles=32)
    assert live == 2
    w = weights * factors
    expected_copies = len(weights) * np.bincount(labels, weights=w) / w.sum()
    assert expected_copies[1] >= 31.9
    assert expected_copies[2] < 1e-3
    assert np.all(factors[labels == 2] == 1.0)
