"""`mcl3d demo`: the README's main command runs end to end (simulate, inspect, map, localize
globally) and never overwrites a run. Smaller than the default demo: a 6 s log, 20k particles."""

import json
from pathlib import Path

from support.pictures import assert_picture
from typer.testing import CliRunner

from mcl3d.cli import app


def test_demo_runs_every_step_into_a_fresh_folder(tmp_path: Path):
    result = CliRunner().invoke(app, ["demo", "-o", str(tmp_path / "demo"), "--backend", "cpu",
                                      "--duration", "6", "--particles", "20000"])
    assert result.exit_code == 0, result.output
    latest = tmp_path / "demo" / "latest"
    assert latest.is_symlink()
    log = latest / "office.mcap"
    assert log.stat().st_size > 1_000_000
    assert (latest / "office_gt.tum").is_file()
    assert "1. Simulate a short office log" in result.output
    assert "/lidar/points" in result.output and "/ground_truth" in result.output
    assert "3. Build a TSDF map" in result.output
    from mcl3d.maps.map_file import read_blocks

    header, _geometry, data = read_blocks(latest / "office.tsdf")
    assert header["source"]["kind"] == "log" and len(data.sdf) > 1000
    assert (latest / "office_map_mesh.ply").stat().st_size > 1_000_000

    assert "4. Localize the log in its map from no initial guess" in result.output
    assert "--init global --particles 20000" in result.output
    summary = json.loads((latest / "localize" / "summary.json").read_text())
    assert summary["init"] == "global" and summary["particles"] == 20000
    assert summary["scans"] == 60
    for text in ("ATE after convergence", "ms per update", "likelihood"):
        assert text in result.output
    # it converged onto the ground truth, and the demo says so
    assert summary["converged_at_scan"] is not None
    after = summary["ate_after_convergence"]
    assert after["translation_max_m"] < 0.2 and after["rotation_max_deg"] < 3.0
    assert "from then on within" in result.output
    assert_picture(latest / "localize" / "localize.png")

    runs = sorted((tmp_path / "demo").iterdir())
    bad = CliRunner().invoke(app, ["demo", "-o", str(tmp_path / "demo"), "--backend", "cpu",
                                   "--duration", "0"])
    assert bad.exit_code == 1 and "duration must be > 0" in str(bad.exception)
    assert bad.exception.setting == "duration"  # the CLI names the flag --duration
    assert sorted((tmp_path / "demo").iterdir()) == runs  # nothing made, latest unchanged
