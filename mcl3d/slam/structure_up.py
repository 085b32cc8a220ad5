"""Which way is up, from the scan alone: trunks, posts and walls stand plumb, so their surface
normals lie in the horizontal plane. A LiDAR-only front-end that sees half a view drifts in
pitch, and the loops alone do not observe that drift (docs/slam.md, "What limits the graph
without an IMU"); the loop graph takes each keyframe's tilt from this measurement instead.

The tilt is found by Gauss-Newton on Σ (n·u)² over the normals within a few degrees of
horizontal, from a guess, coarse to fine; a tilt direction no vertical surface faces (one
wall, a corridor) gets no information and stays at the guess, and many normals cannot
average away that trees lean and walls are not quite plumb (`TILT_FLOOR_DEG`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

WALL_TILT_DEG = (20.0, 10.0, 5.0)  # normals this near horizontal are of plumb surfaces
NORMAL_SIGMA_DEG = 5.0  # one voxel normal's error about the vertical
TILT_FLOOR_DEG = 0.5  # left when many normals agree: trunks lean, walls are out of plumb
MIN_NORMALS = 30  # fewer plumb normals measure nothing
MAX_SURFACE_VARIATION = 0.02  # above: a neighbourhood across two surfaces (an edge, a base)
GUESS_SIGMA_DEG = 5.0  # how far the guess may be off: a tilt no normal measures stays there


@dataclass(frozen=True)
class UpMeasurement:
    """Up in a scan's frame, measured along two horizontal axes."""

    up: np.ndarray  # (3,) unit
    axes: np.ndarray  # (2, 3) unit, orthogonal to `up` and to each other
    information: np.ndarray  # (2,) of the tilt along each axis, 1/rad²


def smooth_normals(points: np.ndarray, k_neighbors: int) -> np.ndarray:
    """(M, 3) unit normals of the points whose `k_neighbors` nearest lie on one smooth surface
    or along one line (surface variation λ₀ / Σλ under `MAX_SURFACE_VARIATION`): where a
    trunk meets the ground or its crown the fitted normal leans, and with half a view all
    such leans point the same way (a pitch bias of ~0.8° in the forest)."""
    if len(points) < max(k_neighbors, MIN_NORMALS):
        return np.zeros((0, 3))
    _, idx = cKDTree(points).query(points, k=k_neighbors)
    neighbours = points[idx]
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    spread, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    smooth = spread[:, 0] < MAX_SURFACE_VARIATION * np.maximum(spread.sum(axis=1), 1e-12)
    return axes[smooth, :, 0]


def measure_up(normals: np.ndarray, up_guess: np.ndarray) -> UpMeasurement | None:
    """Up in the frame of `normals` (unit), from `up_guess` (within `WALL_TILT_DEG[0]`);
    None when too few normals are near horizontal."""
    up = np.asarray(up_guess, np.float64) / np.linalg.norm(up_guess)
    for tilt_deg in WALL_TILT_DEG:
        plumb = normals[np.abs(normals @ up) < np.sin(np.deg2rad(tilt_deg))]
        if len(plumb) < MIN_NORMALS:
            return None
        E = horizontal_axes(up)
        along = plumb @ E.T  # (m, 2): how each normal leans into the axes
        M = along.T @ along
        lam, V = np.linalg.eigh(M)
        damping = (NORMAL_SIGMA_DEG / GUESS_SIGMA_DEG) ** 2  # the guess, as a prior
        step = V @ ((V.T @ (-along.T @ (plumb @ up))) / (lam + damping))
        up = up + step @ E
        up /= np.linalg.norm(up)
    axes = V.T @ E  # the axes of the last step, made orthogonal to the final `up`
    axes[0] -= (axes[0] @ up) * up
    axes[0] /= np.linalg.norm(axes[0])
    axes[1] = np.cross(up, axes[0]) * np.sign(np.cross(up, axes[0]) @ axes[1])
    variance = (np.deg2rad(NORMAL_SIGMA_DEG) ** 2 / np.maximum(lam, 1e-12)
                + np.deg2rad(TILT_FLOOR_DEG) ** 2)
    return UpMeasurement(up, axes, 1.0 / variance)


def horizontal_axes(up: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes orthogonal to `up`."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a)])


class KeyframeUps:
    """The ups a run's keyframes measured, by keyframe number; each measurement is guessed
    from the last one, carried by the odometry (good to a few degrees between keyframes)."""

    def __init__(self, k_neighbors: int) -> None:
        self.k_neighbors = k_neighbors
        self.by_number: dict[int, UpMeasurement] = {}
        self._up_odom: np.ndarray | None = None  # the last one measured, in the odometry's world

    def measure(self, number: int, points: np.ndarray, R_odom_lidar: np.ndarray,
                first_guess: np.ndarray) -> None:
        """Keyframe `number`'s up from its scan `points` (lidar frame); `first_guess` (the
        odometry's world) until one was measured."""
        guess = first_guess if self._up_odom is None else self._up_odom
        up = measure_up(smooth_normals(points, self.k_neighbors), R_odom_lidar.T @ guess)
        if up is not None:
            self.by_number[number] = up
            self._up_odom = R_odom_lidar @ up.up

    def up_world(self, T_world_keyframe: np.ndarray, imu_up: np.ndarray | None
                 ) -> np.ndarray | None:
        """World up for the loop graph: the IMU's, else the first measured keyframe's as
        `T_world_keyframe` places it; None before any was measured."""
        if not self.by_number:
            return None
        if imu_up is not None:
            return imu_up
        first = min(self.by_number)
        return T_world_keyframe[first][:3, :3] @ self.by_number[first].up
