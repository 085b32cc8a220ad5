"""A tiny box room for the TSDF tests: its mesh, exact signed distances, ray-cast scans.

A scan is 4 pinhole depth images (90° each, the rig yawing through 360°), so Open3D's
projective TSDF integration can take the very same data as our ray fusion.
"""

from __future__ import annotations

import numpy as np

W = H = 64
FOV_DEG = 90.0


def room_mesh() -> tuple[np.ndarray, np.ndarray]:
    """6 x 5 x 3 m room of solid 0.2 m slabs plus two boxes; normals face free space."""
    import open3d as o3d

    parts = []

    def box(lo, hi):
        lo, hi = np.array(lo, float), np.array(hi, float)
        b = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
        b.translate(lo)
        parts.append(b)

    box([-0.2, -0.2, -0.2], [6.2, 5.2, 0.0])
    box([-0.2, -0.2, 3.0], [6.2, 5.2, 3.2])
    box([-0.2, -0.2, 0.0], [0.0, 5.2, 3.0])
    box([6.0, -0.2, 0.0], [6.2, 5.2, 3.0])
    box([0.0, -0.2, 0.0], [6.0, 0.0, 3.0])
    box([0.0, 5.0, 0.0], [6.0, 5.2, 3.0])
    box([1.0, 1.0, 0.0], [1.8, 1.6, 0.9])
    box([4.0, 3.0, 0.0], [4.5, 4.2, 1.5])
    mesh = parts[0]
    for p in parts[1:]:
        mesh += p
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def surface_samples(vertices: np.ndarray, triangles: np.ndarray, n: int,
                    rng: np.random.Generator) -> np.ndarray:
    """`n` points uniform over the mesh's surface (triangles picked by area)."""
    tri = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    a, b = rng.random((2, n, 1))
    flip = (a + b) > 1  # fold the far half of the unit square back into the triangle
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    return t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])


def seen_from_inside(pts: np.ndarray) -> np.ndarray:
    """The points of the room's inner faces and boxes: what a scanner inside it could see."""
    return pts[np.all((pts > -1e-3) & (pts < [6.001, 5.001, 3.001]), axis=1)]


def pose(x, y, z, yaw) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


POSES = [pose(3.0, 2.5, 1.2, 0.3), pose(2.0, 3.8, 1.0, 2.0), pose(5.0, 1.5, 1.4, -1.0)]


def intrinsics() -> np.ndarray:
    f = 0.5 * W / np.tan(np.deg2rad(FOV_DEG / 2))
    return np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])


def T_rig_cam(k: int) -> np.ndarray:
    """Camera k looks along rig yaw k·90° (camera z forward, x right, y down)."""
    yaw = k * np.pi / 2
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R0
    return T


def scene_of(vertices, triangles):
    """The mesh's exact signed distance (`.signed_distance`) and ray-casting scene (`.scene`)."""
    from mcl3d.maps.build import MeshDistance

    return MeshDistance(vertices, triangles)


def scan(scene, T_world_rig) -> tuple[np.ndarray, np.ndarray]:
    """Depth images (4, H, W) float32 and the rig-frame points of all valid pixels."""
    import open3d as o3d

    K = intrinsics()
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dirs_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    depths, pts = [], []
    for k in range(4):
        T_wc = T_world_rig @ T_rig_cam(k)
        dirs_w = dirs_c @ T_wc[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T_wc[:3, 3], dirs_w.shape), dirs_w], -1)
        t = scene.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        depth = np.where(np.isfinite(t), t, 0).astype(np.float32)
        depths.append(depth)
        ok = depth > 0
        pc = dirs_c[ok] * depth[ok][:, None]
        pts.append(pc @ T_rig_cam(k)[:3, :3].T + T_rig_cam(k)[:3, 3])
    return np.stack(depths), np.concatenate(pts).astype(np.float32)


def voxel_centers(geometry, coords: np.ndarray) -> np.ndarray:
    """World centres (n*512, 3) of the voxels of blocks `coords`, in [block, x, y, z] order."""
    local = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1)
    vox = (coords[:, None, None, None, :].astype(np.int64) * 8 + local[None]).reshape(-1, 3)
    return np.asarray(geometry.origin_m) + (vox + 0.5) * geometry.voxel_size_m
