"""What a `localize` run shows in Foxglove (result MCAP, live view): per scan the estimate
with its covariance, the scan placed by it, the particles by weight, the other hypotheses,
the ground truth and the error when the log has it, the filter's numbers, its changes of
state and warnings; the TSDF's surface once."""

from __future__ import annotations

import numpy as np

from mcl3d.io.foxglove_results import ResultPublisher, nearest_pose
from mcl3d.localization.estimate import WeightedParticles
from mcl3d.localization.state import LocalizationResult


class LocalizeView:
    """Publishes each update of one run; `gt` is the log's (stamps_ns, T_map_lidar)."""

    def __init__(self, publisher: ResultPublisher, gt: tuple | None) -> None:
        self.pub = publisher
        self.gt = gt
        self.state: str | None = None
        self.warned = 0  # warnings of the run published so far

    def update(self, stamp_ns: int, scan_points: np.ndarray, result: LocalizationResult,
               cloud: WeightedParticles | None, warnings: list[str], max_particles: int
               ) -> None:
        pub = self.pub
        pub.publish_estimate(stamp_ns, result.T_map_lidar, result.covariance, scan_points)
        if cloud is not None:
            pub.publish_particles(stamp_ns, cloud.positions, cloud.weights, max_particles)
        pub.publish_hypotheses(stamp_ns, [(h.T_map_lidar, h.covariance, h.weight)
                                          for h in result.hypotheses[1:]])
        error_m = None
        T_gt = None if self.gt is None else nearest_pose(*self.gt, stamp_ns)
        if T_gt is not None:
            pub.publish_ground_truth(stamp_ns, T_gt)
            error_m = float(np.linalg.norm(T_gt[:3, 3] - result.T_map_lidar[:3, 3]))
        pub.publish_stats(stamp_ns, {
            "ess": result.ess, "particles": result.n_particles,
            "hypotheses": len(result.hypotheses), "match_ratio": result.match_ratio,
            "error_m": error_m, "ms": sum(result.timings_ms.values())})
        self._log_changes(stamp_ns, result, warnings)

    def _log_changes(self, stamp_ns: int, result: LocalizationResult, warnings: list[str]
                     ) -> None:
        state = result.state.value
        if state != self.state:
            self.pub.log(stamp_ns, "warning" if state == "lost" else "info",
                         f"filter {self.state or 'started'} -> {state}")
            self.state = state
        if result.reseeded:
            self.pub.log(stamp_ns, "warning", f"particles re-seeded ({result.reseeded})")
        for text in warnings[self.warned:]:
            self.pub.log(stamp_ns, "warning", text)
        self.warned = len(warnings)
