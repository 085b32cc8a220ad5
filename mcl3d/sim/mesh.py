"""Triangle meshes for simulated worlds: primitives, surface sampling and binary PLY export.

Every triangle carries a diffuse reflectivity in [0, 1] so that simulated LiDAR intensity
depends on the material as well as on range and incidence angle, and a scatter depth: 0 for
a solid surface, else the mean depth (m) a laser pulse travels into a porous volume (a tree's
foliage) before a leaf returns it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d.core.outputs import atomic_open


@dataclass
class Mesh:
    """Vertices (V, 3) float64 in metres, triangles (F, 3) int32, reflectivity (F,) float32,
    scatter depth (F,) float32 in metres (None: every triangle solid)."""

    vertices: np.ndarray
    triangles: np.ndarray
    reflectivity: np.ndarray
    scatter_depth_m: np.ndarray | None = None

    def scatter_depths_m(self) -> np.ndarray:
        if self.scatter_depth_m is None:
            return np.zeros(self.n_triangles, dtype=np.float32)
        return self.scatter_depth_m

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def translated(self, offset_m: np.ndarray) -> Mesh:
        return Mesh(self.vertices + np.asarray(offset_m, dtype=np.float64), self.triangles,
                    self.reflectivity, self.scatter_depth_m)

    def triangle_areas_m2(self) -> np.ndarray:
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    def triangle_normals(self) -> np.ndarray:
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all of `meshes` (vertex indices shifted)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.triangles + off for m, off in zip(meshes, offsets, strict=True)])
        .astype(np.int32),
        np.concatenate([m.reflectivity for m in meshes]).astype(np.float32),
        None if all(m.scatter_depth_m is None for m in meshes)
        else np.concatenate([m.scatter_depths_m() for m in meshes]).astype(np.float32),
    )


class MeshBuilder:
    """Accumulates primitives; `build()` returns one Mesh."""

    def __init__(self) -> None:
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._reflectivity: list[np.ndarray] = []
        self._scatter: list[np.ndarray] = []
        self._n_vertices = 0

    def add(self, vertices: np.ndarray, triangles: np.ndarray, reflectivity: float,
            scatter_depth_m: float = 0.0) -> None:
        vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self._vertices.append(vertices)
        self._triangles.append(triangles + self._n_vertices)
        self._reflectivity.append(np.full(len(triangles), reflectivity, dtype=np.float32))
        self._scatter.append(np.full(len(triangles), scatter_depth_m, dtype=np.float32))
        self._n_vertices += len(vertices)

    def box(self, lo, hi, reflectivity: float) -> None:
        """Axis-aligned box between corners `lo` and `hi` (skipped when degenerate)."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if np.any(hi - lo <= 1e-9):
            return
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                 [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
        self.add(corners, faces, reflectivity)

    def prism(self, base_xy: np.ndarray, z0: float, z1: float, reflectivity: float,
              caps: bool = True) -> None:
        """Vertical prism over a convex polygon `base_xy` (K, 2) from z0 to z1."""
        k = len(base_xy)
        bottom = np.column_stack([base_xy, np.full(k, z0)])
        top = np.column_stack([base_xy, np.full(k, z1)])
        faces = []
        for i in range(k):
            j = (i + 1) % k
            faces += [[i, j, k + j], [i, k + j, k + i]]
        if caps:
            faces += [[0, i + 1, i] for i in range(1, k - 1)]
            faces += [[k, k + i, k + i + 1] for i in range(1, k - 1)]
        self.add(np.vstack([bottom, top]), faces, reflectivity)

    def cylinder(self, center_xy, radius_m: float, z0: float, z1: float, reflectivity: float,
                 sides: int = 12) -> None:
        angles = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
        base = np.asarray(center_xy) + radius_m * np.column_stack([np.cos(angles), np.sin(angles)])
        self.prism(base, z0, z1, reflectivity)

    def cone(self, center_xy, radius_m: float, z0: float, z1: float, reflectivity: float,
             sides: int = 10, scatter_depth_m: float = 0.0) -> None:
        angles = np.linspace(0.0, 2 * np.pi, sides, endpoint=False)
        ring = np.column_stack([center_xy[0] + radius_m * np.cos(angles),
                                center_xy[1] + radius_m * np.sin(angles), np.full(sides, z0)])
        apex = [center_xy[0], center_xy[1], z1]
        centre = [center_xy[0], center_xy[1], z0]
        faces = [[i, (i + 1) % sides, sides] for i in range(sides)]
        faces += [[i, sides + 1, (i + 1) % sides] for i in range(sides)]
        self.add(np.vstack([ring, apex, centre]), faces, reflectivity, scatter_depth_m)

    def ramp(self, x0: float, x1: float, y0: float, y1: float, z_at_x0: float, z_at_x1: float,
             reflectivity: float) -> None:
        """A solid wedge whose top slopes along x from z_at_x0 to z_at_x1 (base at z=0)."""
        v = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0],
                      [x0, y0, z_at_x0], [x1, y0, z_at_x1], [x1, y1, z_at_x1], [x0, y1, z_at_x0]],
                     dtype=np.float64)
        faces = [[4, 5, 6], [4, 6, 7], [0, 2, 1], [0, 3, 2], [0, 1, 5], [0, 5, 4],
                 [3, 7, 6], [3, 6, 2], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]]
        self.add(v, faces, reflectivity)

    def heightfield(self, xs: np.ndarray, ys: np.ndarray, z: np.ndarray,
                    reflectivity: float) -> None:
        """Grid surface z[i, j] over xs[i], ys[j]."""
        nx, ny = len(xs), len(ys)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        vertices = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
        idx = np.arange(nx * ny).reshape(nx, ny)
        a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
        self.add(vertices, faces, reflectivity)

    def build(self) -> Mesh:
        if not self._vertices:
            return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.float32))
        triangles = np.concatenate(self._triangles).astype(np.int32)
        scatter = np.concatenate(self._scatter)
        return Mesh(np.concatenate(self._vertices), triangles,
                    np.concatenate(self._reflectivity), scatter if scatter.any() else None)


