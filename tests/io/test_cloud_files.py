"""Point-cloud files: real PCDs (hdl32_pair: BSD-3-Clause/MIT; pandar64_static: Apache-2.0),
the Ouster map PLY (BSD-3-Clause), and tiny synthetic ascii/binary/compressed/KITTI files."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from mcl3d.core.errors import InputError, PointCloudError
from mcl3d.io.logs.cloud_files import lzf_decompress, read_cloud_file, write_ply


def lzf_compress_literals(data: bytes) -> bytes:
    """A valid LZF stream of literal runs only."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


def test_lzf_back_references_including_overlapping_copies():
    # literal "abc", then a back reference of length 7 at distance 3 (overlapping: abcabca),
    # then a long reference (length 7 + 2 + 5 = 14) at distance 1
    stream = bytes([2]) + b"abc" + bytes([(5 << 5) | 0, 2]) + bytes([(7 << 5) | 0, 5, 0])
    assert lzf_decompress(stream, 24) == b"abcabcabca" + b"a" * 14
    with pytest.raises(ValueError):
        lzf_decompress(bytes([(1 << 5) | 0, 9]), 3)  # reference before the start


def test_hdl32_binary_pcds(shared_data):
    for name, n_points in (("251370668.pcd", 69_088), ("251371071.pcd", 69_792)):
        path = shared_data / "hdl32_pair" / name
        cloud = read_cloud_file(path)
        assert len(cloud) + cloud.n_dropped == n_points
        assert set(cloud.fields) == {"intensity"} and cloud.times_s is None
        raw = np.frombuffer(path.read_bytes()[-n_points * 16:], dtype="<f4").reshape(-1, 4)
        valid = np.isfinite(raw[:, :3]).all(axis=1) & (raw[:, :3] != 0).any(axis=1)
        np.testing.assert_array_equal(cloud.points, raw[valid, :3])
        np.testing.assert_array_equal(cloud.fields["intensity"], raw[valid, 3])
        assert np.linalg.norm(cloud.points, axis=1).max() < 130


def test_pandar_binary_compressed_pcd(shared_data):
    import open3d as o3d

    path = shared_data / "pandar64_static" / "top_center_lidar" / "2021-10-26-16-21-29-468.pcd"
    cloud = read_cloud_file(path)
    assert len(cloud) == 80_787 and cloud.n_dropped == 0
    assert cloud.fields["ring"].dtype == np.uint16 and cloud.fields["ring"].max() <= 63
    # absolute per-point unix times: the stamp is the earliest, times span one 10 Hz sweep
    assert abs(cloud.stamp_ns * 1e-9 - 1635236489.369) < 0.01
    assert cloud.times_s.min() == 0 and 0.09 < cloud.times_s.max() < 0.101
    reference = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    np.testing.assert_allclose(cloud.points, reference, atol=1e-5)


def test_ouster_map_ply(shared_data):
    cloud = read_cloud_file(shared_data / "ouster_os1_128_lb_n3" /
                            "OS-1-128_v2.3.0_1024x10_lb_n3_map-000.ply")
    assert len(cloud) + cloud.n_dropped == 155_000
    lo, hi = cloud.points.min(axis=0), cloud.points.max(axis=0)
    assert lo[0] > -250 and hi[0] < 250 and lo[2] > -5 and hi[2] < 18


def _header(kind: str, n: int, fields="x y z intensity ring", sizes="4 4 4 4 2",
            types="F F F F U") -> bytes:
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\n"
            f"COUNT {' '.join('1' * len(fields.split()))}\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n").encode()


