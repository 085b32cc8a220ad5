"""The same inputs give the same map, bit for bit: `build-map` twice from one point cloud and
twice from one log, fused on 2 cpu threads (where float atomic sums used to come out in
whatever order the threads added them), gives equal arrays and equal file bytes."""

import os
import subprocess
import sys

import numpy as np
from support import tsdf_world as world

# Run in a child process: the cpu backend's thread count is fixed when Taichi starts, and
# the test must fuse on 2 threads whatever the machine (TI_CPU_MAX_NUM_THREADS sets it).
BUILD_TWICE = """
import sys
from pathlib import Path

from mcl3d.core import runtime
from mcl3d.mapping import pipeline

runtime.init("cpu")
assert runtime.loop_threads() == 2, runtime.loop_threads()
for source in map(Path, sys.argv[1:]):
    for k in (1, 2):
        pipeline.run(pipeline.BuildMapRequest(source, source.with_suffix(f".{k}.tsdf")))
"""


def _write_inputs(d):
    """The room's 3 scans as a point cloud (map frame) and as a log with ground truth."""
    import open3d as o3d

    from mcl3d.io.logs.messages import PointCloud, PoseStamped
    from mcl3d.io.logs.writer import LogWriter

    scene = world.scene_of(*world.room_mesh())
    scans = [world.scan(scene, T)[1] for T in world.POSES]
    points = np.concatenate([p @ T[:3, :3].T + T[:3, 3]
                             for p, T in zip(scans, world.POSES, strict=True)])
    cloud = d / "cloud.pcd"
    o3d.io.write_point_cloud(str(cloud), o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(points)))
    log = d / "room.mcap"
    stamps = [1_700_000_000_000_000_000 + i * 100_000_000 for i in range(len(scans))]
    with LogWriter(log) as w:
        for pts, T, stamp in zip(scans, world.POSES, stamps, strict=True):
            times = np.linspace(0, 0.05, len(pts)).astype(np.float32)  # deskewed
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", T))
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, times))
        w.write_pose("/ground_truth", PoseStamped(stamps[-1] + 100_000_000, "map",
                                                  world.POSES[-1]))
    return cloud, log


def _assert_same_map(a, b):
    """Every member equal (the header, the block lists, every distance and weight), then
    every byte of the files."""
    with np.load(a) as first, np.load(b) as second:
        assert first.files == second.files
        differ = {}
        for name in first.files:
            x, y = first[name], second[name]
            assert x.shape == y.shape, name
            if not np.array_equal(x, y):
                differ[name] = f"{np.count_nonzero(x != y)} of {x.size}"
    assert not differ, f"{a.name} and {b.name} differ in {differ}"
    assert a.read_bytes() == b.read_bytes()


def test_building_twice_gives_the_same_bits(tmp_path):
    cloud, log = _write_inputs(tmp_path)
    env = {**os.environ, "TI_CPU_MAX_NUM_THREADS": "2"}
    proc = subprocess.run([sys.executable, "-c", BUILD_TWICE, str(cloud), str(log)],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for source in (cloud, log):
        _assert_same_map(source.with_suffix(".1.tsdf"), source.with_suffix(".2.tsdf"))


def test_fixed_point_sums_are_exact_in_any_order(ti_runtime):
    """add_fixed against exact integer sums: values of either sign, fractions and whole
    parts, many threads on a few voxels, and the same values in reverse order give the
    same sums."""
    import taichi as ti

    from mcl3d.kernels.tsdf_band import add_fixed
    from mcl3d.kernels.tsdf_lookup import fixed_value

    total = ti.field(ti.i64, shape=3)
    value = ti.field(ti.f32, shape=3)

    @ti.kernel
    def add(x: ti.types.ndarray(dtype=ti.f32, ndim=1), voxel: ti.types.ndarray(dtype=ti.i32,
                                                                               ndim=1)):
        for i in range(x.shape[0]):
            add_fixed(total[voxel[i]], x[i])

    @ti.kernel
    def read():
        for v in range(3):
            value[v] = fixed_value(total[v])

    rng = np.random.default_rng(7)
    x = np.concatenate([rng.uniform(0, 1, 20000), rng.uniform(-64, 64, 20000),
                        rng.uniform(-1e-3, 1e-3, 5000)]).astype(np.float32)
    voxel = (np.arange(len(x)) % 3).astype(np.int32)
    exact = [sum(int(np.floor(np.float64(v) * 2**32)) for v in x[k::3]) for k in range(3)]
    for order in (slice(None), slice(None, None, -1)):
        total.fill(0)
        add(x[order].copy(), voxel[order].copy())
        assert [int(t) for t in total.to_numpy()] == exact
    read()
    np.testing.assert_allclose(value.to_numpy(), [e / 2**32 for e in exact], rtol=1e-6)
