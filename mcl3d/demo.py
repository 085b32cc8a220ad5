"""`mcl3d demo`: the whole chain on built-in data that the simulator makes on the spot:
simulate an office log, inspect it, build its TSDF map, then localize the log in that map
globally (no initial guess) and compare with the log's ground truth.

Each run writes into a fresh `<root>/<UTC time>/` folder (and points `<root>/latest` at it),
so running the demo again never overwrites an earlier result.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

from rich.console import RenderableType

from mcl3d.console import ProgressBars, log_info_tables, summary_table
from mcl3d.core import config, runtime
from mcl3d.core.errors import ConfigError, OutputExistsError
from mcl3d.io.logs.info import log_info
from mcl3d.localization.localization_summary import LocalizeSummary
from mcl3d.localization.localization_summary import summary_rows as localize_rows
from mcl3d.localization.particle_set import check_capacity
from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest
from mcl3d.localization.pipeline import run as localize
from mcl3d.localization.sensor_model import MIN_SCAN_POINTS
from mcl3d.mapping.pipeline import BuildMapRequest
from mcl3d.mapping.pipeline import run as build_map
from mcl3d.mapping.pipeline import summary_rows as map_summary_rows
from mcl3d.maps.build import BuildConfig
from mcl3d.sim.pipeline import SimulateRequest
from mcl3d.sim.pipeline import run as simulate
from mcl3d.sim.pipeline import summary_rows as simulation_rows


@dataclass(frozen=True)
class DemoRequest:
    root: Path = Path("demo")
    seed: int = 0
    duration_s: float = 8.0
    sensor: str = "vlp16"
    backend: str = "auto"
    particles: int = 100_000
    points: int | None = None  # scan points per update; None: the localizer's default


# Global localization succeeded when every pose after convergence is this close to the truth
# (the accuracy the issue asks of global localization).
SUCCESS_M = 0.2
SUCCESS_DEG = 3.0


@dataclass
class DemoStep:
    title: str
    command: str  # the equivalent command line, so users can repeat the step by hand
    output: list[RenderableType]
    data: dict | None = None  # the step's machine-readable result (the localization summary)


def verdict(summary: LocalizeSummary) -> tuple[bool, str]:
    """(success, one line): did global localization converge onto the ground truth?"""
    if summary.converged_at_scan is None:
        return False, (f"global localization did not converge in {summary.scans} scans; "
                       f"try more particles (--particles) or a longer log (--duration)")
    after = summary.ate_after_convergence
    if after is None:
        return True, f"converged after {summary.converged_after_s:.1f} s (no ground truth)"
    ok = after.translation_max_m <= SUCCESS_M and after.rotation_max_deg <= SUCCESS_DEG
    where = (f"converged after {summary.converged_after_s:.1f} s; from then on within "
             f"{after.translation_max_m:.3f} m and {after.rotation_max_deg:.2f} deg of the "
             f"ground truth")
    if ok:
        return True, where
    return False, f"{where}: a wrong place (more than {SUCCESS_M} m or {SUCCESS_DEG} deg off)"


def _run_folder(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    folder = root / time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    if folder.exists():
        raise OutputExistsError(f"{folder} already exists; wait a second and run the demo again")
    folder.mkdir()
    latest = root / "latest"
    with contextlib.suppress(FileNotFoundError):
        latest.unlink()
    os.symlink(folder.name, latest)
    return folder


def check(req: DemoRequest) -> None:
    """Refuse impossible parameters before any folder is made."""
    if not math.isfinite(req.duration_s) or req.duration_s <= 0:
        raise ConfigError(f"the log's duration must be > 0 seconds, got {req.duration_s:g}",
                          setting="duration")
    if req.points is not None and req.points < MIN_SCAN_POINTS:
        raise ConfigError(f"the scan points per update must be >= {MIN_SCAN_POINTS}, got "
                          f"{req.points}", setting="points")
    check_capacity(req.particles)


def steps(req: DemoRequest):
    """Run the demo one step at a time, yielding each finished `DemoStep`."""
    check(req)
    folder = _run_folder(req.root)
    log = folder / "office.mcap"
    sim = simulate(SimulateRequest(world="office", sensor=req.sensor, trajectory="ground",
                                   duration_s=req.duration_s, seed=req.seed, output=log))
    yield DemoStep("Simulate a short office log",
                   f"mcl3d simulate office --sensor {req.sensor} --trajectory ground "
                   f"--duration {req.duration_s:g} --seed {req.seed} -o {log}",
                   [summary_table("Simulation", simulation_rows(sim))])
    yield DemoStep("Inspect the log", f"mcl3d info {log}", list(log_info_tables(log_info(log))))

    backend = runtime.init(req.backend).backend
    tsdf = folder / "office.tsdf"
    mesh = folder / "office_map_mesh.ply"
    with ProgressBars() as bars:
        built = build_map(BuildMapRequest(log, tsdf, config.build(BuildConfig, {}), f16=True,
                                          export_mesh=mesh), bars.on_progress)
    yield DemoStep("Build a TSDF map from the log and its ground truth",
                   f"mcl3d --backend {backend} build-map {log} -o {tsdf} --f16 "
                   f"--export-mesh {mesh}",
                   [summary_table("Map built", map_summary_rows(built, backend))])
    yield localize_step(req, log, tsdf, folder / "localize", backend)


def localize_step(req: DemoRequest, log: Path, tsdf: Path, out: Path, backend: str) -> DemoStep:
    """Global localization of the log in its map, with the verdict against ground truth."""
    overrides = {"localizer.init.mode": "global", "localizer.particles": req.particles,
                 "localizer.seed": req.seed, "localizer.sensor.points": req.points}
    cfg = config.load(LocalizeConfig, None, overrides)
    request = LocalizeRequest(log=log, map=tsdf, output_dir=out, config=cfg,
                              backend=req.backend)
    with ProgressBars() as bars:
        result = localize(request, on_progress=bars.on_progress)
    ok, line = verdict(result.summary)
    points = "" if req.points is None else f" --points {req.points}"
    return DemoStep("Localize the log in its map from no initial guess",
                    f"mcl3d --backend {backend} localize {log} --map {tsdf} --init global "
                    f"--particles {req.particles}{points} --seed {req.seed} -o {out}",
                    [summary_table("Localization", localize_rows(result.summary, out)),
                     f"[{'green' if ok else 'yellow'}]{line}"],
                    {"success": ok, **result.summary.to_json()})
