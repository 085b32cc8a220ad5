"""Monte Carlo SLAM end to end: a loop closure with real GICP on a synthetic room, and the
`mcl3d slam` command on a short simulated forest log (outputs, no-IMU, Ctrl-C, bad input)."""

import numpy as np
import pytest
from support.pictures import assert_picture
from typer.testing import CliRunner

from mcl3d.cli import app
from mcl3d.core import geometry
from mcl3d.slam.slam_config import CorrectionConfig


def slam_cli(*args):
    """`mcl3d slam` in this process on the cpu backend, the runtime the other tests use:
    another backend request would restart Taichi (and recompile) at each switch."""
    return CliRunner().invoke(app, ["--backend", "cpu", "slam", *args])


def room_cloud(rng) -> np.ndarray:
    """Walls, floor, ceiling and a few pillars of a 12 x 9 x 3 m room, in its own frame."""
    n = 6000
    faces = []
    for axis, value in ((0, -6.0), (0, 6.0), (1, -4.5), (1, 4.5), (2, 0.0), (2, 3.0)):
        p = rng.uniform([-6, -4.5, 0], [6, 4.5, 3], (n // 6, 3))
        p[:, axis] = value
        faces.append(p)
    for cx, cy in ((-2.0, 1.0), (3.0, -2.0), (1.0, 2.5)):
        a = rng.uniform(0, 2 * np.pi, 400)
        faces.append(np.c_[cx + 0.3 * np.cos(a), cy + 0.3 * np.sin(a), rng.uniform(0, 3, 400)])
    return np.concatenate(faces)


def test_loop_closure_pulls_the_current_pose_and_bends_the_keyframes(ti_runtime):
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.registration.preprocess import estimate_covariances, voxel_downsample
    from mcl3d.slam.slam_particles import SlamParticles

    rng = np.random.default_rng(0)
    world = voxel_downsample(room_cloud(rng), 0.2)
    # a square path around the room; keyframes every 4 m of travel, drift growing with it
    xy = [(-3, -2), (1, -2), (3, 0), (1, 2), (-3, 2), (-4, 0)]
    true_kf = np.stack([geometry.se3(geometry.rpy_to_rot(0, 0, 0.4 * k), [x, y, 1.2])
                        for k, (x, y) in enumerate(xy)])
    travel = np.array([0.0, 4.0, 8.0, 12.0, 16.0, 20.0])
    drift = [geometry.se3(geometry.rpy_to_rot(0, 0, np.deg2rad(1.5) * s / 24),
                          [0.3 * s / 24, -0.2 * s / 24, 0.0]) for s in travel]
    est_kf = np.stack([D @ T for D, T in zip(drift, true_kf, strict=True)])
    true_cur = geometry.se3(geometry.rpy_to_rot(0, 0, 0.05), [-2.8, -1.9, 1.2])
    D_now = geometry.se3(geometry.rpy_to_rot(0, 0, np.deg2rad(1.5)), [0.3, -0.2, 0.0])
    est_cur = D_now @ true_cur

    maps = GaussianVoxelMaps(max_maps=8, buckets_per_map=4096, max_points=4096)
    for k, T in enumerate(true_kf):
        local = geometry.transform_points(geometry.se3_inverse(T), world)
        maps.clear(k, 0.5)
        maps.insert(k, local, estimate_covariances(local, 10))
    src = geometry.transform_points(geometry.se3_inverse(true_cur), world)
    src = src[np.linspace(0, len(src) - 1, 512).astype(int)]
    gicp = BatchGicp(maps, max_groups=3, max_rows=3, max_source_points=512)
    gicp.set_source(src, estimate_covariances(src, 10))
    # the odometry's drift sums (W, Σ w p, V), variance growing evenly with travel
    path = np.r_[travel, 24.0]
    pos = np.r_[est_kf[:, :3, 3], est_cur[None, :3, 3]]
    w = np.diff(path, prepend=0.0) * 1e-5
    drift = np.c_[np.cumsum(w), np.cumsum(w[:, None] * pos, axis=0), 10 * np.cumsum(w)]
    p = SlamParticles(1, 8, gicp, seed=0)
    for k in range(len(true_kf)):
        p.q_cur.from_numpy(geometry.rot_to_quat(est_kf[k:k + 1, :3, :3]).astype(np.float32))
        p.t_cur.from_numpy(est_kf[k:k + 1, :3, 3].astype(np.float32))
        p.add_keyframe(float(travel[k]), drift[k], est_kf[k, :3, 3])
    p.q_cur.from_numpy(geometry.rot_to_quat(est_cur[None, :3, :3]).astype(np.float32))
    p.t_cur.from_numpy(est_cur[None, :3, 3].astype(np.float32))

    assert p.select_neighbours(24.0, 10.0) == 1
    step = CorrectionConfig(min_inliers=30, max_step_deg=5.0, max_step_m=1.0,
                            settled_step_deg=0.2, settled_step_m=0.02)
    nb = p.nb.to_numpy()[0]
    assert 0 in nb
    for _ in range(4):
        p.correct(24.0, drift[-1], est_cur[:3, 3], len(src), step)
        p.select_neighbours(24.0, 10.0)
    cur = p.current_poses()[0]
    before = np.linalg.norm(est_cur[:3, 3] - true_cur[:3, 3])
    after = np.linalg.norm(cur[:3, 3] - true_cur[:3, 3])
    assert before > 0.3 and after < 0.03
    assert geometry.rotation_angle(cur[:3, :3].T @ true_cur[:3, :3]) < np.deg2rad(0.2)
    kf = p.keyframe_poses(0)
    np.testing.assert_allclose(kf[0], est_kf[0], atol=1e-5)  # the loop's anchor stays
    err_before = np.linalg.norm(est_kf[:, :3, 3] - true_kf[:, :3, 3], axis=1)
    err_after = np.linalg.norm(kf[:, :3, 3] - true_kf[:, :3, 3], axis=1)
    assert (err_after[3:] < 0.5 * err_before[3:]).all()  # late keyframes follow the loop


def test_a_truncated_likelihood_costs_a_matched_point_at_most_the_outlier_cost(ti_runtime):
    """likelihood.truncated: min(eᵀΩe, outlier_cost) per matched point, so no frame costs more
    than outlier_cost a point; without it a pose 0.5 m off costs more, and with a cap no
    point reaches the two agree."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.registration.preprocess import estimate_covariances, voxel_downsample
    from mcl3d.slam.slam_config import LikelihoodConfig
    from mcl3d.slam.slam_particles import SlamParticles

    world = voxel_downsample(room_cloud(np.random.default_rng(0)), 0.2)
    maps = GaussianVoxelMaps(max_maps=2, buckets_per_map=4096, max_points=4096)
    maps.clear(0, 0.5)
    maps.insert(0, world, estimate_covariances(world, 10))
    src = world[np.linspace(0, len(world) - 1, 512).astype(int)]
    gicp = BatchGicp(maps, max_groups=3, max_rows=3, max_source_points=512)
    gicp.set_source(src, estimate_covariances(src, 10))
    p = SlamParticles(1, 2, gicp, seed=0)
    p.q_cur.from_numpy(np.array([[0, 0, 0, 1]], np.float32))
    p.t_cur.from_numpy(np.zeros((1, 3), np.float32))
    p.add_keyframe(0.0, np.zeros(5), np.zeros(3))
    p.t_cur.from_numpy(np.array([[0.4, -0.3, 0.0]], np.float32))  # the scan 0.5 m off
    p.select_neighbours(0.0, 10.0)

    def frame_ll(**settings) -> float:
        p.weigh(len(src), LikelihoodConfig(points_weight=2.0, **settings))
        return float(p.frame_ll.to_numpy()[0])

    plain, truncated = frame_ll(outlier_cost=9.0), frame_ll(outlier_cost=9.0, truncated=True)
    assert plain < -0.5 * 2.0 * 9.0 < truncated  # mean cost above / below 9 a point
    np.testing.assert_allclose(frame_ll(outlier_cost=1e9, truncated=True),
                               frame_ll(outlier_cost=1e9), rtol=1e-6)


def test_a_zero_local_weight_leaves_only_loops_to_tell_particles_apart(ti_runtime):
    """likelihood.local_weight 0: particles whose neighbours are not loops score the same
    however well they match them (the odometry already matched the scan to that map),
    while a loop row still costs each particle its own match; at 1 (the paper) the
    non-loop keyframe's match tells them apart."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.registration.preprocess import estimate_covariances, voxel_downsample
    from mcl3d.slam.slam_config import LikelihoodConfig
    from mcl3d.slam.slam_particles import SlamParticles

    world = voxel_downsample(room_cloud(np.random.default_rng(0)), 0.2)
    maps = GaussianVoxelMaps(max_maps=4, buckets_per_map=4096, max_points=4096)
    for k in range(4):  # keyframe 0 saw the room; 1-3 (far away, the newest) saw nothing
        maps.clear(k, 0.5)
    maps.insert(0, world, estimate_covariances(world, 10))
    src = world[np.linspace(0, len(world) - 1, 512).astype(int)]
    gicp = BatchGicp(maps, max_groups=9, max_rows=9, max_source_points=512)
    gicp.set_source(src, estimate_covariances(src, 10))
    p = SlamParticles(3, 4, gicp, seed=0)
    p.q_cur.from_numpy(np.tile(np.array([0, 0, 0, 1], np.float32), (3, 1)))
    for k in range(4):
        p.t_cur.from_numpy(np.full((3, 3), 40.0 * k, np.float32))
        p.add_keyframe(0.0, np.zeros(5), np.zeros(3))
    p.t_cur.from_numpy(np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.3, 0.0]],
                                np.float32))  # the scan 0, 0.2 and 0.3 m off the keyframe

    def frame_ll(local_weight: float, loop_travel_m: float) -> np.ndarray:
        p.select_neighbours(20.0, loop_travel_m)  # keyframe 0 is 20 m of travel back
        p.log_w.fill(0.0)
        p.weigh(len(src), LikelihoodConfig(points_weight=2.0, outlier_cost=9.0,
                                           local_weight=local_weight))
        return p.frame_ll.to_numpy()

    recent_paper, recent_zero = frame_ll(1.0, 50.0), frame_ll(0.0, 50.0)
    assert recent_paper[0] > recent_paper[1] > recent_paper[2]  # the match decides
    np.testing.assert_allclose(recent_zero, recent_zero[1])  # the cloud's median row
    np.testing.assert_allclose(frame_ll(0.0, 10.0), frame_ll(1.0, 10.0), rtol=1e-6)  # a loop


