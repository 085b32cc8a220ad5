"""Porous foliage and the forest hillside: a pulse goes into a crown before a leaf returns
it (exponential depth, mean as set), solids stay exact, and a walker on a hillside stands on
the ground however high it climbs."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.sim.lidars import LidarConfig
from mcl3d.sim.mesh import MeshBuilder, merge
from mcl3d.sim.raycast import WorldCaster
from mcl3d.sim.scan import _scatter_depth
from mcl3d.sim.trajectories import _ground_height
from mcl3d.sim.worlds import World, build_world


def _wall_and_bush(depth_m: float) -> World:
    """A solid wall at x = 10 m (y < 0) and a porous box at x = 10 m (y > 0)."""
    solid, bush = MeshBuilder(), MeshBuilder()
    solid.box([10.0, -5.0, -5.0], [11.0, -0.01, 5.0], 0.5)
    bush.add(*_box(10.0, 0.01), 0.4, scatter_depth_m=depth_m)
    mesh = merge([solid.build(), bush.build()])
    return World("test", 0, mesh, mesh, {}, [0.0], np.eye(4), "")


def _box(x0: float, y0: float):
    corners = np.array([[x, y, z] for x in (x0, x0 + 1.0) for y in (y0, 5.0)
                        for z in (-5.0, 5.0)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return corners, faces


def test_rays_into_foliage_carry_its_depth_and_solids_carry_none():
    caster = WorldCaster(_wall_and_bush(0.5))
    directions = np.array([[1.0, -0.2, 0.0], [1.0, 0.2, 0.0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    hits = caster.cast(np.zeros((2, 3)), directions)
    assert np.allclose(hits.scatter_depth_m, [0.0, 0.5])
    assert np.allclose(hits.range_m, 10.0 / directions[:, 0], atol=1e-4)


def test_scatter_depth_is_exponential_with_the_set_mean_and_zero_on_solids():
    rng = np.random.default_rng(0)
    mean = np.concatenate([np.zeros(1000), np.full(100_000, 0.5)]).astype(np.float32)
    depth = _scatter_depth(mean, rng)
    assert np.all(depth[:1000] == 0.0) and np.all(depth[1000:] >= 0.0)
    assert depth[1000:].mean() == pytest.approx(0.5, rel=0.02)
    assert np.median(depth[1000:]) == pytest.approx(0.5 * np.log(2), rel=0.03)


def test_a_scan_of_the_bush_lands_behind_its_surface_and_of_the_wall_on_it():
    from mcl3d.sim.lidars import make_lidar
    from mcl3d.sim.scan import simulate_scan

    class Still:  # the sensor at the origin, not moving
        def T_map_base(self, t):
            return np.repeat(np.eye(4)[None], len(np.atleast_1d(t)), axis=0)

        def cab_z_m(self, t):
            return np.zeros(len(np.atleast_1d(t)))

        def door_closed(self, t):
            return np.zeros(len(np.atleast_1d(t)), dtype=bool)

    cfg = LidarConfig(range_sigma_m=0.0, dropout_prob=0.0, azimuth_fov_deg=(-60.0, 60.0))
    scan = simulate_scan(make_lidar("mid360"), cfg, WorldCaster(_wall_and_bush(0.5)), Still(),
                         np.eye(4), 0, 0.0, np.random.default_rng(1))
    p = scan.points[np.abs(scan.points[:, 2]) < 3.0]
    wall, bush = p[p[:, 1] < -0.5], p[p[:, 1] > 0.5]
    assert np.allclose(wall[:, 0], 10.0, atol=1e-3)
    assert np.all(bush[:, 0] >= 10.0 - 1e-3)
    assert (bush[:, 0] - 10.0).mean() > 0.3  # ~0.5 m along rays of up to 60 degrees


def test_default_forest_has_solid_foliage_and_the_hillside_climbs_with_its_trees():
    assert build_world("forest", seed=1).static.scatter_depth_m is None
    hill = build_world("forest", seed=1, slope_percent=6.0, foliage_depth_m=0.5)
    assert hill.static.scatter_depth_m is not None
    assert set(np.unique(hill.static.scatter_depth_m)) == {0.0, 0.5}
    xy = np.array([[5.0, 10.0], [35.0, 10.0], [60.0, 10.0]])
    z = _ground_height(hill, xy, 0.0)
    assert z[2] - z[0] == pytest.approx(0.06 * 55.0, abs=0.6)  # 6 % over 55 m (+- relief)
    assert z[2] > 2.5  # above where a cast from 2 m would start


def test_forest_rejects_a_cliff_or_foliage_deeper_than_a_crown():
    with pytest.raises(ConfigError, match="forest_slope_percent"):
        build_world("forest", slope_percent=45.0)
    with pytest.raises(ConfigError, match="forest_foliage_depth_m"):
        build_world("forest", foliage_depth_m=-0.1)
