"""A run shorter than the RPE spacing (1 m of path) still reports its ATE: the RPE falls back
to consecutive frames instead of replacing the whole evaluation with an error."""

import json

import pytest

localize_world = pytest.importorskip("support.localize_world")


def test_a_path_shorter_than_a_metre_keeps_its_ate(tmp_path, ti_runtime):
    from mcl3d.odometry.lidar_odometry import OdometryConfig
    from mcl3d.odometry.pipeline import OdometryRequest, run

    log = tmp_path / "short.mcap"
    localize_world.write_log(log, 5)  # about 0.6 m of path
    result = run(OdometryRequest(log=log, output_dir=tmp_path / "out",
                                 config=OdometryConfig(use_imu=False)))
    assert result.summary.path_length_m < 1.0
    evaluation = json.loads((tmp_path / "out" / "odometry_summary.json").read_text())[
        "evaluation"]
    assert "error" not in evaluation, evaluation
    assert evaluation["ate"]["translation_m"]["rmse"] < 0.05
    assert evaluation["rpe"]["unit"] == "frames" and evaluation["rpe"]["delta"] == 1
