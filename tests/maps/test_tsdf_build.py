"""Maps built from a mesh, from scans and from points agree with the exact signed distance.

The world is a small box room (tests/tsdf_world.py); scans are ray cast from known poses.
"""

import numpy as np
import pytest
from support import tsdf_world as world

from mcl3d.core.errors import MapError, PointCloudError


@pytest.fixture(scope="module")
def room():
    vertices, triangles = world.room_mesh()
    return vertices, triangles, world.scene_of(vertices, triangles)


@pytest.fixture(scope="module")
def scans(room):
    return [world.scan(room[2], T) for T in world.POSES]


def _exact(scene, pts):
    return scene.signed_distance(pts, "normals")


def _voxels(tsdf):
    data = tsdf.blocks()
    centers = world.voxel_centers(tsdf.geometry, data.coords)
    return data, centers, data.sdf.reshape(-1), data.weight.reshape(-1)


def _near_accuracy(tsdf, scene):
    """Fraction of observed voxels with |exact d| < truncation within half a voxel."""
    _, centers, d, w = _voxels(tsdf)
    exact = _exact(scene, centers)
    near = (w > 0) & (np.abs(exact) < tsdf.truncation_m)
    err = np.abs(d[near] - exact[near])
    return (err < 0.5 * tsdf.voxel_size_m).mean(), near.sum()


def _free_blocks_exact(tsdf, scene):
    data = tsdf.blocks()
    return _exact(scene, world.voxel_centers(tsdf.geometry, data.free_coords))


def _fuse(room, scans, **overrides):
    from mcl3d.maps.build import BuildConfig, MapGeometry, ScanFuser, new_map

    cfg = BuildConfig(**overrides)
    vertices = room[0]
    geometry = MapGeometry.around(vertices.min(0), vertices.max(0), cfg.voxel_size_m,
                                  cfg.trunc_m, margin_m=cfg.trunc_m)
    tsdf = new_map(geometry, cfg)
    fuser = ScanFuser(tsdf, cfg)
    for T, (_, pts) in zip(world.POSES, scans, strict=True):
        fuser.fuse(pts, T)
    tsdf.finalize()
    return tsdf


@pytest.fixture(scope="module")
def fused(backend, room, scans):
    """The room fused from its scans with the default settings, built once for the tests
    that only read it (each new map compiles the fusion kernels again)."""
    from mcl3d.core import runtime

    runtime.init(backend)  # the runtime `ti_runtime` keeps
    return _fuse(room, scans)


def test_mesh_map_is_exact_and_marks_free_space(ti_runtime, room):
    from mcl3d.maps.build import BuildConfig, build_from_mesh

    tsdf = build_from_mesh(room[0], room[1], BuildConfig())
    frac, n = _near_accuracy(tsdf, room[2])
    assert n > 10000 and frac > 0.99
    _, centers, d, _w = _voxels(tsdf)
    exact = _exact(room[2], centers)
    far = exact >= tsdf.truncation_m
    assert (d[far] >= tsdf.truncation_m * 0.999).all()  # free voxels are free
    free = _free_blocks_exact(tsdf, room[2])
    assert len(free) > 100 and (free >= tsdf.truncation_m).all()


def test_fused_scans_match_the_exact_distance(room, fused):
    tsdf = fused
    frac, n = _near_accuracy(tsdf, room[2])
    assert n > 10000
    assert frac > 0.95, f"only {frac:.3f} of near-surface voxels within half a voxel"
    _, centers, d, w = _voxels(tsdf)
    exact = _exact(room[2], centers)
    marked_free = (w > 0) & (d >= tsdf.truncation_m * 0.999)
    assert (exact[marked_free] > 0).mean() > 0.995  # free voxels are outside solids
    free = _free_blocks_exact(tsdf, room[2])
    assert len(free) > 50
    assert (free >= tsdf.truncation_m).mean() > 0.99
    assert (free > 0).mean() > 0.999


def test_point_to_plane_beats_projective_distances(ti_runtime, room, scans, fused):
    plane, _ = _near_accuracy(fused, room[2])
    projective, _ = _near_accuracy(_fuse(room, scans, normals="none"), room[2])
    assert plane > projective + 0.1


