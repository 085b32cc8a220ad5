"""Procedural worlds: sizes, look-alike places (the ambiguity the papers study), exports."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.sim.mesh import MeshBuilder, sample_surface, write_mesh_ply, write_points_ply
from mcl3d.sim.worlds import BARK, WORLDS, build_world


def _scene(mesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene


def _distances(scene, points):
    import open3d as o3d

    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


@pytest.mark.parametrize("name", WORLDS)
def test_worlds_are_moderate_meshes_and_seeded(name):
    w = build_world(name, seed=0)
    assert 150 <= w.mesh_at().n_triangles <= 100_000
    assert np.all(np.isfinite(w.static.vertices)) and np.all(w.static.reflectivity > 0)
    again, other = build_world(name, seed=0), build_world(name, seed=1)
    assert np.array_equal(again.static.vertices, w.static.vertices)
    if name != "arena":  # the arena's only random part is one crate
        assert not np.array_equal(other.static.vertices, w.static.vertices)


def test_office_is_50_by_20_m_with_ramps():
    w = build_world("office")
    lo, hi = w.static.vertices.min(axis=0), w.static.vertices.max(axis=0)
    assert hi[0] - lo[0] == pytest.approx(50.4) and hi[1] - lo[1] == pytest.approx(20.4)
    assert w.ground.vertices[:, 2].max() == pytest.approx(0.6)  # the higher ramp platform


def test_office_rooms_are_near_identical_but_not_clones():
    w = build_world("office")
    scene = _scene(w.static)
    rng = np.random.default_rng(0)
    pts, _ = sample_surface(w.static, 200.0, rng)
    room1 = pts[(pts[:, 0] > 7.3) & (pts[:, 0] < 12.7) & (pts[:, 1] > 0.3) & (pts[:, 1] < 7.7)
                & (pts[:, 2] > 0.05) & (pts[:, 2] < 2.0)]  # furniture and walls of room 1
    d = _distances(scene, room1 + np.array([12.0, 0.0, 0.0]))  # compared with room 3
    assert np.median(d) < 0.02  # the same layout...
    assert np.quantile(d, 0.99) > 0.03  # ...up to a few centimetres and the odd extra box


def test_building_floors_are_near_identical():
    w = build_world("building")
    assert len(w.floor_z_m) >= 3 and w.elevator is not None
    scene = _scene(w.static)
    pts, _ = sample_surface(w.static, 50.0, np.random.default_rng(1))
    floor0 = pts[(pts[:, 2] > 0.05) & (pts[:, 2] < 2.5)]
    d = _distances(scene, floor0 + np.array([0.0, 0.0, w.floor_z_m[1]]))
    assert np.mean(d < 0.1) > 0.9


def test_forest_rows_are_regular():
    w = build_world("forest")
    trunks = w.static.triangles[w.static.reflectivity == np.float32(BARK)]
    bark = w.static.vertices[trunks.ravel()]
    rows = np.round(bark[:, 1] / 4.0)
    assert len(np.unique(rows)) == 10
    assert np.abs(bark[:, 1] - 4.0 * rows).max() < 0.8  # jitter + trunk radius


def test_unknown_world_is_a_config_error():
    with pytest.raises(ConfigError, match=r"unknown world 'moon'.*office, building"):
        build_world("moon")


def test_surface_sampling_density_and_ply_files_round_trip(tmp_path):
    import open3d as o3d

    b = MeshBuilder()
    b.box([0, 0, 0], [2, 3, 4], 0.5)
    mesh = b.build()
    area = 2 * (2 * 3 + 2 * 4 + 3 * 4)
    pts, normals = sample_surface(mesh, 2000.0, np.random.default_rng(0))
    assert len(pts) == pytest.approx(area * 2000, rel=0.02)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    write_mesh_ply(mesh, tmp_path / "box.ply")
    write_points_ply(pts, normals, tmp_path / "pts.ply")
    loaded = o3d.io.read_triangle_mesh(str(tmp_path / "box.ply"))
    assert np.allclose(np.asarray(loaded.vertices), mesh.vertices)
    assert np.array_equal(np.asarray(loaded.triangles), mesh.triangles)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "pts.ply"))
    assert np.allclose(np.asarray(cloud.points), pts, atol=1e-5)


def test_world_seed_fixes_the_layout_while_the_seed_changes_the_noise(tmp_path):
    """Same seeds, same files; the world seed places the props, the seed draws the noise."""
    from mcl3d.sim.pipeline import SimulateRequest, run

    def simulate(seed, world_seed, name):
        log, mesh = tmp_path / f"{name}.mcap", tmp_path / f"{name}.ply"
        run(SimulateRequest("arena", "vlp16", "ground", 0.1, seed, log, export_mesh=mesh,
                            overrides={"lidar.column_stride": 20}, world_seed=world_seed))
        return mesh.read_bytes(), log.read_bytes()

    mesh_a, log_a = simulate(1, 7, "a")
    assert simulate(1, 7, "a again") == (mesh_a, log_a)  # the same bytes on one machine
    mesh_b, log_b = simulate(2, 7, "b")
    mesh_c, _ = simulate(7, None, "c")
    mesh_d, _ = simulate(1, None, "d")
    assert mesh_a == mesh_b == mesh_c != mesh_d  # the stage and crate where world seed 7 puts them
    assert log_a != log_b  # other noise
    with pytest.raises(ConfigError, match="world seed"):
        simulate(1, -1, "e")
