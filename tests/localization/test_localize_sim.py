"""`mcl3d localize` end to end on simulator logs (cpu backend, small sizes): tracking from the
first ground-truth pose on a clean office log, and recovery from the office's kidnapping.

The maps come from the simulated world's own mesh (the fast path, independent of the scans
being localized). The tracking map is the office cropped to the part within the sensor's
range of the short route, at 5 cm; the kidnap map is the whole office at 10 cm.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core import geometry

SEED = 0
TRACK_DURATION_S = 5.0
TRACK_RANGE_M = 10.0  # scan points farther than this are dropped: they would leave the crop
TRACK_BOX_M = ((-1.0, -1.0, -1.0), (17.0, 21.0, 4.0))  # covers the route's first 5 s + range
KIDNAP_DURATION_S = 8.0  # the kidnapping happens at half the duration
TIGHT_STD = [0.05, 0.05, 0.02, *np.degrees([0.01, 0.01, 0.02]).tolist()]  # m, deg


def _clip(poly: list[np.ndarray], axis: int, value: float, keep_below: bool) -> list:
    """Sutherland-Hodgman: the part of a convex polygon on one side of a plane x[axis]=value."""
    out = []
    for a, b in zip(poly, poly[1:] + poly[:1], strict=True):
        a_in = a[axis] <= value if keep_below else a[axis] >= value
        b_in = b[axis] <= value if keep_below else b[axis] >= value
        if a_in:
            out.append(a)
        if a_in != b_in:
            out.append(a + (value - a[axis]) / (b[axis] - a[axis]) * (b - a))
    return out


def crop_mesh(vertices: np.ndarray, triangles: np.ndarray, lo, hi):
    """The mesh clipped to the box [lo, hi], triangles re-fanned and vertices welded (shared
    vertices keep the mesh's pseudo-normals, hence the map's signs, right at edges)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = vertices[triangles]
    tmin, tmax = corners.min(axis=1), corners.max(axis=1)
    touch = np.all(tmax >= lo, axis=1) & np.all(tmin <= hi, axis=1)
    inside = touch & np.all(tmin >= lo, axis=1) & np.all(tmax <= hi, axis=1)
    pieces = [corners[inside]]
    for tri in corners[touch & ~inside]:
        poly = list(tri)
        for axis in range(3):
            poly = _clip(poly, axis, lo[axis], keep_below=False)
            poly = _clip(poly, axis, hi[axis], keep_below=True) if poly else poly
        pieces += [np.array([[poly[0], poly[k], poly[k + 1]]]) for k in range(1, len(poly) - 1)]
    flat = np.concatenate(pieces).reshape(-1, 3)
    welded, index = np.unique(np.round(flat, 6), axis=0, return_inverse=True)
    return welded, index.reshape(-1, 3)


