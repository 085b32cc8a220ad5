"""`mcl3d simulate` speed: scans simulated per second for each sensor, against real time.

For each sensor the whole pipeline runs (poses at every firing time, ray casting, noise,
IMU, odometry, CDR encoding and zstd-compressed MCAP writing) on a ground robot in a world.
Baselines measured in the same run: real time (the sensor's 10 Hz), and Open3D ray casting
alone of the same number of rays from one fixed pose (the floor the pipeline cannot beat).
Prints a table and writes bench/results/bench_simulate.json through results_io.

    python bench/bench_simulate.py [--quick] --duration 5 --world office
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from results_io import Run


def raycast_only_scans_per_s(world_name: str, sensor: str, repeats: int) -> float:
    """Scans/s of bare Open3D ray casting: the sensor's rays from one fixed pose."""
    from mcl3d.sim.lidars import make_lidar
    from mcl3d.sim.raycast import WorldCaster
    from mcl3d.sim.worlds import build_world

    world = build_world(world_name)
    caster = WorldCaster(world)
    firing = make_lidar(sensor).firing(0, 0.1, 1)
    origins = np.tile([[3.0, 9.25, 0.5]], (len(firing.directions), 1))
    caster.cast(origins, firing.directions)
    t0 = time.perf_counter()
    for _ in range(repeats):
        caster.cast(origins, firing.directions)
    return repeats / (time.perf_counter() - t0)


def main() -> None:
    from rich.console import Console
    from rich.table import Table

    from mcl3d.sim.lidars import SENSORS
    from mcl3d.sim.pipeline import SimulateRequest, run

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=None,
                        help="simulated seconds per sensor (default 5, --quick 1)")
    parser.add_argument("--quick", action="store_true", help="1 s per sensor")
    parser.add_argument("--backend", default="cpu",
                        help="accepted for run_all; simulation runs on the cpu (Open3D)")
    parser.add_argument("--world", default="office")
    parser.add_argument("--trajectory", default="ground")
    parser.add_argument("--out", type=Path, help="JSON (default bench/results/bench_simulate.json)")
    args = parser.parse_args()
    args.duration = args.duration or (1.0 if args.quick else 5.0)
    bench_run = Run("bench_simulate", baselines=("open3d",))

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sensor in SENSORS:
            log = Path(tmp) / f"{sensor}.mcap"
            # warm-up: imports, world build, Open3D BVH
            run(SimulateRequest(args.world, sensor, args.trajectory, 0.2, 0, log, force=True))
            t0 = time.perf_counter()
            result = run(SimulateRequest(args.world, sensor, args.trajectory, args.duration, 0,
                                         log, force=True))
            wall = time.perf_counter() - t0
            scans_per_s = result.n_scans / wall
            cast_only = raycast_only_scans_per_s(args.world, sensor, 10)
            rows.append({
                "sensor": sensor, "scans": result.n_scans,
                "points_per_scan": round(result.points_per_scan),
                "wall_s": round(wall, 3), "scans_per_s": round(scans_per_s, 2),
                "realtime_factor": round(scans_per_s / result.scan_rate_hz, 2),
                "raycast_only_scans_per_s": round(cast_only, 2),
                "pipeline_vs_raycast": round(scans_per_s / cast_only, 3),
                "log_mb": round(log.stat().st_size / 1e6, 2),
            })

    table = Table(title=f"mcl3d simulate: {args.world}/{args.trajectory}, "
                        f"{args.duration:g} s per sensor", title_justify="left")
    for col in ("sensor", "points/scan", "scans/s", "x real time (10 Hz)",
                "ray cast only scans/s", "pipeline / ray cast", "log MB"):
        table.add_column(col, justify="left" if col == "sensor" else "right")
    for r in rows:
        table.add_row(r["sensor"], str(r["points_per_scan"]), f"{r['scans_per_s']:.1f}",
                      f"{r['realtime_factor']:.2f}", f"{r['raycast_only_scans_per_s']:.1f}",
                      f"{r['pipeline_vs_raycast']:.2f}", f"{r['log_mb']:.1f}")
    Console().print(table)
    table_rows = [{"sensor": r["sensor"], "points/scan": r["points_per_scan"],
                   "scans/s": r["scans_per_s"], "× real time (10 Hz)": r["realtime_factor"],
                   "Open3D ray cast only, scans/s": r["raycast_only_scans_per_s"],
                   "pipeline / ray cast": r["pipeline_vs_raycast"], "log MB": r["log_mb"]}
                  for r in rows]
    path = bench_run.write({
        "tables": {f"mcl3d simulate, {args.world}/{args.trajectory}, {args.duration:g} s per "
                   "sensor": table_rows},
        "notes": ["Whole pipeline per sensor after a 0.2 s warm-up run (imports, world, BVH); "
                  "the ray-cast baseline casts the same rays from one fixed pose, 10 times."],
        "world": args.world, "trajectory": args.trajectory, "duration_s": args.duration,
        "results": rows}, args.out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
