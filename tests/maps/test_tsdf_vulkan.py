"""The same map and the same query results on Vulkan (Mesa's lavapipe in CI) as on cpu."""

import numpy as np
import pytest
from support import tsdf_world as world

pytestmark = pytest.mark.vulkan


def _run(backend, tmp_path):
    """Fuse two scans, query, save with f16 and reload on `backend`; everything back as numpy."""
    import taichi as ti

    from mcl3d.core import runtime
    from mcl3d.kernels import tsdf_lookup as k
    from mcl3d.maps.build import BuildConfig, MapGeometry, ScanFuser, new_map
    from mcl3d.maps.map_file import load_map, save_map

    runtime.init(backend)
    vertices, triangles = world.room_mesh()
    # off the voxel grid: surfaces exactly on voxel faces would make floor() of a point on
    # them depend on the last bit, which FMA changes between backends
    offset = np.array([0.0123, 0.0071, 0.0137])
    vertices = vertices + offset
    scene = world.scene_of(vertices, triangles)
    cfg = BuildConfig()
    geometry = MapGeometry.around(vertices.min(0), vertices.max(0), 0.05, cfg.trunc_m)
    tsdf = new_map(geometry, cfg)
    fuser = ScanFuser(tsdf, cfg)
    for T in world.POSES[:2]:
        T = T.copy()
        T[:3, 3] += offset
        fuser.fuse(world.scan(scene, T)[1], T)
    tsdf.finalize()
    data = tsdf.blocks().sorted()

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              out: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        for i in range(p.shape[0]):
            a = k.sdf_nearest(m, p[i])
            b = k.sdf_trilinear_grad(m, p[i])
            out[i, 0] = a[0]
            out[i, 1] = a[1]
            for j in ti.static(range(4)):
                out[i, 2 + j] = b[j]
            out[i, 6] = k.state_at(m, p[i])

    p = np.random.default_rng(0).uniform([0, 0, 0], [6, 5, 3], (2000, 3)).astype(np.float32)
    out = np.zeros((2000, 7), np.float32)
    query(tsdf, p, out)
    path = tmp_path / f"{backend}.tsdf"
    save_map(path, tsdf, source={}, build={}, f16=True)
    loaded = load_map(path)
    out16 = np.zeros((2000, 7), np.float32)
    query(loaded, p, out16)
    return data, out, out16


def test_cpu_and_vulkan_agree(on_vulkan, tmp_path):
    vk = on_vulkan(_run, tmp_path)
    cpu = _run("cpu", tmp_path)
    (dv, qv, q16v), (dc, qc, q16c) = vk, cpu
    # f32 rounding differs between backends (FMA, atomic order): a sample on a voxel face
    # or a footprint size on its threshold may flip, so a few blocks and voxels differ
    kv = {tuple(c): i for i, c in enumerate(dv.coords)}
    kc = {tuple(c): i for i, c in enumerate(dc.coords)}
    common = sorted(set(kv) & set(kc))
    assert len(set(kv) ^ set(kc)) < 0.01 * len(kc)
    iv = [kv[c] for c in common]
    ic = [kc[c] for c in common]
    assert len(set(map(tuple, dv.free_coords)) ^ set(map(tuple, dc.free_coords))) < 0.01 * len(
        dc.free_coords)
    assert _mismatch(dv.weight[iv], dc.weight[ic], 1e-3) < 1e-3
    assert _mismatch(dv.sdf[iv], dc.sdf[ic], 1e-4) < 1e-3
    assert _mismatch(qv, qc, 1e-3) < 1e-2
    assert _mismatch(q16v, q16c, 1e-3) < 1e-2
    assert _mismatch(q16c[:, 2], qc[:, 2], 2e-3) < 1e-3  # the f16 map ~ the f32 map


def _mismatch(a, b, tol):
    return float(np.mean(np.abs(a - b) > tol + 1e-5 * np.abs(b)))
