"""`mcl3d simulate`: a world, a trajectory and a sensor rig, written as a ROS 2 MCAP log.

The run reads as its steps: check every output can be written, build the world and the
trajectory, write the static extrinsics, then scan by scan the point cloud and ground truth
followed by the IMU and odometry samples of that sweep, and finally the TUM ground truth,
the effective config and the optional mesh and map exports. Everything is seeded, so the
same arguments give the same bytes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from mcl3d.core import config as cfgmod
from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError, RunInterrupted
from mcl3d.core.geometry import rpy_to_rot, se3
from mcl3d.core.outputs import check_writable
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.io.logs.messages import Imu, Odometry, PointCloud, PoseStamped, Transform
from mcl3d.io.logs.writer import LogWriter
from mcl3d.io.trajectory import Trajectory, write_tum
from mcl3d.sim.imu import ImuConfig, ImuSimulator
from mcl3d.sim.lidars import SENSORS, LidarConfig, make_lidar
from mcl3d.sim.mesh import sample_surface, write_mesh_ply, write_points_ply
from mcl3d.sim.raycast import WorldCaster
from mcl3d.sim.scan import simulate_scan
from mcl3d.sim.trajectories import (
    SCENARIO_SENSOR,
    SCENARIO_WORLD,
    TRAJECTORIES,
    VALID,
    build_trajectory,
    default_duration_s,
    listed,
)
from mcl3d.sim.wheel_odometry import WheelOdometryConfig, WheelOdometrySimulator
from mcl3d.sim.worlds import WORLDS, build_world

TOPICS = {"points": "/lidar/points", "imu": "/imu/data", "odom": "/odom",
          "gt": "/ground_truth", "tf_static": "/tf_static"}
# Salts of the random streams, so each noise source has its own stream for a given seed
SCAN_NOISE_STREAM = 11  # with the scan index
IMU_NOISE_STREAM = 12
WHEEL_ODOMETRY_STREAM = 13
MAP_SAMPLES_STREAM = 21
SCAN_COUNT_TOLERANCE = 1e-9  # a duration this close to whole scans counts as whole


class MapExportConfig(Section):
    point_spacing_m: float = Field(0.05, gt=0.001, description="mean spacing of the points "
                                   "sampled on the surfaces for the exported map (m)")


class WorldConfig(Section):
    """Sizes of the procedural worlds (each world reads its own keys)."""

    office_rooms: int = Field(8, description="near-identical rooms along the corridor (6 m each)")
    building_floors: int = Field(3, description="near-identical floors (3.5 m apart)")
    forest_rows: int = Field(10, description="tree rows (4 m apart)")
    forest_trees_per_row: int = Field(20, description="trees per row (3 m apart)")
    forest_border_m: float = Field(0.0, description="wild wood around the rows (m)")
    forest_undergrowth: float = Field(0.15, description="chance of a shrub beside each tree")
    forest_roughness_m: float = Field(0.015, description="ground bumps, sigma 1 m apart (m)")
    forest_slope_percent: float = Field(0.0, description="hillside grade along the rows (%)")
    forest_foliage_depth_m: float = Field(0.0, description="mean depth a laser pulse goes "
                                          "into foliage before a leaf returns it (m; 0: solid)")
    arena_length_m: float = Field(40.0, description="hall length (m)")
    arena_width_m: float = Field(30.0, description="hall width (m)")
    warehouse_aisles: int = Field(6, description="look-alike rack aisles (5 m apart)")
    warehouse_bays: int = Field(13, description="rack bays per row (2.7 m each)")

    def sizes(self, world: str) -> dict[str, float]:
        return {"office": {"n_rooms": self.office_rooms},
                "building": {"n_floors": self.building_floors},
                "forest": {"rows": self.forest_rows, "trees_per_row": self.forest_trees_per_row,
                           "border_m": self.forest_border_m,
                           "undergrowth": self.forest_undergrowth,
                           "roughness_m": self.forest_roughness_m,
                           "slope_percent": self.forest_slope_percent,
                           "foliage_depth_m": self.forest_foliage_depth_m},
                "arena": {"length_m": self.arena_length_m, "width_m": self.arena_width_m},
                "warehouse": {"n_aisles": self.warehouse_aisles, "n_bays": self.warehouse_bays},
                }[world]


class SimConfig(Section):
    """Every simulation parameter; saved beside the log and loadable as a config file."""

    start_stamp_s: int = Field(1_700_000_000, ge=0, description="ROS time of the first scan (s)")
    world: WorldConfig = WorldConfig()
    lidar: LidarConfig = LidarConfig()
    imu: ImuConfig = ImuConfig()
    odometry: WheelOdometryConfig = WheelOdometryConfig()
    map: MapExportConfig = MapExportConfig()


# Extrinsics of the rig (base_link -> sensor). The IMU of a MID-360 is the one built into it
# (offset from Livox's datasheet); the other LiDARs come with a separate IMU on the rig.
T_BASE_LIDAR = se3(rpy_to_rot(0.0, 0.0, 0.0), [0.12, 0.0, 0.42])
T_BASE_IMU = se3(rpy_to_rot(0.0, 0.0, np.pi / 2), [-0.05, 0.02, 0.15])
T_LIDAR_IMU_MID360 = se3(np.eye(3), [0.011, 0.02329, -0.04412])


def extrinsics(sensor: str) -> tuple[np.ndarray, np.ndarray]:
    """(T_base_lidar, T_base_imu) of the rig carrying `sensor`."""
    if sensor == "mid360":
        return T_BASE_LIDAR, T_BASE_LIDAR @ T_LIDAR_IMU_MID360
    return T_BASE_LIDAR, T_BASE_IMU


@dataclass
class SimulateRequest:
    world: str
    sensor: str | None  # None: the trajectory's own (`SCENARIO_SENSOR`), else vlp16
    trajectory: str
    duration_s: float | None  # None: the trajectory's own (`default_duration_s`)
    seed: int
    output: Path
    config_path: Path | None = None
    overrides: dict[str, Any] = field(default_factory=dict)
    export_mesh: Path | None = None
    export_map: Path | None = None
    force: bool = False
    world_seed: int | None = None  # None: `seed`; logs of one world with other paths share it

    @property
    def layout_seed(self) -> int:
        return self.seed if self.world_seed is None else self.world_seed


@dataclass
class SimulateResult:
    request: SimulateRequest
    outputs: list[Path]
    n_scans: int
    points_per_scan: float
    n_imu: int
    n_odom: int
    path_length_m: float
    wall_s: float
    world_triangles: int
    map_points: int | None
    scan_rate_hz: float


def sidecar(log: Path, suffix: str) -> Path:
    """log.mcap -> log_<suffix> in the same folder."""
    return log.with_name(f"{log.stem}_{suffix}")


def _validate(req: SimulateRequest) -> None:
    if req.world not in WORLDS:
        raise ConfigError(f"unknown world {req.world!r}; choose one of {', '.join(WORLDS)}")
    if req.sensor not in SENSORS:
        raise ConfigError(f"unknown sensor {req.sensor!r}; choose one of {', '.join(SENSORS)}")
    if req.trajectory not in TRAJECTORIES:
        raise ConfigError(f"unknown trajectory {req.trajectory!r}; choose one of "
                          f"{listed(TRAJECTORIES)}")
    if req.trajectory not in VALID[req.world]:
        raise ConfigError(f"trajectory {req.trajectory!r} does not fit world {req.world!r}; "
                          f"choose one of {listed(VALID[req.world])}")
    if req.duration_s is not None and (not np.isfinite(req.duration_s)
                                       or req.duration_s <= 0):
        raise ConfigError(f"the duration must be > 0 seconds, got {req.duration_s:g}",
                          setting="duration")
    if req.seed < 0:
        raise ConfigError(f"the seed must be >= 0, got {req.seed}", setting="seed")
    if req.world_seed is not None and req.world_seed < 0:
        raise ConfigError(f"the world seed must be >= 0, got {req.world_seed}",
                          setting="world-seed")


def with_scenario_world(cfg: SimConfig, trajectory: str) -> SimConfig:
    """`cfg` with a named scenario's world settings (`SCENARIO_WORLD`) wherever the config
    left the default, so the saved config lists the world that was simulated."""
    defaults = WorldConfig()
    update = {key: value for key, value in SCENARIO_WORLD.get(trajectory, {}).items()
              if getattr(cfg.world, key) == getattr(defaults, key)}
    return cfg.model_copy(update={"world": cfg.world.model_copy(update=update)})


def output_paths(req: SimulateRequest) -> list[Path]:
    out = [req.output, sidecar(req.output, "gt.tum"), sidecar(req.output, "config.yaml")]
    out += [p for p in (req.export_mesh, req.export_map) if p is not None]
    if len({p.resolve() for p in out}) != len(out):
        raise ConfigError("the log, its sidecars (_gt.tum, _config.yaml), the exported mesh "
                          "and the exported map must all be different files")
    return out


def _scan_count(req: SimulateRequest, cfg: SimConfig) -> int:
    period = 1.0 / cfg.lidar.rate_hz
    n_scans = int(np.floor(req.duration_s / period + SCAN_COUNT_TOLERANCE))
    if n_scans < 1:
        raise ConfigError(f"a duration of {req.duration_s:g} s is shorter than one scan "
                          f"({period:g} s at {cfg.lidar.rate_hz:g} Hz)", setting="duration")
    return n_scans


def run(request: SimulateRequest, on_progress: ProgressCallback | None = None
        ) -> SimulateResult:
    """Simulate and write everything `request` asks for; see the module docstring."""
    req = request
    wall0 = time.perf_counter()
    if req.sensor is None:
        req = replace(req, sensor=SCENARIO_SENSOR.get(req.trajectory, "vlp16"))
    _validate(req)
    cfg = with_scenario_world(cfgmod.load(SimConfig, req.config_path, req.overrides),
                              req.trajectory)
    outputs = output_paths(req)
    for path in outputs:
        check_writable(path, req.force)
    world = build_world(req.world, seed=req.layout_seed, **cfg.world.sizes(req.world))
    if req.duration_s is None:
        req = replace(req, duration_s=default_duration_s(world, req.trajectory))
    n_scans = _scan_count(req, cfg)
    period = 1.0 / cfg.lidar.rate_hz

    traj = build_trajectory(world, req.trajectory, req.duration_s, seed=req.seed)
    lidar = make_lidar(req.sensor)
    caster = WorldCaster(world)
    T_base_lidar, T_base_imu = extrinsics(req.sensor)
    imu = ImuSimulator(traj, T_base_imu, cfg.imu,
                       np.random.default_rng([req.seed, IMU_NOISE_STREAM]))
    odom = WheelOdometrySimulator(traj, cfg.odometry,
                                  np.random.default_rng([req.seed, WHEEL_ODOMETRY_STREAM]))
    state = _Writing(req, cfg, traj, T_base_lidar, period)

    stage = f"simulating {req.world}/{req.sensor}"
    interrupted = False
    with state.open_log() as writer:
        state.write_static(writer, T_base_imu)
        try:
            for k in range(n_scans):
                rng = np.random.default_rng([req.seed, SCAN_NOISE_STREAM, k])
                scan = simulate_scan(lidar, cfg.lidar, caster, traj, T_base_lidar, k, k * period,
                                     rng)
                state.write_scan(writer, k, scan)
                state.write_imu_odom(writer, imu, odom, k * period, (k + 1) * period)
                report(on_progress, Progress(stage, k + 1, n_scans))
        except KeyboardInterrupt:
            interrupted = True
    state.write_sidecars()
    if interrupted:
        raise RunInterrupted(f"interrupted after {state.n_scans} of {n_scans} scans; "
                             f"{req.output} and its ground truth hold the scans finished")
    map_points = None
    if req.export_mesh is not None:
        write_mesh_ply(world.mesh_at(float(traj.cab_z_m(0.0)[0])), req.export_mesh)
    if req.export_map is not None:
        map_points = export_map(world, traj, cfg.map, req.seed, req.export_map)
    return SimulateResult(
        request=req, outputs=outputs, n_scans=state.n_scans,
        points_per_scan=state.n_points / max(state.n_scans, 1), n_imu=state.n_imu,
        n_odom=state.n_odom, path_length_m=traj.path_length_m(),
        wall_s=time.perf_counter() - wall0, world_triangles=world.mesh_at().n_triangles,
        map_points=map_points, scan_rate_hz=cfg.lidar.rate_hz)


def export_map(world, traj, cfg: MapExportConfig, seed: int, path: Path) -> int:
    """Sample the world's surfaces (cab at its start position) into a PLY point map."""
    mesh = world.mesh_at(float(traj.cab_z_m(0.0)[0]))
    points, normals = sample_surface(mesh, 1.0 / cfg.point_spacing_m ** 2,
                                     np.random.default_rng([seed, MAP_SAMPLES_STREAM]))
    write_points_ply(points, normals, path)
    return len(points)


