"""Mesh maps visit only cells near the surface (an octree descent) and hold the same arrays
as when every coarse cell of the bounds was evaluated (kept here as the NumPy reference)."""

import numpy as np
import pytest
from support import localize_world
from support import tsdf_world as world

from mcl3d.maps import build
from mcl3d.maps.build import BuildConfig, MeshDistance


def dense_mesh_cells(mesh, geometry, config):
    """The former implementation: the signed distance at every coarse cell's centre."""
    dims = np.asarray(geometry.coarse_dims)
    cells = np.stack(np.meshgrid(*[np.arange(n) for n in dims], indexing="ij"),
                     axis=-1).reshape(-1, 3).astype(np.int32)
    centers = np.asarray(geometry.origin_m) + (cells + 0.5) * geometry.block_size_m
    sd = mesh.signed_distance(centers, config.mesh_sign)
    half_diag = 0.5 * np.sqrt(3) * geometry.block_size_m
    near = np.abs(sd) < config.trunc_m + half_diag + 1e-6
    return cells[near], cells[sd >= config.trunc_m + half_diag]


def _meshes():
    vertices, triangles = world.room_mesh()
    room, hall = localize_world.room_mesh(), localize_world.hall_mesh()
    return {"tsdf room": (vertices, triangles, {}),
            "room 5 cm": (room.vertices, room.triangles, {}),
            "tsdf room parity": (vertices, triangles, {"mesh_sign": "parity"}),
            "hall 10 cm, wide band": (hall.vertices, hall.triangles,
                                      {"voxel_size_m": 0.1, "truncation_m": 0.5}),
            "office world": (*_world("office"), {}),
            "forest world 10 cm": (*_world("forest"), {"voxel_size_m": 0.1})}


def _world(name):
    from mcl3d.sim.worlds import build_world

    mesh = build_world(name, 0).static
    return mesh.vertices, mesh.triangles


@pytest.mark.parametrize("name", list(_meshes()))
def test_near_and_free_cells_equal_the_dense_evaluation(name):
    vertices, triangles, overrides = _meshes()[name]
    cfg = BuildConfig(**overrides)
    geometry = build.MapGeometry.around(vertices.min(0), vertices.max(0), cfg.voxel_size_m,
                                        cfg.trunc_m, margin_m=cfg.trunc_m)
    mesh = MeshDistance(vertices, triangles)
    near, free = build._mesh_cells(mesh, geometry, cfg)
    want_near, want_free = dense_mesh_cells(mesh, geometry, cfg)
    np.testing.assert_array_equal(near, want_near)
    np.testing.assert_array_equal(free, want_free)
    assert len(near) and len(free)


def test_solids_sharing_faces_differ_only_inside_the_solids():
    """The room at 2 cm: the notch box's face and the wall's inner face coincide with
    opposite normals, and which of the two a query inside the notch finds decides its sign
    (either way). Near cells are the same; free cells differ only inside solids (ray parity
    says inside), where the dense evaluation also marked some free."""
    room = localize_world.room_mesh()
    cfg = BuildConfig(voxel_size_m=0.02)
    geometry = build.MapGeometry.around(room.vertices.min(0), room.vertices.max(0), 0.02,
                                        cfg.trunc_m, margin_m=cfg.trunc_m)
    mesh = MeshDistance(room.vertices, room.triangles)
    near, free = build._mesh_cells(mesh, geometry, cfg)
    want_near, want_free = dense_mesh_cells(mesh, geometry, cfg)
    np.testing.assert_array_equal(near, want_near)
    differ = np.array(sorted(set(map(tuple, free)) ^ set(map(tuple, want_free))))
    centres = np.asarray(geometry.origin_m) + (differ + 0.5) * geometry.block_size_m
    assert 0 < len(differ) < 0.002 * len(want_free)
    assert (mesh.signed_distance(centres, "parity") < 0).all()


def test_the_map_arrays_equal_those_from_every_cell(ti_runtime, monkeypatch):
    """Whole maps: blocks (coordinates, distances, weights) and FREE cells are identical."""
    room = localize_world.room_mesh()
    cfg = BuildConfig(voxel_size_m=0.1)
    got = build.build_from_mesh(room.vertices, room.triangles, cfg).blocks().sorted()
    monkeypatch.setattr(build, "_mesh_cells", dense_mesh_cells)
    want = build.build_from_mesh(room.vertices, room.triangles, cfg).blocks().sorted()
    for field in ("coords", "sdf", "weight", "free_coords"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))


def test_only_cells_near_the_surface_are_evaluated(monkeypatch):
    """Two small boxes 500 m apart at 5 cm: the bounds hold 20,000 coarse cells, the descent
    asks the mesh for a small share of them and finds the same cells."""
    from mcl3d.sim.mesh import MeshBuilder

    b = MeshBuilder()
    b.box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.5)
    b.box((500.0, 0.3, 0.2), (501.0, 1.2, 1.5), 0.5)
    mesh_data = b.build()
    cfg = BuildConfig()
    geometry = build.MapGeometry.around(mesh_data.vertices.min(0), mesh_data.vertices.max(0),
                                        cfg.voxel_size_m, cfg.trunc_m, margin_m=cfg.trunc_m)
    mesh = MeshDistance(mesh_data.vertices, mesh_data.triangles)
    asked = []
    query = mesh.signed_distance
    monkeypatch.setattr(mesh, "signed_distance",
                        lambda q, sign: asked.append(len(q)) or query(q, sign))
    near, free = build._mesh_cells(mesh, geometry, cfg)
    assert geometry.n_cells > 10_000 and sum(asked) < 0.2 * geometry.n_cells
    want_near, want_free = dense_mesh_cells(mesh, geometry, cfg)
    np.testing.assert_array_equal(near, want_near)
    np.testing.assert_array_equal(free, want_free)
