"""Simulated LiDARs: beam tables, and scan geometry against the exported world mesh."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import interpolate_se3
from mcl3d.sim.lidars import LidarConfig, make_lidar
from mcl3d.sim.pipeline import SimulateRequest, run


def _elevations_deg(directions):
    return np.degrees(np.arcsin(np.clip(directions[:, 2], -1, 1)))


def test_vlp16_beam_table_and_firing_times():
    f = make_lidar("vlp16").firing(0, 0.1, 1)
    assert len(f.directions) == 16 * 1800 and f.organized is None
    el = _elevations_deg(f.directions)
    assert np.allclose(np.unique(np.round(el, 6)), np.arange(-15, 16, 2))
    assert np.allclose(el[f.ring == 0], -15) and np.allclose(el[f.ring == 15], 15)
    assert f.times_s.min() == 0 and f.times_s.max() < 0.1
    assert np.all(np.diff(f.times_s) > 0)  # every laser fires at its own instant


@pytest.mark.parametrize(("name", "fov_deg"), [("os1-64", 45.0), ("os0-64", 90.0)])
def test_ouster_beam_tables_are_organized_64_by_1024(name, fov_deg):
    f = make_lidar(name).firing(0, 0.1, 1)
    assert f.organized == (64, 1024)
    el = _elevations_deg(f.directions).reshape(64, 1024)
    assert np.ptp(el) == pytest.approx(fov_deg)
    assert np.all(np.diff(el[:, 0]) < 0)  # row (= ring) 0 is the top beam, as Ouster's driver
    assert np.all(f.ring.reshape(64, 1024)[:, 0] == np.arange(64))
    times = f.times_s.reshape(64, 1024)
    assert np.allclose(times, times[0])  # a column fires at once
    assert np.allclose(np.diff(times[0]), 0.1 / 1024)


def test_mid360_pattern_is_non_repetitive_with_a_limited_field_of_view():
    lidar = make_lidar("mid360")
    scans = [lidar.firing(k, 0.1, 1) for k in range(10)]
    assert len(scans[0].directions) == pytest.approx(20_000, rel=0.01)  # 200 k points/s
    el = np.concatenate([_elevations_deg(s.directions) for s in scans])
    assert el.min() >= -7.0 - 1e-9 and el.max() <= 52.0 + 1e-9
    assert not np.allclose(scans[0].directions, scans[1].directions)

    def cells(firings):
        d = np.concatenate([s.directions for s in firings])
        az = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
        return len(np.unique(np.floor(az / 0.5) * 1000 + np.floor(_elevations_deg(d) / 0.5)))

    assert cells(scans) > 2.5 * cells(scans[:1])  # coverage keeps growing with time


def test_unknown_sensor_is_a_config_error():
    with pytest.raises(ConfigError, match=r"unknown sensor 'hdl64'.*vlp16"):
        make_lidar("hdl64")


def _scans_against_mesh(tmp_path, world, sensor, trajectory, duration_s, overrides=None):
    """Simulate, then put every point of each scan but the last into the map frame with the
    ground truth interpolated at the point's own time; return distances to the mesh."""
    import open3d as o3d

    from mcl3d.io.logs.reader import LogReader

    log, mesh = tmp_path / "s.mcap", tmp_path / "world.ply"
    run(SimulateRequest(world, sensor, trajectory, duration_s, 3, log, export_mesh=mesh,
                        overrides=overrides or {}))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.io.read_triangle_mesh(str(mesh)))
    with LogReader(log) as reader:
        stamps_ns, gt = reader.ground_truth()
        clouds = list(reader.scans())
    per_point, start_only = [], []
    for k, cloud in enumerate(clouds[:-1]):
        alpha = cloud.times_s.astype(np.float64) / ((stamps_ns[k + 1] - stamps_ns[k]) * 1e-9)
        T = interpolate_se3(gt[k][None], gt[k + 1][None], alpha)
        pts = cloud.points.astype(np.float64)
        p_map = np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]
        p_start = pts @ gt[k][:3, :3].T + gt[k][:3, 3]
        for out, p in ((per_point, p_map), (start_only, p_start)):
            out.append(scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy())
    return np.concatenate(per_point), np.concatenate(start_only)


@pytest.mark.parametrize(("world", "sensor", "trajectory"), [
    ("office", "vlp16", "ground"), ("building", "os1-64", "handheld"),
    ("forest", "mid360", "handheld"), ("arena", "os0-64", "drone")])
def test_points_lie_on_the_exported_mesh_at_their_own_time(tmp_path, world, sensor, trajectory):
    d, _ = _scans_against_mesh(tmp_path, world, sensor, trajectory, 0.3,
                               {"lidar.column_stride": 2})
    sigma = make_lidar(sensor).range_sigma_m
    assert len(d) > 5000
    assert np.mean(d < 3 * sigma) > 0.95


def test_scans_are_motion_distorted_not_deskewed(tmp_path):
    """A drone flying ~1.5 m/s: the per-point poses fit, the scan-start pose does not."""
    d_point, d_start = _scans_against_mesh(tmp_path, "arena", "vlp16", "drone", 8.3,
                                           {"lidar.column_stride": 8})
    sigma = make_lidar("vlp16").range_sigma_m
    assert np.mean(d_point < 3 * sigma) > 0.95
    assert np.mean(d_start < 3 * sigma) < 0.85


def test_field_of_view_crop_and_range_limits(tmp_path):
    from mcl3d.io.logs.reader import LogReader

    log = tmp_path / "crop.mcap"
    run(SimulateRequest("forest", "mid360", "ground", 0.2, 0, log,
                        overrides={"lidar.azimuth_fov_deg": [-90, 90],
                                   "lidar.max_range_m": 15.0}))
    with LogReader(log) as reader:
        cloud = next(iter(reader.scans()))
    assert len(cloud) > 1000
    assert np.all(cloud.points[:, 0] > -0.05)  # only the forward half is kept
    assert np.linalg.norm(cloud.points, axis=1).max() < 15.0 + 0.1
    assert cloud.fields["intensity"].min() >= 0 and cloud.fields["intensity"].max() <= 255
    assert cloud.fields["ring"].max() <= 3  # MID-360: 4 laser lines


def test_elevator_scans_see_only_the_cab_during_the_ride():
    from mcl3d.sim.pipeline import extrinsics
    from mcl3d.sim.raycast import WorldCaster
    from mcl3d.sim.scan import simulate_scan
    from mcl3d.sim.trajectories import build_trajectory
    from mcl3d.sim.worlds import build_world

    w = build_world("building")
    traj = build_trajectory(w, "elevator", 40.0)
    caster = WorldCaster(w)
    T_base_lidar, _ = extrinsics("os0-64")
    ride = 0.5 * (traj.door_closed_s[0] + traj.door_closed_s[1])
    cfg = LidarConfig(column_stride=4)
    for t0 in (ride, traj.door_closed_s[1] + 2.0):
        scan = simulate_scan(make_lidar("os0-64"), cfg, caster, traj, T_base_lidar, 0, t0,
                             np.random.default_rng(0))
        valid = np.any(scan.points != 0, axis=1)
        far = np.linalg.norm(scan.points[valid], axis=1).max()
        if t0 == ride:
            assert far < 2.5  # inside a 2.2 m x 2.2 m x 2.4 m cab
        else:
            assert far > 8.0  # doors open after the ride: the corridor is visible
