"""`mcl3d simulate` end to end: every world x sensor, determinism, exports, bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mcl3d.cli import app
from mcl3d.sim.lidars import SENSORS
from mcl3d.sim.pipeline import SimulateRequest, run
from mcl3d.sim.worlds import WORLDS

runner = CliRunner()


def _fast_config(tmp_path, **extra):
    path = tmp_path / "fast.yaml"
    values = {"lidar": {"column_stride": 4}, "map": {"point_spacing_m": 0.5}}
    values.update(extra)
    path.write_text(yaml.safe_dump(values))
    return path


@pytest.mark.parametrize("world", WORLDS)
@pytest.mark.parametrize("sensor", SENSORS)
def test_every_world_and_sensor_writes_a_log_both_readers_open(tmp_path, world, sensor):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from mcl3d.io.logs.reader import LogReader

    log = tmp_path / "one.mcap"
    run(SimulateRequest(world, sensor, "handheld", 0.1, 0, log,
                        overrides={"lidar.column_stride": 8}))
    with LogReader(log) as reader:
        assert reader.topics.points == "/lidar/points" and reader.topics.gt == "/ground_truth"
        assert reader.count("points") == 1 and reader.count("gt") == 1
        assert reader.count("imu") == 20 and reader.count("odom") == 5
        cloud = next(iter(reader.scans()))
        assert len(cloud) > 100 and cloud.frame_id == "lidar"
        assert set(cloud.fields) >= {"intensity", "ring"} and cloud.times_s is not None
        T_base_lidar = reader.static_transform("base_link", "lidar")
        assert T_base_lidar[2, 3] == pytest.approx(0.42)
    counts: dict[str, int] = {}
    with open(log, "rb") as f:
        for _schema, channel, _message, decoded in make_reader(
                f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == "/lidar/points":
                assert decoded.header.frame_id == "lidar"
    assert counts == {"/tf_static": 1, "/lidar/points": 1, "/ground_truth": 1,
                      "/imu/data": 20, "/odom": 5}


def test_cli_simulate_writes_log_ground_truth_config_mesh_and_map(tmp_path):
    import open3d as o3d

    from mcl3d.core import config
    from mcl3d.io.trajectory import read_tum
    from mcl3d.sim.pipeline import SimConfig

    log, mesh, cloud = tmp_path / "run.mcap", tmp_path / "world.ply", tmp_path / "map.ply"
    result = runner.invoke(app, [
        "simulate", "building", "--sensor", "os1-64", "--trajectory", "loop", "--duration",
        "0.35", "--seed", "4", "-o", str(log), "--config", str(_fast_config(tmp_path)),
        "--export-mesh", str(mesh), "--export-map", str(cloud)])
    assert result.exit_code == 0, result.output
    for word in ("points/scan", "IMU samples", "path length", "wall time", "map points"):
        assert word in result.output
    gt = read_tum(tmp_path / "run_gt.tum")
    assert len(gt) == 3 and np.allclose(np.diff(gt.stamps_s), 0.1, atol=1e-6)
    saved = config.load(SimConfig, tmp_path / "run_config.yaml")
    assert saved.lidar.column_stride == 4 and saved.imu.rate_hz == 200.0
    world_mesh = o3d.io.read_triangle_mesh(str(mesh))
    assert len(world_mesh.triangles) > 5000
    points = o3d.io.read_point_cloud(str(cloud))
    assert len(points.points) > 10000 and points.has_normals()
    info = runner.invoke(app, ["info", str(log)])
    assert info.exit_code == 0 and "/ground_truth" in info.output


def test_same_seed_gives_the_same_bytes_and_another_seed_does_not(tmp_path):
    paths = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        path = tmp_path / f"{name}.mcap"
        run(SimulateRequest("forest", "mid360", "drone", 0.25, seed, path,
                            overrides={"lidar.column_stride": 4}))
        paths.append(path)
    a, b, c = (p.read_bytes() for p in paths)
    assert a == b and a != c
    tum = [(tmp_path / f"{n}_gt.tum").read_text() for n in "ab"]
    assert tum[0] == tum[1]


@pytest.mark.parametrize(("args", "message"), [
    (["moon"], "unknown world 'moon'"),
    (["office", "--sensor", "hdl64"], "unknown sensor 'hdl64'"),
    (["office", "--trajectory", "flight"], "unknown trajectory 'flight'"),
    (["office", "--trajectory", "elevator"], "does not fit world 'office'"),
    (["office", "--duration", "0"], "duration must be > 0 seconds, got 0 (--duration)"),
    (["office", "--duration", "-3"], "duration must be > 0 seconds, got -3 (--duration)"),
    (["office", "--duration", "0.05"], "shorter than one scan (0.1 s at 10 Hz) (--duration)"),
    (["office", "--seed", "-1"], "seed must be >= 0, got -1 (--seed)"),
    (["building", "--trajectory", "elevator", "--duration", "3"],
     "needs a duration >= 33 s to finish the ride (got 3 s) (--duration)"),
])
def test_bad_input_is_a_typed_error_and_leaves_nothing_behind(tmp_path, args, message):
    """The library names the setting; the CLI's line adds its flag."""
    from mcl3d.console import with_flag
    from mcl3d.core.errors import ConfigError

    out = tmp_path / "out"
    out.mkdir()
    result = runner.invoke(app, ["simulate", *args, "-o", str(out / "log.mcap")])
    assert isinstance(result.exception, ConfigError)
    assert message in with_flag(str(result.exception), result.exception.setting)
    assert list(out.iterdir()) == []


