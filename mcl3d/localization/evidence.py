"""How well each place explains every scan since the last (re-)initialization: the rival
test that keeps the filter from claiming `converged` at one of several look-alike places,
and the floor that keeps such places alive until the scans rule them out.

A cluster's weight is a Monte Carlo sum whose noise compounds scan by scan: between two
look-alike places (identical rack aisles, identical rooms) the weight ratio random-walks
until one place holds 80% of the weight and looks converged, although no scan ever told the
places apart, and a place whose particles died by chance gives no evidence at all.

Instead each particle carries the evidence of the best path through the places it came
from: before a scan's tempered log-likelihood is added, every particle takes the best
evidence of its place (a cell of position and yaw), and children inherit their parent's at
resampling. A single lineage would pay for every scan in which it, by chance, sat a few
centimetres off the optimum (a sparse place loses several nats a scan that way, the
true place among them); the best of the place does not. The best increment is taken over
a fixed number of the place's particles, else the place with the most particles would win
every scan's maximum by their number alone. A place away from the dominant cluster within
a margin of the dominant's best still explains the scans: the filter is ambiguous,
whatever the weights say.

Which particles a place happens to hold still makes each place's evidence a random walk,
and the best of hundreds of look-alike places outruns any one of them (the true one among
them) by a few nats per hundred scans. So a place is ruled out only when it falls behind by
more than that noise can explain: `noise_margin`, from the spread between two disjoint
draws of the same place's particles, grows with the square root of the scans and with the
number of places compared.
"""

from __future__ import annotations

import numpy as np

from mcl3d.localization.estimate import label_particles

CELL_BITS = 18  # per position axis of the place key (2^18 cells of place_cell_m)


class PlaceEvidence:
    """Accumulated tempered log-likelihood per particle (host, float64); see the module."""

    def __init__(self) -> None:
        self.log_l = np.zeros(0)
        self.scans = 0  # scans accumulated since the last reset
        self.variance = 0.0  # summed per-scan variance of a place's increment, nats^2

    def reset(self, n: int) -> None:
        self.log_l = np.zeros(n)
        self.scans = 0
        self.variance = 0.0

    def noise_margin(self, places: int, false_alarm: float = 0.01) -> float:
        """Nats by which one of `places` equally good places may trail the best by chance:
        a Bonferroni z over the places times the std of two places' evidence difference."""
        z = np.sqrt(2.0 * np.log(max(places, 2) / false_alarm))
        return float(z * np.sqrt(2.0 * self.variance))

    def add(self, increment: np.ndarray, places: np.ndarray, sample: int,
            rng: np.random.Generator, leaders_nats: float = 10.0) -> None:
        """One scan: each place continues from the best evidence among its particles, plus
        the best increment among `sample` of its particles drawn at random (so a place
        with many particles does not win the maximum by their number alone). The places
        within `leaders_nats` of the best measure this scan's noise."""
        if len(self.log_l) != len(increment):
            self.reset(len(increment))
        k = int(places.max()) + 1
        prior = np.full(k, -np.inf)
        np.maximum.at(prior, places, self.log_l)
        order = np.lexsort((rng.random(len(places)), places))
        first = np.searchsorted(places[order], np.arange(k))
        rank = np.empty(len(places), np.int64)
        rank[order] = np.arange(len(places)) - first[places[order]]
        best_inc = _best_of(places, increment, rank < sample, k)
        second = _best_of(places, increment, (rank >= sample) & (rank < 2 * sample), k)
        leaders = (prior >= prior.max() - leaders_nats) & np.isfinite(second)
        self._add_variance(best_inc[leaders] - second[leaders])
        self.log_l = (prior + best_inc)[places]
        self.scans += 1

    def _add_variance(self, differences: np.ndarray) -> None:
        """This scan's sampling noise of a place's increment: half the variance of the
        difference between the best of two disjoint draws from the same place (robust: the
        MAD over the leading places), so real differences between places do not count."""
        if len(differences):
            mad = np.median(np.abs(differences - np.median(differences)))
            self.variance += float((1.4826 * mad) ** 2 / 2.0)

    def inherit(self, parent: np.ndarray) -> None:
        """After resampling: child i continues the evidence of particle `parent[i]`."""
        if len(self.log_l):
            self.log_l = self.log_l[parent]