def test_a_loop_keyframe_that_sees_none_of_the_scan_is_no_evidence(ti_runtime):
    """Eq. 3 scores only the scan points that land in a keyframe voxel, so a particle whose
    loop keyframe sees none of the scan outscores one that matches it. With
    likelihood.unmatched_as_typical (the default) such a point costs what a typical matched
    point costs against the recent map: the two score alike, and a loop matched worse than
    typical (0.15 m off) still scores below."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.registration.preprocess import estimate_covariances, voxel_downsample
    from mcl3d.slam.slam_config import LikelihoodConfig
    from mcl3d.slam.slam_particles import SlamParticles

    world = voxel_downsample(room_cloud(np.random.default_rng(0)), 0.2)
    maps = GaussianVoxelMaps(max_maps=4, buckets_per_map=4096, max_points=4096)
    for k in range(4):  # keyframe 0 (the loop, 20 m of travel back) and 1-3 saw the room
        maps.clear(k, 0.5)
        maps.insert(k, world, estimate_covariances(world, 10))
    src = world[np.linspace(0, len(world) - 1, 512).astype(int)]
    gicp = BatchGicp(maps, max_groups=15, max_rows=15, max_source_points=512)
    gicp.set_source(src, estimate_covariances(src, 10))
    p = SlamParticles(5, 4, gicp, seed=0)
    p.q_cur.from_numpy(np.tile(np.array([0, 0, 0, 1], np.float32), (5, 1)))
    p.t_cur.from_numpy(np.zeros((5, 3), np.float32))
    for _ in range(4):
        p.add_keyframe(0.0, np.zeros(5), np.zeros(3))
    p.t_cur.from_numpy(np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0.15, 0.1, 0.05],
                                 [30, 0, 0]], np.float32))  # 3: 0.15 m off; 4: far away

    def frame_ll(typical: bool) -> np.ndarray:
        assert p.select_neighbours(20.0, 10.0) == 5  # keyframes 0, 1, 2; 0 is a loop
        p.log_w.fill(0.0)
        p.weigh(len(src), LikelihoodConfig(unmatched_as_typical=typical))
        return p.frame_ll.to_numpy()

    paper, typical = frame_ll(False), frame_ll(True)
    # 0 and 4 share the reference rows; 0's loop row costs what one of them does, 4's nothing
    np.testing.assert_allclose(paper[4], paper[0] * 2 / 3, rtol=1e-4)  # missing the loop pays
    np.testing.assert_allclose(typical[4], typical[0], rtol=1e-4)  # no evidence either way
    assert typical[3] < 10 * typical[0] and paper[3] < 10 * paper[0]  # a worse match loses


@pytest.fixture(scope="module")
def forest_log(tmp_path_factory):
    from mcl3d.sim.pipeline import SimulateRequest, run

    log = tmp_path_factory.mktemp("slam") / "forest.mcap"
    run(SimulateRequest(world="forest", sensor="mid360", trajectory="ground", duration_s=5.0,
                        seed=2, output=log,
                        overrides={"world.forest_rows": 6, "world.forest_trees_per_row": 6}))
    return log


def test_slam_command_writes_every_output(forest_log, tmp_path, ti_runtime):
    import json

    from mcl3d.io.trajectory import read_kitti, read_tum
    from mcl3d.maps.map_file import read_blocks

    out = tmp_path / "out"
    tsdf = tmp_path / "map.tsdf"
    result = slam_cli(str(forest_log), "-o", str(out), "--particles",
                      "200", "--tsdf", str(tsdf), "--seed", "3")
    assert result.exit_code == 0, result.output
    assert "ATE SLAM" in result.output
    traj = read_tum(out / "slam.tum")
    assert len(traj) == 50 == len(read_kitti(out / "slam_kitti.txt"))
    assert len(read_tum(out / "slam_online.tum")) == len(read_tum(out / "odometry.tum")) == 50
    summary = json.loads((out / "slam_summary.json").read_text())
    assert summary["keyframes"] >= 1 and summary["particles"] == 200
    assert summary["evaluation"]["slam"]["ate_m"] < 0.1
    lines = (out / "frames.csv").read_text().splitlines()
    assert len(lines) == 51 and lines[0].startswith("stamp_s,x,y,z")
    assert "mean_qw" in lines[0] and "cov_rx_rx" in lines[0] and "cov_z_z" in lines[0]
    cloud = summary["consistency"]  # the cloud's 95% region against the ground truth
    assert cloud["scans"] == 50 and 0.0 <= cloud["fraction_95"] <= 1.0
    assert summary["loops"]["accepted"] >= 0 and summary["loops"]["wrong"] == 0
    assert summary["loop_edges"] == {"registered": 0, "in_map": 0, "rejected": 0}  # no loop yet
    assert "consistency" in result.output
    head = (out / "map.ply").read_bytes()[:200]
    count = int(head.split(b"element vertex ")[1].split(b"\n")[0])
    assert count > 1000
    assert (out / "map.ply").stat().st_size == head.index(b"end_header\n") + 11 + 12 * count
    header, _, data = read_blocks(tsdf)
    assert header["format"] and len(data.sdf) > 0
    assert_picture(out / "slam.png")
    assert "picture" in result.output


def test_slam_without_imu_and_interrupted_keeps_results(forest_log, tmp_path, ti_runtime,
                                                        monkeypatch):
    from mcl3d.core.errors import RunInterrupted
    from mcl3d.io.trajectory import read_tum
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam

    out = tmp_path / "noimu"
    result = slam_cli(str(forest_log), "-o", str(out), "--particles",
                      "100", "--no-imu", "--max-scans", "20")
    assert result.exit_code == 0, result.output
    assert "constant velocity" in result.output
    assert len(read_tum(out / "slam.tum")) == 20
    again = tmp_path / "noimu_again"
    result = slam_cli(str(forest_log), "-o", str(again), "--particles",
                      "100", "--no-imu", "--max-scans", "20")
    assert result.exit_code == 0, result.output
    for name in ("slam.tum", "slam_online.tum", "odometry.tum", "map.ply"):  # reproducible
        assert (out / name).read_bytes() == (again / name).read_bytes(), name

    step = MonteCarloSlam.step

    def interrupted(self, *args, **kwargs):
        if len(self.frames) == 12:
            raise KeyboardInterrupt
        return step(self, *args, **kwargs)

    monkeypatch.setattr(MonteCarloSlam, "step", interrupted)
    out2 = tmp_path / "interrupted"
    result = slam_cli(str(forest_log), "-o", str(out2), "--particles", "100", "--max-scans", "30")
    assert isinstance(result.exception, RunInterrupted)  # the app exits 130 on it
    assert "after 12 scans" in str(result.exception)
    assert len(read_tum(out2 / "slam.tum")) == 12
    assert (out2 / "map.ply").exists() and (out2 / "slam_summary.json").exists()


def test_slam_bad_input_is_one_error(tmp_path, forest_log, ti_runtime):
    """Each is an Mcl3dError (the app prints it as one line and exits 1), nothing written."""
    from mcl3d.core.errors import Mcl3dError

    cases = [([str(tmp_path / "nope.mcap")], "nope.mcap"),
             ([str(forest_log), "--points-topic", "/nothing"], "/nothing"),
             ([str(forest_log), "--particles", "0"], "particles")]
    for k, (args, needle) in enumerate(cases):
        out = tmp_path / f"o{k}"
        result = slam_cli(*args, "-o", str(out))
        assert isinstance(result.exception, Mcl3dError), result.output
        assert needle in str(result.exception)
        assert not out.exists()


def test_slam_survives_a_gap_and_a_stationary_start(forest_log, ti_runtime):
    """The scans in 1.0-2.0 s are missing (their IMU samples still arrive), and the first 5
    scans repeat the first one (the robot stands still): the trajectory stays on track."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_tum
    from mcl3d.odometry.scan_feed import scans_with_imu
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    gt = read_tum(forest_log.with_name(forest_log.stem + "_gt.tum"))
    slam = MonteCarloSlam(SlamConfig(particles=100, seed=1))
    stamps = []
    with LogReader(forest_log) as reader:
        first = None
        imu_gap = []
        for cloud, imu, frame in scans_with_imu(reader, ("points", "imu"), [], []):
            if first is None:
                first = cloud
                slam.odometry.T_lidar_imu = reader.static_transform(cloud.frame_id, frame)
                for k in range(5):  # standing still before driving off
                    slam.step(cloud.points, cloud.times_s, cloud.stamp_ns - (5 - k) * 100_000_000,
                              None)
            t = cloud.stamp_ns * 1e-9 - gt.stamps_s[0]
            if 1.0 <= t < 2.0:
                imu_gap.append(imu)
                continue
            rows = np.concatenate([*imu_gap, imu]) if imu_gap else imu
            imu_gap = []
            slam.step(cloud.points, cloud.times_s, cloud.stamp_ns, rows)
            stamps.append(cloud.stamp_ns * 1e-9)
    _, poses = slam.trajectory()
    poses = poses[5:]
    ref = gt.interpolate_poses(stamps)
    aligned = ref[0] @ geometry.se3_inverse(poses[0]) @ poses
    err = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    assert len(stamps) == 40 and err.max() < 0.25
    # a long run keeps each scan's record in the columns of one store (tests/slam/
    # test_frame_store.py), and the odometry keeps only its last two mid-sweep poses
    assert len(slam.frames) == 45 == len(slam.frames.stamp_ns)
    assert len(slam.odometry.mid_poses) == 2


