"""ATE/RPE, association and Umeyama alignment: equal to evo 1.38 on the same files, and exact
on constructed cases (a known Sim(3) is recovered)."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError, TrajectoryError
from mcl3d.core.geometry import se3, so3_exp
from mcl3d.evaluation.metrics import align, associate, evaluate, read_pair, rpe, umeyama
from mcl3d.io.trajectory import Trajectory, read_tum, write_kitti, write_tum


def drive(n: int = 400, rate_hz: float = 10.0, seed: int = 0) -> Trajectory:
    """A car-like ground truth: varying speed and yaw rate, small roll/pitch, hills."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    dt = 1.0 / rate_hz
    speed = 3.0 + 1.5 * np.sin(2 * np.pi * k / 150)
    yaw = np.cumsum((0.25 * np.sin(2 * np.pi * k / 130) + 0.02 * rng.standard_normal(n)) * dt)
    zero = np.zeros(n)
    R = (so3_exp(np.column_stack([zero, zero, yaw]))
         @ so3_exp(np.column_stack([zero, 0.03 * np.sin(2 * np.pi * k / 70), zero]))
         @ so3_exp(np.column_stack([0.02 * np.sin(2 * np.pi * k / 45), zero, zero])))
    xy = np.cumsum(np.column_stack([speed * np.cos(yaw), speed * np.sin(yaw)]) * dt, axis=0)
    z = 0.8 * np.sin(2 * np.pi * k / 200)
    return Trajectory(1_700_000_000.0 + k * dt, se3(R, np.column_stack([xy, z])))


def noisy_estimate(ref: Trajectory, seed: int = 1, scale: float = 0.9,
                   T_est_ref: np.ndarray | None = None) -> Trajectory:
    """An odometry-like estimate: drift + noise, another frame and scale, stamps 4±1 ms late,
    a later start and a few dropped poses."""
    rng = np.random.default_rng(seed)
    n = len(ref)
    poses = ref.poses.copy()
    poses[:, :3, :3] = poses[:, :3, :3] @ so3_exp(rng.normal(0.0, np.deg2rad(0.5), (n, 3)))
    poses[:, :3, 3] += (np.cumsum(rng.normal(0.0, 0.01, (n, 3)), axis=0)
                        + rng.normal(0.0, 0.03, (n, 3)))
    poses[:, :3, 3] *= scale
    if T_est_ref is None:
        T_est_ref = se3(so3_exp(np.array([0.1, -0.05, 0.7])), np.array([5.0, -3.0, 1.0]))
    poses = T_est_ref @ poses
    stamps = ref.stamps_s + 0.004 + rng.uniform(-0.001, 0.001, n)
    keep = np.ones(n, dtype=bool)
    keep[rng.choice(n, 7, replace=False)] = False
    keep[:12] = False
    return Trajectory(stamps[keep], poses[keep])


def drop_some(traj: Trajectory, count: int, seed: int) -> Trajectory:
    keep = np.ones(len(traj), dtype=bool)
    keep[np.random.default_rng(seed).choice(len(traj), count, replace=False)] = False
    return Trajectory(traj.stamps_s[keep], traj.poses[keep])