class _Writing:
    """Message construction and counters for one run's log."""

    def __init__(self, req: SimulateRequest, cfg: SimConfig, traj, T_base_lidar, period) -> None:
        self.req, self.cfg, self.traj = req, cfg, traj
        self.T_base_lidar, self.period = T_base_lidar, period
        self.start_ns = int(cfg.start_stamp_s) * 1_000_000_000
        self.n_scans = self.n_points = self.n_imu = self.n_odom = 0
        self.gt_stamps: list[float] = []
        self.gt_poses: list[np.ndarray] = []
        self._imu_next = 0
        self._odom_next = 0

    def ns(self, t_s: float) -> int:
        return self.start_ns + round(t_s * 1e9)

    def open_log(self) -> LogWriter:
        return LogWriter(self.req.output, force=self.req.force)

    def write_static(self, writer, T_base_imu) -> None:
        writer.write_tf(TOPICS["tf_static"], [
            Transform(self.start_ns, "base_link", "lidar", self.T_base_lidar),
            Transform(self.start_ns, "base_link", "imu", T_base_imu)])

    def write_scan(self, writer, k: int, scan) -> None:
        t = k * self.period
        stamp = self.ns(t)
        writer.write_points(TOPICS["points"], PointCloud(
            stamp, "lidar", scan.points, scan.times_s,
            {"intensity": scan.intensity, "ring": scan.ring}, 0, scan.height, scan.width))
        T_map_lidar = self.traj.T_map_base(np.array([t]))[0] @ self.T_base_lidar
        writer.write_pose(TOPICS["gt"], PoseStamped(stamp, "map", T_map_lidar))
        self.gt_stamps.append(stamp * 1e-9)
        self.gt_poses.append(T_map_lidar)
        self.n_scans += 1
        self.n_points += scan.n_valid

    def write_imu_odom(self, writer, imu, odom, t0: float, t1: float) -> None:
        """IMU and odometry samples with stamps in [t0, t1), in time order."""
        imu_dt, odom_dt = 1.0 / self.cfg.imu.rate_hz, 1.0 / self.cfg.odometry.rate_hz
        imu_idx = np.arange(self._imu_next, int(np.ceil(t1 / imu_dt - 1e-9)))
        odom_idx = np.arange(self._odom_next, int(np.ceil(t1 / odom_dt - 1e-9)))
        self._imu_next += len(imu_idx)
        self._odom_next += len(odom_idx)
        t_imu, t_odom = imu_idx * imu_dt, odom_idx * odom_dt
        gyro, accel = imu.measure(t_imu)
        poses, twists, covs = odom.measure(t_odom)
        events = sorted([(t, 0, i) for i, t in enumerate(t_imu)]
                        + [(t, 1, i) for i, t in enumerate(t_odom)])
        for t, kind, i in events:
            if kind == 0:
                writer.write_imu(TOPICS["imu"], Imu(self.ns(t), "imu", gyro[i], accel[i]))
            else:
                writer.write_odometry(TOPICS["odom"], Odometry(
                    self.ns(t), "odom", "base_link", poses[i], twists[i], covs[i]))
        self.n_imu += len(t_imu)
        self.n_odom += len(t_odom)

    def write_sidecars(self) -> None:
        write_tum(sidecar(self.req.output, "gt.tum"),
                  Trajectory(np.array(self.gt_stamps), np.array(self.gt_poses)))
        cfgmod.save(self.cfg, sidecar(self.req.output, "config.yaml"))


def summary_rows(result: SimulateResult) -> list[tuple[str, str]]:
    """The rows of the end-of-run summary table."""
    req = result.request
    sim_s = result.n_scans / result.scan_rate_hz
    rows = [("world", f"{req.world} ({result.world_triangles} triangles, seed "
                      f"{req.layout_seed})"),
            ("sensor", req.sensor), ("trajectory", req.trajectory),
            ("scans", str(result.n_scans)), ("points/scan", f"{result.points_per_scan:.0f}"),
            ("IMU samples", str(result.n_imu)), ("odometry samples", str(result.n_odom)),
            ("path length", f"{result.path_length_m:.1f} m"),
            ("duration", f"{req.duration_s:g} s simulated"),
            ("wall time", f"{result.wall_s:.1f} s ({sim_s / max(result.wall_s, 1e-9):.1f}x "
                          f"real time)")]
    if result.map_points is not None:
        rows.append(("map points", str(result.map_points)))
    rows.append(("outputs", ", ".join(str(p) for p in result.outputs)))
    return rows
