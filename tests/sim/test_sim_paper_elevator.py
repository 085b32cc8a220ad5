"""The SLAM paper's elevator route (`paper-elevator`): ground floor, stairs to the top floor
(the middle floor walked to the elevator and back), the elevator one floor down, stairs back
to the ground floor, through identical floors."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.sim.imu import true_imu
from mcl3d.sim.pipeline import SimulateRequest, extrinsics, run
from mcl3d.sim.trajectories import GRAVITY_MPS2, build_trajectory, default_duration_s
from mcl3d.sim.worlds import build_world


@pytest.fixture(scope="module")
def building():
    return build_world("building")


@pytest.fixture(scope="module")
def route(building):
    return build_trajectory(building, "paper-elevator", default_duration_s(building,
                                                                           "paper-elevator"))


def _floor_of(z_feet: np.ndarray, floors: list[float]) -> np.ndarray:
    return np.argmin(np.abs(z_feet[:, None] - np.asarray(floors)[None, :]), axis=1)


def test_the_route_climbs_to_the_top_rides_one_floor_down_and_walks_back_to_the_start(
        building, route):
    floors = building.floor_z_m
    t = np.arange(0.0, route.duration_s, 0.1)
    p = route.T_map_base(t)[:, :3, 3]
    feet = p[:, 2] - (p[0, 2] - floors[0])  # the carry height is constant
    assert 250.0 < route.path_length_m() < 290.0 and route.duration_s == pytest.approx(
        np.ceil(route.motion.t_end), abs=1.0)
    t0, t1 = route.door_closed_s
    before, ride, after = t < t0, (t >= t0) & (t <= t1), t > t1
    assert feet[before].max() == pytest.approx(floors[-1], abs=0.05)  # up to the top floor
    assert feet[after].max() == pytest.approx(floors[-2], abs=0.05)  # out on the one below
    assert np.abs(p[ride, :2] - building.elevator.center_xy).max() < 0.2
    assert feet[ride][0] == pytest.approx(floors[-1], abs=0.05)
    assert feet[ride][-1] == pytest.approx(floors[-2], abs=0.05)
    # on the way up every floor is walked to the elevator's landing: each floor the ride
    # might have ended on has a map there
    at_landing = np.linalg.norm(p[:, :2] - building.elevator.door_approach_xy, axis=1) < 1.0
    assert set(_floor_of(feet[before & at_landing], floors)) == {1, 2}
    assert set(_floor_of(feet[before], floors)) == set(range(len(floors)))
    assert max(np.abs(np.diff(feet[part])).max() for part in (before, after)) < 0.1  # < 1 m/s
    # it ends where it began: beside the ground floor's furnished room, at rest
    assert np.linalg.norm(p[-1] - p[0]) < 0.05
    assert np.linalg.norm(route.T_map_base(t[-1:] - 0.5)[0, :3, 3] - p[-1]) < 1e-3
    room = (p[:, 1] < 6.0) & (np.abs(feet - floors[0]) < 0.05)
    assert room[before].any() and room[after].any()


def test_odometry_does_not_see_the_ride_and_the_imu_does(building, route):
    t0, t1 = route.door_closed_s
    t = np.linspace(t0, t1, 300)
    assert np.ptp(route.T_odom_base(t)[:, 2, 3]) < 1e-9
    assert np.allclose(route.cab_z_m(t), route.T_map_base(t)[:, 2, 3] - route.T_map_base(
        t[:1])[0, 2, 3] + building.floor_z_m[-1])
    _, accel = true_imu(route, np.eye(4), t)
    assert np.abs(accel[:, 2] - GRAVITY_MPS2).max() > 0.2
    assert np.all(route.door_closed(t)) and not route.door_closed(np.array([t0 - 2.0]))[0]


def test_the_sensor_stays_clear_of_the_walls_stairs_and_ceilings(building, route):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(building.static.vertices.astype(np.float32)),
                        o3d.core.Tensor(building.static.triangles.astype(np.uint32)))
    T_base_lidar, _ = extrinsics("mid360")
    T = route.T_map_base(np.arange(0.0, route.duration_s, 0.05)) @ T_base_lidar
    d = scene.compute_distance(o3d.core.Tensor(T[:, :3, 3].astype(np.float32))).numpy()
    assert d.min() > 0.25


def test_needs_three_floors_and_fits_only_the_building():
    with pytest.raises(ConfigError, match="at least 3 floors"):
        build_trajectory(build_world("building", n_floors=2), "paper-elevator", 10.0)
    with pytest.raises(ConfigError, match="does not fit world 'office'"):
        build_trajectory(build_world("office"), "paper-elevator", 10.0)


def test_simulate_writes_the_route_start(tmp_path):
    from mcl3d.io.logs.reader import LogReader

    log = tmp_path / "elevator.mcap"
    result = run(SimulateRequest("building", "mid360", "paper-elevator", 0.3, 1, log,
                                 overrides={"lidar.column_stride": 8}))
    assert result.n_scans == 3
    with LogReader(log) as reader:
        assert reader.count("points") == 3