@pytest.fixture(scope="module")
def tum_pair(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pair")
    ref = drive()
    write_tum(folder / "ref.tum", drop_some(ref, 5, seed=2))
    write_tum(folder / "est.tum", noisy_estimate(ref))
    return folder / "ref.tum", folder / "est.tum"


def evo_statistics(ref_path, est_path, alignment, delta, unit, all_pairs, max_diff=0.01):
    """The same evaluation through evo's Python API, as `evo_ape`/`evo_rpe` run it."""
    pytest.importorskip("evo")
    from evo.core import metrics, sync
    from evo.core.units import Unit
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    scale = 1.0
    if alignment in ("se3", "sim3"):
        scale = est.align(ref, correct_scale=alignment == "sim3")[2]
    elif alignment == "origin":
        est.align_origin(ref)
    relation = metrics.PoseRelation
    delta_unit = Unit.meters if unit == "m" else Unit.frames
    out = {"associated": ref.num_poses, "scale": scale}
    for name, metric in (
        ("ate_t", metrics.APE(relation.translation_part)),
        ("ate_r", metrics.APE(relation.rotation_angle_deg)),
        ("rpe_t", metrics.RPE(relation.translation_part, delta, delta_unit, all_pairs=all_pairs)),
        ("rpe_r", metrics.RPE(relation.rotation_angle_deg, delta, delta_unit,
                              all_pairs=all_pairs)),
    ):
        metric.process_data((ref, est))
        out[name] = (metric.get_all_statistics(), metric.error)
    return out


def assert_same_as_evo(ours, theirs):
    assert len(ours.association) == theirs["associated"]
    assert ours.alignment.scale == pytest.approx(theirs["scale"], rel=1e-9)
    for name, errors in (("ate_t", ours.ate.translation_errors_m),
                         ("ate_r", ours.ate.rotation_errors_deg),
                         ("rpe_t", ours.rpe.translation_errors_m),
                         ("rpe_r", ours.rpe.rotation_errors_deg)):
        stats, evo_errors = theirs[name]
        np.testing.assert_allclose(errors, evo_errors, rtol=1e-6, atol=1e-9, err_msg=name)
        part = ours.ate if name.startswith("ate") else ours.rpe
        mine = (part.translation_m if name.endswith("_t") else part.rotation_deg).as_dict()
        for key, value in mine.items():
            assert value == pytest.approx(stats[key], rel=1e-6, abs=1e-9), (name, key)


@pytest.mark.parametrize(("alignment", "delta", "unit", "all_pairs"), [
    ("none", 1, "frames", False),
    ("se3", 2.0, "m", False),
    ("sim3", 5, "frames", False),
    ("origin", 1.0, "m", True),
    ("sim3", 3, "frames", True),
    ("se3", 10.0, "m", False),
])
def test_equals_evo(tum_pair, alignment, delta, unit, all_pairs):
    ref_path, est_path = tum_pair
    ours = evaluate(read_tum(ref_path), read_tum(est_path), alignment=alignment,
                    rpe_delta=delta, rpe_unit=unit, all_pairs=all_pairs)
    assert len(ours.association) > 350
    assert_same_as_evo(ours, evo_statistics(ref_path, est_path, alignment, delta, unit,
                                            all_pairs))


def _novatel_trajectory(path) -> Trajectory:
    """`<YYYY-MM-DD-hh-mm-ss-mmm> r11 r12 r13 tx r21 ... tz` INS poses at 10 Hz."""
    stamps, rows = [], []
    for line in path.read_text().split("\n"):
        if line.strip():
            stamp, *numbers = line.split()
            when = datetime.strptime(stamp[:19], "%Y-%m-%d-%H-%M-%S").replace(tzinfo=timezone.utc)
            stamps.append(when.timestamp() + int(stamp[20:]) / 1000.0)
            rows.append([float(v) for v in numbers])
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = np.array(rows).reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    return Trajectory(np.array(stamps), poses)


def test_equals_evo_on_a_real_ins_trajectory(shared_data, tmp_path):
    """108 s of NovAtel INS poses (PJLab-ADG/SensorsCalibration, Apache-2.0) as reference."""
    ref = _novatel_trajectory(shared_data / "pandar64_static" / "NovAtel-pose-lidar-time.txt")
    assert len(ref) == 1081 and 200.0 < ref.path_length_m() < 300.0
    write_tum(tmp_path / "ref.tum", ref)
    write_tum(tmp_path / "est.tum", noisy_estimate(ref, seed=7, scale=1.0))
    for alignment, delta, unit in (("se3", 10.0, "m"), ("sim3", 10, "frames")):
        ours = evaluate(read_tum(tmp_path / "ref.tum"), read_tum(tmp_path / "est.tum"),
                        alignment=alignment, rpe_delta=delta, rpe_unit=unit)
        assert_same_as_evo(ours, evo_statistics(tmp_path / "ref.tum", tmp_path / "est.tum",
                                                alignment, delta, unit, False))


def test_sim3_alignment_recovers_a_known_transform():
    ref = drive(300, seed=4)
    T_est_ref = se3(so3_exp(np.array([0.3, -0.2, 2.0])), np.array([-40.0, 12.0, 3.5]))
    est_poses = ref.poses.copy()
    est_poses[:, :3, 3] *= 0.8
    est = Trajectory(ref.stamps_s, T_est_ref @ est_poses)
    result = evaluate(ref, est, alignment="sim3")
    assert result.alignment.scale == pytest.approx(1.25, rel=1e-12)
    T_ref_est = np.linalg.inv(T_est_ref)
    T_ref_est[:3, 3] *= 1.25
    np.testing.assert_allclose(result.alignment.T_ref_est, T_ref_est, atol=1e-9)
    assert result.ate.translation_m.max < 1e-9
    assert result.ate.rotation_deg.max < 1e-6
    assert result.rpe.translation_m.max < 1e-9
    rigid = evaluate(ref, est, alignment="se3")
    assert rigid.alignment.scale == 1.0 and rigid.ate.translation_m.rmse > 1.0


def test_umeyama_matches_a_known_rigid_motion_with_noise():
    rng = np.random.default_rng(3)
    src = rng.uniform(-20.0, 20.0, (500, 3))
    R = so3_exp(np.array([0.4, 0.1, -1.2]))
    dst = src @ R.T + np.array([1.0, 2.0, 3.0]) + rng.normal(0.0, 0.01, (500, 3))
    R_fit, t_fit, s = umeyama(src, dst, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(R_fit, R, atol=1e-3)
    np.testing.assert_allclose(t_fit, [1.0, 2.0, 3.0], atol=3e-3)
    assert np.linalg.det(R_fit) == pytest.approx(1.0)


def test_origin_alignment_makes_first_poses_coincide():
    ref = drive(100)
    est = noisy_estimate(ref)
    result = evaluate(ref, est, alignment="origin")
    np.testing.assert_allclose(result.est_aligned_poses[0], result.association.ref_poses[0],
                               atol=1e-9)
    assert result.ate.translation_errors_m[0] < 1e-9


def test_association_takes_the_nearest_stamp_within_max_diff():
    ref = Trajectory(np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0]), np.repeat(np.eye(4)[None], 6, 0))
    est = Trajectory(np.array([0.995, 2.02, 2.991, 4.5, 5.006]), np.repeat(np.eye(4)[None], 5, 0))
    pairs = associate(ref, est, max_diff_s=0.01)
    np.testing.assert_array_equal(pairs.est_indices, [0, 2, 4])
    np.testing.assert_array_equal(pairs.ref_indices, [1, 3, 5])
    assert len(associate(ref, est, max_diff_s=0.5)) == 5
    tie = Trajectory(np.array([1.5]), np.eye(4)[None])
    np.testing.assert_array_equal(associate(ref, tie, max_diff_s=0.5).ref_indices, [1])