def test_fused_surface_agrees_with_open3d_within_one_voxel(room, scans, fused):
    import open3d as o3d
    import open3d.core as o3c
    import taichi as ti

    from mcl3d.core.geometry import se3_inverse
    from mcl3d.kernels import tsdf_lookup as k

    tsdf = fused
    voxel, trunc_vox = tsdf.voxel_size_m, tsdf.truncation_m / tsdf.voxel_size_m
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1,), (1,)), voxel_size=voxel, block_resolution=8, block_count=20000)
    K = o3c.Tensor(world.intrinsics(), o3c.float64)
    for T, (depths, _) in zip(world.POSES, scans, strict=True):
        for cam, depth in enumerate(depths):
            extrinsic = o3c.Tensor(se3_inverse(T @ world.T_rig_cam(cam)), o3c.float64)
            image = o3d.t.geometry.Image(o3c.Tensor(depth))
            blocks = grid.compute_unique_block_coordinates(
                image, K, extrinsic, depth_scale=1.0, depth_max=20.0,
                trunc_voxel_multiplier=trunc_vox)
            grid.integrate(blocks, image, K, extrinsic, depth_scale=1.0, depth_max=20.0,
                           trunc_voxel_multiplier=trunc_vox)
    surface = grid.extract_point_cloud(weight_threshold=1.0).point.positions.numpy()
    assert len(surface) > 5000

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              out: ti.types.ndarray(dtype=ti.math.vec2, ndim=1)):
        for i in range(p.shape[0]):
            out[i] = k.sdf_trilinear(m, p[i])

    out = np.zeros((len(surface), 2), np.float32)
    query(tsdf, surface.astype(np.float32), out)
    err = np.abs(out[:, 0])
    assert np.median(err) < 0.5 * voxel
    assert (err < voxel).mean() > 0.95
    # and both surfaces lie on the mesh
    assert np.median(np.abs(_exact(room[2], surface))) < 0.5 * voxel


def test_points_map_from_surface_samples(ti_runtime, room):
    from mcl3d.maps.build import BuildConfig
    from mcl3d.maps.point_build import build_from_points

    pts = world.surface_samples(room[0], room[1], 60000, np.random.default_rng(0))
    pts = world.seen_from_inside(pts)
    viewpoints = np.array([T[:3, 3] for T in world.POSES])
    tsdf = build_from_points(pts, BuildConfig(), viewpoints=viewpoints)
    frac, n = _near_accuracy(tsdf, room[2])
    assert n > 10000 and frac > 0.85  # edges and corners of a sampled surface blur
    free = _free_blocks_exact(tsdf, room[2])
    assert len(free) > 50 and (free > 0).mean() > 0.99


def test_capacity_overflow_says_how_many_blocks_are_needed(ti_runtime, room):
    from mcl3d.maps.build import BuildConfig, build_from_mesh

    with pytest.raises(MapError, match=r"needs \d+ blocks.*max_capacity_blocks 100"):
        build_from_mesh(room[0], room[1], BuildConfig(capacity_blocks=100,
                                                      max_capacity_blocks=100))


def test_fusion_grows_and_retries_on_overflow(ti_runtime, room, scans):
    from mcl3d.maps.build import BuildConfig, MapGeometry, ScanFuser, grown_capacity, new_map

    cfg = BuildConfig(capacity_blocks=50)
    geometry = MapGeometry.around(room[0].min(0), room[0].max(0), 0.05, cfg.trunc_m)
    tsdf = new_map(geometry, cfg)
    ScanFuser(tsdf, cfg).fuse(scans[0][1], world.POSES[0])
    assert tsdf.overflowed
    bigger = grown_capacity(tsdf, cfg)
    assert bigger > tsdf.requested_blocks
    with pytest.raises(MapError, match="needs"):
        tsdf.check_capacity()
    tight = BuildConfig(capacity_blocks=50, max_capacity_blocks=60)
    with pytest.raises(MapError, match=r"needs \d+ blocks but max_capacity_blocks is 60"):
        grown_capacity(tsdf, tight)


