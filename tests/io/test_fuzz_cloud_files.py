"""Fuzzing the PCD, PLY and KITTI .bin readers: damaged files (every PCD and PLY encoding) and
random headers are read or refused with an mcl3d error, never a traceback; a cloud read holds
only finite points."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.core.errors import PointCloudError
from mcl3d.io.logs.cloud_files import read_cloud_file, write_ply

N = 6
_PCD_HEAD = ("VERSION 0.7\nFIELDS x y z intensity ring\nSIZE 4 4 4 4 2\nTYPE F F F F U\n"
             f"COUNT 1 1 1 1 1\nWIDTH {N}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {N}\n")


def _columns() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return (rng.normal(size=(N, 3)).astype("<f4"), rng.uniform(size=N).astype("<f4"),
            np.arange(N, dtype="<u2"))


def _literals(data: bytes) -> bytes:
    """A valid LZF stream of literal runs only."""
    return b"".join(bytes([len(data[i:i + 32]) - 1]) + data[i:i + 32]
                    for i in range(0, len(data), 32))


def _valid_files(folder) -> dict[str, bytes]:
    xyz, intensity, ring = _columns()
    rows = "".join(f"{a} {b} {c} {i} {r}\n" for (a, b, c), i, r in zip(xyz, intensity, ring,
                                                                         strict=True))
    packed = np.empty(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4"),
                                ("r", "<u2")])
    packed["x"], packed["y"], packed["z"], packed["i"], packed["r"] = *xyz.T, intensity, ring
    blocks = b"".join(c.tobytes() for c in (*xyz.T, intensity, ring))  # field-major
    lzf = _literals(blocks)
    write_ply(folder / "binary.ply", xyz)
    ply_ascii = ("ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n" + "".join(f"{a} {b} {c}\n" for a, b, c in xyz))
    return {"ascii.pcd": (_PCD_HEAD + "DATA ascii\n" + rows).encode(),
            "binary.pcd": (_PCD_HEAD + "DATA binary\n").encode() + packed.tobytes(),
            "compressed.pcd": (_PCD_HEAD + "DATA binary_compressed\n").encode()
            + np.array([len(lzf), len(blocks)], "<u4").tobytes() + lzf,
            "binary.ply": (folder / "binary.ply").read_bytes(),
            "ascii.ply": ply_ascii.encode(),
            "scan.bin": np.hstack([xyz, intensity[:, None]]).astype("<f4").tobytes()}


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_clouds")
    files = _valid_files(folder)
    for name, blob in files.items():  # the samples themselves read, with every point
        (folder / name).write_bytes(blob)
        assert len(read_cloud_file(folder / name)) == N, name
    return folder, files


def _check(cloud) -> None:
    if cloud is not None:
        assert cloud.points.ndim == 2 and cloud.points.shape[1] == 3
        assert np.isfinite(cloud.points).all()


@pytest.mark.parametrize("name", ["ascii.pcd", "binary.pcd", "compressed.pcd", "binary.ply",
                                  "ascii.ply", "scan.bin"])
@fuzz_settings(examples=50)
@given(data=st.data())
def test_damaged_cloud_files(valid, name, data):
    folder, files = valid
    path = folder / f"damaged{name[name.index('.'):]}"
    path.write_bytes(data.draw(damaged(files[name])))
    _check(reads_or_refuses(lambda: read_cloud_file(path)))


_PCD_LINES = st.lists(st.tuples(
    st.sampled_from(["FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "POINTS", "DATA",
                     "VERSION"]),
    st.lists(st.sampled_from(["x", "y", "z", "t", "_", "1", "2", "4", "8", "0", "-1", "3",
                              "4294967295", "F", "U", "I", "ascii", "binary",
                              "binary_compressed", "x"]), max_size=5)), max_size=9)


@fuzz_settings(examples=150)
@example(lines=[("FIELDS", ["x", "y", "z"]), ("SIZE", ["4", "4", "4"]),  # crashed
                ("TYPE", ["F", "F", "F"]), ("COUNT", ["3", "1", "1"]), ("WIDTH", ["1"]),
                ("DATA", ["ascii"])], body=b"1 2 3 4 5")
@example(lines=[("FIELDS", ["x", "y", "z"]), ("SIZE", ["4", "4", "4"]),  # crashed
                ("TYPE", ["F", "F", "F"]), ("WIDTH", ["1"]), ("POINTS", ["-1"]),
                ("DATA", ["ascii"])], body=b"1 2 3")
@given(lines=_PCD_LINES, body=st.binary(max_size=64))
def test_random_pcd_headers(valid, lines, body):
    path = valid[0] / "random.pcd"
    path.write_bytes("".join(f"{key} {' '.join(values)}\n" for key, values in lines).encode()
                     + body)
    _check(reads_or_refuses(lambda: read_cloud_file(path)))


_PLY_LINES = st.lists(st.sampled_from([
    "format ascii 1.0", "format binary_little_endian 1.0", "format binary_big_endian 1.0",
    "format", "element vertex 2", "element vertex -1", "element vertex x", "element face 1",
    "element", "property float x", "property float y", "property float z", "property float",
    "property uchar x", "property list uchar int vertex_indices", "property double t",
    "comment hi"]), max_size=8)


@fuzz_settings(examples=150)
@example(lines=["format ascii 1.0", "element vertex 1", "property float x", "property float y",
                "property float z"], body=b"1 2 x")  # crashed
@example(lines=["format", "element vertex 1"], body=b"")  # crashed
@example(lines=["format ascii 1.0", "element vertex 1", "property float x", "property float x",
                "property float z"], body=b"1 2 3")  # crashed
@given(lines=_PLY_LINES, body=st.binary(max_size=64))
def test_random_ply_headers(valid, lines, body):
    path = valid[0] / "random.ply"
    path.write_bytes(("ply\n" + "".join(f"{line}\n" for line in lines) + "end_header\n").encode()
                     + body)
    _check(reads_or_refuses(lambda: read_cloud_file(path)))


def test_a_compressed_pcd_claiming_gigabytes_is_refused_at_once(valid):
    """Found by fuzzing: a damaged size made the LZF decoder allocate 4 GB before failing."""
    path = valid[0] / "huge.pcd"
    path.write_bytes((_PCD_HEAD + "DATA binary_compressed\n").encode()
                     + np.array([4, 4_000_000_000], "<u4").tobytes() + bytes(4))
    with pytest.raises(PointCloudError, match="more than 4 LZF bytes can hold"):
        read_cloud_file(path)