def test_crop_mesh_keeps_the_inside_exactly():
    from mcl3d.sim.mesh import MeshBuilder

    b = MeshBuilder()
    b.box((0.0, 0.0, 0.0), (4.0, 2.0, 1.0), 0.5)
    mesh = b.build()
    v, t = crop_mesh(mesh.vertices, mesh.triangles, (1.0, -1.0, -1.0), (3.0, 3.0, 3.0))
    assert v[:, 0].min() == pytest.approx(1.0) and v[:, 0].max() == pytest.approx(3.0)
    a, b_, c = (v[t[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b_ - a, c - a), axis=1).sum()
    assert area == pytest.approx(2 * (2.0 * 2.0) + 2 * (2.0 * 1.0))  # top+bottom, two sides
    assert len(np.unique(v, axis=0)) == len(v) < 3 * len(t)  # welded: corners are shared


def _save_mesh_map(path, vertices, triangles, voxel_size_m: float) -> None:
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.map_file import save_map

    tsdf = build_from_mesh(vertices, triangles, BuildConfig(voxel_size_m=voxel_size_m))
    save_map(path, tsdf, source={"kind": "mesh", "path": "simulated office"}, build={})
    tsdf.destroy()


def _simulate(path, trajectory: str, duration_s: float) -> None:
    from mcl3d.sim.pipeline import SimulateRequest, run

    run(SimulateRequest(world="office", sensor="vlp16", trajectory=trajectory,
                        duration_s=duration_s, seed=SEED, output=path))


@pytest.fixture(scope="session")
def office_ground(tmp_path_factory, backend):
    """A clean simulated `ground` log and the office mesh cropped around its route (5 cm)."""
    from mcl3d.core import runtime
    from mcl3d.sim.worlds import build_world

    runtime.init(backend)
    d = tmp_path_factory.mktemp("office_ground")
    world = build_world("office", seed=SEED).static  # the pipeline's world for this seed
    _simulate(d / "ground.mcap", "ground", TRACK_DURATION_S)
    _save_mesh_map(d / "crop.tsdf", *crop_mesh(world.vertices, world.triangles, *TRACK_BOX_M),
                   0.05)
    return d


@pytest.fixture(scope="session")
def office_kidnap(tmp_path_factory, backend):
    """A simulated `kidnap` log and the whole office's mesh map (10 cm)."""
    from mcl3d.core import runtime
    from mcl3d.sim.worlds import build_world

    runtime.init(backend)
    d = tmp_path_factory.mktemp("office_kidnap")
    world = build_world("office", seed=SEED).static
    _simulate(d / "kidnap.mcap", "kidnap", KIDNAP_DURATION_S)
    _save_mesh_map(d / "office.tsdf", world.vertices, world.triangles, 0.10)
    return d


def _localize(log, map_path, out, overrides: dict):
    from mcl3d.core import config
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    cfg = config.build(LocalizeConfig, {"localizer": {
        "seed": SEED, "init": {"mode": "gt", "std": TIGHT_STD}, **overrides}}, "test")
    return run(LocalizeRequest(log, map_path, out, cfg, backend="cpu"))


def _errors(results, gt) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) error of every scan's estimate against the ground
    truth at its stamp (the simulator writes one ground-truth pose per scan stamp)."""
    stamps_ns, poses = gt
    stamps_s = stamps_ns * 1e-9
    idx = [int(np.argmin(np.abs(stamps_s - r.stamp_s))) for r in results]
    est = np.stack([r.T_map_lidar for r in results])
    ref = poses[idx]
    d = np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1)
    a = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    return d, a


def test_tracking_on_a_clean_log_is_accurate_and_never_diverges(office_ground, tmp_path):
    out = _localize(office_ground / "ground.mcap", office_ground / "crop.tsdf", tmp_path / "out",
                    {"particles": 3000, "sensor": {"max_range_m": TRACK_RANGE_M}})
    assert len(out.results) == round(TRACK_DURATION_S * 10)
    assert out.motion_source == "odom"
    d, a = _errors(out.results, out.gt)
    assert d.max() < 0.15 and a.max() < 2.0, (d.max(), a.max())  # never diverges
    assert not any(r.state == "lost" for r in out.results)
    assert out.results[-1].state == "converged"
    rmse = out.summary.ate_all.translation_rmse_m
    assert rmse <= 0.06, rmse  # the bound for 5 cm voxels
    assert rmse == pytest.approx(float(np.sqrt(np.mean(d**2))), abs=1e-6)


def test_kidnapped_robot_recovers(office_kidnap, tmp_path):
    out = _localize(office_kidnap / "kidnap.mcap", office_kidnap / "office.tsdf",
                    tmp_path / "out",
                    {"particles": 50000})
    d, a = _errors(out.results, out.gt)
    jump = int(np.argmax(np.diff(out.gt[1][:, 0, 3]) > 5.0)) + 1  # the teleport: 24 m in x
    assert 0 < jump < len(d) - 10
    assert d[:jump].max() < 0.2 and a[:jump].max() < 3.0  # tracked before the kidnapping
    states = [r.state for r in out.results]
    assert "lost" in states[jump:jump + 5], states[jump:jump + 5]  # loss detected at once
    wrong = [k for k in range(len(d)) if states[k] == "converged" and (d[k] > 1.0 or a[k] > 10)]
    assert not wrong, f"converged far from the truth at scans {wrong} (jump at {jump})"
    assert any(r.reseeded for r in out.results[jump:])
    back = [k for k in range(jump, len(d)) if states[k] == "converged" and d[k] < 0.2]
    assert back, f"never converged back onto the truth; errors after the jump {d[jump:]}"
    assert d[back[0]:].max() < 0.2 and a[back[0]:].max() < 3.0, (back[0], d[back[0]:])
    assert states[-1] == "converged"
