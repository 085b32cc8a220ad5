"""A tiny room world for the localization tests: mesh -> TSDF map, ray-cast scans, a path.

Small enough to build in about a second; asymmetric furniture so that global localization
has one answer.
"""

from __future__ import annotations

import numpy as np

from mcl3d.core import geometry

ROOM = (8.0, 6.0, 3.0)  # m, inside dimensions
LIDAR_Z_M = 0.8


def room_mesh():
    from mcl3d.sim.mesh import MeshBuilder

    b = MeshBuilder()
    x, y, z = ROOM
    t = 0.2
    b.box((-t, -t, -t), (x + t, y + t, 0.0), 0.5)  # floor
    b.box((-t, -t, z), (x + t, y + t, z + t), 0.5)  # ceiling
    b.box((-t, -t, 0.0), (0.0, y + t, z), 0.5)
    b.box((x, -t, 0.0), (x + t, y + t, z), 0.5)
    b.box((0.0, -t, 0.0), (x, 0.0, z), 0.5)
    b.box((0.0, y, 0.0), (x, y + t, z), 0.5)
    b.box((1.0, 4.0, 0.0), (2.5, 5.0, 0.75), 0.5)  # desk
    b.box((6.2, 0.5, 0.0), (7.0, 1.3, 1.8), 0.5)  # cabinet
    b.box((4.0, 2.5, 0.0), (4.4, 2.9, 1.2), 0.5)  # pillar-ish box
    b.box((0.0, 1.5, 0.0), (0.4, 3.0, 2.0), 0.5)  # shelf on the left wall
    b.box((6.0, 4.6, 0.0), (x, y, z), 0.5)  # a notch: the room is L-shaped
    b.box((2.0, 0.0, 0.0), (3.5, 0.6, 2.2), 0.5)  # a wardrobe on the long wall
    return b.build()


HALL = (16.0, 6.0, 3.0)  # m, inside dimensions
HALL_CRATE = ((13.5, 1.0), (14.5, 2.0))  # the one feature without a 180-degree twin


def hall_mesh():
    """A hall that is 180-degree symmetric about its centre (x, y) = (8, 3) except for one
    crate near its +x end: from the middle, the true pose and its mirror image look alike
    until the crate comes into range."""
    from mcl3d.sim.mesh import MeshBuilder

    b = MeshBuilder()
    x, y, z = HALL
    t = 0.2
    b.box((-t, -t, -t), (x + t, y + t, 0.0), 0.5)
    b.box((-t, -t, z), (x + t, y + t, z + t), 0.5)
    b.box((-t, -t, 0.0), (0.0, y + t, z), 0.5)
    b.box((x, -t, 0.0), (x + t, y + t, z), 0.5)
    b.box((0.0, -t, 0.0), (x, 0.0, z), 0.5)
    b.box((0.0, y, 0.0), (x, y + t, z), 0.5)
    for (x0, y0), (x1, y1), h in (((4.0, 1.5), (4.4, 1.9), 1.5),  # pillars, shelves
                                  ((6.5, 4.2), (7.3, 6.0), 2.0),
                                  ((2.0, 0.0), (3.0, 0.5), 1.0)):
        b.box((x0, y0, 0.0), (x1, y1, h), 0.5)
        b.box((x - x1, y - y1, 0.0), (x - x0, y - y0, h), 0.5)  # the 180-degree twin
    (cx0, cy0), (cx1, cy1) = HALL_CRATE
    b.box((cx0, cy0, 0.0), (cx1, cy1, 1.2), 0.5)
    return b.build()


def build_map(voxel_size_m: float = 0.05, mesh=None):
    from mcl3d.maps.build import BuildConfig, build_from_mesh

    mesh = room_mesh() if mesh is None else mesh
    return build_from_mesh(mesh.vertices, mesh.triangles,
                           BuildConfig(voxel_size_m=voxel_size_m))


class Scanner:
    """A 16-ring spinning lidar (+-15 deg, `n_azimuth` columns) cast against the room."""

    def __init__(self, n_azimuth: int = 360, noise_m: float = 0.01, seed: int = 0, mesh=None):
        import open3d as o3d

        mesh = room_mesh() if mesh is None else mesh
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                                 o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        az = np.linspace(0, 2 * np.pi, n_azimuth, endpoint=False)
        el = np.radians(np.linspace(-15, 15, 16))
        A, E = np.meshgrid(az, el, indexing="ij")
        self.dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)],
                             axis=-1).reshape(-1, 3)
        self.noise_m = noise_m
        self.rng = np.random.default_rng(seed)

    def scan(self, T_map_lidar: np.ndarray) -> np.ndarray:
        import open3d as o3d

        d_map = self.dirs @ T_map_lidar[:3, :3].T
        rays = np.hstack([np.repeat(T_map_lidar[None, :3, 3], len(d_map), 0), d_map])
        hit = self.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        ok = np.isfinite(hit)
        r = hit[ok] + self.noise_m * self.rng.standard_normal(ok.sum())
        return (self.dirs[ok] * r[:, None]).astype(np.float32)


