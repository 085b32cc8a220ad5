"""The `mcl3d` command line: parses, calls one pipeline, prints a Rich summary.

Heavy imports (taichi, open3d, mcap) happen inside the commands so `mcl3d --help` is instant.
Library errors (`Mcl3dError`) become one red line on stderr and exit code 1; usage errors
exit 2; Ctrl-C exits 130 after the running command has kept what it finished.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from mcl3d import __version__
from mcl3d.errors import Mcl3dError, RunInterrupted

BACKEND_HELP = (
    "Compute backend: auto (cuda, then a hardware Vulkan GPU, then cpu), cuda, vulkan or cpu."
)


class _App(typer.Typer):
    """Typer app that turns library errors into one line and the documented exit codes."""

    def __call__(self, *args, **kwargs):
        try:
            return super().__call__(*args, **kwargs)
        except RunInterrupted as exc:
            _error(str(exc))
            sys.exit(130)
        except Mcl3dError as exc:
            _error(str(exc))
            sys.exit(1)


def _error(message: str) -> None:
    from mcl3d.console import err_console

    err_console.print(f"[bold red]error:[/] {message}", soft_wrap=True)


app = _App(
    name="mcl3d",
    help="6-DoF Monte Carlo localization and Monte Carlo SLAM for 3D LiDAR "
    "(Taichi kernels on cuda, vulkan or cpu).",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


class _Globals:
    backend: str = "auto"


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mcl3d {__version__}")
        raise typer.Exit()


def _check_backend(value: str | None) -> str | None:
    from mcl3d.runtime import BACKENDS

    if value is not None and value not in BACKENDS:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(BACKENDS)}")
    return value


BackendOption = Annotated[
    str | None,
    typer.Option("--backend", help=BACKEND_HELP + " Overrides the global --backend.",
                 callback=_check_backend, show_default=False),
]


@app.callback()
def main(
    backend: Annotated[
        str, typer.Option("--backend", help=BACKEND_HELP, callback=_check_backend)
    ] = "auto",
    version: Annotated[
        bool, typer.Option("--version", help="Print the version and exit.", callback=_version,
                           is_eager=True)
    ] = False,
) -> None:
    _Globals.backend = backend


def _init_backend(backend: str | None):
    """Start the compute runtime on the command's --backend, else the global one."""
    from mcl3d import runtime

    return runtime.init(backend or _Globals.backend)


@app.command()
def backends(backend: BackendOption = None) -> None:
    """List the compute backends on this machine and start the selected one."""
    from mcl3d.console import console, summary_table
    from mcl3d.vulkan_probe import vulkan_devices

    devices = vulkan_devices()
    vulkan_text = ", ".join(f"{d.name} ({d.device_type})" for d in devices) or "no Vulkan driver"
    info = _init_backend(backend)
    console.print(summary_table("Compute backends", [
        ("vulkan devices", vulkan_text),
        ("requested", info.requested),
        ("running", f"{info.backend} on {info.device}"),
    ]))


def _one_of(allowed: tuple[str, ...]):
    """A Typer callback that accepts only `allowed` values (usage error, exit 2, otherwise)."""

    def check(value: str) -> str:
        if value not in allowed:
            raise typer.BadParameter(f"{value!r} is not one of {', '.join(allowed)}")
        return value

    return check


