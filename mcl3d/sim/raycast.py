"""Ray casting against a world with Open3D's RaycastingScene (BVH, multi-threaded).

The static world is one scene; the elevator cab and its door are separate scenes in the cab
frame, so each ray is tested against the cab where the cab was at that ray's time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from mcl3d.sim.mesh import Mesh
from mcl3d.sim.worlds import World


@dataclass
class Hits:
    range_m: np.ndarray  # (N,) inf where nothing was hit
    reflectivity: np.ndarray  # (N,) of the surface hit
    cos_incidence: np.ndarray  # (N,) |cos| of the angle between ray and surface normal
    scatter_depth_m: np.ndarray | None = None  # (N,) of the surface hit; None: all solid


class _Scene:
    def __init__(self, mesh: Mesh) -> None:
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                                 o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        self.reflectivity = mesh.reflectivity
        self.scatter_depth_m = mesh.scatter_depth_m

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        out = self.scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = out["t_hit"].numpy()
        prim = out["primitive_ids"].numpy()
        normals = out["primitive_normals"].numpy()
        hit = np.isfinite(t_hit)
        refl = np.zeros(len(t_hit), dtype=np.float32)
        refl[hit] = self.reflectivity[prim[hit]]
        cos_inc = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:]))
        return t_hit, refl, cos_inc, prim

    def scatter_at(self, prim: np.ndarray, hit: np.ndarray) -> np.ndarray | None:
        """Scatter depth (m) of the triangle each ray hit, or None in a world of solids."""
        if self.scatter_depth_m is None:
            return None
        out = np.zeros(len(prim), dtype=np.float32)
        out[hit] = self.scatter_depth_m[prim[hit]]
        return out


class WorldCaster:
    """Casts rays with per-ray times against the static world and the moving elevator cab."""

    def __init__(self, world: World) -> None:
        self.world = world
        self._static = _Scene(world.static)
        elev = world.elevator
        self._shell = _Scene(elev.shell) if elev is not None else None
        self._door = _Scene(elev.door) if elev is not None else None

    def cast(self, origins: np.ndarray, directions: np.ndarray, cab_z_m: np.ndarray | None = None,
             door_closed: np.ndarray | None = None) -> Hits:
        """Cast unit `directions` from `origins` (both (N, 3) in the map frame). `cab_z_m` and
        `door_closed` give the elevator state at each ray's time (ignored without a cab)."""
        rays = np.empty((len(origins), 6), dtype=np.float32)
        rays[:, :3], rays[:, 3:] = origins, directions
        t_hit, refl, cos_inc, prim = self._static.cast(rays)
        scatter = self._static.scatter_at(prim, np.isfinite(t_hit))
        if self._shell is not None and cab_z_m is not None:
            offset = np.zeros((len(rays), 3), dtype=np.float32)
            offset[:, :2] = self.world.elevator.center_xy
            offset[:, 2] = cab_z_m
            local = rays.copy()
            local[:, :3] -= offset
            parts = [(self._shell, np.ones(len(rays), dtype=bool))]
            if door_closed is not None and door_closed.any():
                parts.append((self._door, door_closed))
            for scene, use in parts:
                idx = np.flatnonzero(use)
                t2, r2, c2, _ = scene.cast(local[idx])
                closer = t2 < t_hit[idx]
                sel = idx[closer]
                t_hit[sel], refl[sel], cos_inc[sel] = t2[closer], r2[closer], c2[closer]
                if scatter is not None:  # the cab is solid
                    scatter[sel] = 0.0
        return Hits(t_hit.astype(np.float64), refl, cos_inc, scatter)
