"""Place evidence (mcl3d.localization.evidence, on the device): what each step decides.
The per-particle arithmetic against NumPy is in tests/kernels/test_kernels_place_evidence.py."""

import itertools

import numpy as np
import pytest

from mcl3d.core import geometry

CAPACITY = 9100  # one particle set and one evidence for the module: kernels compile once


def yaw_quats(yaw_rad):
    yaw_rad = np.asarray(yaw_rad, np.float64)
    return geometry.rot_to_quat(geometry.so3_exp(np.column_stack(
        [np.zeros_like(yaw_rad), np.zeros_like(yaw_rad), yaw_rad])))


@pytest.fixture(scope="module")
def state(backend):
    from mcl3d.core import runtime
    from mcl3d.localization.evidence import PlaceEvidence
    from mcl3d.localization.particle_set import ParticleSet

    runtime.init(backend)
    return ParticleSet(CAPACITY), PlaceEvidence(CAPACITY)


def at_places(state, places, log_l=None, w=None):
    """Particle i in the middle of 1 m cell (places[i], 0, 0), heading +x; the evidence
    reset to `log_l`."""
    p, ev = state
    places = np.asarray(places)
    n = len(places)
    pos = np.column_stack([places + 0.5, np.full(n, 0.5), np.full(n, 0.5)])
    p.set_host(pos, yaw_quats(np.full(n, 0.1)))
    if w is not None:
        p.w.from_numpy(np.pad(w, (0, CAPACITY - n)).astype(np.float32))
    ev.reset(n)
    if log_l is not None:
        ev.log_l.from_numpy(np.pad(log_l, (0, CAPACITY - n)).astype(np.float32))
    return p, ev


def add(state, increment, sample, counter=1, leaders_nats=10.0):
    p, ev = state
    n = len(increment)
    p.ll_mean.from_numpy(np.pad(increment, (0, CAPACITY - n)).astype(np.float32))
    ev.add(p, 1.0, 1.0, 12, sample, seed=1, counter=counter, leaders_nats=leaders_nats)
    return ev.log_l.to_numpy()[:n].astype(np.float64)


def test_places_split_position_and_heading(state):
    p, ev = state
    pos = np.array([[0.1, 0.1, 0.0], [0.9, 0.8, 0.5], [1.1, 0.1, 0.0], [0.2, 0.2, 0.1]])
    p.set_host(pos, yaw_quats(np.radians([0.0, 10.0, 0.0, 180.0])))
    p.ll_mean.from_numpy(np.zeros(CAPACITY, np.float32))
    ev.reset(4)
    ev.add(p, 1.0, 1.0, 12, 2, seed=1, counter=1)
    labels = ev.fields.place_of.to_numpy()[:4]
    assert labels[0] == labels[1]  # same cell, same 30-degree bin
    assert len({labels[0], labels[2], labels[3]}) == 3  # next cell; turned around
    assert ev.places == 3 and sorted(set(labels)) == [0, 1, 2]


def test_each_place_continues_from_its_best_and_adds_its_best_drawn_increment(state):
    _, ev = at_places(state, [0, 0, 1, 1, 1], log_l=[-1.0, -3.0, -2.0, -5.0, -4.0])
    log_l = add(state, np.array([0.5, 2.0, -1.0, 1.0, 0.0]), sample=10)
    expected = np.array([-1.0 + 2.0] * 2 + [-2.0 + 1.0] * 3)
    np.testing.assert_allclose(log_l, expected)
    assert ev.scans == 1


def test_the_increment_is_judged_on_the_same_number_of_particles_per_place(state):
    """A place with 1000 particles must not beat a place with 10 on the maximum of noise."""
    rng = np.random.default_rng(1)
    places = np.repeat([0, 1], [1000, 10])
    wins = 0
    for k in range(200):
        at_places(state, places)
        log_l = add(state, rng.normal(size=1010), sample=10, counter=k)
        wins += log_l[0] > log_l[-1]
    assert 70 < wins < 130  # a fair coin, not the 1000-particle place every time


def test_noise_margin_grows_with_scans_and_places(state):
    rng = np.random.default_rng(2)
    places = np.repeat(np.arange(50), 40)
    _, ev = at_places(state, places)
    margins = []
    for k in range(4):
        add(state, rng.normal(0.0, 1.0, len(places)), sample=8, counter=k)
        margins.append(ev.noise_margin(50))
    assert all(b > a for a, b in itertools.pairwise(margins))
    assert ev.noise_margin(500) > ev.noise_margin(5) > 0
    ev.reset(10)
    assert ev.noise_margin(50) == 0.0


def test_the_noise_is_the_sampling_noise_not_the_places_real_differences(state):
    """Places that differ by a constant but whose particles all score alike add no noise."""
    places = np.repeat(np.arange(20), 64)
    _, ev = at_places(state, places)
    for k in range(3):
        log_l = add(state, places * 0.5, sample=16, counter=k, leaders_nats=100.0)
    assert ev.noise_margin(20) == 0.0
    np.testing.assert_allclose(log_l, 3 * places * 0.5)


def test_rival_gap_compares_the_best_away_with_the_best_at_the_dominant_pose(state):
    p, ev = state
    pos = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    p.set_host(pos, yaw_quats(np.radians([0.0, 5.0, 0.0, 180.0])))
    ev.reset(4)
    ev.log_l.from_numpy(np.pad([-2.0, -1.0, -4.0, -3.0], (0, CAPACITY - 4)).astype(np.float32))
    T = np.eye(4)
    assert ev.rival_gap(p, T, radius_m=2.0, angle_rad=1.0) == -3.0 - (-1.0)
    T_far = geometry.se3(np.eye(3), [20.0, 0.0, 0.0])
    assert ev.rival_gap(p, T_far, 2.0, 1.0) == np.inf
    p.n = ev.n = 2  # both near the dominant pose
    assert ev.rival_gap(p, T, 2.0, 1.0) == -np.inf


def test_live_places_keep_their_floor_and_ruled_out_places_do_not(state):
    labels = np.repeat([0, 1, 2], [9000, 10, 10])
    weights = np.concatenate([np.full(9000, 1.0), np.full(20, 1e-6)])
    log_l = np.concatenate([np.zeros(9010), np.full(10, -50.0)])  # place 2 ruled out
    p, ev = at_places(state, labels, log_l, weights)
    add(state, np.zeros(len(labels)), sample=32)
    live = ev.floor(p, margin_nats=10.0,
                    min_particles=32)
    assert live == 2
    factors = p.factor.to_numpy()[:len(labels)].astype(np.float64)
    w = weights * factors
    expected_copies = len(weights) * np.bincount(labels, weights=w) / w.sum()
    assert expected_copies[1] >= 31.9
    assert expected_copies[2] < 1e-3
    assert np.all(factors[labels == 2] == 1.0)
