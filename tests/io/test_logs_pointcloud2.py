"""PointCloud2 decoding against a per-point struct.unpack reference on hand-built messages."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from mcl3d.core.errors import PointCloudError
from mcl3d.io.logs.messages import PointCloud
from mcl3d.io.logs.pointcloud2 import EncodedCloud, FieldSpec, decode, encode

STAMP_NS = 1_600_000_000_250_000_000
_STRUCT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
_NUMPY = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def build(fields: list[FieldSpec], values: dict[str, np.ndarray], point_step: int, height: int,
          width: int, big_endian: bool = False, row_pad: int = 0) -> EncodedCloud:
    """Pack a message point by point with struct (independent of the decoder's numpy path)."""
    order = ">" if big_endian else "<"
    row_step = width * point_step + row_pad
    data = bytearray(b"\xab" * (row_step * height))  # garbage in padding bytes
    for i in range(height * width):
        r, c = divmod(i, width)
        base = r * row_step + c * point_step
        for f in fields:
            struct.pack_into(order + _STRUCT[f.datatype], data, base + f.offset,
                             values[f.name][i].item())
    return EncodedCloud(height=height, width=width, fields=fields, is_bigendian=big_endian,
                        point_step=point_step, row_step=row_step,
                        data=np.frombuffer(bytes(data), dtype=np.uint8), is_dense=False)


def reference_xyz(msg: EncodedCloud, names=("x", "y", "z")) -> np.ndarray:
    order = ">" if msg.is_bigendian else "<"
    data = bytes(msg.data)
    by_name = {f.name: f for f in msg.fields}
    out = []
    for r in range(msg.height):
        for c in range(msg.width):
            base = r * msg.row_step + c * msg.point_step
            out.append([struct.unpack_from(order + _STRUCT[by_name[a].datatype], data,
                                           base + by_name[a].offset)[0] for a in names])
    return np.array(out, dtype=np.float64)


@pytest.mark.parametrize("big_endian", [False, True])
def test_shuffled_padded_organized_cloud_with_invalid_points(big_endian):
    rng = np.random.default_rng(1)
    height, width = 4, 5
    n = height * width
    # field order ring, z, t, x, intensity, y with gaps; x stored as float64
    fields = [FieldSpec("ring", 0, 4), FieldSpec("z", 4, 7), FieldSpec("t", 12, 6),
              FieldSpec("x", 16, 8), FieldSpec("intensity", 28, 7), FieldSpec("y", 36, 7)]
    values = {"ring": np.arange(n, dtype=np.uint16) % 4,
              "x": rng.uniform(-50, 50, n), "y": rng.uniform(-50, 50, n).astype(np.float32),
              "z": rng.uniform(-2, 5, n).astype(np.float32),
              "t": np.arange(n, dtype=np.uint32) * 5_000_000,  # ns since scan start
              "intensity": rng.uniform(0, 255, n).astype(np.float32)}
    values["x"][3] = np.nan
    values["y"][7] = np.inf
    for axis in "xyz":
        values[axis][11] = 0  # "no return" marker
    msg = build(fields, values, point_step=44, height=height, width=width,
                big_endian=big_endian, row_pad=6)
    cloud = decode(msg, STAMP_NS, "lidar")

    ref = reference_xyz(msg)
    valid = np.isfinite(ref).all(axis=1) & (ref != 0).any(axis=1)
    assert cloud.n_dropped == 3 and len(cloud) == n - 3
    assert (cloud.height, cloud.width, cloud.frame_id, cloud.stamp_ns) == (4, 5, "lidar", STAMP_NS)
    np.testing.assert_array_equal(cloud.points, ref[valid].astype(np.float32))
    assert cloud.points.dtype == np.float32
    np.testing.assert_array_equal(cloud.fields["ring"], values["ring"][valid])
    assert cloud.fields["ring"].dtype == np.uint16
    np.testing.assert_array_equal(cloud.fields["intensity"], values["intensity"][valid])
    assert set(cloud.fields) == {"ring", "intensity"}
    np.testing.assert_allclose(cloud.times_s, values["t"][valid] * 1e-9, rtol=1e-6)


@pytest.mark.parametrize(("name", "datatype", "make", "expected"), [
    # float seconds relative to the stamp (Velodyne `time`)
    ("time", 7, lambda rel: rel.astype(np.float32), lambda rel: rel),
    # absolute unix seconds as float64 (Hesai `timestamp`)
    ("timestamp", 8, lambda rel: STAMP_NS * 1e-9 + rel, lambda rel: rel),
    # uint32 nanoseconds relative (Livox `offset_time`)
    ("offset_time", 6, lambda rel: np.round(rel * 1e9).astype(np.uint32), lambda rel: rel),
])
def test_time_field_units(name, datatype, make, expected):
    n = 6
    rel = np.linspace(-0.02, 0.08, n) if datatype == 7 else np.linspace(0.0, 0.09, n)
    fields = [FieldSpec("x", 0, 7), FieldSpec("y", 4, 7), FieldSpec("z", 8, 7),
              FieldSpec(name, 16, datatype)]
    values = {"x": np.ones(n, np.float32), "y": np.arange(n, dtype=np.float32),
              "z": np.ones(n, np.float32), name: make(rel)}
    cloud = decode(build(fields, values, 24, 1, n), STAMP_NS, "l")
    assert cloud.times_s.dtype == np.float32
    np.testing.assert_allclose(cloud.times_s, expected(rel), atol=2e-7)
    assert name not in cloud.fields


def test_absolute_nanosecond_integer_times():
    n = 4
    rel_ns = np.array([0, 1_000_000, 50_000_000, 99_000_000], dtype=np.int64)
    fields = [FieldSpec(a, 4 * i, 7) for i, a in enumerate("xyz")] + [FieldSpec("t", 12, 8)]
    values = {"x": np.ones(n, np.float32), "y": np.ones(n, np.float32),
              "z": np.ones(n, np.float32), "t": (STAMP_NS + rel_ns).astype(np.float64)}
    cloud = decode(build(fields, values, 20, 1, n), STAMP_NS, "l")
    np.testing.assert_allclose(cloud.times_s, rel_ns * 1e-9, atol=1e-6)


def test_cloud_without_xyz_is_an_error():
    fields = [FieldSpec("x", 0, 7), FieldSpec("intensity", 4, 7)]
    msg = build(fields, {"x": np.ones(2, np.float32), "intensity": np.ones(2, np.float32)},
                8, 1, 2)
    with pytest.raises(PointCloudError, match=r"no y/z field"):
        decode(msg, 0, "l", "log.mcap topic /points")


def test_truncated_data_and_bad_layout_are_errors():
    fields = [FieldSpec(a, 4 * i, 7) for i, a in enumerate("xyz")]
    msg = build(fields, {a: np.ones(3, np.float32) for a in "xyz"}, 12, 1, 3)
    msg.data = msg.data[:-1]
    with pytest.raises(PointCloudError, match="truncated"):
        decode(msg, 0, "l")
    bad = build(fields, {a: np.ones(3, np.float32) for a in "xyz"}, 12, 1, 3)
    bad.fields = [*fields, FieldSpec("w", 10, 7)]
    with pytest.raises(PointCloudError, match="does not fit"):
        decode(bad, 0, "l")


def test_empty_cloud():
    fields = [FieldSpec(a, 4 * i, 7) for i, a in enumerate("xyz")]
    cloud = decode(EncodedCloud(1, 0, fields, False, 12, 0, np.zeros(0, np.uint8), True), 5, "l")
    assert cloud.points.shape == (0, 3) and cloud.n_dropped == 0


def test_encode_decode_is_bitwise_exact():
    rng = np.random.default_rng(2)
    n = 50
    cloud = PointCloud(stamp_ns=STAMP_NS, frame_id="lidar",
                       points=rng.normal(size=(n, 3)).astype(np.float32),
                       times_s=rng.uniform(0, 0.1, n).astype(np.float32),
                       fields={"intensity": rng.uniform(size=n).astype(np.float32),
                               "ring": rng.integers(0, 128, n).astype(np.uint16),
                               "range": rng.integers(0, 2**31, n).astype(np.uint32),
                               "normal": rng.normal(size=(n, 3))})
    out = decode(encode(cloud), cloud.stamp_ns, cloud.frame_id)
    assert out.points.tobytes() == cloud.points.tobytes()
    assert out.times_s.tobytes() == cloud.times_s.tobytes()
    for name, values in cloud.fields.items():
        assert out.fields[name].dtype == values.dtype
        assert out.fields[name].tobytes() == values.tobytes()
    assert (out.height, out.width) == (1, n)



def test_encode_rejects_reserved_and_unstorable_fields():
    points = np.ones((2, 3), np.float32)
    with pytest.raises(PointCloudError, match="reserved"):
        encode(PointCloud(0, "l", points, np.zeros(2, np.float32), {"t": np.zeros(2)}))
    with pytest.raises(PointCloudError, match="cannot store"):
        encode(PointCloud(0, "l", points, None, {"id": np.zeros(2, np.int64)}))
    with pytest.raises(PointCloudError, match="3 values for 2 points"):
        encode(PointCloud(0, "l", points, None, {"i": np.zeros(3, np.float32)}))
