"""One batch run through the real pipeline of its command, as `mcl3d <command>` would run it.

`check_run` builds a run's config in the driver (so a bad key stops the batch before any
work); `execute` runs in a Ray worker process: it starts that process's Taichi runtime,
calls the command's `run(request)` and returns the run's row. A typed `Mcl3dError` (bad input,
a log without scans) is the run's result, a failed row; anything else propagates, so the
scheduler can try the run again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from mcl3d.batch import figures
from mcl3d.batch.manifest import RunSpec, SuccessCriterion
from mcl3d.core import config as config_io
from mcl3d.core.errors import ConfigError, Mcl3dError
from mcl3d.core.outputs import output_folder


def _localize_config(spec: RunSpec):
    from mcl3d.localization.localization_config import check_config
    from mcl3d.localization.pipeline import LocalizeConfig
    from mcl3d.localization.presets import localize_preset

    cfg = config_io.load(LocalizeConfig, None, {
        **spec.overrides, "localizer.seed": spec.seed, "localizer.particles": spec.particles,
        "max_scans": spec.max_scans}, preset=localize_preset(spec.preset))
    check_config(cfg.localizer)
    return cfg


def _slam_config(spec: RunSpec):
    from mcl3d.slam.presets import preset
    from mcl3d.slam.slam_config import SlamConfig

    return config_io.load(SlamConfig, None, {**spec.overrides, "seed": spec.seed,
                                             "particles": spec.particles},
                          preset=preset(spec.preset))


def _odometry_config(spec: RunSpec):
    from mcl3d.odometry.lidar_odometry import OdometryConfig

    _no_preset(spec)
    return config_io.load(OdometryConfig, None, spec.overrides)


def _build_config(spec: RunSpec):
    from mcl3d.maps.build import BuildConfig

    _no_preset(spec)
    return config_io.load(BuildConfig, None, spec.overrides)


def _no_preset(spec: RunSpec) -> None:
    if spec.preset != "default":
        raise ConfigError(f"preset: {spec.command} has no presets; remove the key")


CONFIGS = {"localize": _localize_config, "slam": _slam_config,
           "odometry": _odometry_config, "build-map": _build_config}


def check_run(spec: RunSpec) -> None:
    """ConfigError naming the key when the run's settings are not valid for its command."""
    try:
        CONFIGS[spec.command](spec)
    except ConfigError as exc:
        text = str(exc)  # a key of the job's config: "options: KEY: what is wrong"
        raise ConfigError(f"config.{text[9:]}" if text.startswith("options: ") else text
                          ) from None


def _localize(spec: RunSpec, backend: str, force: bool, success: SuccessCriterion) -> dict:
    from mcl3d.localization.pipeline import LocalizeRequest, Topics, run

    t = spec.topics
    result = run(LocalizeRequest(
        log=spec.log, map=spec.map, output_dir=spec.output_dir, config=_localize_config(spec),
        topics=Topics(t.get("points"), t.get("imu"), t.get("odom"), t.get("gt")), force=force,
        backend=backend, preset=spec.preset))
    return figures.localize(spec.output_dir, result, success)


def _odometry(spec: RunSpec, backend: str, force: bool, success: SuccessCriterion) -> dict:
    from mcl3d.odometry.pipeline import OdometryRequest, run

    t = spec.topics
    run(OdometryRequest(log=spec.log, output_dir=spec.output_dir, config=_odometry_config(spec),
                        force=force, points_topic=t.get("points"), imu_topic=t.get("imu"),
                        gt_topic=t.get("gt"), max_scans=spec.max_scans))
    return figures.odometry(spec.output_dir)


def _slam(spec: RunSpec, backend: str, force: bool, success: SuccessCriterion) -> dict:
    from mcl3d.slam.pipeline import SlamRequest, run

    t = spec.topics
    run(SlamRequest(log=spec.log, output_dir=spec.output_dir, config=_slam_config(spec),
                    force=force, points_topic=t.get("points"), imu_topic=t.get("imu"),
                    gt_topic=t.get("gt"), max_scans=spec.max_scans))
    return figures.slam(spec.output_dir, spec.log, t.get("gt"))


def _build_map(spec: RunSpec, backend: str, force: bool, success: SuccessCriterion) -> dict:
    from mcl3d.mapping.pipeline import BuildMapRequest, run

    t = spec.topics
    with output_folder(spec.output_dir):  # build-map writes a file, not a folder
        result = run(BuildMapRequest(spec.log, Path(spec.output_dir) / MAP_FILE,
                                     _build_config(spec), force=force,
                                     points_topic=t.get("points"), gt_topic=t.get("gt")))
    return figures.build_map(result)


MAP_FILE = "map.tsdf"  # what a build-map run writes in its folder
RUNNERS = {"localize": _localize, "odometry": _odometry, "slam": _slam, "build-map": _build_map}


def base_row(spec: RunSpec) -> dict[str, Any]:
    """The columns every row has, in the order results.csv shows them."""
    return {"job": spec.job, "run": spec.run, "command": spec.command, "log": str(spec.log),
            "map": None if spec.map is None else str(spec.map), "preset": spec.preset,
            "seed": spec.seed, "particles": spec.particles, "status": "", "error": None,
            "attempts": 1, "wall_s": None, "backend": None, "output": str(spec.output_dir)}


def execute(spec: RunSpec, backend: str, force: bool, success: SuccessCriterion
            ) -> dict[str, Any]:
    """Run `spec` in this process on `backend` and return its row (status ok or failed)."""
    from mcl3d.core import runtime

    row = base_row(spec)
    start = time.perf_counter()
    try:
        info = runtime.init(backend)
        row["backend"] = info.backend
        row.update(RUNNERS[spec.command](spec, backend, force, success))
        row["status"] = "ok"
    except Mcl3dError as exc:
        row.update(status="failed", error=str(exc))
    row["wall_s"] = round(time.perf_counter() - start, 3)
    return row
