"""Damaged and implausible logs (issue #22), made from a short simulated log: a file cut at 60%
of its bytes is read up to the cut; scans in millimetres or from a planar scanner stop before
any work, with one line naming the problem and no output folder."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from mcl3d.cli import app


@pytest.fixture(scope="module")
def clean_log(tmp_path_factory):
    from mcl3d.sim.pipeline import SimulateRequest, run

    path = tmp_path_factory.mktemp("damaged") / "clean.mcap"
    run(SimulateRequest(world="office", sensor="vlp16", trajectory="ground", duration_s=2.0,
                        seed=3, output=path))
    return path


def _rewritten(clean, path, transform):
    """`clean` with every scan's points replaced by transform(points)."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.logs.writer import LogWriter
    from mcl3d.sim.pipeline import TOPICS

    with LogReader(clean) as reader, LogWriter(path) as w:
        w.write_tf(TOPICS["tf_static"], reader.static_transforms())
        for kind, msg in reader.messages(("points", "imu", "gt")):
            if kind == "points":
                msg.points = transform(np.asarray(msg.points)).astype(np.float32)
                w.write_points(TOPICS["points"], msg)
            elif kind == "imu":
                w.write_imu(TOPICS["imu"], msg)
            else:
                w.write_pose(TOPICS["gt"], msg)
    return path


def _one_error_line(result, words: str) -> None:
    """The run stopped with a library error (the CLI prints it as one red line, exit 1)."""
    from mcl3d.core.errors import Mcl3dError

    assert result.exit_code == 1, result.output
    assert isinstance(result.exception, Mcl3dError), repr(result.exception)
    message = str(result.exception)
    assert words in message and "\n" not in message, message


