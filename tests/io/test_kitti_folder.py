"""KITTI odometry sequence folders as logs: a tiny folder written here (scans ray-cast in the
test room), read through LogReader and compared with an independent numpy decode; `mcl3d info`
and `mcl3d odometry` on it end to end; broken folders fail with one line and write nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from support import localize_world as world

from mcl3d.core import geometry
from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs.kitti_folder import GT_TOPIC, POINTS_TOPIC
from mcl3d.io.logs.reader import LogReader

N_SCANS = 5
# velodyne -> camera 0 of KITTI sequence 00 (calib.txt Tr), rounded
TR = np.array([[4.28e-04, -9.999967e-01, -8.084492e-03, -1.198459e-02],
               [-7.210626e-03, 8.081198e-03, -9.999413e-01, -5.403984e-02],
               [9.999738e-01, 4.859485e-04, -7.206933e-03, -2.921968e-01]])


def write_folder(folder, n_scans: int = N_SCANS):
    """A sequence folder `folder` with scans, times, calib and poses/<name>.txt; returns the
    true lidar poses (T_map_lidar, the first one the identity, as in KITTI)."""
    scanner = world.Scanner(n_azimuth=30, noise_m=0.0)
    lidar_path = world.path(n_scans, step_m=0.1)
    T_map_lidar = geometry.se3_inverse(lidar_path[0]) @ lidar_path
    (folder / "velodyne").mkdir(parents=True)
    for k in range(n_scans):
        xyz = scanner.scan(lidar_path[k])
        reflectance = np.linspace(0.0, 1.0, len(xyz), dtype=np.float32)[:, None]
        np.hstack([xyz, reflectance]).astype("<f4").tofile(folder / "velodyne" / f"{k:06d}.bin")
    (folder / "times.txt").write_text("".join(f"{0.1037 * k:.6e}\n" for k in range(n_scans)))
    T_cam_velo = np.vstack([TR, [0, 0, 0, 1]])
    P0 = " ".join(f"{v:.6e}" for v in np.eye(4)[:3].ravel())
    (folder / "calib.txt").write_text(f"P0: {P0}\nTr: {' '.join(f'{v:.6e}' for v in TR.ravel())}\n")
    camera = T_cam_velo @ T_map_lidar @ np.linalg.inv(T_cam_velo)
    (folder / "poses").mkdir()
    (folder / "poses" / f"{folder.name}.txt").write_text(
        "".join(" ".join(f"{v:.12e}" for v in P[:3].ravel()) + "\n" for P in camera))
    return T_map_lidar


def numpy_decode(folder):
    """Points, stamps and lidar poses straight from the files (the KITTI definitions)."""
    times = np.loadtxt(folder / "times.txt", ndmin=1)
    stamps = np.rint(times * 1e9).astype(np.int64)
    scans = [np.fromfile(folder / "velodyne" / f"{k:06d}.bin", dtype=np.float32).reshape(-1, 4)
             for k in range(len(times))]
    calib = dict(line.split(":", 1) for line in (folder / "calib.txt").read_text().splitlines())
    Tr = np.vstack([np.array(calib["Tr"].split(), float).reshape(3, 4), [0, 0, 0, 1]])
    rows = np.loadtxt(folder / "poses" / f"{folder.name}.txt", ndmin=2)
    P = np.tile(np.eye(4), (len(rows), 1, 1))
    P[:, :3, :] = rows.reshape(-1, 3, 4)
    return scans, stamps, np.linalg.inv(Tr) @ P @ Tr


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("kitti") / "07"
    truth = write_folder(folder)
    return folder, truth


def mcl3d(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], capture_output=True,
                          text=True, env={"COLUMNS": "200", "PATH": ""}, timeout=300)


def test_reader_matches_numpy_decode(folder):
    path, truth = folder
    scans, stamps, poses = numpy_decode(path)
    with LogReader(path) as reader:
        assert reader.topics.points == POINTS_TOPIC and reader.topics.gt == GT_TOPIC
        assert reader.count("points") == N_SCANS
        clouds = list(reader.scans())
        gt_stamps, gt_poses = reader.ground_truth()
    assert [c.stamp_ns for c in clouds] == stamps.tolist() == gt_stamps.tolist()
    assert stamps[1] == 103_700_000
    for cloud, raw in zip(clouds, scans, strict=True):
        assert cloud.frame_id == "velodyne" and cloud.times_s is None
        assert len(raw) >= 200 and np.array_equal(cloud.points, raw[:, :3])
        assert np.array_equal(cloud.fields["intensity"], raw[:, 3])
    np.testing.assert_allclose(gt_poses, poses, atol=1e-6)
    np.testing.assert_allclose(gt_poses, truth, atol=1e-6)  # Tr^-1 P Tr is the lidar pose
    np.testing.assert_allclose(gt_poses[0], np.eye(4), atol=1e-9)


def test_poses_beside_the_folder_and_without_poses(tmp_path):
    path = tmp_path / "sequences" / "03"
    truth = write_folder(path, n_scans=2)
    (tmp_path / "poses").mkdir()
    (path / "poses" / "03.txt").rename(tmp_path / "poses" / "03.txt")  # the dataset layout
    with LogReader(path) as reader:
        np.testing.assert_allclose(reader.ground_truth()[1], truth, atol=1e-6)
    (tmp_path / "poses" / "03.txt").unlink()
    with LogReader(path) as reader:
        assert list(reader.all_topics) == [POINTS_TOPIC] and reader.topics.gt is None


def test_info_and_odometry_end_to_end(folder, tmp_path):
    path, _truth = folder
    info = mcl3d("info", path, "--json")
    assert info.returncode == 0, info.stderr
    doc = json.loads(info.stdout)
    assert doc["format"] == "KITTI odometry folder"
    topics = {t["name"]: t for t in doc["topics"]}
    assert topics[POINTS_TOPIC]["count"] == N_SCANS and topics[GT_TOPIC]["count"] == N_SCANS
    assert topics[POINTS_TOPIC]["frame_ids"] == ["velodyne"]
    assert doc["selection"]["gt"]["topic"] == GT_TOPIC
    assert doc["start_ns"] == 0 and doc["end_ns"] == 4 * 103_700_000
    table = mcl3d("info", path)
    assert table.returncode == 0 and POINTS_TOPIC in table.stdout, table.stderr
    run = mcl3d("odometry", path, "-o", tmp_path / "odo")
    assert run.returncode == 0, run.stderr
    tum = (tmp_path / "odo" / "odometry.tum").read_text().splitlines()
    rows = [line for line in tum if line and not line.startswith("#")]
    assert len(rows) == N_SCANS


def _missing_scan(path):
    (path / "velodyne" / "000002.bin").unlink()


def _extra_scan(path):
    times = path / "times.txt"
    times.write_text("".join(times.read_text().splitlines(keepends=True)[:4]))


def _no_times(path):
    (path / "times.txt").unlink()


def _torn_scan(path):
    with open(path / "velodyne" / "000003.bin", "ab") as f:
        f.write(b"\0" * 6)


def _short_poses(path):
    poses = path / "poses" / f"{path.name}.txt"
    poses.write_text("".join(poses.read_text().splitlines(keepends=True)[:3]))


@pytest.mark.parametrize(("breakage", "named", "words"), [
    (_missing_scan, "velodyne/000002.bin", "missing"),
    (_extra_scan, "velodyne", "times.txt has 4"),
    (_no_times, "07/times.txt", "missing"),
    (_torn_scan, "velodyne/000003.bin", "multiple of 16"),
    (_short_poses, "poses/07.txt", "3 poses"),
])
def test_broken_folder_fails_with_one_line(tmp_path, breakage, named, words):
    path = tmp_path / "07"
    write_folder(path)
    breakage(path)
    with pytest.raises(LogFormatError, match=words) as caught:
        LogReader(path)
    assert named in str(caught.value)
    if breakage is _missing_scan:  # the CLI: one line, exit 1, nothing written
        result = mcl3d("odometry", path, "-o", tmp_path / "out")
        assert result.returncode == 1, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:") and named in lines[0], lines
        assert not (tmp_path / "out").exists()
