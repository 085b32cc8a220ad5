"""The `mcl3d` command line: parses, calls one pipeline, prints a Rich summary.

This file holds the app and the commands that estimate poses or build maps; the commands
around them (info, eval, simulate, map-info, demo, backends) are in `mcl3d/cli_tools.py` and
the options they share in `mcl3d/cli_options.py`.

Heavy imports (taichi, open3d, mcap) happen inside the commands so `mcl3d --help` is instant.
Library errors (`Mcl3dError`) become one red line on stderr and exit code 1; usage errors
exit 2; Ctrl-C exits 130 after the running command has kept what it finished.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from mcl3d import __version__, cli_tools
from mcl3d.cli_options import (
    BACKEND_HELP,
    BackendOption,
    Globals,
    LiveOption,
    LivePortOption,
    ResultMcapOption,
    check_backend,
    init_backend,
    live_port,
    print_notes,
)
from mcl3d.core.errors import Mcl3dError, RunInterrupted


class _App(typer.Typer):
    """Typer app that turns library errors into one line and the documented exit codes."""

    def __call__(self, *args, **kwargs):
        try:
            return super().__call__(*args, **kwargs)
        except RunInterrupted as exc:
            _error(_with_flag(exc))
            sys.exit(130)
        except Mcl3dError as exc:
            _error(_with_flag(exc))
            sys.exit(1)


def _with_flag(exc: Mcl3dError) -> str:
    from mcl3d.console import with_flag

    return with_flag(str(exc), exc.setting)


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


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mcl3d {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    backend: Annotated[
        str, typer.Option("--backend", help=BACKEND_HELP, callback=check_backend)
    ] = "auto",
    version: Annotated[
        bool, typer.Option("--version", help="Print the version and exit.", callback=_version,
                           is_eager=True)
    ] = False,
) -> None:
    Globals.backend = backend


for _name, _command in cli_tools.COMMANDS:
    app.command(_name)(_command)


@app.command("build-map")
def build_map(
    source: Annotated[Path, typer.Argument(
        help="A log (MCAP, ROS bag, KITTI folder, Ouster .pcap) with ground truth or "
             "--trajectory, a point-cloud map (.pcd/.ply/.bin), a mesh (.ply/.obj/.stl/.off/.glb) "
             "or a HATSDF map (.h5).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="The map file to write "
                                         "(.tsdf).")],
    trajectory: Annotated[Path | None, typer.Option(
        "--trajectory", help="TUM/KITTI poses T_map_lidar for the log's scans (default: the "
                             "log's ground truth); for point clouds, viewpoints that orient "
                             "the normals.", show_default=False)] = None,
    voxel_size: Annotated[float | None, typer.Option(
        "--voxel-size", help="Voxel edge in m [default: 0.05].", show_default=False)] = None,
    truncation: Annotated[float | None, typer.Option(
        "--truncation", help="Truncation distance in m [default: 4 voxels].",
        show_default=False)] = None,
    normals: Annotated[str | None, typer.Option(
        "--normals", help="Scans: point-to-plane distances from normals of the range image "
                          "on the device (auto; scans without rings: knn), of the k nearest "
                          "neighbours on the host (knn), or none (projective) [default: "
                          "auto].", show_default=False)] = None,
    max_range: Annotated[float | None, typer.Option(
        "--max-range", help="Ignore scan points farther than this (m) [default: 120].",
        show_default=False)] = None,
    capacity_blocks: Annotated[int | None, typer.Option(
        "--capacity-blocks", help="Most 8³ blocks the map may grow to [default: 1048576].",
        show_default=False)] = None,
    f16: Annotated[bool, typer.Option("--f16", help="Store distances and weights in half "
                                      "precision (read-only localization maps).")] = False,
    export_mesh: Annotated[Path | None, typer.Option(
        "--export-mesh", help="Also write the zero level set as a mesh (.ply/.obj/.stl).",
        show_default=False)] = None,
    export_points: Annotated[Path | None, typer.Option(
        "--export-points", help="Also write the surface voxels as points (.ply/.pcd).",
        show_default=False)] = None,
    points_topic: Annotated[str | None, typer.Option(
        "--points-topic", help="Point-cloud topic of the log.", show_default=False)] = None,
    gt_topic: Annotated[str | None, typer.Option(
        "--gt-topic", help="Ground-truth topic of the log.", show_default=False)] = None,
    config: Annotated[Path | None, typer.Option(
        "--config", help="YAML/TOML with build-map parameters (keys of BuildConfig).",
        show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    backend: BackendOption = None,
) -> None:
    """Build a TSDF map from a log with poses, a point-cloud map, a mesh or a HATSDF map."""
    from mcl3d.console import ProgressBars, console, summary_table
    from mcl3d.core import config as cfg
    from mcl3d.mapping.pipeline import BuildMapRequest, run, summary_rows
    from mcl3d.maps.build import BuildConfig

    settings = cfg.load(BuildConfig, config, {
        "voxel_size_m": voxel_size, "truncation_m": truncation, "normals": normals,
        "max_range_m": max_range, "max_capacity_blocks": capacity_blocks})
    info = init_backend(backend)
    request = BuildMapRequest(source, output, settings, trajectory=trajectory, f16=f16,
                              force=force, export_mesh=export_mesh,
                              export_points=export_points, points_topic=points_topic,
                              gt_topic=gt_topic)
    with ProgressBars() as bars:
        result = run(request, bars.on_progress)
    console.print(summary_table("Map built", summary_rows(result, info.backend)))
    print_notes([], [], 0, result.faults.warnings())


# ------------------------------------------------------------------------ localize
def _localize_overrides(init: str, init_std: str | None, particles: int | None,
                        min_particles: int | None, max_particles: int | None,
                        points: int | None, seed: int | None, height_band: str | None,
                        motion: str | None, max_scans: int | None) -> dict:
    from mcl3d.localization.initialization import parse_floats

    o: dict = {"localizer.seed": seed, "localizer.sensor.points": points,
               "motion_source.source": motion, "max_scans": max_scans}
    if init in ("global", "gt"):
        o["localizer.init.mode"] = init
    else:
        o["localizer.init.mode"] = "pose"
        o["localizer.init.pose"] = parse_floats(init, 6, "--init (x y z [m] roll pitch yaw [deg])")
    if init_std is not None:
        o["localizer.init.std"] = parse_floats(init_std, 6, "--init-std")
    if height_band is not None:
        text = height_band.strip().lower()
        o["localizer.init.height_band_m"] = (
            None if text == "none" else "auto" if text == "auto"
            else parse_floats(height_band, 2, "--height-band (lo hi, m)"))
    if min_particles is not None or max_particles is not None:
        o["localizer.resample.kld"] = True
        o["localizer.resample.min_particles"] = min_particles
        o["localizer.particles"] = max_particles or particles
    else:
        o["localizer.particles"] = particles
    return o


@app.command()
def localize(
    log: Annotated[Path, typer.Argument(help="Log with LiDAR scans (MCAP, ROS 1 bag, ROS 2 bag, "
                                        "KITTI folder, Ouster .pcap).")],
    map_file: Annotated[Path, typer.Option("--map", help="TSDF map (.tsdf) from build-map.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder.")],
    init: Annotated[str, typer.Option(
        help='"global" (uniform over free space), "gt" (first ground-truth pose) or '
             '"x y z roll pitch yaw" (m, deg).')] = "global",
    init_std: Annotated[str | None, typer.Option(
        help='Std around --init pose: "sx sy sz sroll spitch syaw" (m, deg).')] = None,
    particles: Annotated[int | None, typer.Option(
        help="Particles N (default 100000).")] = None,
    min_particles: Annotated[int | None, typer.Option(
        help="Enable KLD-sampling with at least this many particles.")] = None,
    max_particles: Annotated[int | None, typer.Option(
        help="Enable KLD-sampling with at most this many particles.")] = None,
    points: Annotated[int | None, typer.Option(
        help="Scan points M per update (default 256).")] = None,
    height_band: Annotated[str | None, typer.Option(
        help='Global init: lidar height above the floor "lo hi" (m); "auto" (default: the '
             'floor in the first scan, levelled by the IMU, else "0.2 2.5"); "none": anywhere.'
    )] = None,
    motion: Annotated[str | None, typer.Option(
        help="Motion source: auto, odom, imu or constant_velocity.")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed (reproducible runs).")] = None,
    max_scans: Annotated[int | None, typer.Option(help="Stop after this many scans.")] = None,
    config: Annotated[Path | None, typer.Option(
        help="YAML/TOML config (sections as in the saved config.yaml).")] = None,
    preset: Annotated[str, typer.Option(help="Settings under --config and the flags: default "
                                        "or paper (the MCL paper's model and filter).")
                      ] = "default",
    points_topic: Annotated[str | None, typer.Option(help="Point-cloud topic.")] = None,
    imu_topic: Annotated[str | None, typer.Option(help="IMU topic.")] = None,
    odom_topic: Annotated[str | None, typer.Option(help="Odometry topic.")] = None,
    gt_topic: Annotated[str | None, typer.Option(help="Ground-truth topic.")] = None,
    result_mcap: ResultMcapOption = None,
    live: LiveOption = False,
    port: LivePortOption = 8765,
    force: Annotated[bool, typer.Option(help="Overwrite existing outputs.")] = False,
    backend: BackendOption = None,
) -> None:
    """6-DoF Monte Carlo localization of a log in a TSDF map (global or tracking)."""
    from mcl3d.console import ProgressBars, console, summary_table
    from mcl3d.core import config as config_mod
    from mcl3d.localization.localization_summary import summary_rows
    from mcl3d.localization.motion_source import KINDS
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, Topics, run
    from mcl3d.localization.presets import localize_preset

    if motion is not None and motion not in KINDS:
        raise typer.BadParameter("--motion must be auto, odom, imu or constant_velocity")
    overrides = _localize_overrides(init, init_std, particles, min_particles, max_particles,
                                    points, seed, height_band, motion, max_scans)
    cfg = config_mod.load(LocalizeConfig, config, overrides, preset=localize_preset(preset))
    info = init_backend(backend)
    request = LocalizeRequest(log=log, map=map_file, output_dir=out, config=cfg, preset=preset,
                              topics=Topics(points_topic, imu_topic, odom_topic, gt_topic),
                              force=force, result_mcap=result_mcap,
                              live_port=live_port(live, port), backend=info.requested)
    with ProgressBars() as bars:
        result = run(request, on_progress=bars.on_progress)
    s = result.summary
    console.print(summary_table("Localization", summary_rows(s, out)))
    print_notes([], s.warnings, len(s.warnings), s.faults.warnings())


@app.command()
def odometry(
    log: Annotated[Path, typer.Argument(help="Log with LiDAR scans (MCAP, ROS 1 bag, ROS 2 bag, "
                                        "KITTI folder, Ouster .pcap). IMU and ground truth are "
                                        "used when present.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder: odometry.tum, "
                                      "odometry_kitti.txt, relative_motion.npz, "
                                      "odometry_summary.json, odometry_config.yaml.")],
    voxel_size: Annotated[float | None, typer.Option(
        help="Downsampling voxel edge in m (default 0.25).")] = None,
    map_voxel_size: Annotated[float | None, typer.Option(
        help="Finest keyframe voxel map edge in m, a 2x level is added (default: 0.25 to "
             "0.5 m from the first scan's median range).")] = None,
    keyframe_overlap: Annotated[float | None, typer.Option(
        help="New keyframe when the overlap drops below this (default 0.7).")] = None,
    no_imu: Annotated[bool, typer.Option("--no-imu", help="Ignore the IMU: constant-velocity "
                                         "prediction.")] = False,
    no_deskew: Annotated[bool, typer.Option("--no-deskew", help="Do not deskew sweeps.")] = False,
    max_scans: Annotated[int | None, typer.Option(help="Stop after this many scans.")] = None,
    config: Annotated[Path | None, typer.Option(
        help="YAML/TOML odometry config (keys as in the saved odometry_config.yaml).")] = None,
    points_topic: Annotated[str | None, typer.Option(help="Point-cloud topic.")] = None,
    imu_topic: Annotated[str | None, typer.Option(help="IMU topic.")] = None,
    gt_topic: Annotated[str | None, typer.Option(help="Ground-truth topic.")] = None,
    result_mcap: ResultMcapOption = None,
    live: LiveOption = False,
    port: LivePortOption = 8765,
    force: Annotated[bool, typer.Option(help="Overwrite existing outputs.")] = False,
    backend: BackendOption = None,
) -> None:
    """LiDAR(-inertial) odometry: scan-to-model GICP against recent keyframes."""
    from mcl3d.console import ProgressBars, console, summary_table
    from mcl3d.core import config as config_io
    from mcl3d.odometry.lidar_odometry import OdometryConfig
    from mcl3d.odometry.odometry_summary import summary_rows
    from mcl3d.odometry.pipeline import OdometryRequest, run

    info = init_backend(backend)
    overrides = {"voxel_size_m": voxel_size, "map_voxel_size_m": map_voxel_size,
                 "keyframe_overlap": keyframe_overlap,
                 "use_imu": False if no_imu else None, "deskew": False if no_deskew else None}
    cfg = config_io.load(OdometryConfig, config, overrides)
    with ProgressBars() as bars:
        result = run(OdometryRequest(log=log, output_dir=out, config=cfg, force=force,
                                     points_topic=points_topic, imu_topic=imu_topic,
                                     gt_topic=gt_topic, max_scans=max_scans,
                                     result_mcap=result_mcap, live_port=live_port(live, port)),
                     bars.on_progress)
    s = result.summary
    console.print(summary_table("Odometry", summary_rows(s, f"{info.backend} ({info.device})",
                                                          out)))
    print_notes(s.notes, s.warnings, s.num_warnings, s.faults.warnings())


@app.command()
def slam(
    log: Annotated[Path, typer.Argument(help="Log with LiDAR scans (MCAP, ROS 1 bag, ROS 2 bag, "
                                        "KITTI folder, Ouster .pcap). IMU and ground truth are "
                                        "used when present.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder: slam.tum, "
                                      "slam_kitti.txt, slam_online.tum, odometry.tum, map.ply, "
                                      "frames.csv, slam_summary.json, slam_config.yaml.")],
    particles: Annotated[int | None, typer.Option(
        help="Particles N (default 10000).")] = None,
    fov: Annotated[float | None, typer.Option(
        help="Keep points within ±fov/2 degrees of the lidar's +x axis (default 360).")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed (reproducible runs).")] = None,
    no_imu: Annotated[bool, typer.Option("--no-imu", help="Ignore the IMU: constant-velocity "
                                         "prediction.")] = False,
    max_scans: Annotated[int | None, typer.Option(help="Stop after this many scans.")] = None,
    tsdf: Annotated[Path | None, typer.Option(
        help="Also build a TSDF map (.tsdf) from the log placed by the SLAM trajectory, ready "
             "for `mcl3d localize`.")] = None,
    config: Annotated[Path | None, typer.Option(
        help="YAML/TOML SLAM config (keys as in the saved slam_config.yaml).")] = None,
    preset: Annotated[str, typer.Option(help="Settings under --config and the flags: default "
                                        "or paper (the SLAM paper's filter).")] = "default",
    points_topic: Annotated[str | None, typer.Option(help="Point-cloud topic.")] = None,
    imu_topic: Annotated[str | None, typer.Option(help="IMU topic.")] = None,
    gt_topic: Annotated[str | None, typer.Option(help="Ground-truth topic.")] = None,
    result_mcap: ResultMcapOption = None,
    live: LiveOption = False,
    port: LivePortOption = 8765,
    force: Annotated[bool, typer.Option(help="Overwrite existing outputs.")] = False,
    backend: BackendOption = None,
) -> None:
    """Range-based 6-DoF Monte Carlo SLAM: particles with their own keyframe poses, corrected
    by Gauss-Newton steps on a GICP likelihood when they close a loop."""
    from mcl3d.console import ProgressBars, console, summary_table
    from mcl3d.core import config as config_io
    from mcl3d.slam.pipeline import SlamRequest, run
    from mcl3d.slam.presets import preset as slam_preset
    from mcl3d.slam.slam_config import SlamConfig
    from mcl3d.slam.slam_summary import summary_rows

    overrides = {"particles": particles, "front_end.fov_deg": fov, "seed": seed,
                 "odometry.use_imu": False if no_imu else None}
    cfg = config_io.load(SlamConfig, config, overrides, preset=slam_preset(preset))
    info = init_backend(backend)
    with ProgressBars() as bars:
        result = run(SlamRequest(log=log, output_dir=out, config=cfg, force=force,
                                 points_topic=points_topic, imu_topic=imu_topic,
                                 gt_topic=gt_topic, max_scans=max_scans, tsdf=tsdf,
                                 result_mcap=result_mcap, live_port=live_port(live, port)),
                     bars.on_progress)
    rows = summary_rows(result.summary, f"{info.backend} ({info.device})", out,
                        result.tsdf.path if result.tsdf else None)
    console.print(summary_table("Monte Carlo SLAM", rows))
    print_notes(result.summary.notes, [], 0, result.summary.faults.warnings())