def test_slam_config_file_round_trips_in_its_sections(tmp_path):
    """The saved slam_config.yaml loads back as the same config; a key outside its section
    is named in the error."""
    from mcl3d.core import config as config_io
    from mcl3d.core.errors import ConfigError
    from mcl3d.slam.slam_config import SlamConfig

    cfg = config_io.load(SlamConfig, None, {"particles": 7, "front_end.fov_deg": 180.0,
                                            "keyframes.capacity": 32})
    path = tmp_path / "slam_config.yaml"
    config_io.save(cfg, path)
    assert config_io.load(SlamConfig, path) == cfg
    assert cfg.front_end.fov_deg == 180.0 and cfg.keyframes.capacity == 32
    path.write_text("fov_deg: 180\n")
    with pytest.raises(ConfigError, match="fov_deg"):
        config_io.load(SlamConfig, path)
    with pytest.raises(ConfigError, match=r"keyframes\.voxel_m must be >= front_end"):
        config_io.load(SlamConfig, None, {"keyframes.voxel_m": 0.1})


def test_slam_preset_paper_and_an_unknown_preset(forest_log, tmp_path, ti_runtime):
    """--preset paper runs the paper's settings (saved in slam_config.yaml), flags still win;
    an unknown preset is one error naming the choices, before anything is written."""
    import yaml

    from mcl3d.core.errors import ConfigError

    out = tmp_path / "paper"
    result = slam_cli(str(forest_log), "-o", str(out), "--particles",
                      "100", "--max-scans", "15", "--preset", "paper")
    assert result.exit_code == 0, result.output
    saved = yaml.safe_load((out / "slam_config.yaml").read_text())
    assert saved["particles"] == 100
    assert saved["correction"]["refine_without_loop"] is False
    assert saved["loop_closure"]["facing_gate"] is False
    assert saved["prediction_noise"]["odometry_scale"] == 1.0
    assert saved["trajectory"]["bridge_between_loops"] is False
    bad = tmp_path / "bad"
    result = slam_cli(str(forest_log), "-o", str(bad), "--preset", "nope")
    assert isinstance(result.exception, ConfigError)
    assert "default, paper" in str(result.exception) and not bad.exists()