def test_bad_inputs(ti_runtime):
    from mcl3d.core.errors import ConfigError
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.point_build import build_from_points

    with pytest.raises(PointCloudError, match="0 valid points"):
        build_from_points(np.zeros((0, 3)), BuildConfig())
    with pytest.raises(PointCloudError, match="valid points"):
        build_from_points(np.full((50, 3), np.nan), BuildConfig())
    with pytest.raises(PointCloudError, match="no triangles"):
        build_from_mesh(np.zeros((3, 3)), np.zeros((0, 3), int), BuildConfig())
    with pytest.raises(PointCloudError, match="outside its vertex list"):
        build_from_mesh(np.eye(3), np.array([[0, 1, 5]]), BuildConfig())
    from mcl3d.core.config import build

    with pytest.raises(ConfigError, match="truncation_m"):
        build(BuildConfig, {"voxel_size_m": 0.1, "truncation_m": 0.05})
    with pytest.raises(ConfigError, match="voxel_size_m"):
        build(BuildConfig, {"voxel_size_m": -1})


def test_deskewing_uses_each_points_pose(ti_runtime, room, scans):
    """A scan taken while moving, deskewed, gives the map of the scan taken standing still."""
    from mcl3d.core.geometry import interpolate_se3, se3_inverse
    from mcl3d.maps.build import BuildConfig, MapGeometry, ScanFuser, new_map

    cfg = BuildConfig(normals="none")
    geometry = MapGeometry.around(room[0].min(0), room[0].max(0), 0.05, cfg.trunc_m)
    T = world.POSES[0]
    pts = scans[0][1]
    world_pts = pts @ T[:3, :3].T + T[:3, 3]
    T_end = T.copy()
    T_end[:3, 3] += [0.25, -0.1, 0.0]  # 2.5 m/s for 0.1 s
    alpha = np.random.default_rng(0).random(len(pts)).astype(np.float32)
    T_point = interpolate_se3(T, T_end, alpha.astype(np.float64))
    T_inv = se3_inverse(T_point)
    moving = (np.einsum("nij,nj->ni", T_inv[:, :3, :3], world_pts) + T_inv[:, :3, 3])
    tsdf = new_map(geometry, cfg)  # one map, cleared between runs: compiled once

    def residual(*args):
        tsdf.clear()
        tsdf.as_sums = True
        ScanFuser(tsdf, cfg).fuse(*args)
        tsdf.finalize()
        return np.median(np.abs(_at(tsdf, world_pts)))

    assert residual(pts, T) < 0.01
    assert residual(moving.astype(np.float32), T, T_end, alpha) < 0.01
    assert residual(moving.astype(np.float32), T) > 0.03  # not deskewed: smeared


def _at(tsdf, pts):
    import taichi as ti

    from mcl3d.kernels import tsdf_lookup as k

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              out: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(p.shape[0]):
            out[i] = k.sdf_trilinear(m, p[i])[0]

    out = np.zeros(len(pts), np.float32)
    query(tsdf, np.ascontiguousarray(pts, dtype=np.float32), out)
    return out


def test_mesh_sign_is_right_beside_edges_and_corners():
    """Nearest-face normals get the sign wrong beside edges whose faces meet at more than 90
    degrees (a tetrahedron's); angle-weighted pseudo-normals agree with ray parity."""
    import open3d as o3d

    from mcl3d.maps.build import MeshDistance

    tetra = o3d.geometry.TriangleMesh.create_tetrahedron(1.0)  # closed, normals outward
    mesh = MeshDistance(np.asarray(tetra.vertices), np.asarray(tetra.triangles))
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (20000, 3))
    ours = mesh.signed_distance(pts, "normals")
    np.testing.assert_allclose(ours, mesh.signed_distance(pts, "parity"), atol=1e-5)
    res = mesh.scene.compute_closest_points(o3d.core.Tensor(pts.astype(np.float32)))
    face_n = mesh.face_normals[res["primitive_ids"].numpy()]
    face_sign = np.einsum("ij,ij->i", pts - res["points"].numpy(), face_n) >= 0
    assert (face_sign != (ours >= 0)).sum() > 1000  # the nearest-face rule fails here
