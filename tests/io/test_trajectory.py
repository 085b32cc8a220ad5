"""TUM/KITTI trajectory files and SE(3) interpolation: exact round trips, evo compatibility,
and one clear error naming file and line for every malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import TrajectoryError
from mcl3d.core.geometry import interpolate_se3, random_rotations, se3, so3_exp
from mcl3d.io.trajectory import (
    Trajectory,
    detect_format,
    read_kitti,
    read_trajectory,
    read_tum,
    write_kitti,
    write_tum,
)


def _random_trajectory(n: int = 300, seed: int = 0) -> Trajectory:
    """A trajectory with epoch stamps, irregular spacing and arbitrary orientations."""
    rng = np.random.default_rng(seed)
    stamps = 1_700_000_000.0 + np.cumsum(rng.uniform(0.05, 0.15, n))
    positions = np.cumsum(rng.normal(0.0, 0.5, (n, 3)), axis=0) + np.array([1234.5, -87.25, 3.0])
    return Trajectory(stamps, se3(random_rotations(rng, n), positions))


def _rotation_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a[:, :3, :3] - b[:, :3, :3]).max())


def test_tum_round_trip_is_exact_to_written_precision(tmp_path):
    traj = _random_trajectory()
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    back = read_tum(path)
    assert len(back) == len(traj)
    np.testing.assert_allclose(back.stamps_s, traj.stamps_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.positions(), traj.positions(), rtol=0, atol=6e-10)
    assert _rotation_diff(back.poses, traj.poses) < 1e-8
    write_tum(tmp_path / "again.tum", back)
    again = read_tum(tmp_path / "again.tum")
    np.testing.assert_array_equal(again.stamps_s, back.stamps_s)
    np.testing.assert_array_equal(again.positions(), back.positions())
    assert _rotation_diff(again.poses, back.poses) < 3e-9


def test_tum_rows_are_eight_columns_with_ns_stamps(tmp_path):
    path = tmp_path / "traj.tum"
    write_tum(path, _random_trajectory(20))
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#")
    for line in lines[1:]:
        columns = line.split(" ")
        assert len(columns) == 8 and line == line.strip()
        assert len(columns[0].split(".")[1]) == 9


def test_kitti_round_trip_and_given_stamps(tmp_path):
    traj = _random_trajectory(50, seed=3)
    path = tmp_path / "poses.txt"
    write_kitti(path, traj)
    back = read_kitti(path)
    np.testing.assert_array_equal(back.stamps_s, np.arange(50.0))
    np.testing.assert_allclose(back.poses, traj.poses, rtol=0, atol=6e-10)
    stamped = read_kitti(path, stamps_s=traj.stamps_s)
    np.testing.assert_array_equal(stamped.stamps_s, traj.stamps_s)
    with pytest.raises(TrajectoryError, match="has 50 poses but 3 stamps"):
        read_kitti(path, stamps_s=[0.0, 1.0, 2.0])


def test_files_we_write_load_in_evo_unchanged(tmp_path):
    pytest.importorskip("evo")
    from evo.tools import file_interface

    traj = _random_trajectory(100, seed=5)
    write_tum(tmp_path / "t.tum", traj)
    write_kitti(tmp_path / "k.txt", traj)
    evo_tum = file_interface.read_tum_trajectory_file(str(tmp_path / "t.tum"))
    evo_kitti = file_interface.read_kitti_poses_file(str(tmp_path / "k.txt"))
    np.testing.assert_allclose(evo_tum.timestamps, traj.stamps_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.array(evo_tum.poses_se3), traj.poses, rtol=0, atol=1e-8)
    np.testing.assert_allclose(np.array(evo_kitti.poses_se3), traj.poses, rtol=0, atol=1e-9)


def test_real_ouster_kitti_poses(shared_data):
    """Ouster SDK odometry poses, BSD-3-Clause (ouster-lidar/ouster-sdk)."""
    path = shared_data / "ouster_os1_128_lb_n3" / "OS-1-128_v2.3.0_1024x10_lb_n3_poses_kitti.txt"
    assert detect_format(path) == "kitti"
    traj = read_trajectory(path)
    assert len(traj) == 3
    np.testing.assert_allclose(traj.poses[0], np.eye(4))
    np.testing.assert_allclose(traj.positions()[1], [0.2454105, -0.0068616, 0.0084499], atol=1e-6)
    assert traj.path_length_m() == pytest.approx(0.2455 + 0.2531, abs=2e-3)


def test_read_trajectory_detects_the_format(tmp_path):
    traj = _random_trajectory(10)
    write_tum(tmp_path / "a.txt", traj)
    write_kitti(tmp_path / "b.txt", traj)
    assert detect_format(tmp_path / "a.txt") == "tum"
    assert detect_format(tmp_path / "b.txt") == "kitti"
    np.testing.assert_allclose(read_trajectory(tmp_path / "a.txt").poses, traj.poses, atol=1e-8)
    np.testing.assert_allclose(read_trajectory(tmp_path / "b.txt", "kitti").poses, traj.poses,
                               atol=1e-8)
    (tmp_path / "c.txt").write_text("1 2 3 4 5 6 7 8 9 10\n")
    with pytest.raises(TrajectoryError, match=r"c\.txt: line 1 has 10 columns.*8.*12"):
        read_trajectory(tmp_path / "c.txt")
    with pytest.raises(TrajectoryError, match="unknown trajectory format 'csv'"):
        read_trajectory(tmp_path / "a.txt", "csv")


def test_comments_and_blank_lines_are_skipped(tmp_path):
    path = tmp_path / "t.tum"
    path.write_text("# t x y z qx qy qz qw\n\n0.0 1 2 3 0 0 0 1\n   \n# x\n0.1 1 2 3 0 0 0 1\n")
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.stamps_s, [0.0, 0.1])


GOOD = "0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n"


@pytest.mark.parametrize(("text", "message"), [
    ("# header\n\n0.2 1 2 3 0 0 1\n",
     r"bad\.tum: line 3 has 7 columns, TUM needs 8: t x y z qx qy qz qw$"),
    (GOOD + "0.2 1 2 3 0 0 0 1 5\n", r"line 3 has 9 columns, TUM needs 8"),
    ("0.0,1,2,3,0,0,0,1\n", r"line 1 has 1 column, .*separated by spaces, not commas"),
    (GOOD + "0.2 1 2 three 0 0 0 1\n", r"line 3: 'three' is not a number"),
    (GOOD + "0.2 1 nan 3 0 0 0 1\n", r"line 3 contains NaN or inf"),
    (GOOD + "0.1 1 2 3 0 0 0 1\n", r"line 3 has stamp 0\.100000000 s, not after .*increasing"),
    (GOOD + "0.2 1 2 3 0 0 0 0\n", r"line 3 has a quaternion of norm 0, not 1"),
    ("# only a comment\n\n", r"bad\.tum: contains no poses"),
])
def test_malformed_tum_names_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=message) as info:
        read_tum(path)
    assert "\n" not in str(info.value)


def test_malformed_kitti_and_missing_or_binary_files(tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt: line 2 is not a rigid pose"):
        read_kitti(bad)
    with pytest.raises(TrajectoryError, match=r"nothere\.tum: trajectory file not found"):
        read_trajectory(tmp_path / "nothere.tum")
    binary = tmp_path / "cloud.bin"
    binary.write_bytes(np.random.default_rng(0).bytes(256) + b"\xff\xfe")
    with pytest.raises(TrajectoryError, match=r"cloud\.bin: is not a text trajectory file"):
        read_trajectory(binary)


def test_trajectory_validates_stamps_and_shapes():
    eye = np.repeat(np.eye(4)[None], 3, axis=0)
    with pytest.raises(TrajectoryError, match=r"stamp 2 \(1\.000000000 s\) does not come after"):
        Trajectory(np.array([0.0, 1.0, 1.0]), eye)
    with pytest.raises(TrajectoryError, match=r"shape \(N,\).*\(N, 4, 4\)"):
        Trajectory(np.array([0.0, 1.0]), eye)
    with pytest.raises(TrajectoryError, match="NaN"):
        Trajectory(np.array([0.0, np.nan, 2.0]), eye)


def test_interpolation_is_exact_at_knots_and_follows_a_screw_between():
    """Constant yaw rate and constant velocity: slerp + lerp reproduce it exactly."""
    stamps = np.array([10.0, 10.5, 11.25, 12.0])
    yaw_rate, velocity = 0.4, np.array([2.0, -1.0, 0.3])

    def pose(t):
        return se3(so3_exp(np.array([0.0, 0.0, yaw_rate * t])), velocity * t)

    traj = Trajectory(stamps, np.stack([pose(t) for t in stamps]))
    np.testing.assert_allclose(traj.interpolate(stamps).poses, traj.poses, atol=1e-12)
    query = np.array([10.0, 10.1, 10.77, 11.9, 12.0])
    got = traj.interpolate(query)
    np.testing.assert_array_equal(got.stamps_s, query)
    np.testing.assert_allclose(got.poses, np.stack([pose(t) for t in query]), atol=1e-12)
    unsorted = traj.interpolate_poses([11.9, 10.1, 10.1])
    np.testing.assert_allclose(unsorted[1], unsorted[2])
    np.testing.assert_allclose(unsorted[0], interpolate_se3(traj.poses[2], traj.poses[3],
                                                            (11.9 - 11.25) / 0.75), atol=1e-12)


def test_interpolation_names_the_first_stamp_outside():
    traj = _random_trajectory(5)
    t0, t1 = traj.stamps_s[0], traj.stamps_s[-1]
    with pytest.raises(TrajectoryError, match=rf"stamp {t1 + 0.5:.9f} s \(index 1\) is outside"):
        traj.interpolate([t0, t1 + 0.5, t1 + 1.0])
    with pytest.raises(TrajectoryError, match="index 0"):
        traj.interpolate_poses([t0 - 1e-6])


def test_positions_and_path_length():
    stamps = np.arange(4.0)
    poses = se3(np.repeat(np.eye(3)[None], 4, axis=0),
                np.array([[0, 0, 0], [3, 4, 0], [3, 4, 12], [3, 4, 12]], dtype=float))
    traj = Trajectory(stamps, poses)
    assert traj.path_length_m() == pytest.approx(17.0)
    np.testing.assert_array_equal(traj.positions()[2], [3, 4, 12])
    assert len(traj) == 4


def test_tum_stamps_are_exact_integer_ns(tmp_path):
    """Stamps parse from their decimal text into ns exactly, and ns stamps are written back
    exactly (a float second at 1.3e9 s is only good to ~0.2 us)."""
    path = tmp_path / "t.tum"
    path.write_text("1317000015.2 0 0 0 0 0 0 1\n1317000015.300000000 1 0 0 0 0 0 1\n")
    traj = read_tum(path)
    assert traj.stamps_ns.tolist() == [1_317_000_015_200_000_000, 1_317_000_015_300_000_000]
    assert traj.range_ns() == (1_317_000_015_200_000_000, 1_317_000_015_300_000_000)
    assert traj.stamps_s[-1] == 1317000015.3
    write_tum(tmp_path / "out.tum", Trajectory.from_ns(traj.stamps_ns, traj.poses))
    rows = (tmp_path / "out.tum").read_text().splitlines()[1:]
    assert [r.split()[0] for r in rows] == ["1317000015.200000000", "1317000015.300000000"]
    assert read_tum(tmp_path / "out.tum").stamps_ns.tolist() == traj.stamps_ns.tolist()
