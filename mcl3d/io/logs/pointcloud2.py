"""sensor_msgs/PointCloud2 <-> PointCloud, vectorized with numpy structured dtypes.

Decoding accepts any field order, padding, endianness and row padding, organized or not.
Invalid points (NaN/inf or exactly zero x, y, z: how Ouster and others mark "no return")
are dropped and counted. A per-point time field (t, time, timestamp, offset_time) becomes
float32 seconds relative to the header stamp, whatever its units (see `_relative_seconds`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcl3d.core.errors import PointCloudError
from mcl3d.io.logs.messages import PointCloud

# sensor_msgs/PointField datatypes -> numpy kind+size.
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
DATATYPE_NAMES = {1: "int8", 2: "uint8", 3: "int16", 4: "uint16", 5: "int32", 6: "uint32",
                  7: "float32", 8: "float64"}
_NUMPY_TO_DATATYPE = {v: k for k, v in DATATYPES.items()}
TIME_FIELDS = ("t", "time", "timestamp", "offset_time")
_MAX_POINT_STEP = 2**31 - 1  # numpy's limit on an item's bytes


@dataclass
class FieldSpec:
    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass
class EncodedCloud:
    """The PointCloud2 body (everything but the header) as plain values."""

    height: int
    width: int
    fields: list[FieldSpec]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: np.ndarray  # uint8
    is_dense: bool


def time_field_name(names: list[str]) -> str | None:
    """The per-point time field among `names`, by the conventional names, in priority order."""
    for name in TIME_FIELDS:
        if name in names:
            return name
    return None


def _structured_dtype(fields: list[FieldSpec], point_step: int, big_endian: bool,
                      where: str) -> np.dtype:
    if point_step > _MAX_POINT_STEP:
        raise PointCloudError(f"{where}: point_step {point_step} is not a point's size; the "
                              "message is corrupt")
    order = ">" if big_endian else "<"
    names, formats, offsets = [], [], []
    for f in fields:
        if f.datatype not in DATATYPES:
            raise PointCloudError(f"{where}: field {f.name!r} has unknown PointField datatype "
                                  f"{f.datatype}; expected 1..8")
        if f.name in names or not f.name:
            continue  # duplicate or unnamed fields (e.g. padding declared as a field) are skipped
        if f.count > 1 and f.name in ("x", "y", "z", *TIME_FIELDS):
            raise PointCloudError(f"{where}: field {f.name!r} has {f.count} values per point; "
                                  "coordinates and the per-point time have one")
        size = int(DATATYPES[f.datatype][1]) * max(f.count, 1)
        if f.offset + size > point_step:
            raise PointCloudError(f"{where}: field {f.name!r} (offset {f.offset}, {size} bytes) "
                                  f"does not fit in point_step {point_step}")
        fmt = order + DATATYPES[f.datatype]
        names.append(f.name)
        formats.append(fmt if f.count <= 1 else (fmt, (f.count,)))
        offsets.append(f.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": point_step})


def _relative_seconds(values: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Per-point times as float32 seconds relative to the header stamp.

    Integer fields are nanoseconds (Ouster `t`, Livox `offset_time`); float fields are seconds
    (Velodyne `time`, Hesai `timestamp`) unless their spread only makes sense as nanoseconds.
    A field is absolute (unix or sensor time) when its values lie closer to the header stamp
    than to zero; then the stamp is subtracted.
    """
    v = values.astype(np.float64)
    if v.size == 0:
        return v.astype(np.float32)
    median = float(np.median(v))
    if values.dtype.kind in "iu":
        to_s, stamp = 1e-9, float(stamp_ns)
    else:
        span = float(v.max() - v.min())
        to_s = 1e-9 if span > 1e3 or abs(median - stamp_ns) < abs(median) else 1.0
        stamp = stamp_ns * 1e-9 if to_s == 1.0 else float(stamp_ns)
    if stamp != 0.0 and abs(median - stamp) < abs(median):
        if values.dtype.kind in "iu":  # exact integer arithmetic for absolute nanoseconds
            rel = (values.astype(np.int64) - np.int64(stamp_ns)).astype(np.float64)
        else:
            rel = v - stamp
        return (rel * to_s).astype(np.float32)
    return (v * to_s).astype(np.float32)


