"""Up from the plumb surfaces a scan sees (mcl3d.slam.structure_up)."""

import numpy as np

from mcl3d.core.geometry import so3_exp
from mcl3d.slam.structure_up import measure_up, smooth_normals


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _tilt_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def _forest_normals(rng: np.random.Generator) -> np.ndarray:
    """Trunk normals all around (horizontal, noisy), the ground's (up) and crowns' (cones
    leaning 15° up), in the world frame."""
    az = rng.uniform(0, 2 * np.pi, 600)
    trunks = np.c_[np.cos(az[:400]), np.sin(az[:400]), rng.normal(0, 0.03, 400)]
    ground = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.05, (300, 3))
    lean = np.radians(15.0)
    crowns = np.c_[np.cos(az[400:]) * np.cos(lean), np.sin(az[400:]) * np.cos(lean),
                   np.full(200, np.sin(lean))]
    return _unit(np.concatenate([trunks, ground, crowns]))


def test_up_of_a_tilted_sensor_from_trunks_among_ground_and_crowns():
    """The sensor tilted 5.4°: the crowns' and the ground's normals are left out, the
    trunks' give up to a tenth of a degree, each tilt axis measured to the floor."""
    R_world_lidar = so3_exp(np.array([0.05, -0.08, 0.3]))
    normals = _forest_normals(np.random.default_rng(0)) @ R_world_lidar  # in the lidar frame
    up = measure_up(normals, np.array([0.0, 0.0, 1.0]))
    assert up is not None
    assert _tilt_deg(up.up, R_world_lidar[2]) < 0.1
    assert np.allclose(up.axes @ up.up, 0.0, atol=1e-9)
    assert np.allclose(up.axes @ up.axes.T, np.eye(2), atol=1e-9)
    sigma_deg = np.degrees(1.0 / np.sqrt(up.information))
    assert np.all((sigma_deg > 0.5) & (sigma_deg < 0.7))


def test_one_wall_measures_one_tilt_and_leaves_the_other_at_the_guess():
    """A wall facing x: its normals say how far up leans toward x, nothing about y."""
    rng = np.random.default_rng(1)
    true_up = _unit(np.array([np.sin(np.radians(3.0)), np.sin(np.radians(2.0)), 1.0]))
    wall = _unit(np.cross(true_up, [0.0, 1.0, 0.0]) * -1 + rng.normal(0, 0.02, (200, 3)))
    guess = np.array([0.0, 0.0, 1.0])
    up = measure_up(wall, guess)
    assert up is not None
    assert abs(np.degrees(np.arcsin(up.up[0])) - 3.0) < 0.3  # the measured tilt
    assert abs(up.up[1]) < np.sin(np.radians(0.3))  # the other stays at the guess
    strong = int(np.argmax(up.information))
    assert abs(up.axes[strong, 0]) > 0.99  # information along x only
    assert up.information.min() < 1e-2 * up.information.max()


def test_too_few_plumb_normals_measure_nothing():
    rng = np.random.default_rng(2)
    ground = _unit(np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.05, (500, 3)))
    assert measure_up(ground, np.array([0.0, 0.0, 1.0])) is None


def test_smooth_normals_leave_out_where_surfaces_meet(monkeypatch):
    """A floor and a wall meeting along x = 0, a thin trunk (a line of points): nearly all
    normals are the floor's, the wall's or horizontal (the trunk's); most of those fitted
    across the corner, which lean, are left out."""
    import mcl3d.slam.structure_up as structure_up

    rng = np.random.default_rng(3)
    floor = np.c_[rng.uniform(-4, 0, 4000), rng.uniform(-2, 2, 4000), np.zeros(4000)]
    wall = np.c_[np.zeros(2000), rng.uniform(-2, 2, 2000), rng.uniform(0, 2, 2000)]
    trunk = np.c_[np.full(300, -2.0) + rng.normal(0, 0.01, 300),
                  np.full(300, 1.0) + rng.normal(0, 0.01, 300), rng.uniform(0, 3, 300)]
    points = np.concatenate([floor, wall, trunk])

    def leaning(normals: np.ndarray) -> int:  # more than 2.6° off both vertical and horizontal
        return int(np.sum((np.abs(normals[:, 2]) < 0.999) & (np.abs(normals[:, 2]) > 0.001)))

    normals = smooth_normals(points, 10)
    assert len(normals) > 5000
    monkeypatch.setattr(structure_up, "MAX_SURFACE_VARIATION", 1.0)
    every = smooth_normals(points, 10)
    assert leaning(normals) < 0.02 * len(normals)
    assert leaning(normals) < 0.25 * leaning(every)
    assert smooth_normals(floor[:5], 10).shape == (0, 3)
