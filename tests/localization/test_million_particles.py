"""A million particles actually run (the README's claim), on cpu at M = 16 scan points: the
whole `localize` command for three scans of the tiny room, and the filter's own state."""

import json

import numpy as np
import pytest

from mcl3d.core import geometry

localize_world = pytest.importorskip("support.localize_world")

MILLION = 1_000_000
TIGHT = "0.05 0.05 0.02 0.573 0.573 1.146"  # m, deg


@pytest.fixture(scope="module")
def room(tmp_path_factory, backend):
    from mcl3d.core import runtime

    runtime.init(backend)
    d = tmp_path_factory.mktemp("million")
    localize_world.write_log(d / "room.mcap", 3, n_azimuth=90)
    localize_world.save_room_map(d / "room.tsdf", 0.1)
    return d


def test_localize_command_runs_a_million_particles(room, tmp_path):
    from typer.testing import CliRunner

    from mcl3d.cli import app

    out = tmp_path / "out"
    r = CliRunner().invoke(app, [
        "localize", str(room / "room.mcap"), "--map", str(room / "room.tsdf"), "-o", str(out),
        "--init", "gt", "--init-std", TIGHT, "--particles", str(MILLION), "--points", "16",
        "--seed", "1", "--backend", "cpu"])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["particles"] == MILLION and summary["points"] == 16
    assert summary["scans"] == 3 and summary["skipped_scans"] == 0
    header, *rows = [line.split(",") for line in (out / "scans.csv").read_text().splitlines()]
    col = {name: i for i, name in enumerate(header)}
    assert len(rows) == 3
    assert all(int(row[col["n_particles"]]) == MILLION for row in rows)
    assert all(0.0 < float(row[col["ess"]]) <= MILLION for row in rows)
    tum = np.loadtxt(out / "trajectory.tum")
    truth = localize_world.path(3)
    assert np.isfinite(tum).all()
    assert np.abs(tum[:, 1:4] - truth[:, :3, 3]).max() < 0.3


def test_a_million_particle_update_keeps_the_weights_normalized(room, ti_runtime):
    from mcl3d.localization.localization_config import LocalizerConfig, SensorModelConfig
    from mcl3d.localization.localizer import Localizer
    from mcl3d.maps.map_file import load_map

    tsdf = load_map(room / "room.tsdf", f16=False)
    scanner = localize_world.Scanner(n_azimuth=90, seed=5)
    path = localize_world.path(2)
    loc = Localizer(tsdf, LocalizerConfig(particles=MILLION, seed=2,
                                          sensor=SensorModelConfig(points=16)))
    loc.init_pose(path[0], [0.05, 0.05, 0.02, 0.01, 0.01, 0.02])
    loc.shown_particles = 1000  # what a view copies each update: evenly picked, bounded
    results = [loc.step(scanner.scan(path[0]), None, 0.0),
               loc.step(scanner.scan(path[1]), geometry.relative_se3(path[0], path[1]), 0.1)]
    for r in results:
        assert r.n_particles == MILLION and r.n_points == 16
        assert np.isfinite(r.T_map_lidar).all() and np.isfinite(r.covariance).all()
        assert 1.0 <= r.ess <= MILLION
    w = loc.last_cloud.weights
    assert len(w) == 1000 and np.isfinite(w).all() and (w >= 0).all() and w.sum() <= 1.0
    pos, quat, log_w = loc.particles.host()
    assert np.isfinite(pos).all() and np.isfinite(log_w).all()
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-4)
    assert np.linalg.norm(results[-1].T_map_lidar[:3, 3] - path[1][:3, 3]) < 0.3
    tsdf.destroy()
