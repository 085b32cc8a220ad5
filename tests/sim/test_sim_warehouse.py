"""The warehouse world: look-alike aisles (and its 180-degree twin), one ramp a robot drives."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import rpy_to_rot
from mcl3d.sim.pipeline import extrinsics
from mcl3d.sim.trajectories import build_trajectory
from mcl3d.sim.worlds import build_world

RANGE_GATE_M = 6.0  # the short-range view of the MCL ambiguity study


@pytest.fixture(scope="module")
def hall():
    import open3d as o3d

    w = build_world("warehouse", seed=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(w.static.vertices.astype(np.float32)),
                        o3d.core.Tensor(w.static.triangles.astype(np.uint32)))
    return w, scene


def _beams() -> np.ndarray:
    """Unit directions of a VLP-16-like sweep: 16 rings over +-15 degrees, 0.4 degree steps."""
    el, az = np.meshgrid(np.radians(np.linspace(-15, 15, 16)),
                         np.radians(np.arange(0.0, 360.0, 0.4)))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                    -1).reshape(-1, 3)


def _cast(scene, origin, R) -> tuple[np.ndarray, np.ndarray]:
    """Ranges clipped at the gate, and the id of the triangle each ray hit."""
    import open3d as o3d

    d = _beams() @ R.T
    rays = np.hstack([np.repeat(np.asarray(origin)[None], len(d), 0), d]).astype(np.float32)
    out = scene.cast_rays(o3d.core.Tensor(rays))
    return np.minimum(out["t_hit"].numpy(), RANGE_GATE_M), out["primitive_ids"].numpy()


def _scan(scene, x, y, yaw):
    return _cast(scene, [x, y, 0.42], rpy_to_rot(0.0, 0.0, yaw))[0]


def _far_share(a, b):
    """Share of rays whose ranges differ by more than 25 cm."""
    return float(np.mean(np.abs(a - b) > 0.25))


def test_hall_size_overrides_and_limits():
    w = build_world("warehouse", seed=0)
    lo, hi = w.static.vertices.min(axis=0), w.static.vertices.max(axis=0)
    assert hi[0] - lo[0] == pytest.approx(55.1 + 0.4)  # 13 bays of 2.7 m + two 10 m cross aisles
    assert hi[1] - lo[1] == pytest.approx(30.0 + 0.4)
    assert 10_000 < w.static.n_triangles < 40_000
    big = build_world("warehouse", seed=0, n_aisles=7, n_bays=15)
    assert big.static.vertices[:, 1].max() == pytest.approx(35.2)
    assert big.static.vertices[:, 0].max() == pytest.approx(15 * 2.7 + 20.2)
    with pytest.raises(ConfigError, match=r"world\.warehouse_aisles.*>= 6, got 5"):
        build_world("warehouse", n_aisles=5)


def test_aisles_look_alike_and_only_the_ramp_tells_the_halves_apart(hall):
    _, scene = hall
    L, W = 55.1, 30.0
    here = _scan(scene, 25.0, 7.5, np.pi)  # mid aisle 1, facing west
    for x, y, yaw in [(25.0, 17.5, np.pi), (25.0, 27.5, np.pi),  # aisles 3 and 5
                      (L - 25.0, W - 7.5, 0.0),  # the 180-degree twin (aisle 4)
                      (25.0 + 2.7, 7.5, np.pi)]:  # one bay further along
        there = _scan(scene, x, y, yaw)
        assert np.median(np.abs(here - there)) < 0.02  # same racks up to the jitter
        assert _far_share(here, there) < 0.05
    beside_ramp = _scan(scene, 47.5, 17.5, 0.0)  # east cross aisle, at the end of aisle 3
    twin = _scan(scene, L - 47.5, W - 17.5, np.pi)  # its twin in the west cross aisle
    assert _far_share(beside_ramp, twin) > 0.12


def test_the_ramp_is_ground_and_the_ground_robot_drives_over_it(hall):
    w, _ = hall
    assert w.ground.vertices[:, 2].max() == pytest.approx(1.0)  # the dock platform
    traj = build_trajectory(w, "ground", 150.0)
    z = traj.T_map_base(np.arange(0.0, 150.0, 0.5))[:, 2, 3]
    assert z.max() == pytest.approx(1.0, abs=0.01) and np.mean(z > 0.5) > 0.03


def test_the_ground_route_sees_only_look_alike_aisles_before_the_ramp(hall):
    """The study's premise: within the range gate, no point on the dock for the first 40 s,
    the dock seen before 90 s."""
    w, scene = hall
    corners = w.static.vertices[w.static.triangles]
    dock = np.all((corners[..., 0] > 49.2) & (corners[..., 1] > 13.9) & (corners[..., 1] < 26.1),
                  axis=1)
    assert 50 < dock.sum() < 300  # ramps, platform, rail, door, two pallets
    traj = build_trajectory(w, "ground", 100.0)
    T_base_lidar, _ = extrinsics("vlp16")
    seen = []
    for t in np.arange(0.0, 100.0, 1.0):
        T = traj.T_map_base(np.array([t]))[0] @ T_base_lidar
        r, prim = _cast(scene, T[:3, 3], T[:3, :3])
        if np.sum((r < RANGE_GATE_M) & dock[np.minimum(prim, len(dock) - 1)]) >= 20:
            seen.append(t)
    assert seen and 40.0 <= seen[0] < 90.0


def test_simulate_reads_the_warehouse_sizes_from_the_config(tmp_path):
    from mcl3d.sim.pipeline import SimulateRequest, run

    result = run(SimulateRequest("warehouse", "vlp16", "kidnap", 0.1, 0, tmp_path / "w.mcap",
                                 overrides={"world.warehouse_bays": 8,
                                            "world.warehouse_aisles": 7,
                                            "lidar.column_stride": 8}))
    assert result.world_triangles == build_world("warehouse", 0, n_aisles=7,
                                                 n_bays=8).static.n_triangles
    assert result.world_triangles != build_world("warehouse", 0).static.n_triangles
