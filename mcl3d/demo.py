"""`mcl3d demo`: the whole chain on built-in data that the simulator makes on the spot:
simulate an office log, inspect it, build its TSDF map.

Each run writes into a fresh `<root>/<UTC time>/` folder (and points `<root>/latest` at it),
so running the demo again never overwrites an earlier result.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from rich.console import RenderableType

from mcl3d.errors import OutputExistsError


@dataclass(frozen=True)
class DemoRequest:
    root: Path = Path("demo")
    seed: int = 0
    duration_s: float = 8.0
    sensor: str = "vlp16"
    backend: str = "auto"


@dataclass
class DemoStep:
    title: str
    command: str  # the equivalent command line, so users can repeat the step by hand
    output: list[RenderableType]


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


def steps(req: DemoRequest):
    """Run the demo one step at a time, yielding each finished `DemoStep`."""
    from mcl3d import config, runtime
    from mcl3d.build_map import BuildMapPipeline
    from mcl3d.build_map import summary_rows as map_summary_rows
    from mcl3d.console import summary_table
    from mcl3d.logs.info import log_info, render
    from mcl3d.maps.build import BuildConfig
    from mcl3d.sim.pipeline import SimulateRequest, summary_rows
    from mcl3d.sim.pipeline import run as simulate

    folder = _run_folder(req.root)
    log = folder / "office.mcap"
    sim = simulate(SimulateRequest(world="office", sensor=req.sensor, trajectory="ground",
                                   duration_s=req.duration_s, seed=req.seed, output=log))
    yield DemoStep("Simulate a short office log",
                   f"mcl3d simulate office --sensor {req.sensor} --trajectory ground "
                   f"--duration {req.duration_s:g} --seed {req.seed} -o {log}",
                   [summary_table("Simulation", summary_rows(sim))])
    yield DemoStep("Inspect the log", f"mcl3d info {log}", list(render(log_info(log))))

    backend = runtime.init(req.backend).backend
    tsdf = folder / "office.tsdf"
    mesh = folder / "office_map_mesh.ply"
    built = BuildMapPipeline(log, tsdf, config.build(BuildConfig, {}), f16=True,
                             export_mesh=mesh).run()
    yield DemoStep("Build a TSDF map from the log and its ground truth",
                   f"mcl3d --backend {backend} build-map {log} -o {tsdf} --f16 "
                   f"--export-mesh {mesh}",
                   [summary_table("Map built", map_summary_rows(built, backend))])