def sample_surface(mesh: Mesh, density_per_m2: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) spread uniformly over the surfaces at `density_per_m2`, with their normals."""
    areas = mesh.triangle_areas_m2()
    counts = rng.poisson(areas * density_per_m2)
    tri = np.repeat(np.arange(mesh.n_triangles), counts)
    u, v = rng.random(len(tri)), rng.random(len(tri))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = (mesh.vertices[mesh.triangles[tri, i]] for i in range(3))
    points = a + u[:, None] * (b - a) + v[:, None] * (c - a)
    return points, mesh.triangle_normals()[tri]


def write_mesh_ply(mesh: Mesh, path: Path) -> None:
    """Binary little-endian PLY with float32 vertices and int32 faces (opens in Open3D, MeshLab)."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment mcl3d simulated world\n"
        f"element vertex {len(mesh.vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        f"element face {mesh.n_triangles}\nproperty list uchar int vertex_indices\n"
        "property float reflectivity\nend_header\n"
    )
    faces = np.zeros(mesh.n_triangles, dtype=[("n", "u1"), ("idx", "<i4", 3), ("r", "<f4")])
    faces["n"], faces["idx"], faces["r"] = 3, mesh.triangles, mesh.reflectivity
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(mesh.vertices.astype("<f4").tobytes())
        f.write(faces.tobytes())


def write_points_ply(points: np.ndarray, normals: np.ndarray, path: Path) -> None:
    """Binary little-endian PLY point cloud with normals (the prior map format Open3D reads)."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment mcl3d simulated prior map\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nend_header\n"
    )
    data = np.hstack([points, normals]).astype("<f4")
    with atomic_open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())
