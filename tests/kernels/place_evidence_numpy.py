"""The place evidence in NumPy (float64), as the host computed it before it moved to the
device (mcl3d.localization.evidence, kernels/place_evidence.py): the reference the device
is tested against. The random draw within a place is given as keys `rand` (the device's),
so that both pick the same particles."""

from __future__ import annotations

import numpy as np

from mcl3d.localization.estimate import label_particles

CELL_BITS = 18  # per position axis of the place key (2^18 cells of cell_m)


def place_labels(positions: np.ndarray, quats_xyzw: np.ndarray, cell_m: float,
                 yaw_bins: int) -> np.ndarray:
    """A place index (0..k-1) per particle: its cell of `cell_m` in x, y, z and of
    360/`yaw_bins` degrees of yaw."""
    q = np.asarray(quats_xyzw, np.float64)
    yaw = np.arctan2(2.0 * (q[:, 3] * q[:, 2] + q[:, 0] * q[:, 1]),
                     1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2))
    yaw_bin = np.floor((yaw + np.pi) / (2.0 * np.pi) * yaw_bins).astype(np.int64) % yaw_bins
    cells = np.floor(positions / cell_m).astype(np.int64) + (1 << (CELL_BITS - 1))
    key = yaw_bin
    for axis in range(3):
        key = (key << CELL_BITS) | (cells[:, axis] & ((1 << CELL_BITS) - 1))
    return np.unique(key, return_inverse=True)[1].ravel()


def add(log_l: np.ndarray, increment: np.ndarray, places: np.ndarray, sample: int,
        rand: np.ndarray, leaders_nats: float = 10.0) -> tuple[np.ndarray, float | None]:
    """One scan: (the new log_l, this scan's variance, None without leading places)."""
    k = int(places.max()) + 1
    prior = np.full(k, -np.inf)
    np.maximum.at(prior, places, log_l)
    order = np.lexsort((rand, places))
    first = np.searchsorted(places[order], np.arange(k))
    rank = np.empty(len(places), np.int64)
    rank[order] = np.arange(len(places)) - first[places[order]]
    best_inc = _best_of(places, increment, rank < sample, k)
    second = _best_of(places, increment, (rank >= sample) & (rank < 2 * sample), k)
    leaders = (prior >= prior.max() - leaders_nats) & np.isfinite(second)
    differences = best_inc[leaders] - second[leaders]
    variance = None
    if len(differences):
        mad = np.median(np.abs(differences - np.median(differences)))
        variance = float((1.4826 * mad) ** 2 / 2.0)
    return (prior + best_inc)[places], variance


def _best_of(places: np.ndarray, values: np.ndarray, drawn: np.ndarray, k: int) -> np.ndarray:
    best = np.full(k, -np.inf)
    np.maximum.at(best, places[drawn], values[drawn])
    return best


def rival_gap(positions: np.ndarray, quats_xyzw: np.ndarray, log_l: np.ndarray,
              T_dominant: np.ndarray, radius_m: float, angle_rad: float) -> float:
    """Best evidence away from the dominant pose minus the best close to it."""
    inside = label_particles(positions, quats_xyzw, [T_dominant], 0.5 * radius_m,
                             0.5 * angle_rad) == 0
    away = label_particles(positions, quats_xyzw, [T_dominant], radius_m, angle_rad) < 0
    if not away.any():
        return -np.inf
    if not inside.any():
        return np.inf
    return float(log_l[away].max() - log_l[inside].max())


def place_floor(labels: np.ndarray, weights: np.ndarray, log_l: np.ndarray,
                margin_nats: float, min_particles: int) -> tuple[np.ndarray, int]:
    """Resampling factors giving every live place at least `min_particles` expected
    copies, and the number of live places."""
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
    share = min(min_particles / n, 0.5 / n_live)
    place_f = np.ones(k)
    for _ in range(3):
        total = float(w @ place_f[labels])
        place_f[live] = np.maximum(1.0, share * total / place_w[live])
    return place_f[labels], n_live
