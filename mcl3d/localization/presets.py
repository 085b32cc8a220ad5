"""Named settings of `mcl3d localize --preset NAME`: dotted config keys applied over the
defaults and under a config file and the command-line flags (`mcl3d.core.config.load`).

Each preset is a function whose docstring says what it reproduces; the saved config.yaml of
a run holds the effective values, and summary.json the preset's name.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mcl3d.core.errors import ConfigError


def default() -> dict[str, Any]:
    """Today's settings, unchanged (docs/sensor-model.md): the free/unknown-aware model with
    tempering, a coarse-to-fine global search with annealing and exploration noise,
    mode-preserving resampling when the ESS is low, candidates in the floor band with
    roll/pitch from gravity, stratified, and the heaviest cluster's mean as the estimate."""
    return {}


def paper() -> dict[str, Any]:
    """Eisoldt et al., "Towards 6D MCL for LiDARs in 3D TSDF Maps on Embedded Systems with
    GPUs": the sensor model of eq. 3 (a Gaussian of the TSDF value precomputed per voxel,
    interpolated, summed over the points; sigma 0.1 m as the authors' map loader), particles
    uniform in 6 DoF over all observed free space (independent draws, any rotation),
    resampling after every scan, the weighted mean of all particles as the estimate, and
    none of the search aids the paper does not have: no coarse phase, no annealing, no
    exploration noise, no mode or place protection, no rival test, no convergence check,
    no re-seeding."""
    return {
        "localizer.sensor.model": "paper",
        "localizer.sensor.sigma_m": 0.1,
        "localizer.sensor.search_sigma_m": 0.1,
        "localizer.sensor.coarse_sigma_m": 0.0,
        "localizer.init.height_band_m": "none",
        "localizer.init.covered": False,
        "localizer.init.uniform_rotation": True,
        "localizer.init.stratified": False,
        "localizer.resample.ess_threshold": 1.0,
        "localizer.resample.anneal_min_ess": 0.0,
        "localizer.resample.mode_share": 0.0,
        "localizer.motion.explore_trans_m": 0.0,
        "localizer.motion.explore_rot_deg": 0.0,
        "localizer.estimate.mean": "all",
        "localizer.estimate.rival_margin_nats": 0.0,
        "localizer.recovery.enabled": False,
        "localizer.check.enabled": False,
    }


LOCALIZE_PRESETS: dict[str, Callable[[], dict[str, Any]]] = {"default": default, "paper": paper}


def localize_preset(name: str) -> dict[str, Any]:
    """The dotted keys of preset `name`; ConfigError naming the choices when unknown."""
    if name not in LOCALIZE_PRESETS:
        raise ConfigError(f"unknown preset {name!r}: choose one of "
                          f"{', '.join(LOCALIZE_PRESETS)}", setting="preset")
    return LOCALIZE_PRESETS[name]()