def _best_of(places: np.ndarray, values: np.ndarray, drawn: np.ndarray, k: int) -> np.ndarray:
    best = np.full(k, -np.inf)
    np.maximum.at(best, places[drawn], values[drawn])
    return best


def place_labels(positions: np.ndarray, quats_xyzw: np.ndarray, cell_m: float,
                 yaw_bins: int) -> np.ndarray:
    """A place index (0..k-1) per particle: its cell of `cell_m` in x, y, z and of
    360/`yaw_bins` degrees of yaw (look-alike places are apart in position or heading)."""
    q = np.asarray(quats_xyzw, np.float64)
    yaw = np.arctan2(2.0 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]),
                     1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2))
    yaw_bin = np.floor((yaw + np.pi) / (2.0 * np.pi) * yaw_bins).astype(np.int64) % yaw_bins
    cells = np.floor(positions / cell_m).astype(np.int64) + (1 << (CELL_BITS - 1))
    key = yaw_bin
    for axis in range(3):
        key = (key << CELL_BITS) | (cells[:, axis] & ((1 << CELL_BITS) - 1))
    return np.unique(key, return_inverse=True)[1].ravel()


def rival_gap(positions: np.ndarray, quats_xyzw: np.ndarray, log_l: np.ndarray,
              T_dominant: np.ndarray, radius_m: float, angle_rad: float) -> float:
    """Best evidence among particles away from the dominant pose (farther than `radius_m`
    or turned more than `angle_rad`) minus the best within `radius_m / 2` and `angle_rad / 2`
    of it: > -margin means another place still explains the scans. -inf when every particle
    is near the dominant pose, +inf when none is close to it."""
    if len(log_l) != len(positions) or not len(log_l):
        return -np.inf
    inside = label_particles(positions, quats_xyzw, [T_dominant], 0.5 * radius_m,
                             0.5 * angle_rad) == 0
    away = label_particles(positions, quats_xyzw, [T_dominant], radius_m, angle_rad) < 0
    if not away.any():
        return -np.inf
    best_inside = log_l[inside].max() if inside.any() else -np.inf
    if best_inside == -np.inf:  # no particle (with evidence) at the mean: no verdict
        return np.inf
    return float(log_l[away].max() - best_inside)


def place_floor(labels: np.ndarray, weights: np.ndarray, log_l: np.ndarray,
                margin_nats: float, min_particles: int) -> tuple[np.ndarray, int]:
    """Resampling factors that give every place whose evidence is within `margin_nats` of
    the best one at least `min_particles` expected copies (at most half the particles go
    to such floors), and the number of such live places.

    Resampling by weight alone lets a look-alike place whose cluster weight drifted low die
    by chance, and a dead place can never win again; with these factors (applied as
    weight * factor, each copy carrying -log(factor), see `resampling`) a place dies only
    when the scans rule it out.
    """
    n = len(weights)
    w = np.asarray(weights, np.float64) / np.sum(weights)
    k = int(labels.max()) + 1
    best = np.full(k, -np.inf)
    np.maximum.at(best, labels, log_l)
    place_w = np.bincount(labels, weights=w, minlength=k)
    live = (best >= log_l.max() - margin_nats) & (place_w > 0)
    factors = np.ones(n)
    n_live = int(live.sum())
    if n_live < 2:
        return factors, n_live
    share = min(min_particles / n, 0.5 / n_live)  # the floor of each live place
    place_f = np.ones(k)
    for _ in range(3):  # the floors' total changes the normalization they are relative to
        total = float(w @ place_f[labels])
        place_f[live] = np.maximum(1.0, share * total / place_w[live])
    return place_f[labels], n_live