def test_association_equals_evo_on_random_stamps():
    pytest.importorskip("evo")
    from evo.core.sync import matching_time_indices

    rng = np.random.default_rng(9)
    for _ in range(20):
        a = np.sort(rng.choice(2000, 300, replace=False)) * 0.01 + rng.uniform(-0.004, 0.004, 300)
        b = np.sort(rng.choice(2000, 500, replace=False)) * 0.01
        a = np.unique(a)
        ours = associate(Trajectory(b, np.repeat(np.eye(4)[None], b.size, 0)),
                         Trajectory(a, np.repeat(np.eye(4)[None], a.size, 0)), max_diff_s=0.005)
        theirs = matching_time_indices(a, b, max_diff=0.005)
        np.testing.assert_array_equal(ours.est_indices, theirs[0])
        np.testing.assert_array_equal(ours.ref_indices, theirs[1])


def test_no_overlapping_stamps_says_so():
    ref = drive(50)
    est = Trajectory(ref.stamps_s + 100.0, ref.poses)
    with pytest.raises(TrajectoryError, match=r"no stamps of est\.tum .*larger difference"):
        evaluate(ref, est, ref_name="ref.tum", est_name="est.tum")


def test_umeyama_needs_three_poses_that_are_not_on_a_line():
    ref = drive(50)
    with pytest.raises(TrajectoryError, match="at least 3 associated poses, got 2"):
        align(ref.poses[:2], ref.poses[:2], "se3")
    line = se3(np.repeat(np.eye(3)[None], 10, 0), np.outer(np.arange(10.0), [1.0, 2.0, 0.0]))
    with pytest.raises(TrajectoryError, match=r"one line or point.*origin"):
        align(line, line, "sim3")
    with pytest.raises(ConfigError, match="unknown alignment 'affine'"):
        align(line, line, "affine")


def test_rpe_rejects_impossible_deltas_and_empty_pair_lists():
    ref = drive(30)
    poses, stamps = ref.poses, ref.stamps_s
    with pytest.raises(ConfigError, match="whole number >= 1"):
        rpe(poses, poses, stamps, delta=1.5, unit="frames")
    with pytest.raises(ConfigError, match="must be > 0"):
        rpe(poses, poses, stamps, delta=0.0, unit="m")
    with pytest.raises(ConfigError, match="unknown RPE delta unit 's'"):
        rpe(poses, poses, stamps, delta=1.0, unit="s")
    with pytest.raises(TrajectoryError, match=r"RPE delta 500 m gives no pose pairs.*smaller"):
        rpe(poses, poses, stamps, delta=500.0, unit="m")


def test_rpe_sees_a_constant_velocity_scale_error():
    """An estimate moving 10 % too far per step has RPE = 10 % of the step length."""
    n = 50
    stamps = np.arange(n) * 0.1
    ref_poses = se3(np.repeat(np.eye(3)[None], n, 0), np.outer(np.arange(n), [1.0, 0.0, 0.0]))
    est_poses = ref_poses.copy()
    est_poses[:, :3, 3] *= 1.1
    result = rpe(ref_poses, est_poses, stamps, delta=2, unit="frames")
    np.testing.assert_allclose(result.translation_errors_m, 0.2, atol=1e-12)
    assert result.pairs.shape == (24, 2)
    assert result.rotation_deg.max == 0.0


def test_read_pair_refuses_mixed_and_unequal_kitti(tmp_path):
    ref = drive(20)
    write_tum(tmp_path / "ref.tum", ref)
    write_kitti(tmp_path / "est.kitti", ref)
    write_kitti(tmp_path / "short.kitti", Trajectory(ref.stamps_s[:5], ref.poses[:5]))
    with pytest.raises(TrajectoryError, match=r"est\.kitti is a KITTI file \(no stamps\)"):
        read_pair(tmp_path / "ref.tum", tmp_path / "est.kitti")
    with pytest.raises(TrajectoryError, match=r"paired by line.*5 poses.*20"):
        read_pair(tmp_path / "est.kitti", tmp_path / "short.kitti")
    a, b = read_pair(tmp_path / "est.kitti", tmp_path / "est.kitti")
    assert len(evaluate(a, b).association) == 20
