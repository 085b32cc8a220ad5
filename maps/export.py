"""Looking at a map in any viewer: its zero level set as a mesh, surface voxels as points."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, MapError
from mcl3d.core.outputs import atomic_path
from mcl3d.maps.tsdf import BLOCK, BlockData, MapGeometry, surface_points

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".gltf", ".glb")
POINT_SUFFIXES = (".ply", ".pcd", ".xyz", ".pts")


def level_set_mesh(geometry: MapGeometry, data: BlockData, min_weight: float = 1e-6):
    """Marching cubes over the blocks with Open3D's VoxelBlockGrid (block resolution 8).

    Returns an open3d.t.geometry.TriangleMesh in the map frame.
    """
    import open3d as o3d  # in the functions: 0.5 s of import a map build does not need
    import open3d.core as o3c

    n = len(data.coords)
    if n == 0:
        raise MapError("the map has no allocated blocks: there is no surface to export")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1,), (1,)), voxel_size=geometry.voxel_size_m,
        block_resolution=BLOCK, block_count=n + 16)
    keys = o3c.Tensor(np.ascontiguousarray(data.coords, dtype=np.int32))
    buf_indices, _ = grid.hashmap().activate(keys)
    idx = buf_indices.cpu().numpy().astype(np.int64)
    tsdf = grid.attribute("tsdf")
    weight = grid.attribute("weight")
    # Open3D stores a block's voxels as [z, y, x]; ours are [x, y, z]; tsdf is d / trunc.
    values = np.transpose(data.sdf.astype(np.float32), (0, 3, 2, 1)) / geometry.truncation_m
    weights = np.transpose(data.weight.astype(np.float32), (0, 3, 2, 1))
    weights = np.where(weights > min_weight, weights, 0.0).astype(np.float32)
    tsdf_np = np.zeros(tuple(tsdf.shape), np.float32)
    weight_np = np.zeros(tuple(weight.shape), np.float32)
    tsdf_np[idx] = values[..., None]
    weight_np[idx] = weights[..., None]
    tsdf[:] = o3c.Tensor(tsdf_np)
    weight[:] = o3c.Tensor(weight_np)
    mesh = grid.extract_triangle_mesh(weight_threshold=min_weight)
    # Open3D puts voxel (i, j, k) at (i, j, k) * voxel; ours is at origin + (i + 0.5) voxel.
    shift = np.asarray(geometry.origin_m) + 0.5 * geometry.voxel_size_m
    mesh.vertex.positions = mesh.vertex.positions + o3c.Tensor(shift.astype(np.float32))
    return mesh


def write_mesh(path: Path, geometry: MapGeometry, data: BlockData) -> int:
    """Write the zero level set to a mesh file atomically; returns the triangle count."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: unknown mesh type; use one of {', '.join(MESH_SUFFIXES)}")
    import open3d as o3d

    mesh = level_set_mesh(geometry, data).to_legacy()
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise MapError(f"could not write the mesh to {path}")
    return len(mesh.triangles)


def write_points(path: Path, geometry: MapGeometry, data: BlockData) -> int:
    """Write surface voxel centres as a point cloud atomically; returns the point count."""
    path = Path(path)
    if path.suffix.lower() not in POINT_SUFFIXES:
        raise InputError(f"{path}: unknown point-cloud type; use one of "
                         f"{', '.join(POINT_SUFFIXES)}")
    import open3d as o3d

    pts = surface_points(geometry, data)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd):
            raise MapError(f"could not write the point cloud to {path}")
    return len(pts)