def test_presets_apply_under_a_config_file(tmp_path):
    from mcl3d.core import config as config_io
    from mcl3d.slam.presets import PRESETS, preset
    from mcl3d.slam.slam_config import SlamConfig

    path = tmp_path / "c.yaml"
    path.write_text("correction:\n  min_inliers: 50\n")
    cfg = config_io.load(SlamConfig, path, {"seed": 2}, preset=preset("paper"))
    assert cfg.correction.min_inliers == 50 and cfg.seed == 2  # the file and flags win
    assert cfg.correction.refine_without_loop is False  # the preset's, where the file is silent
    assert config_io.load(SlamConfig, None, preset=preset(None)) == SlamConfig()
    for name in PRESETS:  # every preset builds a valid config
        config_io.load(SlamConfig, None, preset=preset(name))


def test_spread_draws_from_the_steps_gaussian_posterior(ti_runtime):
    """After a step, each moved particle draws δ ~ N(0, (Σ⁻¹ + k H)⁻¹): the sample covariance
    of the cloud matches that posterior; particles with too few inliers or a loop (when only
    refinement ran) do not move."""
    from mcl3d.registration.batch_gicp import BatchGicp
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.slam.slam_particles import SlamParticles

    n, num_src, weight = 6000, 100, 30.0
    maps = GaussianVoxelMaps(max_maps=2, buckets_per_map=64, max_points=64)
    gicp = BatchGicp(maps, max_groups=3 * n, max_rows=3 * n, max_source_points=num_src)
    p = SlamParticles(n, 2, gicp, seed=0)
    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 6))
    H_row = A @ A.T * 2e3 + np.diag([4e4, 4e4, 4e4, 1e4, 1e4, 1e4])
    H = np.zeros((3 * n, 6, 6), np.float32)
    H[0::3] = H_row  # one neighbour row per particle
    matched = np.zeros(3 * n, np.int32)
    matched[0::3] = 80
    matched[3 * (n - 1)] = 5  # the last particle sees too little to move
    gicp.poses.best.H.from_numpy(H)
    gicp.poses.best.n.from_numpy(matched)
    nb = np.full((n, 3), -1, np.int32)
    nb[:, 0] = 0
    p.nb.from_numpy(nb)
    loop = np.zeros((n, 3), np.int32)
    loop[n - 2, 0] = 1  # a looping particle: refinement did not move it
    p.nb_loop.from_numpy(loop)
    cov = np.diag(np.r_[np.full(3, 1e-3**2), np.full(3, 0.01**2)])
    moved = p.spread(cov, num_src, weight, 30, refined=True, corrected=False, step=1)
    assert moved == n - 2
    xi = geometry.se3_log(p.current_poses())
    np.testing.assert_allclose(xi[n - 2:], 0.0, atol=1e-7)
    post = np.linalg.inv(np.linalg.inv(cov) + weight / num_src * H_row)
    sample = np.cov(xi[:n - 2].T)
    np.testing.assert_allclose(np.sqrt(np.diag(sample)), np.sqrt(np.diag(post)), rtol=0.05)
    assert abs(sample[0, 1] / np.sqrt(sample[0, 0] * sample[1, 1])
               - post[0, 1] / np.sqrt(post[0, 0] * post[1, 1])) < 0.05


