"""The MCL paper's office experiment, 11 trajectories (`paper-office-1` .. `paper-office-11`):
closed ground-robot tours that start inside look-alike rooms, in the corridor or in the open
area, and cross the open area with its ramps."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.sim.pipeline import SimulateRequest, extrinsics, run
from mcl3d.sim.trajectories import PAPER_OFFICE, build_trajectory, default_duration_s
from mcl3d.sim.worlds import build_world

ROOMS_Y_M, CORRIDOR_Y_M = 8.0, 10.5  # the office's room wall and corridor wall


@pytest.fixture(scope="module")
def office():
    return build_world("office", seed=3)


@pytest.fixture(scope="module")
def tours(office):
    return {k: build_trajectory(office, k, default_duration_s(office, k), seed=1)
            for k in PAPER_OFFICE}


def test_eleven_closed_tours_from_rooms_corridor_and_open_area(office, tours):
    assert len(tours) == 11
    starts, rooms = [], set()
    for tour in tours.values():
        t = np.arange(0.0, tour.duration_s, 0.1)
        p = tour.T_map_base(t)[:, :3, 3]
        assert np.linalg.norm(p[-1] - p[0]) < 0.05  # back at the start, at rest
        assert tour.duration_s == pytest.approx(np.ceil(tour.motion.t_end), abs=1.0)
        assert 60.0 < tour.path_length_m() < 140.0
        assert (p[:, 1] > CORRIDOR_Y_M + 2.0).any()  # through the open area
        x, y = p[0, :2]
        starts.append("room" if y < ROOMS_Y_M else "corridor" if y < CORRIDOR_Y_M else "open")
        if y < ROOMS_Y_M:
            rooms.add(int((x - 1.0) // 6.0))
    assert starts.count("room") == 8 and starts.count("corridor") == 2
    assert starts.count("open") == 1 and rooms == set(range(8))
    over_ramps = [tour.T_map_base(np.arange(0.0, tour.duration_s, 0.1))[:, 2, 3].max() > 0.4
                  for tour in tours.values()]
    assert 4 <= sum(over_ramps) < len(tours)  # some drive over both ramps, some round them


def test_the_tours_keep_clear_of_every_wall_and_piece_of_furniture(office, tours):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(office.static.vertices.astype(np.float32)),
                        o3d.core.Tensor(office.static.triangles.astype(np.uint32)))
    T_base_lidar, _ = extrinsics("vlp16")
    for tour in tours.values():
        T = tour.T_map_base(np.arange(0.0, tour.duration_s, 0.05))
        body = T[:, :3, 3] + [0.0, 0.0, 0.3]
        for points in (body, (T @ T_base_lidar)[:, :3, 3]):
            d = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
            assert d.min() > 0.2


def test_the_same_tour_in_every_world_seed(office):
    other = build_world("office", seed=8)
    for k in PAPER_OFFICE:
        np.testing.assert_array_equal(office.routes[k], other.routes[k])


def test_only_the_office_has_them(tmp_path):
    with pytest.raises(ConfigError, match="does not fit world 'arena'"):
        build_trajectory(build_world("arena"), "paper-office-1", 10.0)
    with pytest.raises(ConfigError, match=r"paper-office-1\.\.11"):
        run(SimulateRequest("office", "vlp16", "paper-office-12", 0.3, 1, tmp_path / "x.mcap"))
    assert not (tmp_path / "x.mcap").exists()
