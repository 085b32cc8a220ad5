"""`mcl3d demo`: the README's main command runs end to end and never overwrites a run."""

from pathlib import Path

from typer.testing import CliRunner

from mcl3d.cli import app


def test_demo_runs_every_step_into_a_fresh_folder(tmp_path: Path):
    result = CliRunner().invoke(app, ["demo", "-o", str(tmp_path / "demo"), "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    latest = tmp_path / "demo" / "latest"
    assert latest.is_symlink()
    log = latest / "office.mcap"
    assert log.stat().st_size > 1_000_000
    assert (latest / "office_gt.tum").is_file()
    assert "1. Simulate a short office log" in result.output
    assert "/lidar/points" in result.output and "/ground_truth" in result.output
    assert "3. Build a TSDF map" in result.output
    from mcl3d.maps.io import read_blocks

    header, _geometry, data = read_blocks(latest / "office.tsdf")
    assert header["source"]["kind"] == "log" and len(data.sdf) > 1000
    assert (latest / "office_map_mesh.ply").stat().st_size > 1_000_000
