"""The place evidence kernels (kernels/place_evidence.py, through
mcl3d.localization.evidence.PlaceEvidence) against the NumPy reference on tiny inputs: the
same random draw within each place, so the same per-particle results."""

import numpy as np
import pytest

from mcl3d.core import geometry
from tests.kernels import place_evidence_numpy as ref


def yaw_quats(yaw_rad):
    return geometry.rot_to_quat(geometry.so3_exp(np.column_stack(
        [np.zeros_like(yaw_rad), np.zeros_like(yaw_rad), yaw_rad])))


def cloud(n, rng, extent_m=4.0, places_m=1.0):
    """Particles away from the cell and yaw-bin borders (f32 and f64 agree on the place)."""
    cells = rng.integers(-3, int(extent_m), size=(n, 3)) * [1, 1, 0]
    pos = (cells + rng.uniform(0.1, 0.9, (n, 3))) * places_m
    yaw = np.radians(rng.integers(0, 12, n) * 30.0 - 180.0 + rng.uniform(2.0, 28.0, n))
    return pos, yaw_quats(yaw)


CAPACITY = 3000  # one particle set and one evidence for every test: kernels compile once


@pytest.fixture(scope="module")
def state(backend):
    from mcl3d.core import runtime
    from mcl3d.localization.evidence import PlaceEvidence
    from mcl3d.localization.particle_set import ParticleSet

    runtime.init(backend)
    return ParticleSet(CAPACITY), PlaceEvidence(CAPACITY)


def load(state, pos, quats, ll_mean, w=None):
    """The particle set holds (pos, quats) with these ll_mean and w; the evidence is new."""
    p, ev = state
    p.set_host(pos, quats)
    for field, values in ((p.ll_mean, ll_mean), (p.w, w)):
        if values is not None:
            padded = np.zeros(CAPACITY, np.float32)
            padded[:len(values)] = values
            field.from_numpy(padded)
    ev.reset(len(pos))
    return p, ev


def drawn_keys(ev, n):
    """The random keys the last add drew for each particle."""
    f = ev.fields
    src = ev._sorted
    rand = np.empty(n, np.int64)
    rand[f.idx.to_numpy()[src, :n]] = f.rand.to_numpy()[src, :n]
    return rand


@pytest.mark.parametrize("n, sample, apart_m", [(1, 2, 0), (40, 2, 0), (700, 4, 0),
                                                (3000, 8, 0), (500, 4, 60_000)])
def test_add_matches_numpy(state, n, sample, apart_m):
    """apart_m: half the particles that far away in x and y (the places' bounding box holds
    more than 2^32 cells, as rooms a kilometre apart at finer cells)."""
    rng = np.random.default_rng(n)
    pos, quats = cloud(n, rng)
    pos[::2, :2] += apart_m
    places = ref.place_labels(pos, quats, 1.0, 12)
    _, ev = load(state, pos, quats, None)
    log_l = np.zeros(n)
    variance = 0.0
    for scan in range(3):
        ll = rng.normal(-1.0, 0.3, n)
        p, _ = state
        p.ll_mean.from_numpy(np.pad(ll, (0, CAPACITY - n)).astype(np.float32))
        ev.add(p, 2.5, 1.0, 12, sample, seed=7, counter=scan)
        inc = 2.5 * ll.astype(np.float32).astype(np.float64)
        log_l, var = ref.add(log_l, inc, places, sample, drawn_keys(ev, n))
        variance += var or 0.0
        assert ev.places == places.max() + 1
        np.testing.assert_allclose(ev.log_l.to_numpy()[:n], log_l, rtol=1e-5, atol=1e-4)
        assert ev.variance == pytest.approx(variance, rel=1e-3, abs=1e-9)
        assert ev.scans == scan + 1


def test_the_draw_is_reproducible_and_changes_with_the_counter(state):
    rng = np.random.default_rng(3)
    pos, quats = cloud(500, rng)
    p, ev = load(state, pos, quats, rng.normal(size=500))
    keys = []
    for counter in (5, 5, 6):
        ev.add(p, 1.0, 1.0, 12, 4, seed=1, counter=counter)
        keys.append(drawn_keys(ev, 500))
    assert np.array_equal(keys[0], keys[1]) and not np.array_equal(keys[0], keys[2])


