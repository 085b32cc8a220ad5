"""The commands around the estimators: inspect logs and maps, evaluate trajectories, simulate,
run the demo, run a manifest of runs on Ray. `cli.py` registers them on the app; heavy imports
stay inside each command.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mcl3d.cli_options import (
    BackendOption,
    Globals,
    GtTopicOption,
    ImuTopicOption,
    JsonOption,
    OdomTopicOption,
    PointsTopicOption,
    init_backend,
    one_of,
)


def backends(backend: BackendOption = None) -> None:
    """List the compute backends on this machine and start the selected one."""
    from mcl3d.console import console, summary_table
    from mcl3d.core.vulkan_probe import vulkan_devices

    devices = vulkan_devices()
    vulkan_text = ", ".join(f"{d.name} ({d.device_type})" for d in devices) or "no Vulkan driver"
    info = init_backend(backend)
    console.print(summary_table("Compute backends", [
        ("vulkan devices", vulkan_text),
        ("requested", info.requested),
        ("running", f"{info.backend} on {info.device}"),
    ]))


def eval_trajectory(
    est: Annotated[Path, typer.Argument(
        help="Estimated trajectory: TUM (t x y z qx qy qz qw) or KITTI (12 numbers), by content.",
        show_default=False)],
    ref: Annotated[Path, typer.Option(
        "--ref", help="Reference (ground-truth) trajectory, TUM or KITTI.", show_default=False)],
    align: Annotated[str, typer.Option(
        "--align", callback=one_of(("se3", "sim3", "origin", "none")),
        help="Alignment of the estimate before the errors: se3 or sim3 (Umeyama over all "
             "associated positions; sim3 also fits the scale), origin (first poses coincide) "
             "or none (same as evo without -a).")] = "none",
    t_max_diff: Annotated[float, typer.Option(
        "--t-max-diff", min=0.0,
        help="Largest stamp difference in seconds for pairing poses (as evo's --t_max_diff).")
    ] = 0.01,
    rpe_delta: Annotated[float, typer.Option(
        "--rpe-delta", help="RPE pose-pair spacing, in --rpe-unit.")] = 1.0,
    rpe_unit: Annotated[str, typer.Option(
        "--rpe-unit", callback=one_of(("m", "frames")),
        help="RPE spacing unit: m (travelled distance) or frames.")] = "m",
    rpe_all_pairs: Annotated[bool, typer.Option(
        "--rpe-all-pairs", help="Use every pose as an RPE pair start, not consecutive pairs.")
    ] = False,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Write a figure (.png, .pdf or .svg): top view of both trajectories "
                       "and the ATE over time.", show_default=False)] = None,
    json_path: Annotated[Path | None, typer.Option(
        "--json", help="Write the numbers as JSON.", show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
) -> None:
    """Accuracy of a trajectory against a reference: ATE and RPE, with evo's numbers."""
    import json

    from mcl3d.console import console, evaluation_tables
    from mcl3d.core.outputs import check_writable, write_text_atomic
    from mcl3d.evaluation.metrics import evaluate, read_pair
    from mcl3d.evaluation.plots import plot_evaluation, plot_format

    for path in (plot, json_path):
        if path is not None:
            check_writable(path, force)
    if plot is not None:
        plot_format(plot)
    reference, estimate = read_pair(ref, est)
    result = evaluate(reference, estimate, alignment=align, max_diff_s=t_max_diff,
                      rpe_delta=rpe_delta, rpe_unit=rpe_unit, all_pairs=rpe_all_pairs,
                      ref_name=str(ref), est_name=str(est))
    if plot is not None:
        plot_evaluation(plot, result, reference, estimate, ref_label=ref.name,
                        est_label=est.name)
    if json_path is not None:
        numbers = {"reference": str(ref), "estimate": str(est), **result.as_dict()}
        write_text_atomic(json_path, json.dumps(numbers, indent=2) + "\n")
    for table in evaluation_tables(result, ref, est, plot, json_path):
        console.print(table)


