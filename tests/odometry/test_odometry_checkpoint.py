"""Long runs lose nothing (issue #22): `odometry` checkpoints the trajectory so far, so a
kill -9 part way keeps the poses done; a run that ends writes its final outputs over them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from mcl3d.core.checkpoint import CHECKPOINT_ENV, Checkpointer
from mcl3d.io.trajectory import read_tum

SCANS = 40


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    from mcl3d.sim.pipeline import SimulateRequest, run

    path = tmp_path_factory.mktemp("checkpoint") / "office.mcap"
    run(SimulateRequest(world="office", sensor="vlp16", trajectory="ground",
                        duration_s=SCANS / 10, seed=3, output=path))
    return path


def _poses(path) -> int:
    try:
        return sum(1 for line in path.read_text().splitlines() if line.strip())
    except FileNotFoundError:
        return 0


def test_kill_9_keeps_the_trajectory_so_far(log, tmp_path):
    out = tmp_path / "odo"
    env = {**os.environ, CHECKPOINT_ENV: "0"}  # a checkpoint after every scan
    proc = subprocess.Popen([sys.executable, "-m", "mcl3d", "odometry", str(log), "-o", str(out)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    try:
        # kill at the first checkpoint (its summary is written after its trajectory)
        while not (out / "odometry_summary.json").exists() and proc.poll() is None:
            assert time.monotonic() < deadline, "no checkpoint written in time"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    traj = read_tum(out / "odometry.tum")
    assert 0 < len(traj) <= SCANS
    summary = json.loads((out / "odometry_summary.json").read_text())
    assert summary["checkpoint"] is True
    assert summary["scans"] in (len(traj), len(traj) - 1)  # may be one checkpoint behind
    assert "faults" in summary


def test_final_outputs_replace_the_checkpoints(log, tmp_path, monkeypatch):
    from mcl3d.odometry.pipeline import OdometryRequest, run

    monkeypatch.setenv(CHECKPOINT_ENV, "0")
    result = run(OdometryRequest(log=log, output_dir=tmp_path / "odo"))
    summary = json.loads(result.outputs.summary.read_text())
    assert "checkpoint" not in summary
    assert summary["scans"] == len(result.frames) == len(read_tum(result.outputs.tum))
    assert not list((tmp_path / "odo").glob(".*part*"))  # no temporary file left behind


def test_checkpoints_follow_the_wall_clock():
    now = [0.0]
    written = []
    checkpoint = Checkpointer(lambda: written.append(now[0]), interval_s=30.0,
                              clock=lambda: now[0])
    for now[0] in (1.0, 29.9, 30.0, 45.0, 59.9, 60.1, 61.0):
        checkpoint.tick()
    assert written == [30.0, 60.1]


def test_slam_checkpoints_its_online_and_odometry_trajectories(log, tmp_path, monkeypatch):
    """SLAM's odometry front-end and online estimate are checkpointed; slam.tum is placed by
    the keyframes at the end, so a crash leaves none."""
    from mcl3d.slam.pipeline import SlamRequest, run
    from mcl3d.slam.slam_config import SlamConfig

    monkeypatch.setenv(CHECKPOINT_ENV, "0")

    def crash_at_six(progress):
        if progress.done == 6:
            raise RuntimeError("crash")

    out = tmp_path / "slam"
    with pytest.raises(RuntimeError, match="crash"):
        run(SlamRequest(log=log, output_dir=out, config=SlamConfig(particles=50, seed=1)),
            on_progress=crash_at_six)
    assert len(read_tum(out / "slam_online.tum")) == len(read_tum(out / "odometry.tum")) == 5
    assert not (out / "slam.tum").exists()
    summary = json.loads((out / "slam_summary.json").read_text())
    assert summary["checkpoint"] is True and summary["scans"] == 5
