"""Fuzzing the PointCloud2 decoder: damaged data bytes and random layouts (fields, offsets,
datatypes, counts, steps, sizes) are decoded or refused with a PointCloudError, never a
traceback; a decoded cloud holds only finite points."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.io.logs.messages import PointCloud
from mcl3d.io.logs.pointcloud2 import EncodedCloud, FieldSpec, decode, encode

STAMP_NS = 1_317_000_015_000_000_000


def _valid() -> EncodedCloud:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(12, 3)).astype(np.float32)
    fields = {"intensity": rng.uniform(size=12).astype(np.float32),
              "ring": np.arange(12, dtype=np.uint16)}
    return encode(PointCloud(STAMP_NS, "lidar", points, np.linspace(0, 0.1, 12, dtype=np.float32),
                             fields=fields, height=3, width=4))


def _check(cloud) -> None:
    if cloud is not None:
        assert cloud.points.ndim == 2 and cloud.points.shape[1] == 3
        assert np.isfinite(cloud.points).all()
        assert cloud.times_s is None or len(cloud.times_s) == len(cloud.points)


_NAMES = st.sampled_from(["x", "y", "z", "t", "time", "timestamp", "offset_time", "intensity",
                          "ring", "", "x "])
_U32 = st.one_of(st.integers(0, 8), st.integers(0, 64), st.just(2**32 - 1),
                st.integers(0, 2**32 - 1))  # small sizes reach the decoding, large the checks
_FIELD = st.builds(FieldSpec, name=_NAMES, offset=_U32, datatype=st.integers(0, 9),
                   count=_U32)


@fuzz_settings(examples=150)
@given(data=st.data())
def test_damaged_cloud_data(data):
    msg = _valid()
    msg.data = np.frombuffer(data.draw(damaged(msg.data.tobytes())), dtype=np.uint8)
    _check(reads_or_refuses(lambda: decode(msg, STAMP_NS, "lidar")))


@fuzz_settings(examples=200)
@example(fields=[], height=2**32 - 1, width=0, point_step=2**32 - 1, row_step=0,  # crashed
         big_endian=False, data=b"", xyz_count=1)
@example(fields=[], height=1, width=2, point_step=20, row_step=40, big_endian=False,  # crashed
         data=bytes(40), xyz_count=2)
@given(fields=st.lists(_FIELD, max_size=6), height=_U32, width=_U32, point_step=_U32,
       row_step=_U32, big_endian=st.booleans(), data=st.binary(max_size=512),
       xyz_count=st.sampled_from([None, 0, 1, 1, 2]))
def test_random_cloud_layouts(fields, height, width, point_step, row_step, big_endian, data,
                              xyz_count):
    if xyz_count is not None:  # most random layouts lack x, y or z; these reach the decoding
        fields = [FieldSpec(a, 4 * i, 7, xyz_count) for i, a in enumerate("xyz")] + fields
    msg = EncodedCloud(height=height, width=width, fields=fields, is_bigendian=big_endian,
                       point_step=point_step, row_step=row_step,
                       data=np.frombuffer(data, dtype=np.uint8), is_dense=False)
    _check(reads_or_refuses(lambda: decode(msg, STAMP_NS, "lidar")))