@pytest.mark.parametrize("n", [30, 900])
def test_floor_matches_numpy(state, n):
    rng = np.random.default_rng(10 + n)
    pos, quats = cloud(n, rng)
    places = ref.place_labels(pos, quats, 1.0, 12)
    ll = rng.normal(-1.0, 2.0, n)
    w = rng.exponential(size=n) * (rng.random(n) < 0.7)
    p, ev = load(state, pos, quats, ll, w)
    ev.add(p, 3.0, 1.0, 12, 4, seed=2, counter=1)
    log_l = ev.log_l.to_numpy()[:n].astype(np.float64)
    for margin, min_particles in ((4.0, 3), (1e3, 32), (1e-3, 32)):
        factors, live = ref.place_floor(places, w, log_l, margin, min_particles)
        assert ev.floor(p, margin, min_particles) == live
        if live >= 2:
            np.testing.assert_allclose(p.factor.to_numpy()[:n], factors, rtol=1e-4)


def test_rival_gap_matches_numpy(state):
    rng = np.random.default_rng(4)
    n = 400
    pos = rng.uniform(-3.0, 3.0, (n, 3)) * [1, 1, 0.1]
    quats = yaw_quats(rng.uniform(-np.pi, np.pi, n))
    p, ev = load(state, pos, quats, rng.normal(size=n))
    ev.add(p, 1.0, 0.5, 12, 2, seed=3, counter=1)
    log_l = ev.log_l.to_numpy()[:n].astype(np.float64)
    for T in (np.eye(4), geometry.se3(geometry.rpy_to_rot(0, 0, 2.0), [1.0, -1.0, 0.0]),
              geometry.se3(np.eye(3), [40.0, 0.0, 0.0])):
        for radius, angle in ((2.0, 1.0), (20.0, 7.0)):
            expected = ref.rival_gap(pos, quats, log_l, T, radius, angle)
            assert ev.rival_gap(p, T, radius, angle) == pytest.approx(expected, abs=1e-5)


def test_children_inherit_their_parents_evidence(state):
    rng = np.random.default_rng(5)
    pos, quats = cloud(50, rng)
    p, ev = load(state, pos, quats, rng.normal(size=50))
    ev.add(p, 1.0, 1.0, 12, 2, seed=3, counter=1)
    before = ev.log_l.to_numpy()[:50]
    parent = rng.integers(0, 50, 30)
    p.parent.from_numpy(np.pad(parent, (0, CAPACITY - 30)).astype(np.int32))
    ev.inherit(p.parent, 30)
    assert ev.n == 30
    np.testing.assert_array_equal(ev.log_l.to_numpy()[:30], before[parent])


def test_the_same_inputs_give_the_same_bits(state):
    """Fixed-order sums, a stable sort and order-free maxima: every result repeats bit for
    bit (the filter's same-seed reproducibility on any thread count)."""
    rng = np.random.default_rng(6)
    n = CAPACITY
    pos, quats = cloud(n, rng, extent_m=2.0)
    ll, w = rng.normal(-1.0, 0.5, n), rng.exponential(size=n)
    results = []
    for _ in range(2):
        p, ev = load(state, pos, quats, ll, w)
        for scan in range(2):
            ev.add(p, 2.0, 1.0, 12, 8, seed=4, counter=scan)
        live = ev.floor(p, 1e3, 32)
        results.append((ev.log_l.to_numpy()[:n], p.factor.to_numpy()[:n], ev.variance,
                        ev.places, live, ev.rival_gap(p, np.eye(4), 2.0, 1.0)))
    assert results[0][4] >= 2
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    assert results[0][2:] == results[1][2:]


def test_a_live_place_far_lighter_than_the_heaviest_keeps_a_finite_floor(state):
    """A live place 1e-36 of the heaviest particle once got an infinite factor (its weight
    divided by the total, ~300, fell below f32's normal range and was flushed to 0): w *
    factor was inf or NaN and the next resampling collapsed the cloud onto one place. The
    factors now stay finite and equal NumPy's (float64)."""
    rng = np.random.default_rng(7)
    pos, quats = cloud(300, rng)
    places = ref.place_labels(pos, quats, 1.0, 12)
    light = places == places[0]
    w = np.where(light, 1e-36, 1.0).astype(np.float32)
    p, ev = load(state, pos, quats, np.full(300, -1.0), w)
    ev.add(p, 1.0, 1.0, 12, 4, seed=2, counter=1)
    assert ev.floor(p, 10.0, 32) == places.max() + 1
    factors = p.factor.to_numpy()[:300].astype(np.float64)
    expected, _ = ref.place_floor(places, w.astype(np.float64), np.zeros(300), 10.0, 32)
    assert np.all(np.isfinite(factors)) and np.all(np.isfinite(w * factors))
    np.testing.assert_allclose(factors, expected, rtol=1e-4)
    assert factors[light].min() > 1e33
