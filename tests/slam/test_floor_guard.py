"""The floor guard after an elevator ride: strata, the weight bound, stratified pruning and
when the guard ends (mcl3d/slam/floor_guard.py; host NumPy, no kernels)."""

import numpy as np

from mcl3d.slam.floor_guard import (
    FloorGuard,
    clamp_groups,
    group_log_mass,
    one_floor_dominates,
    strata,
    stratified_prune_plan,
)
from mcl3d.slam.monte_carlo_slam import prune_plan
from mcl3d.slam.slam_config import ElevatorConfig, PruningConfig


def test_strata_are_height_bands():
    np.testing.assert_array_equal(strata(np.array([-0.1, 0.0, 0.99, 1.0, 3.6, 7.2]), 1.0),
                                  [-1, 0, 0, 1, 3, 7])


def test_clamp_raises_a_lagging_group_to_the_bound_and_keeps_its_shape():
    log_w = np.array([0.0, -1.0, -50.0, -52.0, -3.0])
    groups = np.array([4, 4, 1, 1, 7])
    lw = clamp_groups(log_w, groups, 20.0)
    mass = {g: np.log(np.exp(lw[groups == g]).sum()) for g in (1, 4, 7)}
    np.testing.assert_allclose(mass[4] - mass[1], 20.0)  # exactly at the bound
    np.testing.assert_allclose(lw[2] - lw[3], 2.0)  # one offset for the whole group
    np.testing.assert_array_equal(lw[[0, 1, 4]], log_w[[0, 1, 4]])  # others untouched


def test_one_floor_dominates_when_every_other_floor_is_held_at_the_bound():
    labels, _, log_mass = group_log_mass(np.array([0.0, -0.5, -19.5, -30.0]),
                                         np.array([3, 4, 7, 9]))
    np.testing.assert_array_equal(labels, [3, 4, 7, 9])
    counts = np.array([50, 30, 19, 1])
    assert one_floor_dominates(labels, log_mass, counts, 20.0, 2)  # 4: floor 3's neighbour
    assert not one_floor_dominates(labels, log_mass, counts, 25.0, 2)  # 7: 5.5 nats above
    assert not one_floor_dominates(labels, log_mass, counts, 20.0, 0)  # 4: another floor
    few = np.array([800, 150, 5, 45])  # 7 holds 0.5% of the particles: not a floor to wait for
    assert one_floor_dominates(labels, log_mass, few, 25.0, 2)
    assert one_floor_dominates(np.array([2]), np.array([0.0]), np.array([5]), 20.0, 2)


def test_stratified_pruning_refills_each_group_from_itself():
    cfg = PruningConfig(posterior=1e-3, likelihood_ratio=1e-6)
    # group 0 leads by far; group 5 lags by 30 nats but holds one good particle
    log_w = np.array([0.0, -20.0, -1.0, -30.0, -31.0, -60.0])
    frame_ll = np.array([0.0, 0.0, 0.0, -1.0, -1.0, -1.0])
    groups = np.array([0, 0, 0, 5, 5, 5])
    dead, sources, lw = stratified_prune_plan(log_w, frame_ll, groups, cfg,
                                              np.random.default_rng(0))
    np.testing.assert_array_equal(dead, [1, 5])
    assert groups[sources[list(dead).index(1)]] == 0 and groups[sources[list(dead).index(5)]] == 5
    np.testing.assert_array_equal(np.bincount(groups[np.r_[np.setdiff1d(np.arange(6), dead),
                                                               sources]]), [3, 0, 0, 0, 0, 3])
    # the same weights pruned globally lose the whole lagging group
    dead_global, src_global, _ = prune_plan(log_w, frame_ll, cfg, np.random.default_rng(0))
    assert set(dead_global) >= {3, 4, 5} and set(groups[src_global]) == {0}
    # a source and its copies share the source's weight
    copies = np.bincount(sources, minlength=6)
    for s in set(sources):
        np.testing.assert_allclose(np.exp(lw[s]) * (1 + copies[s]), np.exp(log_w[s]))


def test_hopeless_matches_die_even_inside_their_group():
    cfg = PruningConfig(posterior=1e-8, likelihood_ratio=1e-6)
    frame_ll = np.array([0.0, -1.0, -30.0, -30.0])  # group 2 matches nothing this scan
    dead, sources, _ = stratified_prune_plan(np.zeros(4), frame_ll, np.array([0, 0, 2, 2]),
                                             cfg, np.random.default_rng(1))
    np.testing.assert_array_equal(dead, [2, 3])
    assert set(sources) <= {0, 1}  # no living particle of its own: copies of the others


def test_guard_keeps_both_floors_until_one_dominates():
    cfg = ElevatorConfig(floor_strata_m=1.0, floor_max_gap_nats=10.0, floor_decide_scans=3)
    guard = FloorGuard(cfg, PruningConfig(), 2.0)
    heights = np.r_[np.full(4, 4.9), np.full(4, 8.4)]  # two floors
    scored = np.ones(8, bool)
    log_w = np.zeros(8)
    guard.start()
    for scan in range(4):  # the upper floor matches better: it leads, the other is kept
        assert guard.active
        frame_ll = np.r_[np.full(4, -5.0), np.zeros(4)]
        dead, _, log_w = guard.prune_plan(log_w + frame_ll, frame_ll, scored, heights,
                                          np.random.default_rng(scan))
        assert len(dead) == 0
        lower = np.log(np.exp(log_w[:4]).sum()) - np.log(np.exp(log_w[4:]).sum())
        assert lower >= -10.0 - 1e-9
    assert not guard.active  # the lower floor at the bound from the 2nd scan on: 3 in a row


def test_guard_does_not_protect_unmapped_strata():
    guard = FloorGuard(ElevatorConfig(), PruningConfig(), 2.0)
    guard.start()
    heights = np.array([4.9, 4.9, 12.0, 12.0])  # two particles above every keyframe
    scored = np.array([True, True, False, False])
    log_w = np.array([0.0, 0.0, -25.0, -25.0])
    dead, sources, _ = guard.prune_plan(log_w, np.array([0.0, 0.0, -1.0, -1.0]), scored,
                                        heights, np.random.default_rng(0))
    np.testing.assert_array_equal(dead, [2, 3])
    assert set(sources) <= {0, 1}

