"""Floor hypotheses after an elevator ride: kept alive until the scans decide.

Without an IMU the vertical random walk spreads the particles over every floor the cab
could stop at. On identical floors the floor whose keyframes are freshest (the one the ride
started from) matches the lobby best for the first seconds, and pruning by cumulative weight
removes every other floor within a few seconds, long before a place that tells the floors
apart (a stairwell with no flight down, a furnished room) comes into view. The paper keeps
"three major hypothesis groups across different floors" until "sufficient observations
were made" (§IV-B, Fig. 8); with 100,000 particles and absolute thresholds its pruning
rarely removes a group, with ours (relative thresholds, 1,000-10,000 particles) it does.

From the first scored scan after a ride, the guard therefore sorts particles into height
strata (`elevator.floor_strata_m` wide, along world up) and prunes each stratum on its own:
a dead particle is replaced by a copy of a living one *of its stratum*, so every stratum
keeps its particles, and a stratum's total weight is kept within
`elevator.floor_max_gap_nats` of the best stratum's, so the head start a floor gathered in
the first seconds cannot outlast later evidence by more than that. Particles whose frame
likelihood is hopeless against the best particle's (`pruning.likelihood_ratio`) still die
(between floors, nothing matches) and strata without any scored particle (no keyframe
within reach: unmapped space) are not protected. The guard ends when every stratum of the other
floors (more than `loop_closure.neighbour_max_dz_m` from the best stratum) has been held
down at that bound for `elevator.floor_decide_scans` scored scans in a row: one
floor's evidence then dominates, and ordinary pruning removes the others.
"""

from __future__ import annotations

import numpy as np

from mcl3d.slam.slam_config import ElevatorConfig, PruningConfig

AT_BOUND_NATS = 1.0  # a stratum this close above the weight bound counts as held down by it
MIN_FLOOR_SHARE = 0.01  # a stratum with fewer of the particles is not waited for


def strata(heights: np.ndarray, stratum_m: float) -> np.ndarray:
    """The height stratum (an integer) of every particle: floor(height / stratum_m)."""
    return np.floor(np.asarray(heights, np.float64) / stratum_m).astype(np.int64)


def group_log_mass(log_w: np.ndarray, groups: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(labels, each particle's index into them, each group's log total weight relative
    to the heaviest particle's)."""
    lw = np.asarray(log_w, np.float64)
    labels, inverse = np.unique(groups, return_inverse=True)
    mass = np.bincount(inverse, weights=np.exp(lw - lw.max()), minlength=len(labels))
    return labels, inverse, np.log(np.maximum(mass, np.finfo(np.float64).tiny))


def clamp_groups(log_w: np.ndarray, groups: np.ndarray, max_gap_nats: float) -> np.ndarray:
    """The log weights with every group's total weight raised, by one offset for all its
    particles, to at least exp(-max_gap_nats) times the best group's."""
    _, inverse, log_mass = group_log_mass(log_w, groups)
    lift = np.maximum(log_mass.max() - max_gap_nats - log_mass, 0.0)
    return np.asarray(log_w, np.float64) + lift[inverse]


def one_floor_dominates(labels: np.ndarray, log_mass: np.ndarray, counts: np.ndarray,
                        max_gap_nats: float, floor_strata: int) -> bool:
    """Whether every stratum of another floor (more than `floor_strata` strata from the
    best one: one floor's cloud may straddle borders) holding at least `MIN_FLOOR_SHARE`
    of the particles lies within `AT_BOUND_NATS` of the bound or below it, i.e. was
    outweighed again on this scan."""
    b = int(np.argmax(log_mass))
    floor = (np.abs(labels - labels[b]) > floor_strata) & \
        (counts >= MIN_FLOOR_SHARE * counts.sum())
    others = log_mass[floor]
    return bool(np.all(others <= log_mass[b] - max_gap_nats + AT_BOUND_NATS))


def _draw(weights: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` systematic draws (indices into `weights`) by weight."""
    cdf = np.cumsum(weights)
    u = (rng.random() + np.arange(count)) / count * cdf[-1]
    return np.minimum(np.searchsorted(cdf, u), len(weights) - 1)


def stratified_prune_plan(log_w: np.ndarray, frame_ll: np.ndarray, groups: np.ndarray,
                          cfg: PruningConfig, rng: np.random.Generator
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dead, sources, new log weights) as `prune_plan`, but the posterior threshold is
    applied within each group and a dead particle becomes a copy of a living particle of
    its own group (drawn by weight); only a group with no living particle takes copies of
    the others. The frame-likelihood threshold stays global (hopeless matches die). A
    particle copied c times shares its weight with its copies."""
    lw = np.asarray(log_w, np.float64) - float(np.max(log_w))
    ratio = np.log(cfg.likelihood_ratio) if cfg.likelihood_ratio > 0 else -np.inf
    dead = frame_ll - np.max(frame_ll) < ratio
    for g in np.unique(groups):
        members = groups == g
        post = np.exp(lw[members] - lw[members].max())
        dead[members] |= post / post.sum() < cfg.posterior
    if dead.all():
        dead[int(np.argmax(lw))] = False
    dead_idx = np.flatnonzero(dead)
    sources = np.empty(len(dead_idx), np.int64)
    living_all = np.flatnonzero(~dead)
    for g in np.unique(groups[dead_idx]):
        lost = groups[dead_idx] == g
        living = np.flatnonzero(~dead & (groups == g))
        if len(living) == 0:
            living = living_all
        w = np.exp(lw[living] - lw[living].max())
        sources[lost] = living[_draw(w, int(lost.sum()), rng)]
    share = np.log1p(np.bincount(sources, minlength=len(lw)))
    out = lw - share
    out[dead_idx] = lw[sources] - share[sources]
    return dead_idx, sources, out


class FloorGuard:
    """Keeps every height stratum's particles alive after a ride until one dominates
    (module docstring). `start()` when a ride ends; `prune_plan(...)` replaces the filter's
    pruning while `active`."""

    def __init__(self, cfg: ElevatorConfig, pruning: PruningConfig, floor_dz_m: float):
        """`floor_dz_m`: heights further apart than this are other floors
        (`loop_closure.neighbour_max_dz_m`)."""
        self.cfg, self.pruning = cfg, pruning
        self.floor_strata = int(np.floor(floor_dz_m / cfg.floor_strata_m))
        self.active = False
        self.dominant_scans = 0  # scored scans in a row with every other floor at the bound

    def start(self) -> None:
        self.active = True
        self.dominant_scans = 0

    def prune_plan(self, log_w: np.ndarray, frame_ll: np.ndarray, scored: np.ndarray,
                   heights: np.ndarray, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dead, sources, new log weights) of one scored scan; `scored`: the particles
        that had a neighbour keyframe, `heights`: every particle's height along world up."""
        groups = strata(heights, self.cfg.floor_strata_m)
        mapped = np.unique(groups[scored])
        best = groups[int(np.argmax(np.where(scored, log_w, -np.inf)))] if scored.any() else 0
        groups = np.where(np.isin(groups, mapped), groups, best)  # unmapped: no protection
        gap = self.cfg.floor_max_gap_nats
        labels, inverse, log_mass = group_log_mass(log_w, groups)
        dominates = one_floor_dominates(labels, log_mass, np.bincount(inverse), gap,
                                        self.floor_strata)
        self.dominant_scans = self.dominant_scans + 1 if dominates else 0
        lw = clamp_groups(log_w, groups, gap)
        if self.dominant_scans >= self.cfg.floor_decide_scans:
            self.active = False
        return stratified_prune_plan(lw, frame_ll, groups, self.pruning, rng)