def test_a_run_that_fills_every_keyframe_goes_on_and_says_so(forest_log, tmp_path, ti_runtime):
    """A walk longer than keyframes.capacity allows goes on, each new keyframe replacing a
    kept one, with one warning naming the setting, instead of ending the run."""
    import json

    config = tmp_path / "small.yaml"
    config.write_text("keyframes:\n  capacity: 2\n  overlap: 0.99\n")
    out = tmp_path / "out"
    result = slam_cli(str(forest_log), "-o", str(out), "--particles",
                      "100", "--seed", "3", "--config", str(config))
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "slam_summary.json").read_text())
    assert summary["keyframes"] == 2 and summary["scans"] == 50
    assert summary["keyframes_made"] > 2
    full = [w for w in summary["odometry_warnings"] if "keyframes.capacity" in w]
    assert len(full) == 1, summary["odometry_warnings"]


def test_slam_with_free_space_and_the_ride_settings_stays_on_track(forest_log, ti_runtime):
    """The opt-in likelihood term (points in seen-through space) and the ride settings run
    through a whole short log: the trajectory stays on the truth, and the free-space count
    is in use (the true poses see almost nothing through a keyframe's free space)."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_tum
    from mcl3d.odometry.scan_feed import LidarImuFeed
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    gt = read_tum(forest_log.with_name(forest_log.stem + "_gt.tum"))
    cfg = SlamConfig.model_validate({"particles": 100, "seed": 1,
                                     "likelihood": {"free_space_cost": 3.0},
                                     "elevator": {"resample_on_entry": True,
                                                  "exit_open_sectors": 3}})
    slam = MonteCarloSlam(cfg)
    seen = []
    with LogReader(forest_log) as reader:
        for cloud, imu, T_lidar_imu in LidarImuFeed(reader, True):
            slam.odometry.T_lidar_imu = T_lidar_imu
            slam.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu)
            rows = slam.particles.nb.to_numpy().ravel() >= 0
            seen.append(slam.particles.seen.to_numpy()[rows].mean() if rows.any() else 0.0)
    assert slam.free_space is not None and slam.free_space.kf_counts.to_numpy().max() > 0
    assert np.max(seen) > 0 and np.mean(seen) < 0.1 * cfg.likelihood.free_space_points
    stamps, poses = slam.trajectory()
    ref = gt.interpolate_poses(stamps * 1e-9)
    aligned = ref[0] @ geometry.se3_inverse(poses[0]) @ poses
    assert np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1).max() < 0.25


def box_surface(rng, half_xy: float, z0: float, z1: float, n: int) -> np.ndarray:
    """Points on the walls, floor and ceiling of a box around the sensor (lidar frame)."""
    faces = []
    for axis, value in ((0, -half_xy), (0, half_xy), (1, -half_xy), (1, half_xy), (2, z0),
                        (2, z1)):
        p = rng.uniform([-half_xy, -half_xy, z0], [half_xy, half_xy, z1], (n // 6, 3))
        p[:, axis] = value
        faces.append(p)
    return np.concatenate(faces)


def test_the_guard_starts_when_a_ride_ends_and_only_then(ti_runtime):
    """A room, a shut cab (the elevator detector holds), the room again: the guard is off
    before and during the ride and prunes by strata from the first scan after it; while it
    holds, every neighbour weighs (the particles' heights are not the odometry's), before
    the ride only loops do."""
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    rng = np.random.default_rng(0)
    room = box_surface(rng, 6.0, -1.2, 1.8, 6000)
    cab = box_surface(rng, 1.1, -1.2, 1.2, 6000)
    slam = MonteCarloSlam(SlamConfig.model_validate({"particles": 20, "seed": 1}))
    calls = []
    real = slam.floor_guard.prune_plan
    slam.floor_guard.prune_plan = lambda *a: calls.append(len(slam.frames)) or real(*a)
    weighs = []
    real_weigh = slam.particles.weigh
    slam.particles.weigh = lambda n, cfg, *a, local_weight: weighs.append(
        cfg.local_weight if local_weight is None else local_weight) or real_weigh(
        n, cfg, *a, local_weight=local_weight)
    states = []
    for k, cloud in enumerate([room] * 3 + [cab] * 3 + [room] * 3):
        frame = slam.step(cloud, None, k * 100_000_000)
        states.append((frame.elevator, slam.floor_guard.active))
    assert [e for e, _ in states] == [False] * 3 + [True] * 3 + [False] * 3
    assert [a for _, a in states] == [False] * 6 + [True] * 3
    assert calls == [6, 7, 8]  # the scored scans after the ride
    assert weighs == [0.0, 0.0, 1.0, 1.0, 1.0]  # scans 1, 2 and 6, 7, 8
    off = MonteCarloSlam(SlamConfig.model_validate({"particles": 20, "seed": 1,
                                                    "elevator": {"floor_guard": False}}))
    for k, cloud in enumerate([room] * 3 + [cab] * 3 + [room] * 2):
        off.step(cloud, None, k * 100_000_000)
    assert not off.floor_guard.active


def test_the_free_space_term_weighs_only_while_the_guard_holds_the_floors(ti_runtime):
    """`elevator.free_space_cost`: the term costs nothing before and during a ride and
    applies from the first scored scan after it, while the floor guard is active."""
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    rng = np.random.default_rng(0)
    room = box_surface(rng, 6.0, -1.2, 1.8, 6000)
    cab = box_surface(rng, 1.1, -1.2, 1.2, 6000)
    slam = MonteCarloSlam(SlamConfig.model_validate(
        {"particles": 20, "seed": 1, "elevator": {"free_space_cost": 3.0}}))
    costs = []
    real = slam.particles.weigh
    slam.particles.weigh = lambda n, cfg, fs, cost, **kw: costs.append(cost) or real(
        n, cfg, fs, cost, **kw)
    for k, cloud in enumerate([room] * 3 + [cab] * 3 + [room] * 3):
        slam.step(cloud, None, k * 100_000_000)
    assert slam.free_space is not None
    assert costs == [0.0, 0.0, 3.0, 3.0, 3.0]  # scans 1-2 before the ride, 6-8 after it


def test_loops_the_representative_takes_are_registered_and_hold_in_the_written_map(ti_runtime):
    """A lidar seeing 4 m circles a room 1.2 times: the loops the representative takes become
    keyframe-to-keyframe edges (the scan's registration and the odometry from its keyframe:
    within 3 cm and 0.3° of the truth; in this box of look-alike walls some registrations
    slide off the filter's estimate and are dropped), and the written keyframes hold every
    registered loop within 2 cm."""
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    world = room_cloud(np.random.default_rng(0))
    n = 50

    def truth(i: int) -> np.ndarray:
        a = 2 * np.pi * 1.2 * i / n
        return geometry.se3(geometry.rpy_to_rot(0, 0, a + np.pi / 2),
                            [2.0 * np.cos(a), 1.5 * np.sin(a), 1.2])

    cfg = SlamConfig.model_validate({
        "particles": 50, "seed": 1, "loop_closure": {"min_travel_m": 4.0},
        "keyframes": {"overlap": 0.9}, "odometry": {"use_imu": False, "max_range_m": 4.0}})
    slam = MonteCarloSlam(cfg)
    for i in range(n):
        slam.step(geometry.transform_points(geometry.se3_inverse(truth(i)), world), None,
                  int(1e9 + i * 1e8))
    edges = slam.map_loop_edges()
    assert len(edges) >= 2
    kf_scans = slam.keyframe_frames
    written = slam._keyframe_poses_by_number()
    for e in edges:
        true_rel = geometry.se3_inverse(truth(kf_scans[e.target])) @ truth(kf_scans[e.source])
        off = geometry.se3_inverse(true_rel) @ e.T_target_source
        assert np.linalg.norm(off[:3, 3]) < 0.03
        assert geometry.rotation_angle(off[:3, :3]) < np.radians(0.3)
        held = geometry.se3_inverse(e.T_target_source) @ geometry.se3_inverse(
            written[e.target]) @ written[e.source]
        assert np.linalg.norm(held[:3, 3]) < 0.02
