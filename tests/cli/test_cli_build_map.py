"""End to end: `mcl3d build-map` from a mesh, a point cloud and a log; `mcl3d map-info`."""

import numpy as np
import pytest
from support import tsdf_world as world
from typer.testing import CliRunner

from mcl3d.cli import app

runner = CliRunner()
STAMP0_NS = 1_700_000_000_000_000_000


def _invoke(*args):
    return runner.invoke(app, ["--backend", "cpu", *map(str, args)])


def _failed(result) -> str:
    """The error of a failed command: a typed Mcl3dError, as the app prints it in one line
    (the message, then the flag of the setting that fixes it)."""
    from mcl3d.cli import _with_flag
    from mcl3d.core.errors import Mcl3dError

    assert result.exit_code == 1, result.output
    assert isinstance(result.exception, Mcl3dError), repr(result.exception)
    return _with_flag(result.exception)


@pytest.fixture(scope="module")
def room_files(tmp_path_factory):
    import open3d as o3d

    d = tmp_path_factory.mktemp("room")
    vertices, triangles = world.room_mesh()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices),
                                     o3d.utility.Vector3iVector(triangles))
    o3d.io.write_triangle_mesh(str(d / "room.ply"), mesh)
    scene = world.scene_of(vertices, triangles)
    scans = [world.scan(scene, T)[1] for T in world.POSES]
    world_pts = np.concatenate([p @ T[:3, :3].T + T[:3, 3]
                                for p, T in zip(scans, world.POSES, strict=True)])
    o3d.io.write_point_cloud(str(d / "cloud.pcd"),
                             o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world_pts)))
    return d, scans


def _write_log(path, scans, poses, stamps_ns, empty=False):
    from mcl3d.io.logs.messages import PointCloud, PoseStamped
    from mcl3d.io.logs.writer import LogWriter

    with LogWriter(path) as w:
        for pts, T, stamp in zip(scans, poses, stamps_ns, strict=True):
            pts = pts[:0] if empty else pts
            times = np.linspace(0, 0.05, len(pts)).astype(np.float32)
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", T))
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, times))
        w.write_pose("/ground_truth", PoseStamped(stamps_ns[-1] + 100_000_000, "map", poses[-1]))


def test_build_from_mesh_then_map_info_and_exports(ti_runtime, room_files, tmp_path):
    d, _ = room_files
    out = tmp_path / "room.tsdf"
    result = _invoke("build-map", d / "room.ply", "-o", out, "--export-mesh",
                     tmp_path / "surface.ply")
    assert result.exit_code == 0, result.output
    assert "Map built" in result.output and "mesh" in result.output
    assert out.is_file() and (tmp_path / "surface.ply").is_file()
    info = _invoke("map-info", out, "--export-points", tmp_path / "pts.pcd")
    assert info.exit_code == 0, info.output
    assert "mcl3d-tsdf v1" in info.output and '"kind": "mesh"' in info.output
    assert (tmp_path / "pts.pcd").stat().st_size > 1000
    again = _invoke("build-map", d / "room.ply", "-o", out)
    assert "(--force)" in _failed(again)


def test_build_from_point_cloud_with_f16(ti_runtime, room_files, tmp_path):
    from mcl3d.io.trajectory import Trajectory, write_tum
    from mcl3d.maps.map_file import read_header

    d, _ = room_files
    out = tmp_path / "cloud.tsdf"
    viewpoints = tmp_path / "viewpoints.tum"  # orient the normals towards the scanner
    write_tum(viewpoints, Trajectory(np.arange(3.0), np.stack(world.POSES)))
    result = _invoke("build-map", d / "cloud.pcd", "-o", out, "--f16", "--voxel-size", "0.1",
                     "--trajectory", viewpoints)
    assert result.exit_code == 0, result.output
    header = read_header(out)
    assert header["distance_dtype"] == "float16" and header["voxel_size_m"] == 0.1
    assert header["truncation_m"] == pytest.approx(0.4) and header["source"]["kind"] == "points"


