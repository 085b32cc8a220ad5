"""`mcl3d eval` end to end: tables, --plot PNG, --json numbers, and bad input (one line,
exit 1, no traceback, nothing written)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mcl3d.cli import app
from mcl3d.core.geometry import se3, so3_exp
from mcl3d.evaluation.metrics import evaluate
from mcl3d.io.trajectory import Trajectory, read_tum, write_kitti, write_tum

REPO = Path(__file__).resolve().parents[2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _pair(n: int = 300, seed: int = 0) -> tuple[Trajectory, Trajectory]:
    """A curvy 10 Hz ground truth and a noisy, shifted, 5 ms late estimate missing 6 poses."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    yaw = 0.3 * np.sin(2 * np.pi * k / 120) + 0.002 * k
    R = so3_exp(np.column_stack([np.zeros(n), np.zeros(n), yaw]))
    xy = np.cumsum(np.column_stack([np.cos(yaw), np.sin(yaw)]) * 0.3, axis=0)
    ref = Trajectory(100.0 + 0.1 * k, se3(R, np.column_stack([xy, 0.2 * np.sin(k / 30)])))
    est_poses = ref.poses.copy()
    est_poses[:, :3, 3] += rng.normal(0.0, 0.05, (n, 3))
    est_poses[:, :3, :3] = est_poses[:, :3, :3] @ so3_exp(rng.normal(0.0, 0.005, (n, 3)))
    est_poses = se3(so3_exp(np.array([0.0, 0.0, 0.5])), np.array([2.0, 1.0, 0.0])) @ est_poses
    keep = np.ones(n, dtype=bool)
    keep[rng.choice(n, 6, replace=False)] = False
    return ref, Trajectory(ref.stamps_s[keep] + 0.005, est_poses[keep])


@pytest.fixture
def files(tmp_path):
    ref, est = _pair()
    write_tum(tmp_path / "ref.tum", ref)
    write_tum(tmp_path / "est.tum", est)
    return tmp_path


def _mcl3d(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The installed entry point's behaviour (error handling included), in a subprocess."""
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    return subprocess.run([sys.executable, "-m", "mcl3d", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": path, "COLUMNS": "200"})


def test_eval_prints_table_and_writes_plot_and_json(files):
    result = CliRunner().invoke(app, [
        "eval", str(files / "est.tum"), "--ref", str(files / "ref.tum"), "--align", "se3",
        "--rpe-delta", "2", "--rpe-unit", "m", "--plot", str(files / "out.png"),
        "--json", str(files / "out.json")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    for text in ("ATE translation", "ATE rotation", "RPE translation", "RPE rotation",
                 "294 poses within 0.01 s", "se3 (Umeyama)"):
        assert text in result.stdout
    png = (files / "out.png").read_bytes()
    assert png.startswith(PNG_MAGIC) and len(png) > 20_000
    numbers = json.loads((files / "out.json").read_text())
    expected = evaluate(read_tum(files / "ref.tum"), read_tum(files / "est.tum"),
                        alignment="se3", rpe_delta=2.0, rpe_unit="m")
    assert numbers["poses"]["associated"] == 294
    assert numbers["ate"]["translation_m"] == pytest.approx(
        expected.ate.translation_m.as_dict(), rel=1e-12)
    assert numbers["rpe"]["rotation_deg"] == pytest.approx(
        expected.rpe.rotation_deg.as_dict(), rel=1e-12)
    assert 0.06 < numbers["ate"]["translation_m"]["rmse"] < 0.11
    assert [p.name for p in files.iterdir() if p.name.startswith(".")] == []


def test_eval_sim3_reports_scale_and_kitti_pairs_by_line(tmp_path):
    ref, _ = _pair(100)
    est_poses = ref.poses.copy()
    est_poses[:, :3, 3] *= 0.5
    write_kitti(tmp_path / "ref.txt", ref)
    write_kitti(tmp_path / "est.txt", Trajectory(ref.stamps_s, est_poses))
    result = CliRunner().invoke(app, ["eval", str(tmp_path / "est.txt"), "--ref",
                                      str(tmp_path / "ref.txt"), "--align", "sim3",
                                      "--rpe-delta", "5", "--rpe-unit", "frames"],
                                env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "scale 2.000000" in result.stdout and "100 poses within" in result.stdout


def test_force_overwrites_and_bad_choices_are_usage_errors(files):
    (files / "out.json").write_text("old")
    args = ["eval", str(files / "est.tum"), "--ref", str(files / "ref.tum"),
            "--json", str(files / "out.json")]
    assert CliRunner().invoke(app, [*args, "--force"]).exit_code == 0
    assert json.loads((files / "out.json").read_text())["alignment"]["method"] == "none"
    assert CliRunner().invoke(app, [*args, "--force", "--align", "affine"]).exit_code == 2
    assert CliRunner().invoke(app, [*args, "--force", "--rpe-unit", "s"]).exit_code == 2


def _write_bad_cases(folder: Path) -> None:
    est = _pair(60)[1]
    (folder / "seven.tum").write_text("# t x y z qx qy qz qw\n0.0 0 0 0 0 0 0 1\n"
                                      "0.1 1 0 0 0 0 1\n")
    write_tum(folder / "late.tum", Trajectory(est.stamps_s + 500.0, est.poses))
    write_tum(folder / "two.tum", Trajectory(est.stamps_s[:2], est.poses[:2]))
    (folder / "exists.json").write_text("{}")


@pytest.mark.parametrize(("est", "extra", "message"), [
    ("seven.tum", [], r"seven\.tum: line 3 has 7 columns, TUM needs 8: t x y z qx qy qz qw"),
    ("late.tum", [], r"no stamps of .*late\.tum .* match .* within 0\.01 s.*--t-max-diff"),
    ("two.tum", ["--align", "se3"], r"Umeyama alignment needs at least 3 associated poses, got 2"),
    ("est.tum", ["--json", "exists.json"],
     r"exists\.json already exists; allow overwriting it \(--force\)"),
    ("missing.tum", [], r"missing\.tum: trajectory file not found"),
    ("est.tum", ["--plot", "fig.jpg"], r"fig\.jpg: unknown image type \.jpg.*\(--plot\)"),
])
def test_bad_input_is_one_line_exit_1_and_leaves_no_output(files, est, extra, message):
    _write_bad_cases(files)
    outputs = ["--plot", "fig.png", "--json", "numbers.json"]
    if "--json" in extra or "--plot" in extra:
        outputs = []
    before = sorted(p.name for p in files.iterdir())
    run = _mcl3d("eval", est, "--ref", "ref.tum", *extra, *outputs, cwd=files)
    assert run.returncode == 1, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in run.stderr, run.stderr
    assert lines[0].startswith("error:")
    assert re.search(message, lines[0]), lines[0]
    assert sorted(p.name for p in files.iterdir()) == before