def _mcl3d(*args: str) -> subprocess.CompletedProcess:
    """The installed entry point's behaviour (error handling included), in a subprocess."""
    return subprocess.run([sys.executable, "-m", "mcl3d", *args], capture_output=True,
                          text=True, timeout=120)


def test_entry_point_prints_one_red_line_and_exits_1(tmp_path):
    result = _mcl3d("simulate", "moon", "-o", str(tmp_path / "log.mcap"))
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown world 'moon'" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_existing_output_needs_force(tmp_path):
    log = tmp_path / "log.mcap"
    log.write_bytes(b"keep me")
    args = ["simulate", "arena", "--duration", "0.1", "-o", str(log), "--config",
            str(_fast_config(tmp_path))]
    result = _mcl3d(*args)
    assert result.returncode == 1 and "--force" in result.stderr
    assert log.read_bytes() == b"keep me" and not (tmp_path / "log_gt.tum").exists()
    result = runner.invoke(app, [*args, "--force"])
    assert result.exit_code == 0, result.output
    assert log.read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_usage_errors_exit_2(tmp_path):
    result = runner.invoke(app, ["simulate", "office", "--duration", "soon", "-o",
                                 str(tmp_path / "x.mcap")])
    assert result.exit_code == 2


def test_world_sizes_come_from_the_config(tmp_path):
    from mcl3d.core.errors import ConfigError
    from mcl3d.io.logs.reader import LogReader

    log = tmp_path / "tall.mcap"
    run(SimulateRequest("building", "os0-64", "kidnap", 0.2, 0, log,
                        overrides={"world.building_floors": 5, "lidar.column_stride": 8}))
    with LogReader(log) as reader:
        _, gt = reader.ground_truth()
    assert gt[0][2, 3] == pytest.approx(4 * 3.5 + 0.42)  # the kidnap starts on the top floor
    with pytest.raises(ConfigError, match=r"world.office_rooms must be >= 7"):
        run(SimulateRequest("office", "vlp16", "ground", 0.2, 0, tmp_path / "small.mcap",
                            overrides={"world.office_rooms": 3}))


def test_ctrl_c_keeps_the_scans_finished(tmp_path, monkeypatch):
    import mcl3d.sim.pipeline as pipeline_module
    from mcl3d.core.errors import RunInterrupted
    from mcl3d.io.logs.reader import LogReader

    real = pipeline_module.simulate_scan
    calls = []

    def interrupt_on_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline_module, "simulate_scan", interrupt_on_third)
    log = tmp_path / "cut.mcap"
    with pytest.raises(RunInterrupted, match="after 2 of 10 scans"):
        run(SimulateRequest("arena", "vlp16", "ground", 1.0, 0, log,
                            overrides={"lidar.column_stride": 8}))
    with LogReader(log) as reader:
        assert reader.count("points") == 2 and reader.count("gt") == 2
    assert len((tmp_path / "cut_gt.tum").read_text().splitlines()) == 3  # header + 2 poses
