"""End to end: `mcl3d build-map` from a mesh, a point cloud and a log; `mcl3d map-info`."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
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
    assert "mcl3d-tsdf v2" in info.output and '"kind": "mesh"' in info.output
    assert (tmp_path / "pts.pcd").stat().st_size > 1000
    again = _invoke("build-map", d / "room.ply", "-o", out)
    assert "(--force)" in _failed(again)
    _map_info_json_agrees_with_the_file_and_the_table(out, info.stdout, tmp_path)


def _map_info_json_agrees_with_the_file_and_the_table(map_path, table, tmp_path):
    """`map-info --json` (run as a user runs it) prints one JSON document, nothing else on
    stdout, whose numbers match an independent read of the file (numpy alone) and the
    table's text."""
    import json
    import subprocess
    import sys

    import open3d as o3d

    result = subprocess.run([sys.executable, "-m", "mcl3d", "map-info", str(map_path), "--json",
                             "--export-mesh", str(tmp_path / "m.ply")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    doc = json.loads(result.stdout)
    with np.load(map_path) as npz:
        header = json.loads(str(npz["header"]))
        sdf, weight = npz["sdf"], npz["weight"]
        n_blocks, n_free = len(npz["block_coords"]), int(np.unpackbits(npz["free_masks"]).sum())
        tiles = {tuple(c) for c in np.concatenate([npz["block_coords"] >> 3, npz["free_tiles"]])}
    assert doc["schema"] == "mcl3d.map_info/1" and doc["path"] == str(map_path)
    assert (doc["format"], doc["format_version"]) == ("mcl3d-tsdf", 2)
    for key in ("mcl3d_version", "frame_id", "voxel_size_m", "truncation_m",
                "origin_m", "coarse_dims", "source", "build"):
        assert doc[key] == header[key], key
    # the header records inputs, not the clock (reproducible files): no date, no build time
    assert doc["created_utc"] is None and "seconds" not in header["build"]
    assert doc["precision"] == header["distance_dtype"] == "float32"
    assert doc["block_size_m"] == pytest.approx(8 * header["voxel_size_m"])
    hi = np.add(header["origin_m"], np.multiply(header["coarse_dims"], doc["block_size_m"]))
    assert doc["extent_lo_m"] == pytest.approx(header["origin_m"])
    assert doc["extent_hi_m"] == pytest.approx(hi) and doc["extent_size_m"] == pytest.approx(
        hi - header["origin_m"])
    cells = int(np.prod(header["coarse_dims"]))
    assert doc["blocks"] == {"allocated": n_blocks, "free": n_free,
                             "unknown_cells": cells - n_blocks - n_free}
    surface = (weight > 0) & (np.abs(sdf) < 0.5 * header["voxel_size_m"] * np.sqrt(3))
    assert doc["voxels"]["surface"] == int(surface.sum())
    assert doc["voxels"]["observed"] == int((weight > 0).sum()) + 512 * n_free
    memory = doc["memory"]
    assert memory["file_bytes"] == map_path.stat().st_size
    assert memory["pool_bytes"] == n_blocks * memory["bytes_per_block"]
    top = 8 * int(np.prod(-(-np.asarray(header["coarse_dims"]) // 8)))
    assert memory["tiles"] == len(tiles) and memory["coarse_top_bytes"] == top
    assert memory["coarse_bytes"] == top + memory["coarse_tile_bytes"]
    assert memory["coarse_tile_bytes"] == len(tiles) * (512 * 8 + 12)
    assert memory["dense_index_bytes"] == 8 * cells
    assert memory["loaded_bytes"] == memory["pool_bytes"] + memory["coarse_bytes"]
    triangles = len(o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).triangles)
    assert doc["exports"] == {"mesh": {"path": str(tmp_path / "m.ply"), "triangles": triangles},
                              "points": None}
    blocks = doc["blocks"]
    assert (f"{blocks['allocated']} allocated, {blocks['free']} free, "
            f"{blocks['unknown_cells']} unknown") in table
    assert f"{doc['voxels']['surface']} on the surface" in table
    assert f"({memory['bytes_per_block']} B/block)" in table


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


def test_trajectory_ending_exactly_at_the_last_scan_is_inside(ti_runtime, room_files, tmp_path):
    """Stamps compare as integer ns: a TUM pose at 1317000015.300000000 s covers the scan at
    1317000015300000000 ns (as floats they round to ...15.299999952 and ...15.300000191)."""
    from mcl3d.maps.map_file import read_header

    _, scans = room_files
    stamps = [1_317_000_015_100_000_000 + i * 100_000_000 for i in range(3)]
    log = tmp_path / "room.mcap"
    _write_log(log, scans, world.POSES, stamps)
    rows = [" ".join(f"{v:.9f}" for v in (*T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_quat()))
            for T in world.POSES]
    # exact stamps, and stamps written through float64 seconds (off by up to ~0.2 us)
    for name, stamp_text in (("exact", lambda ns: f"{ns // 10**9}.{ns % 10**9:09d}"),
                             ("float", lambda ns: f"{ns * 1e-9:.9f}")):
        traj = tmp_path / f"{name}.tum"
        traj.write_text("".join(f"{stamp_text(ns)} {row}\n"
                                for ns, row in zip(stamps, rows, strict=True)))
        out = tmp_path / f"{name}.tsdf"
        result = _invoke("build-map", log, "-o", out, "--trajectory", traj)
        assert result.exit_code == 0, result.output
        assert read_header(out)["source"]["scans"] == 3


def test_faults_in_the_log_are_dropped_counted_and_named(ti_runtime, room_files, tmp_path):
    """A scan published twice and a NaN ground-truth pose: the map is built from the rest,
    the header's source lists the faults and the CLI names each kind once."""
    from mcl3d.io.logs.messages import PointCloud, PoseStamped
    from mcl3d.io.logs.writer import LogWriter
    from mcl3d.maps.map_file import read_header

    _, scans = room_files
    log = tmp_path / "faults.mcap"
    with LogWriter(log) as w:
        for k, (pts, T) in enumerate(zip(scans, world.POSES, strict=True)):
            stamp = STAMP0_NS + k * 100_000_000
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", T))
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, None))
            if k == 1:
                w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, None))
                w.write_pose("/ground_truth", PoseStamped(stamp + 50_000_000, "map",
                                                          np.full((4, 4), np.nan)))
    result = _invoke("build-map", log, "-o", tmp_path / "m.tsdf")
    assert result.exit_code == 0, result.output
    assert "1 scan dropped with the same stamp" in result.output
    assert "1 ground-truth pose dropped with NaN or inf" in result.output
    source = read_header(tmp_path / "m.tsdf")["source"]
    assert source["scans"] == 3
    assert {k: v["count"] for k, v in source["faults"].items()} == {
        "scan_repeated_stamp": 1, "ground_truth_not_finite": 1}


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
    assert "no scan on /lidar/points has 10 points or more" in _failed(result)
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
    out = subprocess.run([sys.executable, "-m", "mcl3d", "map-info", str(broken), "--json"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "not an mcl3d map" in lines[0]
