"""The paper-forest scenario: a ~10 min walk through look-alike tree rows that revisits
lanes and ends near its start, in free space and on the ground."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import so3_log
from mcl3d.sim import pipeline
from mcl3d.sim.trajectories import _ground_height, build_trajectory, default_duration_s
from mcl3d.sim.worlds import build_world

ROW_SPACING_M = 4.0  # the forest's default
LANE_HALF_WIDTH_M = 1.0  # a pose this close to a lane's centre line is in the lane


@pytest.fixture(scope="module")
def walk():
    sizes = pipeline.with_scenario_world(pipeline.SimConfig(), "paper-forest").world
    world = build_world("forest", seed=1, **sizes.sizes("forest"))
    duration = default_duration_s(world, "paper-forest")
    traj = build_trajectory(world, "paper-forest", duration, seed=1)
    t = np.arange(0.0, duration, 0.25)
    return world, traj, t, traj.T_map_base(t)


def test_the_walk_lasts_about_ten_minutes_and_is_long(walk):
    world, traj, _, _ = walk
    assert 500.0 <= traj.duration_s <= 700.0
    assert traj.path_length_m() >= 500.0
    assert default_duration_s(world, "ground") == 10.0


def test_the_walk_ends_near_its_start_facing_the_same_way(walk):
    _, _, _, T = walk
    assert np.linalg.norm(T[-1, :2, 3] - T[0, :2, 3]) < 5.0
    heading = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    assert abs(np.angle(np.exp(1j * (heading[-1] - heading[0])))) < np.radians(20)


def test_the_walker_stays_on_the_ground_and_clear_of_trees_and_undergrowth(walk):
    world, _, _, T = walk
    xy = T[:, :2, 3]
    ground = _ground_height(world, xy, 0.0)
    assert np.all(np.abs(T[:, 2, 3] - ground - 1.25) < 0.1)  # hand height above the ground
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(world.static.vertices.astype(np.float32)),
                        o3d.core.Tensor(world.static.triangles.astype(np.uint32)))
    body = np.concatenate([np.column_stack([xy, ground + h]) for h in (0.6, 1.0, 1.4, 1.9)])
    clearance = scene.compute_distance(o3d.core.Tensor(body.astype(np.float32))).numpy()
    assert clearance.min() > 0.5  # from knee to head height: no trunk, bush or ground


def _lane_passes(x: np.ndarray, y: np.ndarray, lane_y: float, span: tuple[float, float]):
    """Directions (+1 east, -1 west) of the walks along a lane over most of its length."""
    inside = np.abs(y - lane_y) < LANE_HALF_WIDTH_M
    edges = np.flatnonzero(np.diff(np.concatenate([[0], inside.astype(int), [0]])))
    passes = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if x[a:b].max() - x[a:b].min() > 0.8 * (span[1] - span[0]):
            passes.append(int(np.sign(x[b - 1] - x[a])))
    return passes


def test_the_walk_passes_through_several_lanes_more_than_once_both_ways(walk):
    _, _, _, T = walk
    x, y = T[:, 0, 3], T[:, 1, 3]
    span = (3.0, 60.0)  # the default forest's first and last tree along a row
    passes = {r: _lane_passes(x, y, (r + 1.5) * ROW_SPACING_M, span) for r in range(9)}
    walked = [r for r, p in passes.items() if p]
    revisited = [r for r, p in passes.items() if len(p) >= 2]
    assert len(walked) >= 6
    assert len(revisited) >= 2
    same_way = [r for r in revisited if len(set(passes[r])) == 1]
    both_ways = [r for r in revisited if len(set(passes[r])) == 2]
    assert same_way and both_ways


def test_the_walks_motion_is_smooth_and_consistent_with_its_rates(walk):
    _, traj, _, _ = walk
    t = np.linspace(100.0, 110.0, 40)
    h = 1e-5
    k = traj.kinematics(t)
    Tp, Tm = traj.T_map_base(t + h), traj.T_map_base(t - h)
    w_num = so3_log(np.swapaxes(Tm[:, :3, :3], 1, 2) @ Tp[:, :3, :3]) / (2 * h)
    assert np.allclose(k.w_base, w_num, atol=1e-5)
    dense = traj.kinematics(np.arange(2.0, traj.duration_s - 2.0, 0.01))
    assert np.abs(dense.w_base).max() < 2.0  # rad/s: a hand-held sensor, not a shake
    speed = np.linalg.norm(dense.v_map[:, :2], axis=1)
    assert speed.max() < 1.3 and np.median(speed) > 0.8


def test_the_walk_climbs_a_hillside_turns_quickly_and_nods_at_each_step(walk):
    from mcl3d.sim.trajectories import PAPER_FOREST_STEP_HZ

    _, traj, _, T = walk
    assert np.ptp(T[:, 2, 3]) > 3.0  # rows run down a 6 % slope: metres of climb per lane
    t = np.arange(2.0, traj.duration_s - 2.0, 0.01)
    k = traj.kinematics(t)
    assert np.abs(k.w_base[:, 2]).max() > 1.2  # a walker turns round at a row's end
    pitch_rate = k.w_base[:, 1] - k.w_base[:, 1].mean()
    power = np.abs(np.fft.rfft(pitch_rate)) ** 2
    hz = np.fft.rfftfreq(len(t), 0.01)
    assert abs(hz[np.argmax(power)] - PAPER_FOREST_STEP_HZ) < 0.1


def test_the_scenario_brings_its_wood_unless_the_config_sets_it():
    cfg = pipeline.SimConfig.model_validate({"world": {"forest_border_m": 5.0}})
    world = pipeline.with_scenario_world(cfg, "paper-forest").world
    assert world.forest_border_m == 5.0 and world.forest_undergrowth > 0.15
    assert pipeline.with_scenario_world(cfg, "loop").world == cfg.world
    wood = build_world("forest", seed=1, **world.sizes("forest"))
    assert wood.static.n_triangles > 1.5 * build_world("forest", seed=1).static.n_triangles


def test_the_walk_needs_a_forest_of_eight_rows():
    small = build_world("forest", seed=0, rows=6, trees_per_row=8)
    with pytest.raises(ConfigError, match=r"paper-forest.*8 rows"):
        build_trajectory(small, "paper-forest", 60.0)


def test_simulate_without_duration_or_sensor_takes_the_scenarios_own(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from mcl3d.cli import app
    from mcl3d.io.logs.reader import LogReader

    asked = []
    monkeypatch.setattr(pipeline, "default_duration_s",
                        lambda world, kind: asked.append(kind) or 0.3)
    config = tmp_path / "thin.yaml"
    config.write_text("lidar:\n  column_stride: 20\n")
    log = tmp_path / "walk.mcap"
    result = CliRunner().invoke(app, ["simulate", "forest", "--trajectory", "paper-forest",
                                      "--config", str(config), "-o", str(log)])
    assert result.exit_code == 0, result.output
    assert asked == ["paper-forest"]
    with LogReader(log) as reader:
        assert len(reader.ground_truth()[0]) == 3  # 0.3 s at 10 Hz
    assert "mid360" in result.output
    saved = pipeline.cfgmod.load(pipeline.SimConfig, tmp_path / "walk_config.yaml", {})
    assert saved.world.forest_border_m == 20.0  # the scenario's wood, listed as simulated
