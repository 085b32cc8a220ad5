"""What one filter update reports: the filter's state and the per-scan result."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Literal

import numpy as np

from mcl3d.core.errors import InputError
from mcl3d.localization.estimate import Hypothesis

# the stages of one update, in the order they run (timings, scans.csv columns)
STAGES = ("motion", "likelihood", "weights", "estimate", "resample", "recovery")


class FilterState(str, Enum):
    """Where the filter stands after an update (the strings appear in scans.csv)."""

    INITIALIZING = "initializing"  # no dominant cluster yet, one strong hypothesis at most
    CONVERGED = "converged"  # one compact cluster holds most of the weight
    AMBIGUOUS = "ambiguous"  # several strong hypotheses, or no longer converged
    LOST = "lost"  # the scans stopped matching the map (recovery re-seeds)

    def __str__(self) -> str:
        return self.value


Reseed = Literal["", "expansion", "global"]


@dataclass
class LocalizationResult:
    stamp_s: float
    T_map_lidar: np.ndarray  # (4, 4) mean of the dominant cluster
    T_best: np.ndarray  # (4, 4) the heaviest particle
    covariance: np.ndarray  # (6, 6) rotation-first [rad^2, m^2]
    state: FilterState
    hypotheses: list[Hypothesis]
    ess: float
    n_particles: int
    match_ratio: float  # weighted mean fraction of scan points on a surface
    mean_log_likelihood: float  # weighted mean per-point log-likelihood
    n_points: int
    resampled: bool
    reseeded: Reseed  # "" (none), "expansion" or "global"
    places: int = 0  # look-alike places the scans have not ruled out (global search only)
    best_match_ratio: float = 0.0  # the best particle's fraction of scan points on a surface
    timings_ms: dict[str, float] = field(default_factory=dict)  # per stage of STAGES


@dataclass(slots=True)
class ScanRecord:
    """What a run keeps of one update for its outputs (trajectory, scans.csv, summary,
    picture): the pose and the numbers, not the hypotheses' poses and covariances nor the
    best particle: ~1.1 KB a scan instead of ~2.5 KB, so memory stays flat over long logs."""

    stamp_s: float
    T_map_lidar: np.ndarray  # (4, 4)
    variances: np.ndarray  # (6,) the covariance's diagonal, rotation first [rad^2, m^2]
    state: FilterState
    hypotheses: tuple[float, ...]  # each hypothesis's share of the weight, dominant first
    ess: float
    n_particles: int
    match_ratio: float
    mean_log_likelihood: float
    n_points: int
    resampled: bool
    reseeded: Reseed
    places: int
    timings_ms: dict[str, float]

    @classmethod
    def of(cls, r: LocalizationResult) -> ScanRecord:
        return cls(r.stamp_s, r.T_map_lidar, np.diag(r.covariance).copy(), r.state,
                   tuple(h.weight for h in r.hypotheses), r.ess, r.n_particles, r.match_ratio,
                   r.mean_log_likelihood, r.n_points, r.resampled, r.reseeded, r.places,
                   r.timings_ms)


class EmptyScan(InputError):
    """A scan with too few points left after the range gate (skipped by the pipeline)."""
