"""Simulated trajectories, IMU and odometry: smoothness, consistency, elevator and kidnap."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import rotation_angle, se3_inverse, se3_log, so3_exp, so3_log
from mcl3d.sim.imu import ImuConfig, ImuSimulator, true_imu
from mcl3d.sim.pipeline import extrinsics
from mcl3d.sim.spline import QuinticHermite, catmull_rom_rates
from mcl3d.sim.trajectories import GRAVITY_MPS2, VALID, build_trajectory
from mcl3d.sim.wheel_odometry import WheelOdometryConfig, WheelOdometrySimulator
from mcl3d.sim.worlds import build_world

_WORLDS: dict = {}


def world(name):
    if name not in _WORLDS:
        _WORLDS[name] = build_world(name, seed=0)
    return _WORLDS[name]


def test_quintic_hermite_derivatives_match_finite_differences_and_stops_hold():
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.0])
    v = np.array([[0.0], [1.0], [1.0], [3.0], [2.0]])
    stops = np.array([True, False, True, False, True])
    curve = QuinticHermite(t, v, catmull_rom_rates(t, v, stops))
    ts = np.linspace(0.01, 3.99, 200)
    h = 1e-5
    num1 = (curve(ts + h) - curve(ts - h)) / (2 * h)
    num2 = (curve(ts + h, 1) - curve(ts - h, 1)) / (2 * h)
    assert np.allclose(curve(ts, 1), num1, atol=1e-5)
    assert np.allclose(curve(ts, 2), num2, atol=1e-3)
    assert np.allclose(curve(t), v)
    hold = np.linspace(1.0, 2.5, 50)  # values 1 -> 1 with stops at 2.5: no overshoot
    assert np.all(curve(hold)[:, 0] >= 1.0 - 1e-12)
    assert np.allclose(curve(np.array([-1.0, 5.0]), 1), 0.0)


@pytest.mark.parametrize(("name", "kind"), [("office", "handheld"), ("arena", "drone"),
                                            ("office", "ground"), ("forest", "ground")])
def test_kinematics_are_the_derivatives_of_the_poses(name, kind):
    traj = build_trajectory(world(name), kind, 20.0)
    t = np.linspace(1.0, 19.0, 60)
    h = 1e-5
    k = traj.kinematics(t)
    Tp, Tm = traj.T_map_base(t + h), traj.T_map_base(t - h)
    v_num = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
    w_num = so3_log(np.swapaxes(Tm[:, :3, :3], 1, 2) @ Tp[:, :3, :3]) / (2 * h)
    dw_num = (traj.kinematics(t + h).w_base - traj.kinematics(t - h).w_base) / (2 * h)
    a_num = (traj.kinematics(t + h).v_map - traj.kinematics(t - h).v_map) / (2 * h)
    assert np.allclose(k.v_map, v_num, atol=1e-5)
    assert np.allclose(k.w_base, w_num, atol=1e-5)
    assert np.allclose(k.dw_base, dw_num, atol=1e-3)
    assert np.allclose(k.a_map, a_num, atol=1e-3)


def _integrate_imu(traj, T_base_imu, t0, seconds, rate_hz, gyro, accel):
    """Midpoint strapdown integration of IMU samples from the true state at t0."""
    dt = 1.0 / rate_hz
    t = t0 + np.arange(round(seconds * rate_hz) + 1) * dt
    k = traj.kinematics(t[:1])
    R = (k.R_map_base[0] @ T_base_imu[:3, :3])
    lever = T_base_imu[:3, 3]
    p = k.p_map_base[0] + k.R_map_base[0] @ lever
    v = k.v_map[0] + k.R_map_base[0] @ np.cross(k.w_base[0], lever)
    g = np.array([0.0, 0.0, -GRAVITY_MPS2])
    for i in range(len(t) - 1):
        R_next = R @ so3_exp(0.5 * (gyro[i] + gyro[i + 1]) * dt)
        a0, a1 = R @ accel[i] + g, R_next @ accel[i + 1] + g
        p = p + v * dt + (2 * a0 + a1) / 6 * dt**2
        v = v + 0.5 * (a0 + a1) * dt
        R = R_next
    T_true = traj.T_map_base(t[-1:])[0] @ T_base_imu
    return np.linalg.norm(p - T_true[:3, 3]), np.degrees(rotation_angle(R.T @ T_true[:3, :3]))


@pytest.mark.parametrize(("name", "kind", "sensor"), [
    ("office", "handheld", "vlp16"), ("arena", "drone", "os0-64"),
    ("office", "ground", "mid360"), ("building", "elevator", "os1-64")])
def test_noiseless_imu_integrates_to_the_ground_truth(name, kind, sensor):
    traj = build_trajectory(world(name), kind, 40.0)
    _, T_base_imu = extrinsics(sensor)
    for t0 in (3.0, 12.5, 21.0):  # the elevator ride is around t = 12..20 s
        t = t0 + np.arange(201) / 200.0
        gyro, accel = true_imu(traj, T_base_imu, t)
        err_m, err_deg = _integrate_imu(traj, T_base_imu, t0, 1.0, 200.0, gyro, accel)
        assert err_m < 0.01 and err_deg < 0.1, (t0, err_m, err_deg)


def test_imu_at_rest_measures_gravity_up():
    traj = build_trajectory(world("arena"), "ground", 5.0)
    gyro, accel = true_imu(traj, np.eye(4), np.array([0.0]))
    assert np.allclose(accel[0], [0, 0, GRAVITY_MPS2], atol=1e-9)
    assert np.allclose(gyro[0], 0.0, atol=1e-12)


def test_imu_white_noise_matches_the_configured_densities():
    traj = build_trajectory(world("office"), "handheld", 320.0)
    cfg = ImuConfig(gyro_bias_random_walk=0.0, accel_bias_random_walk=0.0,
                    gyro_bias_initial=0.0, accel_bias_initial=0.0)
    imu = ImuSimulator(traj, np.eye(4), cfg, np.random.default_rng(1))
    t = np.arange(0, 300 * 200) / 200.0
    gyro, accel = imu.measure(t)
    w, f = true_imu(traj, np.eye(4), t)
    sqrt_rate = np.sqrt(cfg.rate_hz)
    assert np.std(gyro - w) == pytest.approx(cfg.gyro_noise_density * sqrt_rate, rel=0.03)
    assert np.std(accel - f) == pytest.approx(cfg.accel_noise_density * sqrt_rate, rel=0.03)
    # integrated over 1 s windows the gyro noise is an angle random walk: sigma = N * sqrt(1 s)
    angle = (gyro - w).reshape(300, 200, 3).sum(axis=1) / cfg.rate_hz
    assert np.std(angle) == pytest.approx(cfg.gyro_noise_density, rel=0.1)


def test_imu_bias_random_walk_matches_the_configured_density():
    traj = build_trajectory(world("arena"), "ground", 120.0)
    cfg = ImuConfig(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_bias_initial=0.0,
                    accel_bias_initial=0.0)
    imu = ImuSimulator(traj, np.eye(4), cfg, np.random.default_rng(2))
    t = np.arange(0, 100 * 200) / 200.0
    chunks = [imu.measure(c) for c in np.array_split(t, 37)]  # state carries across chunks
    gyro = np.concatenate([c[0] for c in chunks])
    accel = np.concatenate([c[1] for c in chunks])
    w, f = true_imu(traj, np.eye(4), t)
    step_g, step_a = np.diff(gyro - w, axis=0), np.diff(accel - f, axis=0)
    dt = 1.0 / cfg.rate_hz
    assert np.std(step_g) == pytest.approx(cfg.gyro_bias_random_walk * np.sqrt(dt), rel=0.03)
    assert np.std(step_a) == pytest.approx(cfg.accel_bias_random_walk * np.sqrt(dt), rel=0.03)


def test_elevator_rides_one_floor_with_no_horizontal_motion_and_odometry_does_not_see_it():
    w = world("building")
    traj = build_trajectory(w, "elevator", 40.0)
    t0, t1 = traj.door_closed_s
    t = np.linspace(t0, t1, 400)
    T = traj.T_map_base(t)
    xy = T[:, :2, 3]
    assert np.abs(xy - w.elevator.center_xy).max() < 1e-6
    dz = T[-1, 2, 3] - T[0, 2, 3]
    assert dz == pytest.approx(w.floor_z_m[-2] - w.floor_z_m[-1], abs=1e-9)
    assert np.allclose(traj.cab_z_m(t), T[:, 2, 3])  # the rig rides on the cab floor
    assert np.all(traj.door_closed(t))
    odom_z = traj.T_odom_base(t)[:, 2, 3]
    assert np.ptp(odom_z) < 1e-9
    _, accel = true_imu(traj, np.eye(4), t)
    assert np.abs(accel[:, 2] - GRAVITY_MPS2).max() > 0.2  # the IMU feels the ride
    before, after = traj.T_map_base(np.array([0.0, 39.0]))
    assert before[2, 3] == pytest.approx(w.floor_z_m[-1]) and after[2, 3] == pytest.approx(
        w.floor_z_m[-2])


def test_elevator_needs_a_long_enough_duration():
    with pytest.raises(ConfigError, match=r"elevator.*duration"):
        build_trajectory(world("building"), "elevator", 5.0)


@pytest.mark.parametrize("name", ["office", "building", "forest", "arena", "warehouse"])
def test_kidnap_jumps_in_ground_truth_but_not_in_imu_or_odometry(name):
    w = world(name)
    traj = build_trajectory(w, "kidnap", 30.0)
    tk = traj.kidnap_t_s
    t = np.arange(0.0, 30.0, 0.02)
    p = traj.T_map_base(t)[:, :3, 3]
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    jump = np.searchsorted(t, tk) - 1
    assert steps[jump] > 3.0 and np.delete(steps, jump).max() < 0.05
    odom = traj.T_odom_base(t)[:, :3, 3]
    assert np.linalg.norm(np.diff(odom, axis=0), axis=1).max() < 0.05
    gyro, accel = true_imu(traj, np.eye(4), np.array([tk - 1e-6, tk + 1e-6]))
    assert np.allclose(gyro[0], gyro[1], atol=1e-4) and np.allclose(accel[0], accel[1], atol=1e-3)


@pytest.mark.parametrize("name", ["office", "building", "forest", "arena", "warehouse"])
def test_every_trajectory_stays_in_free_space(name):
    import open3d as o3d

    w = world(name)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(w.static.vertices.astype(np.float32)),
                        o3d.core.Tensor(w.static.triangles.astype(np.uint32)))
    T_base_lidar, _ = extrinsics("vlp16")
    for kind in VALID[name]:
        traj = build_trajectory(w, kind, 120.0)
        T = traj.T_map_base(np.arange(0.0, 120.0, 0.1)) @ T_base_lidar
        d = scene.compute_distance(o3d.core.Tensor(T[:, :3, 3].astype(np.float32))).numpy()
        assert d.min() > 0.2, (kind, d.min())


def test_trajectory_names_are_checked_per_world():
    with pytest.raises(ConfigError, match=r"does not fit world 'office'.*ground, loop"):
        build_trajectory(world("office"), "elevator", 10.0)
    with pytest.raises(ConfigError, match="duration"):
        build_trajectory(world("office"), "ground", 0.0)


def test_odometry_is_exact_without_noise_and_drifts_consistently_with_its_covariance():
    traj = build_trajectory(world("office"), "ground", 20.0)
    t = np.arange(0, 20 * 50) / 50.0
    quiet = WheelOdometryConfig(trans_noise=0, rot_noise_per_m=0, rot_noise_per_rad=0,
                           scale_error_sigma=0, turn_bias_sigma=0, twist_noise=(0, 0))
    poses, _, _ = WheelOdometrySimulator(traj, quiet, np.random.default_rng(0)).measure(t)
    assert np.allclose(poses, traj.T_odom_base(t), atol=1e-9)
    noisy = WheelOdometryConfig(trans_noise=0.05, rot_noise_per_m=0.01, scale_error_sigma=0,
                           turn_bias_sigma=0)
    nees = []
    for seed in range(16):
        poses, _, covs = WheelOdometrySimulator(traj, noisy, np.random.default_rng(seed)).measure(t)
        err = se3_inverse(traj.T_odom_base(t[-1:])[0]) @ poses[-1]
        e_ros = np.concatenate([poses[-1][:3, 3] - traj.T_odom_base(t[-1:])[0][:3, 3],
                                poses[-1][:3, :3] @ so3_log(err[:3, :3])])
        nees.append(e_ros @ np.linalg.solve(covs[-1] + 1e-12 * np.eye(6), e_ros))
    assert 2.0 < np.mean(nees) < 12.0  # chi-square with 6 dof: mean 6


def test_velocity_noise_corrupts_each_increment_by_sigma_times_the_interval():
    traj = build_trajectory(world("office"), "ground", 20.0)
    t = np.arange(0, 20 * 50) / 50.0
    sigma_v, sigma_w = 0.1, 0.05
    cfg = WheelOdometryConfig(trans_noise=0, rot_noise_per_m=0, rot_noise_per_rad=0,
                              scale_error_sigma=0, turn_bias_sigma=0,
                              velocity_noise=(sigma_v, sigma_w))
    poses, _, _ = WheelOdometrySimulator(traj, cfg, np.random.default_rng(3)).measure(t)
    truth = traj.T_odom_base(t)
    err = [se3_log(se3_inverse(se3_inverse(truth[i]) @ truth[i + 1])
                   @ se3_inverse(poses[i]) @ poses[i + 1]) for i in range(len(t) - 1)]
    err = np.array(err)
    assert np.std(err[:, 3:]) == pytest.approx(sigma_v / 50, rel=0.1)
    assert np.std(err[:, :3]) == pytest.approx(sigma_w / 50, rel=0.1)


def test_office_survey_enters_every_room_and_the_open_area_once_round():
    office = world("office")
    xy = build_trajectory(office, "survey", 325.0).T_map_base(np.arange(0.0, 325.0, 0.5))[:, :2, 3]
    in_rooms = xy[xy[:, 1] < 7.0]
    rooms_entered = set(((in_rooms[:, 0] - 1.0) // 6.0).astype(int))
    assert rooms_entered == set(range(8))
    assert (xy[:, 1] > 16.0).any()  # the open area beyond the ramps
    assert np.linalg.norm(xy[-1] - xy[0]) < 3.0  # back at the start