def test_a_log_cut_at_60_percent_is_read_up_to_the_cut(clean_log, tmp_path, ti_runtime):
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_tum

    data = clean_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    with LogReader(cut) as reader:
        readable = sum(1 for _ in reader.scans())
    assert 10 <= readable < 20  # of 20 scans: the intact chunks and the cut one's start

    out = tmp_path / "odo"
    result = CliRunner().invoke(app, ["odometry", str(cut), "-o", str(out), "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    assert "truncated or damaged" in result.output
    assert len(read_tum(out / "odometry.tum")) == readable
    truncated = json.loads((out / "odometry_summary.json").read_text())["faults"]["log_truncated"]
    assert truncated["scans_read"] == readable
    assert truncated["damaged_at_byte"] < truncated["total_bytes"] == len(data) * 6 // 10


def test_a_log_damaged_before_its_first_message_stops(clean_log, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(clean_log.read_bytes()[:2000])
    out = tmp_path / "odo"
    result = CliRunner().invoke(app, ["odometry", str(cut), "-o", str(out), "--backend", "cpu"])
    _one_error_line(result, "damaged before its first message")
    assert not out.exists()


def test_scans_in_millimetres_stop_before_work(clean_log, tmp_path):
    import subprocess
    import sys

    log = _rewritten(clean_log, tmp_path / "mm.mcap", lambda p: p * 1000.0)
    run = subprocess.run([sys.executable, "-m", "mcl3d", "odometry", str(log), "-o",
                          str(tmp_path / "cli")], capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and "Traceback" not in run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), run.stderr
    assert "coordinates look like millimetres" in lines[0]
    assert not (tmp_path / "cli").exists()
    for command, out in (("odometry", tmp_path / "odo"), ("slam", tmp_path / "slam"),
                         ("build-map", tmp_path / "map.tsdf")):
        result = CliRunner().invoke(app, [command, str(log), "-o", str(out), "--backend", "cpu"])
        _one_error_line(result, "coordinates look like millimetres")
        assert not out.exists()


def test_a_planar_scanner_stops_6dof_commands(clean_log, tmp_path):
    log = _rewritten(clean_log, tmp_path / "planar.mcap", lambda p: p * [1.0, 1.0, 0.0])
    for command in ("odometry", "slam"):
        out = tmp_path / command
        result = CliRunner().invoke(app, [command, str(log), "-o", str(out), "--backend", "cpu"])
        _one_error_line(result, "one ring: every scan lies in one plane")
        assert "6-DoF is not observable" in str(result.exception)
        assert not out.exists()


def test_a_log_without_a_usable_scan_names_its_topic(clean_log, tmp_path):
    log = _rewritten(clean_log, tmp_path / "nan.mcap", lambda p: p * np.nan)
    for command, out in (("odometry", tmp_path / "odo"), ("slam", tmp_path / "slam"),
                         ("build-map", tmp_path / "map.tsdf")):
        result = CliRunner().invoke(app, [command, str(log), "-o", str(out), "--backend", "cpu"])
        _one_error_line(result, "no scan on /lidar/points has 10 points or more")
        assert "--points-topic" in str(result.exception)
        assert not out.exists()


def test_real_scans_pass_the_checks(clean_log):
    from mcl3d.io.logs.plausibility import check_scans
    from mcl3d.io.logs.reader import LogReader

    with LogReader(clean_log) as reader:
        check_scans(reader, clean_log, needs_3d=True)


@pytest.fixture(scope="module")
def chunked_log(clean_log, tmp_path_factory):
    """The clean log in chunks of about one scan each, as recorders with small chunks write."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.logs.writer import LogWriter
    from mcl3d.sim.pipeline import TOPICS

    path = tmp_path_factory.mktemp("chunked") / "chunked.mcap"
    with LogReader(clean_log) as reader, LogWriter(path, chunk_size=256 * 1024) as w:
        w.write_tf(TOPICS["tf_static"], reader.static_transforms())
        write = {"points": w.write_points, "imu": w.write_imu, "gt": w.write_pose}
        for kind, msg in reader.messages(("points", "imu", "gt")):
            write[kind](TOPICS[kind], msg)
    return path


def _chunks(path) -> list:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return make_reader(f).get_summary().chunk_indexes


def _damaged(chunked_log, tmp_path, where: str) -> tuple:
    """The log with 4 kB of garbage over a middle chunk's records or its head; where it is."""
    data = bytearray(chunked_log.read_bytes())
    chunks = _chunks(chunked_log)
    chunk = chunks[len(chunks) // 2]
    at = chunk.chunk_start_offset + (chunk.chunk_length // 3 if where == "records" else 0)
    data[at:at + 4096] = np.random.default_rng(7).bytes(4096)
    bad = tmp_path / f"damaged_{where}.mcap"
    bad.write_bytes(bytes(data))
    return bad, at


def test_a_log_damaged_in_the_middle_keeps_the_rest(chunked_log, tmp_path, ti_runtime):
    """Garbage over a middle chunk's records (found when the run reads that chunk): the chunk
    is skipped, the rest is used, and the damage is named once."""
    from mcl3d.io.trajectory import read_tum

    bad, at = _damaged(chunked_log, tmp_path, "records")
    out = tmp_path / "odo"
    result = CliRunner().invoke(app, ["odometry", str(bad), "-o", str(out), "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    assert result.output.count("the log is damaged in 1 place") == 1, result.output
    poses = len(read_tum(out / "odometry.tum"))
    assert poses >= 18  # of 20 scans
    damaged = json.loads((out / "odometry_summary.json").read_text())["faults"]["log_damaged"]
    assert damaged["scans_lost"] == 20 - poses >= 1
    assert damaged["stretches"][0][0] <= at < damaged["stretches"][0][1]
    info = CliRunner().invoke(app, ["info", str(bad), "--json"])  # it reads a few scans only
    assert info.exit_code == 0, info.output


def test_info_names_a_damaged_chunk_head(chunked_log, tmp_path):
    """Garbage over a middle chunk's head is found on opening: info names it and counts the
    scans that can be read."""
    from mcl3d.io.logs.reader import LogReader

    bad, _at = _damaged(chunked_log, tmp_path, "head")
    with LogReader(bad) as reader:
        readable = sum(1 for _ in reader.scans())
    assert 18 <= readable < 20
    info = CliRunner().invoke(app, ["info", str(bad), "--json"])
    assert info.exit_code == 0, info.output
    described = json.loads(info.stdout)
    assert "1 damaged stretch skipped" in described["format"]
    assert {t["name"]: t["count"] for t in described["topics"]}["/lidar/points"] == readable