def path(n: int, step_m: float = 0.15) -> np.ndarray:
    """(n, 4, 4) lidar poses along an ellipse in the room's free middle, facing forward."""
    s = np.arange(n) * step_m / 2.3
    x = 3.8 + 2.3 * np.cos(s)
    y = 2.8 + 1.1 * np.sin(s)
    yaw = np.arctan2(1.1 * np.cos(s), -2.3 * np.sin(s))
    return np.stack([geometry.se3(geometry.rpy_to_rot(0.0, 0.0, a), [px, py, LIDAR_Z_M])
                     for px, py, a in zip(x, y, yaw, strict=True)])


T_BASE_LIDAR = geometry.se3(geometry.rpy_to_rot(0.0, 0.0, 0.1), [0.2, 0.0, 0.5])
START_NS = 1_700_000_000_000_000_000


def write_log(log_path, n_scans: int = 12, *, odom: bool = True, gt: bool = True,
              empty_scans: tuple[int, ...] = (), n_azimuth: int = 180, seed: int = 0) -> None:
    """A 10 Hz log of the room: /lidar/points, /odom at 50 Hz (base_link, drifting a little),
    /ground_truth (T_map_lidar) and /tf_static base_link -> lidar."""
    from mcl3d.io.logs.messages import Odometry, PointCloud, PoseStamped, Transform
    from mcl3d.io.logs.writer import LogWriter

    rng = np.random.default_rng(seed)
    scanner = Scanner(n_azimuth=n_azimuth, seed=seed)
    lidar_path = path(n_scans)
    T_lidar_base = geometry.se3_inverse(T_BASE_LIDAR)
    base = lidar_path @ T_lidar_base
    T_odom_map = geometry.se3(geometry.rpy_to_rot(0.0, 0.0, 0.5), [1.0, -2.0, 0.0])
    with LogWriter(log_path) as w:
        w.write_tf("/tf_static", [Transform(START_NS, "base_link", "lidar", T_BASE_LIDAR)])
        for k in range(n_scans):
            stamp = START_NS + k * 100_000_000
            if odom:
                for j in range(5):
                    a = j / 5.0
                    T = (geometry.interpolate_se3(base[k - 1], base[k], a) if k > 0
                         else base[0])
                    T = T @ geometry.se3_exp(rng.normal(0, 0.002, 6))
                    w.write_odometry("/odom", Odometry(stamp - 100_000_000 + int(a * 1e8) + 1,
                                                       "odom", "base_link", T_odom_map @ T,
                                                       np.zeros(6), np.eye(6) * 1e-4))
                w.write_odometry("/odom", Odometry(stamp, "odom", "base_link",
                                                   T_odom_map @ base[k], np.zeros(6),
                                                   np.eye(6) * 1e-4))
            pts = (np.zeros((0, 3), np.float32) if k in empty_scans
                   else scanner.scan(lidar_path[k]))
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, None))
            if gt:
                w.write_pose("/ground_truth", PoseStamped(stamp, "map", lidar_path[k]))


def save_room_map(path, voxel_size_m: float = 0.05, offset_m=(0.0, 0.0, 0.0)) -> None:
    """The room's map as a .tsdf file (optionally built from the room moved by offset_m)."""
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.map_file import save_map

    mesh = room_mesh()
    tsdf = build_from_mesh(mesh.vertices + np.asarray(offset_m), mesh.triangles,
                           BuildConfig(voxel_size_m=voxel_size_m))
    save_map(path, tsdf, source={"kind": "test room"}, build={})


def placed_together(parts, voxel_size_m: float):
    """One map holding each (map, offset in blocks) at its offset: bounds over all of them,
    blocks and FREE cells copied (the maps share voxel size, truncation and block grid)."""
    from mcl3d.maps.tsdf import MapGeometry, TsdfMap

    first = parts[0][0]
    dims = np.max([np.asarray(m.coarse_dims) + off for m, off in parts], axis=0)
    g = MapGeometry(voxel_size_m, first.truncation_m, first.origin_m, tuple(int(d) for d in dims))
    data = [(m.blocks(), np.asarray(off, np.int32)) for m, off in parts]
    n = sum(len(d.coords) for d, _ in data)
    tsdf = TsdfMap(g, n, writable=False, capacity_tiles=4096)
    for d, off in data:
        tsdf.allocate(d.coords + off)
        tsdf.write_blocks(d.coords + off, d.sdf, d.weight)
        tsdf.mark_free(d.free_coords + off)
    return tsdf