def test_build_from_log_with_ground_truth_and_trajectory(ti_runtime, room_files, tmp_path):
    from mcl3d.io.trajectory import Trajectory, write_tum
    from mcl3d.maps.map_file import read_header

    _, scans = room_files
    stamps = [STAMP0_NS + i * 100_000_000 for i in range(3)]
    log = tmp_path / "room.mcap"
    _write_log(log, scans, world.POSES, stamps)
    out = tmp_path / "log.tsdf"
    result = _invoke("build-map", log, "-o", out)
    assert result.exit_code == 0, result.output
    assert "3 (" in result.output  # scans and scans/s in the summary
    header = read_header(out)
    assert header["source"]["scans"] == 3 and header["source"]["deskewed"] is True
    # an explicit trajectory that does not cover the log: clear error, nothing written
    short = tmp_path / "short.tum"
    write_tum(short, Trajectory(np.array(stamps[:2]) * 1e-9, np.stack(world.POSES[:2])))
    bad_out = tmp_path / "bad.tsdf"
    bad = _invoke("build-map", log, "-o", bad_out, "--trajectory", short)
    message = _failed(bad)
    assert "outside the trajectory" in message and "(--trajectory)" in message
    assert not bad_out.exists() and not list(tmp_path.glob(".bad.tsdf*"))


def test_pipeline_reports_every_scan_and_returns_typed_results(ti_runtime, room_files,
                                                               tmp_path):
    """The library contract: run(request, on_progress) -> BuildMapResult, one Progress per
    scan of a log."""
    from mcl3d.mapping.pipeline import BuildMapRequest, run

    _, scans = room_files
    log = tmp_path / "room.mcap"
    _write_log(log, scans, world.POSES, [STAMP0_NS + i * 100_000_000 for i in range(3)])
    reports = []
    result = run(BuildMapRequest(log, tmp_path / "lib.tsdf"), reports.append)
    assert [(p.done, p.total) for p in reports] == [(1, 3), (2, 3), (3, 3)]
    assert result.n_scans == 3 and result.source_kind == "log"
    assert result.stats.blocks > 0
    assert result.stats.file_bytes == (tmp_path / "lib.tsdf").stat().st_size
    assert result.exports.mesh_triangles is None


def test_too_small_a_capacity_names_the_flag(ti_runtime, room_files, tmp_path):
    d, _ = room_files
    result = _invoke("build-map", d / "room.ply", "-o", tmp_path / "m.tsdf",
                     "--capacity-blocks", "1")
    message = _failed(result)
    assert "more than max_capacity_blocks 1" in message and message.endswith("(--capacity-blocks)")


def test_bad_inputs_are_clear_errors(ti_runtime, room_files, tmp_path):
    _, scans = room_files
    stamps = [STAMP0_NS + i * 100_000_000 for i in range(3)]
    empty_log = tmp_path / "empty.mcap"
    _write_log(empty_log, scans, world.POSES, stamps, empty=True)
    result = _invoke("build-map", empty_log, "-o", tmp_path / "e.tsdf")
    assert "none of its 3 scans has points" in _failed(result)
    assert not (tmp_path / "e.tsdf").exists()
    empty_cloud = tmp_path / "empty.pcd"
    empty_cloud.write_text("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
                           "COUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 0\n"
                           "DATA ascii\n")
    result = _invoke("build-map", empty_cloud, "-o", tmp_path / "c.tsdf")
    assert "empty" in _failed(result)
    result = _invoke("build-map", tmp_path / "nothing.ply", "-o", tmp_path / "n.tsdf")
    assert "no such file" in _failed(result)
    broken = tmp_path / "broken.tsdf"
    broken.write_bytes(b"PK\x03\x04 not really a zip")
    result = _invoke("map-info", broken)
    assert "broken.tsdf" in _failed(result)
    result = _invoke("build-map", room_files[0] / "room.ply", "-o", tmp_path / "x.tsdf",
                     "--voxel-size", "-1")
    assert "voxel_size_m" in _failed(result)


def test_errors_are_one_red_line_and_exit_1(tmp_path):
    import subprocess
    import sys

    broken = tmp_path / "broken.tsdf"
    broken.write_text("hello")
    out = subprocess.run([sys.executable, "-m", "mcl3d", "map-info", str(broken)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert "error:" in out.stderr and "not an mcl3d map" in out.stderr
    assert "Traceback" not in out.stderr
