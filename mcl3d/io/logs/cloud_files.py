"""Point-cloud files: PCD (ascii, binary, binary_compressed), PLY (ascii, binary) and KITTI .bin.

Each reader builds a numpy structured array and hands it to the same decoding as PointCloud2
messages, so invalid points are dropped and counted and per-point times (t, time, timestamp,
offset_time) become seconds relative to the cloud stamp. Files carry no header stamp: when the
per-point times are absolute (unix seconds or ns), the stamp is the earliest point time,
otherwise 0.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, PointCloudError
from mcl3d.core.outputs import atomic_open
from mcl3d.io.logs.messages import PointCloud
from mcl3d.io.logs.pointcloud2 import cloud_from_structured, time_field_name

CLOUD_SUFFIXES = (".pcd", ".ply", ".bin")


def read_cloud_file(path: Path) -> PointCloud:
    """Read a .pcd, .ply or KITTI .bin file into a PointCloud (frame_id is the empty string)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        raw, height, width = _read_pcd(path)
    elif suffix == ".ply":
        raw = _read_ply(path)
        height, width = 1, len(raw)
    elif suffix == ".bin":
        raw = _read_kitti_bin(path)
        height, width = 1, len(raw)
    else:
        raise InputError(f"{path}: unknown point-cloud file type {suffix!r}; mcl3d reads "
                         f"{', '.join(CLOUD_SUFFIXES)} (KITTI float32 x y z intensity)")
    names = raw.dtype.names or ()
    missing = [a for a in "xyz" if a not in names]
    if missing:
        raise PointCloudError(f"{path}: no {'/'.join(missing)} field(s) (fields: "
                              f"{', '.join(names) or 'none'}); it cannot be used as 3D points")
    several = [a for a in ("x", "y", "z", time_field_name(list(names))) if a and raw.dtype[a].shape]
    if several:
        raise PointCloudError(f"{path}: field {several[0]!r} has several values per point; "
                              "coordinates and the per-point time have one")
    return cloud_from_structured(raw, _file_stamp_ns(raw), "", height, width)


def _file_stamp_ns(raw: np.ndarray) -> int:
    """The earliest per-point time when the times are absolute (unix s or ns), else 0."""
    name = time_field_name(list(raw.dtype.names))
    if name is None or len(raw) == 0:
        return 0
    values = raw[name]
    finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values
    if finite.size == 0:
        return 0
    lo = finite.min()
    if values.dtype.kind in "iu":
        return int(lo) if lo > 1e15 else 0
    if lo > 1e15:
        return int(lo)
    return round(float(lo) * 1e9) if lo > 1e6 else 0


# ---- PCD ----

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4",
              ("U", 8): "u8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}
_LZF_MAX_RATIO = 88  # a 3-byte back reference copies at most 264 bytes