@app.command("eval")
def eval_trajectory(
    est: Annotated[Path, typer.Argument(
        help="Estimated trajectory: TUM (t x y z qx qy qz qw) or KITTI (12 numbers), by content.",
        show_default=False)],
    ref: Annotated[Path, typer.Option(
        "--ref", help="Reference (ground-truth) trajectory, TUM or KITTI.", show_default=False)],
    align: Annotated[str, typer.Option(
        "--align", callback=_one_of(("se3", "sim3", "origin", "none")),
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
        "--rpe-unit", callback=_one_of(("m", "frames")),
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

    from mcl3d.console import console
    from mcl3d.evaluation import evaluate, read_pair
    from mcl3d.outputs import check_writable, write_text_atomic
    from mcl3d.plots import plot_evaluation, plot_format

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
    for table in _eval_tables(result, ref, est, plot, json_path):
        console.print(table)


def _eval_tables(result, ref: Path, est: Path, plot: Path | None, json_path: Path | None):
    """The run summary and the error statistics of `mcl3d eval` as Rich tables."""
    from rich.table import Table

    from mcl3d.console import summary_table

    how = result.alignment
    aligned = {"none": "none", "origin": "origin (first poses coincide)",
               "se3": "se3 (Umeyama)", "sim3": f"sim3 (Umeyama), scale {how.scale:.6f}"}
    rows = [("reference", f"{ref} ({result.num_ref} poses)"),
            ("estimate", f"{est} ({result.num_est} poses)"),
            ("associated", f"{len(result.association)} poses within "
                           f"{result.association.max_diff_s:g} s"),
            ("alignment", aligned[how.method]),
            ("RPE pairs", f"{result.rpe.pairs.shape[0]} at {result.rpe.delta:g} {result.rpe.unit}"
                          f"{' (all pairs)' if result.rpe.all_pairs else ''}")]
    rows += [(name, str(path)) for name, path in (("plot", plot), ("json", json_path)) if path]
    stats = Table(title="Trajectory error", title_justify="left")
    for column in ("metric", "unit", "rmse", "mean", "median", "std", "min", "max"):
        stats.add_column(column, justify="left" if column in ("metric", "unit") else "right")
    for name, unit, s in (("ATE translation", "m", result.ate.translation_m),
                          ("ATE rotation", "deg", result.ate.rotation_deg),
                          ("RPE translation", "m", result.rpe.translation_m),
                          ("RPE rotation", "deg", result.rpe.rotation_deg)):
        stats.add_row(name, unit, *(f"{v:.4f}" for v in
                                    (s.rmse, s.mean, s.median, s.std, s.min, s.max)))
    return summary_table("Evaluation", rows), stats


# Topic overrides shared by every command that reads a log (CONVENTIONS §3).
PointsTopicOption = Annotated[str | None, typer.Option(
    "--points-topic", help="PointCloud2 topic (default: the only one in the log).")]
ImuTopicOption = Annotated[str | None, typer.Option(
    "--imu-topic", help="Imu topic (default: the only one in the log).")]
OdomTopicOption = Annotated[str | None, typer.Option(
    "--odom-topic", help="Odometry topic (default: the only one not named like ground truth).")]
GtTopicOption = Annotated[str | None, typer.Option(
    "--gt-topic", help="Ground-truth pose topic (default: the one named ground_truth, "
                       "groundtruth or gt).")]


@app.command()
def info(
    log: Annotated[Path, typer.Argument(help="MCAP file, ROS 1 .bag file or ROS 2 bag folder.",
                                        metavar="LOG", show_default=False)],
    points_topic: PointsTopicOption = None,
    imu_topic: ImuTopicOption = None,
    odom_topic: OdomTopicOption = None,
    gt_topic: GtTopicOption = None,
    scans: Annotated[int, typer.Option(min=1, help="Scans decoded per cloud topic for the "
                                       "point statistics.")] = 3,
) -> None:
    """Describe a log like `ros2 bag info`: topics, types, counts, rates, frames, cloud layout."""
    from mcl3d.console import console
    from mcl3d.logs.info import log_info, render

    result = log_info(log, max_scans=scans, points_topic=points_topic, imu_topic=imu_topic,
                      odom_topic=odom_topic, gt_topic=gt_topic)
    for table in render(result):
        console.print(table)


@app.command()
def simulate(
    world: Annotated[str, typer.Argument(
        help="World: office (rooms + ramps), building (floors + elevator), forest (tree rows) "
             "or arena (symmetric hall).", show_default=False)],
    output: Annotated[Path, typer.Option(
        "-o", "--output", help="The ROS 2 MCAP log to write; NAME_gt.tum (ground truth) and "
                               "NAME_config.yaml (effective config) go beside it.",
        show_default=False)],
    sensor: Annotated[str, typer.Option(
        "--sensor", help="LiDAR: vlp16, os0-64, os1-64 or mid360.")] = "vlp16",
    trajectory: Annotated[str, typer.Option(
        "--trajectory", help="ground, loop, handheld, drone (forest, arena), elevator "
                             "(building) or kidnap.")] = "ground",
    duration: Annotated[float, typer.Option("--duration", help="Seconds to simulate.")] = 10.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the world, the path and every "
                                      "noise: same seed, same bytes.")] = 0,
    config: Annotated[Path | None, typer.Option(
        "--config", help="YAML/TOML with sections lidar, imu, odometry, map (see the saved "
                         "_config.yaml for every key).", show_default=False)] = None,
    export_mesh: Annotated[Path | None, typer.Option(
        "--export-mesh", help="Also write the world's triangle mesh (.ply).",
        show_default=False)] = None,
    export_map: Annotated[Path | None, typer.Option(
        "--export-map", help="Also write a prior point-cloud map sampled on the surfaces (.ply).",
        show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
) -> None:
    """Simulate a LiDAR, IMU, odometry and ground truth in a world, as a ROS 2 MCAP log."""
    from mcl3d.console import console
    from mcl3d.sim.pipeline import SimulateRequest, run, summary_rows

    result = run(SimulateRequest(world=world, sensor=sensor, trajectory=trajectory,
                                 duration_s=duration, seed=seed, output=output,
                                 config_path=config, export_mesh=export_mesh,
                                 export_map=export_map, force=force))
    from mcl3d.console import summary_table

    console.print(summary_table("Simulation", summary_rows(result)))