def test_synthetic_pcd_encodings_agree(tmp_path):
    rng = np.random.default_rng(0)
    n = 40
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    xyz[5] = np.nan
    intensity = rng.uniform(size=n).astype(np.float32)
    ring = rng.integers(0, 32, n).astype(np.uint16)
    ascii_rows = "".join(f"{a!r} {b!r} {c!r} {i!r} {r}\n" for (a, b, c), i, r in
                         zip(xyz.tolist(), intensity.tolist(), ring.tolist(), strict=True))
    (tmp_path / "a.pcd").write_bytes(_header("ascii", n) + ascii_rows.encode())
    rows = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4"),
                              ("r", "<u2")])
    rows["x"], rows["y"], rows["z"], rows["i"], rows["r"] = *xyz.T, intensity, ring
    (tmp_path / "b.pcd").write_bytes(_header("binary", n) + rows.tobytes())
    plain = xyz[:, 0].tobytes() + xyz[:, 1].tobytes() + xyz[:, 2].tobytes() + \
        intensity.tobytes() + ring.tobytes()
    packed = lzf_compress_literals(plain)
    (tmp_path / "c.pcd").write_bytes(_header("binary_compressed", n) +
                                     struct.pack("<II", len(packed), len(plain)) + packed)
    clouds = [read_cloud_file(tmp_path / f"{k}.pcd") for k in "abc"]
    for cloud in clouds:
        assert len(cloud) == n - 1 and cloud.n_dropped == 1
        np.testing.assert_array_equal(cloud.points, np.delete(xyz, 5, axis=0))
        np.testing.assert_array_equal(cloud.fields["intensity"], np.delete(intensity, 5))
        np.testing.assert_array_equal(cloud.fields["ring"], np.delete(ring, 5))


def test_bad_pcd_files(tmp_path):
    n = 10
    (tmp_path / "short.pcd").write_bytes(_header("binary", n) + b"\0" * 50)
    with pytest.raises(PointCloudError, match="truncated"):
        read_cloud_file(tmp_path / "short.pcd")
    (tmp_path / "noxyz.pcd").write_bytes(_header("binary", n, "a b", "4 4", "F F") + b"\0" * 80)
    with pytest.raises(PointCloudError, match="no x/y/z"):
        read_cloud_file(tmp_path / "noxyz.pcd")
    (tmp_path / "bad.pcd").write_bytes(_header("binary_compressed", n) +
                                       struct.pack("<II", 4, 180) + b"\xff\xff\xff\xff")
    with pytest.raises(PointCloudError, match="corrupt"):
        read_cloud_file(tmp_path / "bad.pcd")
    (tmp_path / "x.xyz").write_text("1 2 3\n")
    with pytest.raises(InputError, match="unknown point-cloud file type"):
        read_cloud_file(tmp_path / "x.xyz")


def test_kitti_bin(tmp_path):
    data = np.arange(20, dtype=np.float32).reshape(5, 4)
    data.tofile(tmp_path / "000000.bin")
    cloud = read_cloud_file(tmp_path / "000000.bin")
    np.testing.assert_array_equal(cloud.points, data[:, :3])
    np.testing.assert_array_equal(cloud.fields["intensity"], data[:, 3])
    (tmp_path / "bad.bin").write_bytes(b"\0" * 15)
    with pytest.raises(PointCloudError, match="multiple of 16"):
        read_cloud_file(tmp_path / "bad.bin")


def test_write_ply_round_trip_and_ascii_ply(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(1)
    points = rng.normal(size=(30, 3)).astype(np.float32)
    normals = rng.normal(size=(30, 3)).astype(np.float32)
    colors = rng.uniform(size=(30, 3))
    write_ply(tmp_path / "m.ply", points, normals, colors)
    cloud = read_cloud_file(tmp_path / "m.ply")
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.fields["nx"], normals[:, 0])
    np.testing.assert_array_equal(cloud.fields["green"], np.round(colors[:, 1] * 255))
    o3d_cloud = o3d.io.read_point_cloud(str(tmp_path / "m.ply"))
    np.testing.assert_allclose(np.asarray(o3d_cloud.points), points, atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]  # no temp file left

    text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n" \
           "property float z\nproperty uchar ring\nelement face 0\n" \
           "property list uchar int vertex_indices\nend_header\n1 2 3 4\n5 6 7 8\n"
    (tmp_path / "a.ply").write_text(text)
    cloud = read_cloud_file(tmp_path / "a.ply")
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [5, 6, 7]])
    np.testing.assert_array_equal(cloud.fields["ring"], [4, 8])