def lzf_decompress(src: bytes, out_len: int) -> bytes:
    """LZF decompression (the format PCD binary_compressed uses); ValueError when corrupt."""
    if out_len > _LZF_MAX_RATIO * len(src):
        raise ValueError(f"header says {out_len} bytes, more than {len(src)} LZF bytes can hold")
    out = bytearray(out_len)
    ip = op = 0
    n = len(src)
    while ip < n:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n or op + length > out_len:
                raise ValueError("literal run past the end of the data")
            out[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
            continue
        length = ctrl >> 5  # back reference
        if length == 7:
            if ip >= n:
                raise ValueError("back reference past the end of the data")
            length += src[ip]
            ip += 1
        if ip >= n:
            raise ValueError("back reference past the end of the data")
        ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
        ip += 1
        length += 2
        if ref < 0 or op + length > out_len:
            raise ValueError("back reference outside the output")
        distance = op - ref
        if distance >= length:
            out[op:op + length] = out[ref:ref + length]
        else:  # overlapping copy repeats the last `distance` bytes
            pattern = bytes(out[ref:op])
            out[op:op + length] = (pattern * (length // distance + 1))[:length]
        op += length
    if op != out_len:
        raise ValueError(f"decompressed {op} bytes, header says {out_len}")
    return bytes(out)


def _pcd_header(path: Path, blob: bytes) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = blob.find(b"\n", pos)
        if end < 0:
            raise PointCloudError(f"{path}: PCD header has no DATA line; the file is truncated or "
                                  "not a PCD file")
        line = blob[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos


def _read_pcd(path: Path) -> tuple[np.ndarray, int, int]:
    blob = path.read_bytes()
    header, data_start = _pcd_header(path, blob)
    try:
        names = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        width, height = int(header["WIDTH"][0]), int(header.get("HEIGHT", ["1"])[0])
        n = int(header.get("POINTS", [width * height])[0])
        data_kind = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise PointCloudError(f"{path}: malformed PCD header ({exc!r} missing or invalid)"
                              ) from None
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise PointCloudError(f"{path}: PCD header FIELDS/SIZE/TYPE/COUNT lengths differ")
    if not names or min(counts) < 1 or min(width, height, n) < 0:
        raise PointCloudError(f"{path}: malformed PCD header (no FIELDS, a COUNT below 1 or a "
                              "negative WIDTH, HEIGHT or POINTS)")
    formats, offsets, keep, offset = [], [], [], 0
    for name, size, typ, count in zip(names, sizes, types, counts, strict=True):
        code = _PCD_TYPES.get((typ, size))
        if code is None:
            raise PointCloudError(f"{path}: field {name!r} has unsupported TYPE {typ} SIZE {size}")
        if name != "_" and name not in keep:
            keep.append(name)
            formats.append("<" + code if count == 1 else ("<" + code, (count,)))
            offsets.append(offset)
        offset += size * count
    dtype = np.dtype({"names": keep, "formats": formats, "offsets": offsets, "itemsize": offset})
    body = blob[data_start:]
    if data_kind == "ascii":
        raw = _pcd_ascii(path, body, names, sizes, types, counts, dtype, n)
    elif data_kind == "binary":
        if len(body) < n * offset:
            raise PointCloudError(f"{path}: PCD binary data has {len(body)} bytes, {n} points need "
                                  f"{n * offset}; the file is truncated")
        raw = np.frombuffer(body, dtype=dtype, count=n)
    elif data_kind == "binary_compressed":
        raw = _pcd_compressed(path, body, names, sizes, counts, dtype, n)
    else:
        raise PointCloudError(f"{path}: unknown PCD DATA kind {data_kind!r} (ascii, binary, "
                              "binary_compressed)")
    if height * width != n:
        height, width = 1, n
    return raw, height, width


def _pcd_ascii(path, body, names, sizes, types, counts, dtype, n) -> np.ndarray:
    columns = sum(counts)
    text = body.decode("ascii", errors="replace").split()
    if len(text) < n * columns:
        raise PointCloudError(f"{path}: PCD ascii data has {len(text)} values, {n} points x "
                              f"{columns} columns need {n * columns}; the file is truncated")
    try:
        table = np.array(text[: n * columns], dtype=np.float64).reshape(n, columns)
    except ValueError as exc:
        raise PointCloudError(f"{path}: PCD ascii data is not numeric ({exc})") from None
    raw = np.zeros(n, dtype=dtype)
    col = 0
    for name, count in zip(names, counts, strict=True):
        if name != "_" and name in dtype.names:
            values = table[:, col:col + count]
            raw[name] = values[:, 0] if count == 1 else values
        col += count
    return raw


def _pcd_compressed(path, body, names, sizes, counts, dtype, n) -> np.ndarray:
    if len(body) < 8:
        raise PointCloudError(f"{path}: PCD binary_compressed data is truncated")
    compressed, uncompressed = struct.unpack("<II", body[:8])
    if len(body) < 8 + compressed:
        raise PointCloudError(f"{path}: PCD compressed block has {len(body) - 8} of {compressed} "
                              "bytes; the file is truncated")
    try:
        plain = lzf_decompress(body[8:8 + compressed], uncompressed)
    except ValueError as exc:
        raise PointCloudError(f"{path}: PCD compressed data is corrupt ({exc})") from None
    if n * dtype.itemsize > len(plain):
        raise PointCloudError(f"{path}: PCD compressed data holds {len(plain)} bytes, less than "
                              f"{n} points need; the file is corrupt")
    raw = np.zeros(n, dtype=dtype)
    start = 0  # binary_compressed stores each field as one contiguous block (field-major)
    for name, size, count in zip(names, sizes, counts, strict=True):
        block = n * size * count
        if start + block > len(plain):
            raise PointCloudError(f"{path}: PCD compressed data holds {len(plain)} bytes, less "
                                  f"than the fields need; the file is corrupt")
        if name != "_" and name in dtype.names:
            base = dtype.fields[name][0]
            values = np.frombuffer(plain, dtype=base.base, count=n * count, offset=start)
            raw[name] = values if count == 1 else values.reshape(n, count)
        start += block
    return raw


# ---- PLY ----

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


def _read_ply(path: Path) -> np.ndarray:
    """The vertex element of a PLY file with all its scalar properties."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise PointCloudError(f"{path}: not a PLY file (no 'ply' magic line)")
        fmt, elements, current = None, [], None
        while True:
            line = f.readline()
            if not line:
                raise PointCloudError(f"{path}: PLY header has no end_header; file truncated")
            words = line.decode("ascii", errors="replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            try:
                if words[0] == "format":
                    fmt = words[1]
                elif words[0] == "element":
                    current = (words[1], int(words[2]), [])
                    elements.append(current)
                elif words[0] == "property" and current is not None:
                    current[2].append((words[1], words[4] if words[1] == "list" else words[2]))
            except (IndexError, ValueError):
                raise PointCloudError(f"{path}: malformed PLY header line {line.strip()!r}"
                                      ) from None
            if current is not None and current[1] < 0:
                raise PointCloudError(f"{path}: PLY element {current[0]!r} has a negative count")
        body_start = f.tell()
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise PointCloudError(f"{path}: unknown PLY format {fmt!r}")
    order = ">" if fmt == "binary_big_endian" else "<"
    skip_bytes, skip_lines = 0, 0
    for name, count, props in elements:
        if any(p[0] == "list" for p in props) and name != "vertex":
            raise PointCloudError(f"{path}: PLY element {name!r} with list properties comes "
                                  "before the vertices; write vertices first")
        try:
            dtype = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
        except KeyError as exc:
            raise PointCloudError(f"{path}: PLY property type {exc} is not supported") from None
        except ValueError:  # a property name twice
            raise PointCloudError(f"{path}: PLY element {name!r} repeats a property name "
                                  f"({' '.join(p[1] for p in props)})") from None
        if name == "vertex":
            if fmt == "ascii":
                return _ply_ascii(path, body_start, skip_lines, count, dtype)
            data = np.fromfile(path, dtype=dtype, count=count, offset=body_start + skip_bytes)
            if len(data) < count:
                raise PointCloudError(f"{path}: PLY has {len(data)} of {count} vertices; the file "
                                      "is truncated")
            return data.astype(dtype.newbyteorder("="))
        skip_bytes += dtype.itemsize * count
        skip_lines += count
    raise PointCloudError(f"{path}: PLY file has no vertex element")


def _ply_ascii(path: Path, body_start: int, skip_lines: int, count: int, dtype: np.dtype
               ) -> np.ndarray:
    with open(path, "rb") as f:
        f.seek(body_start)
        lines = f.read().decode("ascii", errors="replace").splitlines()[skip_lines:]
    values = " ".join(lines[:count]).split()
    width = len(dtype.names)
    if len(values) < count * width:
        raise PointCloudError(f"{path}: PLY has fewer than {count} ascii vertices; truncated")
    try:
        table = np.array(values[: count * width], dtype=np.float64).reshape(count, width)
    except ValueError as exc:
        raise PointCloudError(f"{path}: PLY ascii vertices are not numeric ({exc})") from None
    raw = np.zeros(count, dtype=dtype.newbyteorder("="))
    for i, name in enumerate(dtype.names):
        raw[name] = table[:, i]
    return raw


def write_ply(path: Path, points: np.ndarray, normals: np.ndarray | None = None,
              colors: np.ndarray | None = None) -> None:
    """Write a binary little-endian PLY (x y z float32, optional normals, uchar RGB) atomically.

    `colors` may be uint8 0..255 or floats 0..1.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{path}: points must be (N, 3), got {points.shape}")
    n = len(points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != (n, 3):
            raise InputError(f"{path}: normals must be ({n}, 3), got {normals.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (n, 3):
            raise InputError(f"{path}: colors must be ({n}, 3), got {colors.shape}")
        if colors.dtype.kind == "f":
            colors = np.clip(np.round(colors * 255.0), 0, 255)
        colors = colors.astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(n, dtype=fields)
    for i, axis in enumerate("xyz"):
        data[axis] = points[:, i]
        if normals is not None:
            data["n" + axis] = normals[:, i]
    if colors is not None:
        for i, channel in enumerate(("red", "green", "blue")):
            data[channel] = colors[:, i]
    types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment written by mcl3d",
              f"element vertex {n}"]
    header += [f"property {types[t]} {name}" for name, t in fields]
    header.append("end_header")
    with atomic_open(Path(path), "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())


# ---- KITTI ----

def _read_kitti_bin(path: Path) -> np.ndarray:
    size = path.stat().st_size
    if size % 16:
        raise PointCloudError(f"{path}: {size} bytes is not a multiple of 16; a KITTI .bin holds "
                              "float32 x y z intensity per point")
    return np.fromfile(path, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("intensity", "<f4")])