def info(
    log: Annotated[Path, typer.Argument(help="MCAP file, ROS 1 .bag file, ROS 2 bag folder, "
                                        "KITTI sequence folder or Ouster .pcap (with its "
                                        "metadata JSON beside it).", metavar="LOG",
                                        show_default=False)],
    points_topic: PointsTopicOption = None,
    imu_topic: ImuTopicOption = None,
    odom_topic: OdomTopicOption = None,
    gt_topic: GtTopicOption = None,
    scans: Annotated[int, typer.Option(min=1, help="Scans decoded per cloud topic for the "
                                       "point statistics.")] = 3,
    as_json: JsonOption = False,
) -> None:
    """Describe a log like `ros2 bag info`: topics, types, counts, rates, frames, cloud layout."""
    from mcl3d.console import log_info_json, log_info_tables, print_json, print_tables
    from mcl3d.io.logs.info import log_info

    result = log_info(log, max_scans=scans, points_topic=points_topic, imu_topic=imu_topic,
                      odom_topic=odom_topic, gt_topic=gt_topic)
    if as_json:
        print_json(log_info_json(result))
    else:
        print_tables(log_info_tables(result))


def simulate(
    world: Annotated[str, typer.Argument(
        help="World: office (rooms + ramps), building (floors + elevator), forest (tree rows), "
             "arena (symmetric hall) or warehouse (rack aisles + ramp).", show_default=False)],
    output: Annotated[Path, typer.Option(
        "-o", "--output", help="The ROS 2 MCAP log to write; NAME_gt.tum (ground truth) and "
                               "NAME_config.yaml (effective config) go beside it.",
        show_default=False)],
    sensor: Annotated[str | None, typer.Option(
        "--sensor", help="LiDAR: vlp16, os0-64, os1-64 or mid360 (default: mid360 for "
                         "paper-forest, else vlp16).", show_default=False)] = None,
    trajectory: Annotated[str, typer.Option(
        "--trajectory", help="ground, loop, handheld, drone (forest, arena), elevator "
                             "(building), kidnap, survey (office: every room, once round in "
                             "~325 s), paper-office-1..11 (office: the MCL paper's tours from "
                             "look-alike rooms), paper-forest (forest) or paper-elevator "
                             "(building).")
    ] = "ground",
    duration: Annotated[float | None, typer.Option(
        "--duration", help="Seconds to simulate (default: the route's own length for "
                           "the paper-* routes, else 10).",
        show_default=False)] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the world, the path and every "
                                      "noise: same seed, same bytes.")] = 0,
    world_seed: Annotated[int | None, typer.Option(
        "--world-seed", help="Seed of the world's layout alone (furniture, the arena's stage; "
                             "default: --seed): a second log of the same world, e.g. one to "
                             "build a map from.", show_default=False)] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="YAML/TOML with sections world, lidar, imu, odometry, map (the "
                         "saved _config.yaml lists every key).", show_default=False)] = None,
    export_mesh: Annotated[Path | None, typer.Option(
        "--export-mesh", help="Also write the world's triangle mesh (.ply).",
        show_default=False)] = None,
    export_map: Annotated[Path | None, typer.Option(
        "--export-map", help="Also write a prior point-cloud map sampled on the surfaces (.ply).",
        show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
) -> None:
    """Simulate a LiDAR, IMU, odometry and ground truth in a world, as a ROS 2 MCAP log."""
    from mcl3d.console import ProgressBars, console, summary_table
    from mcl3d.sim.pipeline import SimulateRequest, run, summary_rows

    with ProgressBars() as bars:
        result = run(SimulateRequest(world=world, sensor=sensor, trajectory=trajectory,
                                     duration_s=duration, seed=seed, output=output,
                                     config_path=config, export_mesh=export_mesh,
                                     export_map=export_map, force=force,
                                     world_seed=world_seed), bars.on_progress)
    console.print(summary_table("Simulation", summary_rows(result)))


def map_info(
    map_file: Annotated[Path, typer.Argument(help="A map file written by build-map (.tsdf).")],
    export_mesh: Annotated[Path | None, typer.Option(
        "--export-mesh", help="Write the zero level set as a mesh (.ply/.obj/.stl).",
        show_default=False)] = None,
    export_points: Annotated[Path | None, typer.Option(
        "--export-points", help="Write the surface voxels as points (.ply/.pcd).",
        show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    as_json: JsonOption = False,
) -> None:
    """Print a map's header and statistics; optionally export it for viewers."""
    from mcl3d.console import map_info_table, print_json, print_tables
    from mcl3d.mapping.map_info import map_info as read_map_info

    result = read_map_info(map_file, export_mesh=export_mesh, export_points=export_points,
                           force=force)
    if as_json:
        print_json(result.as_dict())
    else:
        print_tables([map_info_table(result)])


def demo(
    root: Annotated[Path, typer.Option(
        "-o", "--output", help="Folder for the demo runs; each run gets a new timestamped "
                               "subfolder and `latest` points at it.")] = Path("demo"),
    seed: Annotated[int, typer.Option("--seed", help="Seed of the simulated log and of the "
                                               "particle filter.")] = 0,
    duration: Annotated[float, typer.Option(help="Seconds of log to simulate.")] = 8.0,
    particles: Annotated[int, typer.Option(help="Particles for global localization.")] = 100_000,
    points: Annotated[int | None, typer.Option(
        help="Scan points per update (default 256).")] = None,
    backend: BackendOption = None,
) -> None:
    """Run the chain on built-in demo data: simulate an office log, inspect it, map it,
    localize it globally in its map and compare with the ground truth."""
    from mcl3d.console import console
    from mcl3d.demo import DemoRequest, steps

    request = DemoRequest(root=root, seed=seed, duration_s=duration, particles=particles,
                          points=points, backend=backend or Globals.backend)
    for number, step in enumerate(steps(request), start=1):
        console.rule(f"[bold]{number}. {step.title}")
        console.print(f"[dim]$ {step.command}")
        for renderable in step.output:
            console.print(renderable)


def batch(
    manifest: Annotated[Path, typer.Argument(
        help="YAML manifest: jobs of a command on a log with settings, seeds and particle "
             "counts (docs/batch.md).")],
    out: Annotated[Path, typer.Option(
        "-o", "--out", help="Output folder: <job>/<run>/ per run, results.csv, results.json "
                            "and the pictures.")],
    workers: Annotated[int | None, typer.Option(
        min=1, help="Runs at once on the local Ray (default: one per CPU).",
        show_default=False)] = None,
    address: Annotated[str | None, typer.Option(
        help='Run on this Ray cluster ("auto", "ray://head:10001") instead of a local Ray.',
        show_default=False)] = None,
    retries: Annotated[int, typer.Option(
        min=0, help="Times a run whose process crashed is tried again.")] = 1,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    backend: BackendOption = None,
) -> None:
    """Run a manifest's jobs (logs x seeds x particle counts) on Ray, each run in its own
    process, and tabulate them: one row per run."""
    from rich.table import Table

    from mcl3d.batch.pipeline import BatchRequest, run, summary_rows
    from mcl3d.batch.results import job_rows
    from mcl3d.console import ProgressBars, console, summary_table

    request = BatchRequest(manifest, out, workers=workers, address=address, retries=retries,
                           backend=backend or Globals.backend, force=force)
    with ProgressBars() as bars:
        result = run(request, bars.on_progress)
    jobs = Table(title="Jobs", title_justify="left")
    for column in ("job", "command", "runs ok", "success", "median ATE (m)"):
        jobs.add_column(column)
    for row in job_rows(result.rows):
        jobs.add_row(*row)
    console.print(jobs)
    console.print(summary_table("Batch", summary_rows(result)))
    for row in [r for r in result.rows if r["status"] != "ok"][:5]:
        console.print(f"[yellow]failed:[/] {row['job']}/{row['run']}: {row['error']}")


COMMANDS = (("backends", backends), ("eval", eval_trajectory), ("info", info),
            ("simulate", simulate), ("map-info", map_info), ("demo", demo), ("batch", batch))
