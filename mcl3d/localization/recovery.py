"""Loss detection and the re-seeding plan (AMCL-style fast/slow averages).

The fast and slow averages follow the weighted match ratio and mean per-point
log-likelihood of each update; the filter is lost when the fast one falls below a floor or
well below the slow one (the healthy reference level). After `patience` lost scans it
re-seeds part of the cloud around the estimate (expansion resetting, wider each attempt),
then over the whole free space.
"""

from __future__ import annotations

import numpy as np

from mcl3d.localization.localization_config import RecoveryConfig
from mcl3d.localization.state import Reseed

# expansion resetting: the std of z and of roll/pitch, relative to that of x/y and of yaw
# (a robot slips and turns; it hardly changes height or tilt)
EXPANSION_Z_SHARE = 0.25
EXPANSION_TILT_SHARE = 0.3


class Recovery:
    """Fast/slow averages of the match quality and the state of the re-seeding attempts."""

    def __init__(self, cfg: RecoveryConfig):
        self.cfg = cfg
        self._fast: np.ndarray | None = None
        self._slow: np.ndarray | None = None
        self._lost_run = 0
        self._healthy = False  # converged since the last reset
        self.attempt = 0  # re-seeding attempts since the filter was last converged
        self._since_attempt = 0

    def reset_reference(self) -> None:
        """Forget the averages (the log-likelihoods changed scale with the sensor sigma)."""
        self._fast = self._slow = None
        self._healthy = False

    def is_lost(self, match_ratio: float, mean_ll: float, converged: bool, active: bool) -> bool:
        """Feed one update's quality; True when the filter is lost (only while `active`)."""
        r = self.cfg
        x = np.array([match_ratio, mean_ll])
        if self._fast is None:
            self._fast, self._slow = x.copy(), x.copy()
        self._fast += r.alpha_fast * (x - self._fast)
        lost = active and bool(self._fast[0] < r.lost_match_ratio
                               or self._fast[0] < r.drop_ratio * self._slow[0]
                               or self._fast[1] < self._slow[1] - r.ll_drop)
        if not lost:  # while lost, the slow average keeps the healthy reference level
            self._slow += r.alpha_slow * (x - self._slow)
        if converged and not lost:
            if self.attempt or not self._healthy:
                self._slow = self._fast.copy()  # the reference level: a converged filter
            self._healthy = True
            self.attempt = 0
        self._lost_run = self._lost_run + 1 if lost else 0
        return lost

    def scan_disagrees(self, match_ratio: float, mean_ll: float) -> bool:
        """This scan alone is as far below the healthy level as the fast averages must fall
        to be lost, or the fast averages are halfway there: a `converged` claim is withheld
        (a kidnap onto a look-alike place shows in the first scan after it; re-seeding
        still waits for the averages)."""
        if self._slow is None or not self._healthy:
            return False
        r = self.cfg
        halfway_match = 0.5 * (1.0 + r.drop_ratio) * self._slow[0]
        return bool(match_ratio < r.drop_ratio * self._slow[0]
                    or mean_ll < self._slow[1] - r.ll_drop
                    or self._fast[0] < halfway_match
                    or self._fast[1] < self._slow[1] - 0.5 * r.ll_drop)

    def action(self, lost: bool) -> Reseed:
        """The re-seeding to do now: "" (none yet), "expansion" or "global"."""
        r = self.cfg
        self._since_attempt += 1
        if not lost or self._lost_run < r.patience or self._since_attempt < r.attempt_scans:
            return ""
        self._since_attempt = 0
        self.attempt += 1
        return "expansion" if self.attempt <= r.expansion_attempts else "global"

    def expansion_std(self) -> list[float]:
        """x y z [m], roll pitch yaw [rad] of this expansion attempt (wider each time)."""
        r, k = self.cfg, self.attempt
        return ([r.expansion_std_m * k] * 2 + [EXPANSION_Z_SHARE * r.expansion_std_m * k]
                + [EXPANSION_TILT_SHARE * r.expansion_std_rad * k] * 2
                + [r.expansion_std_rad * k])
