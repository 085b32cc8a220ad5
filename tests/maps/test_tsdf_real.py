"""Real Ouster OS1-128 data (ouster-sdk test set, BSD-3-Clause): its pcap read as a log lies on
its 155k-point map, and on the zero level set of a map built from that cloud (the pcap
decoding itself is tested against the SDK in tests/io/test_ouster_pcap.py)."""

import numpy as np
import pytest

FOLDER = "ouster_os1_128_lb_n3"
STEM = "OS-1-128_v2.3.0_1024x10"


@pytest.fixture(scope="module")
def ouster(shared_data):
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_kitti

    d = shared_data / FOLDER
    with LogReader(d / f"{STEM}_lb_n3.pcap") as reader:
        clouds = list(reader.scans())
    poses = read_kitti(d / f"{STEM}_lb_n3_poses_kitti.txt").poses
    return d, clouds, poses


def test_pcap_decodes_three_frames_in_the_sensor_frame(ouster):
    import open3d as o3d
    from scipy.spatial import cKDTree

    d, clouds, poses = ouster
    assert len(clouds) == 3
    for cloud in clouds:
        assert 106000 < len(cloud.points) < 109000  # ~107.5k valid returns per frame
        assert (cloud.height, cloud.width) == (128, 1024)
        assert cloud.times_s.min() >= 0 and cloud.times_s.max() < 0.1
    assert np.diff([c.stamp_ns for c in clouds]) == pytest.approx(1e8, rel=1e-3)  # 10 Hz
    map_points = np.asarray(o3d.io.read_point_cloud(str(d / f"{STEM}_lb_n3_map-000.ply")).points)
    tree = cKDTree(map_points)
    for cloud, T in zip(clouds, poses, strict=True):
        dist, _ = tree.query(cloud.points @ T[:3, :3].T + T[:3, 3])
        assert np.median(dist) < 0.05  # README: 2-4 cm with the poses


def test_real_scans_lie_on_the_zero_level_set_of_the_real_map(ti_runtime, ouster):
    import open3d as o3d
    import taichi as ti

    from mcl3d.kernels import tsdf_lookup as k
    from mcl3d.maps.build import BuildConfig
    from mcl3d.maps.point_build import build_from_points

    d, clouds, poses = ouster
    cloud = np.asarray(o3d.io.read_point_cloud(str(d / f"{STEM}_lb_n3_map-000.ply")).points)
    tsdf = build_from_points(cloud, BuildConfig(), viewpoints=poses[:, :3, 3])

    @ti.kernel
    def query(m: ti.template(), p: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
              out: ti.types.ndarray(dtype=ti.math.vec2, ndim=1)):
        for i in range(p.shape[0]):
            out[i] = k.sdf_trilinear(m, p[i])

    for scan, T in zip(clouds, poses, strict=True):
        world = (scan.points @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        out = np.zeros((len(world), 2), np.float32)
        query(tsdf, world, out)
        observed = out[:, 1] > 0
        assert observed.mean() > 0.95
        assert np.median(np.abs(out[observed, 0])) < tsdf.voxel_size_m
