"""Odometry: degeneracy (a corridor, a flat field, not a room or a hall) and empty-scan
reporting on synthetic scans, degenerate stretches as one warning, and `mcl3d odometry`
end to end on a short simulated office log (with IMU and ground truth)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from mcl3d.core.geometry import se3, so3_exp, transform_points


def box_scan(rng, length_m, n=6000):
    """Points on the inside of a box (a room, or a corridor when long): the sensor at 0."""
    half = np.array([length_m / 2 + 0.13, 1.37, 1.61])  # faces off the voxel grid
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = rng.uniform(-half, half, (n // 6, 3))
            p[:, axis] = sign * half[axis]
            faces.append(p)
    return np.vstack(faces)


@pytest.fixture(scope="module")
def module_odometry(backend):
    """One Odometry for the tests below, `reset` between them: its kernels compile once."""
    from mcl3d.core import runtime
    from mcl3d.odometry.lidar_odometry import LidarOdometry, OdometryConfig

    runtime.init(backend)
    cfg = OdometryConfig(voxel_size_m=0.2, map_voxel_size_m=0.5, max_keyframes=2,
                         buckets_per_map=1 << 13, max_points=4096)
    return LidarOdometry(cfg)


@pytest.fixture
def odometry(module_odometry):
    module_odometry.reset()
    return module_odometry


def test_room_motion_is_tracked(odometry):
    rng = np.random.default_rng(0)
    room = box_scan(rng, 6.0)
    odometry.step(room, None, 0)
    moved = transform_points(np.linalg.inv(se3(so3_exp([0, 0, 0.05]), [0.2, 0.1, 0.0])),
                             box_scan(rng, 6.0))  # what the sensor sees after moving
    frame = odometry.step(moved, None, 100_000_000)
    assert not frame.degenerate and frame.converged
    np.testing.assert_allclose(frame.T_world_lidar[:3, 3], [0.2, 0.1, 0.0], atol=0.02)
    assert np.all(np.linalg.eigvalsh(frame.covariance) > 0)


def test_reset_starts_a_new_log_on_the_same_fields(odometry):
    rng = np.random.default_rng(2)
    room = box_scan(rng, 6.0)
    moved = transform_points(np.linalg.inv(se3(so3_exp([0, 0, 0.05]), [0.2, 0.1, 0.0])),
                             box_scan(rng, 6.0))
    before = [odometry.step(room, None, 0), odometry.step(moved, None, 100_000_000)]
    odometry.reset()
    again = [odometry.step(room, None, 0), odometry.step(moved, None, 100_000_000)]
    assert again[0].keyframe and odometry.last_frame is again[1]
    np.testing.assert_allclose(again[1].T_world_lidar, before[1].T_world_lidar, atol=1e-5)


def test_empty_scan_is_reported_not_silently_wrong(odometry):
    from mcl3d.odometry.lidar_odometry import LOST_COVARIANCE

    rng = np.random.default_rng(1)
    odometry.step(box_scan(rng, 6.0), None, 0)
    frame = odometry.step(np.zeros((0, 3)), None, 100_000_000)
    assert frame.degenerate and frame.num_inliers == 0
    assert "usable points" in frame.warnings[0]
    assert frame.covariance[0, 0] == LOST_COVARIANCE


@pytest.fixture(scope="module")
def office_log(tmp_path_factory):
    from mcl3d.sim.pipeline import SimulateRequest, run

    out = tmp_path_factory.mktemp("sim") / "office.mcap"
    run(SimulateRequest(world="office", sensor="vlp16", trajectory="ground", duration_s=5.0,
                        seed=3, output=out, config_path=None, export_mesh=None,
                        export_map=None, force=False))
    return out


def test_cli_odometry_end_to_end(office_log, tmp_path, ti_runtime):
    from typer.testing import CliRunner

    from mcl3d.cli import app
    from mcl3d.io.trajectory import read_kitti, read_tum

    out = tmp_path / "odo"
    runner = CliRunner()
    result = runner.invoke(app, ["odometry", str(office_log), "-o", str(out),
                                 "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    assert "Odometry" in result.output and "ATE" in result.output
    traj = read_tum(out / "odometry.tum")
    assert len(traj) == 50 and len(read_kitti(out / "odometry_kitti.txt")) == 50
    summary = json.loads((out / "odometry_summary.json").read_text())
    ev = summary["evaluation"]
    assert ev["ate"]["translation_m"]["rmse"] < 0.05
    assert summary["scans"] == 50 and summary["keyframes"] >= 1
    assert 0 <= summary["redeskewed_frames"] <= 5  # a steady robot with an IMU: few
    motion = np.load(out / "relative_motion.npz")
    assert motion["covariance"].shape == (50, 6, 6)
    # outputs exist: refused without --force, one red line, exit 1
    again = runner.invoke(app, ["odometry", str(office_log), "-o", str(out), "--no-imu",
                                "--backend", "cpu"])
    assert again.exit_code == 1 and again.exception.setting == "force"


def test_cli_odometry_bad_topic(office_log, tmp_path, ti_runtime):
    from typer.testing import CliRunner

    from mcl3d.cli import app

    result = CliRunner().invoke(app, ["odometry", str(office_log), "-o", str(tmp_path),
                                      "--points-topic", "/nope", "--backend", "cpu"])
    assert result.exit_code == 1 and "/nope" in str(result.exception)


def test_real_ouster_mcap_with_imu_on_another_clock(shared_data, tmp_path, ti_runtime):
    """Real OS1-64 ROS 1 MCAP (pointcloudset, MIT): 2 scans; its IMU is stamped in sensor
    time, so the IMU must be set aside with a note, not integrated across 50 years."""
    from mcl3d.odometry.pipeline import OdometryRequest, run

    result = run(OdometryRequest(log=shared_data / "ouster_os1_64_mcap" / "test.mcap",
                                 output_dir=tmp_path))
    assert result.summary.scans == 2
    assert any("not on the LiDAR's clock" in n for n in result.summary.notes)
    second = result.frames[1]
    assert second.num_inliers > 1000 and not second.degenerate
    assert np.linalg.norm(second.T_prev_curr[:3, 3]) < 0.05  # the sensor stood still


def endless_corridor_scan(rng, n=6000):
    """Walls, floor and ceiling of a corridor running along x past the sensor's reach (no
    ends): nothing pins x."""
    half = np.array([40.0, 1.37, 1.61])
    faces = []
    for axis in (1, 2):
        for sign in (-1.0, 1.0):
            p = rng.uniform(-half, half, (n // 4, 3))
            p[:, axis] = sign * half[axis]
            faces.append(p)
    return np.vstack(faces)


def flat_field_scan(rng, n=6000):
    """Ground only, 1.8 m below the sensor, out to 30 m: nothing pins x, y or yaw."""
    p = rng.uniform(-30.0, 30.0, (n, 3))
    p[:, 2] = -1.8
    return p


def degenerate_translations(frame):
    return [np.array(re.search(r"along \[(.*)\]", w).group(1).split(", "), float)
            for w in frame.warnings if w.startswith("degenerate translation")]


@pytest.mark.parametrize("scan, free_axes", [(endless_corridor_scan, [0]),
                                             (flat_field_scan, [0, 1])])
def test_endless_corridor_and_flat_field_are_degenerate(odometry, scan, free_axes):
    rng = np.random.default_rng(4)
    odometry.step(scan(rng), None, 0)
    frame = odometry.step(scan(rng), None, 100_000_000)
    directions = degenerate_translations(frame)
    assert frame.degenerate and directions
    assert np.linalg.norm(directions[0][free_axes]) > 0.99  # within the free directions


def hall_scan(rng, wall_points=300, floor_points=5000):
    """A wide, low hall (14 x 14 x 3.2 m) whose floor and ceiling hold most points."""
    half = np.array([7.13, 6.85, 1.61])
    faces = []
    for axis, n in ((0, wall_points), (1, wall_points), (2, floor_points)):
        for sign in (-1.0, 1.0):
            p = rng.uniform(-half, half, (n, 3))
            p[:, axis] = sign * half[axis]
            faces.append(p)
    return np.vstack(faces)


@pytest.mark.parametrize("scan", [lambda rng: box_scan(rng, 6.0), hall_scan])
def test_a_room_and_a_hall_are_not_degenerate(odometry, scan):
    """The hall's translation eigenvalues are ~40:1 (floor against walls): the old min/max
    test (below 0.05) fired there, yet its walls pin x and y to millimetres."""
    rng = np.random.default_rng(5)
    odometry.step(scan(rng), None, 0)
    frame = odometry.step(scan(rng), None, 100_000_000)
    assert not frame.degenerate, frame.warnings


def test_degenerate_stretch_is_one_warning():
    from mcl3d.odometry.lidar_odometry import OdometryFrame
    from mcl3d.odometry.odometry_summary import run_warnings

    eye = np.eye(4)
    corridor = "degenerate translation: information share 0.001 along [1.00, 0.00, 0.00]"
    per_scan = [[], [corridor], [corridor, "odd"], [corridor], [], [corridor], []]
    frames = [OdometryFrame(i * 100_000_000, eye, eye, np.eye(6), 100, 100, 1, True, False,
                            1.0, bool(w), w) for i, w in enumerate(per_scan)]
    warnings, stretches = run_warnings(frames)
    assert [(s.first_scan, s.last_scan, s.scans) for s in stretches] == [(1, 3, 3), (5, 5, 1)]
    assert warnings == [
        f"scans 1 to 3 (0.100 to 0.300 s, 3 scans): {corridor} at the first",
        "scan 2 (0.200 s): odd",
        f"scan 5 (0.500 s): {corridor}"]
    assert stretches[0].as_dict()["block"] == "translation"


def test_ordinary_office_loop_warns_of_no_degeneracy(tmp_path, ti_runtime):
    """The first 7 s of the office loop: the old min/max test fired on scans 58-65 (a
    corridor-like stretch of rooms with a dominant floor), none are degenerate."""
    from mcl3d.odometry.pipeline import OdometryRequest
    from mcl3d.odometry.pipeline import run as run_odometry
    from mcl3d.sim.pipeline import SimulateRequest, run

    log = tmp_path / "loop.mcap"
    run(SimulateRequest(world="office", sensor="vlp16", trajectory="loop", duration_s=7.0,
                        seed=0, output=log, config_path=None, export_mesh=None,
                        export_map=None, force=False))
    summary = run_odometry(OdometryRequest(log=log, output_dir=tmp_path / "odo")).summary
    assert summary.degenerate_frames == 0 and not summary.degenerate_stretches
    assert not [w for w in summary.warnings if "degenerate" in w]
