"""The elevator detector: it fires in a closed cab and nowhere else, neither in narrow aisles
nor beside walls, on ray-cast scans from still poses and on the real OS1-64 recording
(ouster_os1_64_mcap, MIT licence), whose median range (1.3-1.7 m) the paper's test takes
for a cab."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.geometry import rpy_to_rot, se3
from mcl3d.sim.lidars import make_lidar
from mcl3d.sim.mesh import MeshBuilder
from mcl3d.sim.raycast import WorldCaster
from mcl3d.sim.worlds import World, build_world
from mcl3d.slam.elevator import in_elevator, open_sectors, sector_ranges
from mcl3d.slam.slam_config import ElevatorConfig

SENSORS = ("vlp16", "os1-64", "os0-64", "mid360")
ENCLOSURE = ElevatorConfig()
MEDIAN = ElevatorConfig(detector="median")


def still_scan(world: World, sensor: str, xyz, yaw: float = 0.0, cab_z_m: float | None = None,
               door_closed: bool = False) -> np.ndarray:
    """One sweep of `sensor` from a still pose (lidar frame), returns within its range."""
    lidar = make_lidar(sensor)
    firing = lidar.firing(0, 0.1, 2)
    T = se3(rpy_to_rot(0.0, 0.0, yaw), xyz)
    directions = firing.directions @ T[:3, :3].T
    n = len(directions)
    cab = None if cab_z_m is None else np.full(n, cab_z_m)
    hits = WorldCaster(world).cast(np.broadcast_to(T[:3, 3], directions.shape), directions,
                                   cab, np.full(n, door_closed))
    r = hits.range_m
    ok = np.isfinite(r) & (r >= lidar.min_range_m) & (r <= lidar.max_range_m)
    return firing.directions[ok] * r[ok, None]


def aisle(gap_m: float) -> World:
    """Two 60 m racks 6 m tall, `gap_m` apart, under a roof at 8 m (a warehouse aisle)."""
    b = MeshBuilder()
    b.box([-30, -10, -0.2], [30, 10, 0.0], 0.4)
    b.box([-30, gap_m / 2, 0.0], [30, gap_m / 2 + 1.0, 6.0], 0.5)
    b.box([-30, -gap_m / 2 - 1.0, 0.0], [30, -gap_m / 2, 6.0], 0.5)
    b.box([-30, -10, 8.0], [30, 10, 8.2], 0.5)
    mesh = b.build()
    return World("aisle", 0, mesh, mesh, {}, [0.0], np.eye(4), "")


@pytest.fixture(scope="module")
def building():
    return build_world("building")


def test_sector_ranges_match_a_per_sector_percentile():
    rng = np.random.default_rng(0)
    azimuth = rng.uniform(-np.pi, np.pi, 4000)
    ranges = rng.uniform(0.5, 10.0, 4000)
    points = np.column_stack([ranges * np.cos(azimuth), ranges * np.sin(azimuth),
                              np.zeros(4000)])
    got = sector_ranges(np.vstack([points, np.zeros((5, 3))]), 8, 90.0)  # zeros: no return
    sector = np.minimum(((azimuth + np.pi) / (2 * np.pi) * 8).astype(int), 7)
    want = [np.percentile(ranges[sector == s], 90.0) for s in range(8)]
    np.testing.assert_allclose(got, want)
    front = np.abs(azimuth) <= np.pi / 4  # a 90° field of view in 3 sectors
    got = sector_ranges(points, 3, 50.0, fov_deg=90.0)
    sector = np.minimum(((azimuth[front] + np.pi / 4) / (np.pi / 2) * 3).astype(int), 2)
    want = [np.median(ranges[front][sector == s]) for s in range(3)]
    np.testing.assert_allclose(got, want)
    assert np.isinf(sector_ranges(points[:10], 8, 90.0, min_points=20)).all()  # open


@pytest.mark.parametrize("sensor", SENSORS)
def test_fires_in_the_closed_cab_and_not_once_its_doors_open(building, sensor):
    elev = building.elevator
    for z in elev.floor_z_m[-1], 0.5 * (elev.floor_z_m[0] + elev.floor_z_m[1]):
        xyz = [elev.center_xy[0] + 0.3, elev.center_xy[1] - 0.2, z + 1.0]
        closed = still_scan(building, sensor, xyz, 0.4, z, door_closed=True)
        assert in_elevator(closed, ENCLOSURE)
        assert in_elevator(closed, ENCLOSURE, fov_deg=180.0)  # the paper's cropped scans
        if z in elev.floor_z_m:
            opened = still_scan(building, sensor, xyz, 0.4, z, door_closed=False)
            assert not in_elevator(opened, ENCLOSURE)


def test_the_cab_with_its_doors_open_leaves_fewer_open_sectors_than_the_lobby(building):
    """After a ride SLAM can wait for `elevator.exit_open_sectors` open sectors (3 was
    studied): the cab with its doors open has 1 or 2, the sensor out in front of it more."""
    elev = building.elevator
    z = elev.floor_z_m[1]
    inside = [elev.center_xy[0] + 0.3, elev.center_xy[1] - 0.2, z + 1.0]
    opened = still_scan(building, "mid360", inside, 0.4, z, door_closed=False)
    assert 1 <= open_sectors(opened, ENCLOSURE) < 3
    lobby = [*elev.door_approach_xy, z + 1.0]
    assert open_sectors(still_scan(building, "mid360", lobby, 0.4, z), ENCLOSURE) >= 3
    closed = still_scan(building, "mid360", inside, 0.4, z, door_closed=True)
    assert open_sectors(closed, ENCLOSURE) == 0


@pytest.mark.parametrize("gap_m", [1.5, 2.0, 2.5])
@pytest.mark.parametrize("sensor", ["vlp16", "os1-64", "mid360"])
def test_never_fires_in_a_narrow_aisle_where_the_median_test_does(gap_m, sensor):
    world = aisle(gap_m)
    for yaw in (0.0, 0.8, np.pi / 2):  # along, across, facing a rack 0.45 m away
        points = still_scan(world, sensor, [0.0, 0.3, 1.0], yaw)
        assert not in_elevator(points, ENCLOSURE)
        assert not in_elevator(points, ENCLOSURE, fov_deg=180.0)
    if gap_m == 1.5:
        assert in_elevator(still_scan(world, sensor, [0.0, 0.3, 1.0]), MEDIAN)


@pytest.mark.parametrize("sensor", ["vlp16", "mid360"])
def test_never_fires_in_the_office_the_building_corridors_and_the_forest(building, sensor):
    office = build_world("office")
    for xy in office.routes["ground"]:
        assert not in_elevator(still_scan(office, sensor, [*xy, 0.6]), ENCLOSURE)
    for z in building.floor_z_m:
        cab = building.elevator.floor_z_m[0]
        for xyz in ([20.0, 7.25, z + 1.0], [2.5, 11.0, z + 1.2], [35.5, 7.25, z + 1.0]):
            assert not in_elevator(still_scan(building, sensor, xyz, 0.0, cab), ENCLOSURE)
    forest = build_world("forest")
    for xy in forest.routes["loop"][:4]:
        assert not in_elevator(still_scan(forest, sensor, [*xy, 0.8]), ENCLOSURE)


def test_never_fires_on_the_real_handheld_os1_64_recording(shared_data):
    from mcl3d.io.logs.reader import LogReader

    with LogReader(shared_data / "ouster_os1_64_mcap" / "test.mcap") as reader:
        scans = list(reader.scans())
    assert len(scans) == 2
    for scan in scans:
        assert not in_elevator(scan.points, ENCLOSURE)
        assert not in_elevator(scan.points, ENCLOSURE, fov_deg=180.0)
        assert in_elevator(scan.points, MEDIAN)  # the paper's test takes it for a cab


def test_off_never_fires_and_an_empty_scan_is_no_cab(building):
    elev = building.elevator
    z = elev.floor_z_m[-1]
    closed = still_scan(building, "vlp16", [*elev.center_xy, z + 1.0], 0.0, z, True)
    assert not in_elevator(closed, ElevatorConfig(detector="off"))
    assert in_elevator(closed, MEDIAN)
    assert not in_elevator(np.zeros((0, 3)), ENCLOSURE)
    assert not in_elevator(np.zeros((0, 3)), MEDIAN)


@pytest.mark.parametrize("sensor", ["vlp16", "mid360"])
def test_on_the_paper_elevator_route_it_fires_exactly_while_the_cab_doors_are_shut(building,
                                                                                   sensor):
    """Every 2 s of the route (corridors, stairwell, the cab with its doors open and shut):
    the detector holds exactly while the doors are shut."""
    from mcl3d.sim.lidars import LidarConfig
    from mcl3d.sim.pipeline import extrinsics
    from mcl3d.sim.scan import simulate_scan
    from mcl3d.sim.trajectories import build_trajectory, default_duration_s

    traj = build_trajectory(building, "paper-elevator",
                            default_duration_s(building, "paper-elevator"))
    caster = WorldCaster(building)
    T_base_lidar, _ = extrinsics(sensor)
    lidar, cfg = make_lidar(sensor), LidarConfig(column_stride=8)
    shut_s = traj.door_closed_s
    fired = []
    for k, t in enumerate(np.arange(0.0, traj.duration_s - 0.1, 2.0)):
        scan = simulate_scan(lidar, cfg, caster, traj, T_base_lidar, k, t,
                             np.random.default_rng(k))
        fired.append(in_elevator(scan.points, ENCLOSURE))
        assert fired[-1] == (shut_s[0] <= t <= shut_s[1] - 0.1), t
    assert sum(fired) >= 3


def test_an_unknown_detector_is_a_config_error():
    from mcl3d.core import config as config_io
    from mcl3d.core.errors import ConfigError
    from mcl3d.slam.slam_config import SlamConfig

    with pytest.raises(ConfigError, match=r"elevator\.detector.*enclosure"):
        config_io.load(SlamConfig, None, {"elevator.detector": "nope"})
    cfg = config_io.load(SlamConfig, None, {"elevator.detector": "median"})
    assert cfg.elevator.detector == "median"