def decode(msg: EncodedCloud, stamp_ns: int, frame_id: str, where: str = "PointCloud2"
           ) -> PointCloud:
    """Decode a PointCloud2 body into valid points, per-point times and other fields."""
    names = [f.name for f in msg.fields]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise PointCloudError(f"{where}: the cloud has no {'/'.join(missing)} field(s) "
                              f"(fields: {', '.join(names) or 'none'}); it cannot be used as "
                              "3D points")
    height, width, step = int(msg.height), int(msg.width), int(msg.point_step)
    n = height * width
    row_step = int(msg.row_step) or width * step
    if step <= 0 and n > 0:
        raise PointCloudError(f"{where}: point_step is {step}")
    if row_step < width * step:
        raise PointCloudError(f"{where}: row_step {row_step} < width {width} x point_step {step}")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    need = row_step * (height - 1) + width * step if n else 0
    if data.size < need:
        raise PointCloudError(f"{where}: data has {data.size} bytes, but {height}x{width} points "
                              f"of {step} bytes need {need}; the message is truncated")
    dtype = _structured_dtype(list(msg.fields), step, bool(msg.is_bigendian), where)
    if n == 0:
        raw = np.zeros(0, dtype=dtype)
    elif row_step == width * step:
        raw = data[: n * step].view(dtype)
    else:  # padded rows: view each row's used bytes, then flatten
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step),
                                               strides=(row_step, 1))
        raw = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    return cloud_from_structured(raw, int(stamp_ns), frame_id, height, width)


def cloud_from_structured(raw: np.ndarray, stamp_ns: int, frame_id: str, height: int = 1,
                          width: int | None = None) -> PointCloud:
    """A PointCloud from a structured array with x, y, z fields (PointCloud2 or file data)."""
    n = len(raw)
    xyz = np.empty((n, 3), dtype=np.float32)
    for i, axis in enumerate("xyz"):
        xyz[:, i] = raw[axis]
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]  # column by column: axis-1 reductions of an
    valid = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)  # (n, 3) array take 8x longer
    valid &= (x != 0) | (y != 0) | (z != 0)
    keep = None if valid.all() else np.flatnonzero(valid)
    points = xyz if keep is None else np.take(xyz, keep, axis=0)  # 6x faster than xyz[keep]
    tname = time_field_name(list(raw.dtype.names))
    times = None
    fields: dict[str, np.ndarray] = {}
    for name in raw.dtype.names:
        if name in ("x", "y", "z"):
            continue
        col = raw[name]
        native = col.dtype.newbyteorder("=")
        col = (col.astype(native) if keep is None  # a contiguous copy in native order
               else np.take(col, keep, axis=0).astype(native, copy=False))
        if name == tname:
            times = _relative_seconds(col, stamp_ns)
        else:
            fields[name] = col
    return PointCloud(stamp_ns=int(stamp_ns), frame_id=frame_id, points=points, times_s=times,
                      fields=fields, n_dropped=int(n - len(points)), height=height,
                      width=n if width is None else width)


def encode(cloud: PointCloud, where: str = "PointCloud") -> EncodedCloud:
    """Pack a cloud as a dense little-endian PointCloud2 body: x y z float32, the other fields
    with their own dtypes, and the per-point time as field `t` (float32 seconds)."""
    points = np.asarray(cloud.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise PointCloudError(f"{where}: points must be (N, 3), got {points.shape}")
    n = len(points)
    columns: list[tuple[str, np.ndarray]] = [(a, points[:, i]) for i, a in enumerate("xyz")]
    for name, values in cloud.fields.items():
        columns.append((name, np.asarray(values)))
    if cloud.times_s is not None:
        columns.append(("t", np.asarray(cloud.times_s, dtype=np.float32)))
    names = [name for name, _ in columns]
    if len(set(names)) != len(names):
        raise PointCloudError(f"{where}: field names repeat ({', '.join(names)}); x, y, z and "
                              "t (from times_s) are reserved")
    specs, formats, offset = [], [], 0
    for name, values in columns:
        if len(values) != n:
            raise PointCloudError(f"{where}: field {name!r} has {len(values)} values for "
                                  f"{n} points")
        code = "f4" if name in "xyz" else values.dtype.newbyteorder("<").str[1:]
        if values.dtype.kind == "b":
            code = "u1"
        if code not in _NUMPY_TO_DATATYPE:
            raise PointCloudError(f"{where}: field {name!r} has dtype {values.dtype}, which "
                                  "PointCloud2 cannot store (use int8..uint32, float32, float64)")
        count = int(np.prod(values.shape[1:])) if values.ndim > 1 else 1
        specs.append(FieldSpec(name, offset, _NUMPY_TO_DATATYPE[code], count))
        formats.append(("<" + code) if count == 1 else ("<" + code, values.shape[1:]))
        offset += int(code[1]) * count
    dtype = np.dtype({"names": [c[0] for c in columns], "formats": formats,
                      "offsets": [s.offset for s in specs], "itemsize": offset})
    packed = np.empty(n, dtype=dtype)
    for name, values in columns:
        packed[name] = values
    height, width = int(cloud.height), int(cloud.width)
    if height * width != n or height < 1:
        height, width = 1, n
    return EncodedCloud(height=height, width=width, fields=specs, is_bigendian=False,
                        point_step=offset, row_step=offset * width,
                        data=packed.view(np.uint8).reshape(-1), is_dense=True)
