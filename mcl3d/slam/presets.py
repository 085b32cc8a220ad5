"""Named sets of SLAM settings (`mcl3d slam --preset NAME`), applied over the defaults and
under a config file and flags. "paper" is the SLAM paper's filter as written (§III):
the odometry's inverse GICP Hessian as prediction noise, unscaled and uncapped, a loop
whenever an old keyframe is among the three nearest, no step without a loop, pruning at
1e-8 posterior / 1e-16 likelihood. docs/slam.md lists where the defaults differ and why."""

from __future__ import annotations

from typing import Any

from mcl3d.core.errors import ConfigError

PAPER: dict[str, Any] = {
    # eq. 1: δ ~ N(0, Σ_ΔT), Σ_ΔT the inverse Hessian of the GICP cost, nothing added
    "prediction_noise.odometry_scale": 1.0,
    "prediction_noise.max_odometry_sigma_m": 1.0,  # only a lost registration is capped
    "prediction_noise.max_odometry_sigma_deg": 10.0,
    "prediction_noise.trans_per_m": 0.0,
    "prediction_noise.rot_deg_per_m": 0.0,
    "prediction_noise.rot_deg_per_deg": 0.0,
    "prediction_noise.trans_min_m": 0.0,
    "prediction_noise.rot_min_deg": 0.0,
    # §III-C2: a loop is an old keyframe among the three nearest; no other gate
    "loop_closure.min_travel_m": 1e-3,
    "loop_closure.neighbour_max_dz_m": 1e3,
    "loop_closure.facing_gate": False,
    "correction.min_inliers": 6,
    "correction.refine_without_loop": False,
    "correction.spread_after_step": False,
    # eq. 2-3: every neighbour keyframe weighs alike (the defaults: only loops tell particles
    # apart); only scan points in a keyframe voxel are scored
    "likelihood.local_weight": 1.0,
    "likelihood.unmatched_as_typical": False,
    "likelihood.free_space_cost": 0.0,
    # §III-F
    "pruning.posterior": 1e-8,
    "pruning.likelihood_ratio": 1e-16,
    # §III-E: the elevator is detected by the median range of the scan; none of our ride aids
    "elevator.detector": "median",
    "elevator.resample_on_entry": False,
    "elevator.exit_open_sectors": 0,
    "elevator.free_space_cost": 0.0,
    "elevator.floor_guard": False,
    # the best particle's own map is the result
    "trajectory.bridge_between_loops": False,
    "trajectory.loop_graph": False,
    "trajectory.structure_up": False,
}

PRESETS: dict[str, dict[str, Any]] = {"default": {}, "paper": PAPER}


def preset(name: str | None) -> dict[str, Any]:
    """The dotted settings of preset `name` (None: the defaults')."""
    if name is None:
        return {}
    if name not in PRESETS:
        raise ConfigError(f"unknown SLAM preset {name!r}; choose one of: "
                          f"{', '.join(PRESETS)}", setting="preset")
    return dict(PRESETS[name])
