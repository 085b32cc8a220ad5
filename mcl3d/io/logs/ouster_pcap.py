"""Ouster lidar and IMU packets in a classic pcap file -> frames and IMU samples, streamed
packet by packet (without the Ouster SDK).

Supports firmware 2.x sensor metadata (JSON) with the `RNG15_RFL8_NIR8` ("low data rate")
and `RNG19_RFL8_SIG16_NIR16` ("single return") lidar profiles and the `LEGACY` IMU profile.
A lidar packet holds a 32-byte header (u16 packet type, u16 frame id, ...),
`columns_per_packet` columns (12-byte header: u64 timestamp ns, u16 measurement id, u16
status; then one pixel per beam) and a 32-byte footer. Points are computed as in the Ouster
sensor documentation ("lidar range to XYZ") in the **sensor frame**, i.e. after
`lidar_to_sensor_transform` (for OS1: 180° about z, then +36.18 mm up), metres; they match
the SDK's `XYZLut(info, use_extrinsics=False)` to float32 rounding. An IMU packet (48 bytes)
holds u64 system, accelerometer and gyroscope timestamps (ns), acceleration in g and angular
velocity in deg/s (f32 x y z each), in the IMU frame (`imu_to_sensor_transform`); it is
stamped with its gyroscope time, as ouster-ros does.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, LogFormatError

_PROFILES = {
    # profile: (bytes per pixel, range bits mask, range unit in mm, reflectivity byte)
    "RNG15_RFL8_NIR8": (4, 0x7FFF, 8.0, 2),
    "RNG19_RFL8_SIG16_NIR16": (12, 0x7FFFF, 1.0, 4),
}
_PACKET_HEADER = 32
_PACKET_FOOTER = 32
_COLUMN_HEADER = 12
IMU_PACKET_BYTES = 48  # the LEGACY IMU profile
STANDARD_G = 9.80665


@dataclass(frozen=True)
class OusterMeta:
    path: Path
    sensor: str  # product line and mode, e.g. "OS-1-128 1024x10"
    columns_per_frame: int
    columns_per_packet: int
    pixels_per_column: int
    profile: str
    altitude_rad: np.ndarray  # (rows,)
    azimuth_rad: np.ndarray  # (rows,)
    beam_origin_mm: float
    T_sensor_lidar: np.ndarray  # (4, 4), translation in metres
    T_sensor_imu: np.ndarray  # (4, 4), translation in metres
    udp_port_lidar: int
    udp_port_imu: int | None  # None when the IMU profile is not LEGACY (not read)

    @property
    def packet_size(self) -> int:
        pixel = _PROFILES[self.profile][0]
        return (_PACKET_HEADER + _PACKET_FOOTER
                + self.columns_per_packet * (_COLUMN_HEADER + self.pixels_per_column * pixel))


def _transform_m(values, path: Path, key: str) -> np.ndarray:
    T = np.asarray(values, dtype=np.float64).reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError(f"{path}: {key} is not a homogeneous transform")
    T[:3, 3] *= 1e-3  # the JSON gives millimetres
    return T


def read_metadata(path: Path) -> OusterMeta:
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
        fmt = meta["data_format"]
        profile = fmt.get("udp_profile_lidar", "RNG19_RFL8_SIG16_NIR16")
        if profile not in _PROFILES:
            raise InputError(f"{path}: UDP lidar profile {profile!r} is not supported "
                             f"(supported: {', '.join(_PROFILES)})")
        rows = int(fmt["pixels_per_column"])
        alt = np.deg2rad(np.asarray(meta["beam_altitude_angles"], dtype=np.float64))
        azi = np.deg2rad(np.asarray(meta["beam_azimuth_angles"], dtype=np.float64))
        if alt.shape != (rows,) or azi.shape != (rows,):
            raise InputError(f"{path}: {len(alt)} beam angles for {rows} pixels per column")
        identity_mm = np.eye(4).ravel().tolist()
        return OusterMeta(
            path, f"{meta.get('prod_line', 'Ouster')} {meta.get('lidar_mode', '')}".strip(),
            int(fmt["columns_per_frame"]), int(fmt["columns_per_packet"]), rows, profile, alt,
            azi, float(meta["lidar_origin_to_beam_origin_mm"]),
            _transform_m(meta["lidar_to_sensor_transform"], path, "lidar_to_sensor_transform"),
            _transform_m(meta.get("imu_to_sensor_transform", identity_mm), path,
                         "imu_to_sensor_transform"),
            int(meta.get("udp_port_lidar", 7502)),
            int(meta.get("udp_port_imu", 7503))
            if fmt.get("udp_profile_imu", "LEGACY") == "LEGACY" else None)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not readable as Ouster sensor metadata ({exc!r})") from exc


class PcapPackets:
    """The UDP datagrams of a classic libpcap file, streamed record by record: iterating
    yields (destination port, payload). A file cut inside a record ends the iteration and sets
    `cut_at_byte` (where that record starts); the header is checked on construction."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.cut_at_byte: int | None = None
        with open(self.path, "rb") as f:
            head = f.read(24)
        if len(head) < 24:
            raise LogFormatError(f"{path}: too short for a pcap file")
        magic = head[:4]
        if magic in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1"):
            self._endian = "<"
        elif magic in (b"\xa1\xb2\xc3\xd4", b"\xa1\xb2\x3c\x4d"):
            self._endian = ">"
        else:
            raise LogFormatError(f"{path}: not a classic pcap file (magic {magic.hex()}); pcapng "
                                 "is not supported, convert it with `editcap -F pcap`")
        linktype = struct.unpack(self._endian + "I", head[20:24])[0]
        if linktype != 1:
            raise LogFormatError(f"{path}: link type {linktype} is not Ethernet")

    def __iter__(self) -> Iterator[tuple[int, bytes]]:
        record = struct.Struct(self._endian + "IIII")
        with open(self.path, "rb") as f:
            f.seek(24)
            while True:
                start = f.tell()
                head = f.read(16)
                if not head:
                    return
                length = record.unpack(head)[2] if len(head) == 16 else -1
                frame = f.read(length) if length >= 0 else b""
                if len(frame) != length:
                    self.cut_at_byte = start
                    return
                udp = _udp(frame, self.path)
                if udp is not None:
                    yield udp


def _udp(frame: bytes, path: Path) -> tuple[int, bytes] | None:
    """(destination port, payload) of an Ethernet/IPv4/UDP frame, None for other frames."""
    if len(frame) < 42 or frame[12:14] != b"\x08\x00" or frame[23] != 17:
        return None
    if struct.unpack(">H", frame[20:22])[0] & 0x3FFF:
        raise LogFormatError(f"{path}: fragmented IP packets are not supported")
    udp = 14 + (frame[14] & 0x0F) * 4
    dport, length = struct.unpack(">HH", frame[udp + 2:udp + 6])
    return dport, frame[udp + 8:udp + length]


@dataclass
class LidarColumns:
    """The valid columns of one lidar packet."""

    frame_id: int
    measurement_id: np.ndarray  # (n,) column index in the frame
    stamp_ns: np.ndarray  # (n,) uint64
    range_m: np.ndarray  # (n, rows)
    reflectivity: np.ndarray  # (n, rows) uint8


def decode_lidar_packet(meta: OusterMeta, payload: bytes, where: Path) -> LidarColumns:
    if len(payload) != meta.packet_size:
        raise LogFormatError(
            f"{where}: its lidar packets hold {len(payload)} bytes, but {meta.path.name} "
            f"({meta.sensor}, {meta.pixels_per_column} beams, {meta.profile}) means "
            f"{meta.packet_size}-byte packets: the metadata belongs to another sensor or mode; "
            "use the JSON saved with this recording")
    pixel, mask, unit_mm, refl_byte = _PROFILES[meta.profile]
    rows, n = meta.pixels_per_column, meta.columns_per_packet
    body = np.frombuffer(payload, np.uint8, offset=_PACKET_HEADER,
                         count=n * (_COLUMN_HEADER + rows * pixel)).reshape(n, -1)
    head = body[:, :_COLUMN_HEADER].copy()
    stamp = head[:, 0:8].view("<u8")[:, 0]
    mid = head[:, 8:10].view("<u2")[:, 0]
    status = head[:, 10:12].view("<u2")[:, 0]
    pixels = body[:, _COLUMN_HEADER:].reshape(n, rows, pixel)
    rng = pixels[:, :, 0:4].copy().view("<u4")[..., 0]
    ok = ((status & 1) == 1) & (mid < meta.columns_per_frame)
    if not ok.all() and (mid >= meta.columns_per_frame).any():
        raise LogFormatError(f"{where}: measurement id {int(mid.max())} in a lidar packet, but "
                             f"{meta.path.name} ({meta.sensor}) has {meta.columns_per_frame} "
                             "columns: the metadata belongs to another mode; use the JSON "
                             "saved with this recording")
    return LidarColumns(struct.unpack("<H", payload[2:4])[0], mid[ok], stamp[ok],
                        (rng[ok] & mask).astype(np.float64) * unit_mm * 1e-3,
                        pixels[ok][:, :, refl_byte])


@dataclass
class Frame:
    """One frame's range image being filled, column by column."""

    frame_id: int
    range_m: np.ndarray  # (rows, columns)
    reflectivity: np.ndarray  # (rows, columns) uint8
    stamp_ns: np.ndarray  # (columns,) uint64
    seen: np.ndarray  # (columns,) bool
    packets: int = field(default=0)

    @classmethod
    def empty(cls, meta: OusterMeta, frame_id: int) -> Frame:
        rows, width = meta.pixels_per_column, meta.columns_per_frame
        return cls(frame_id, np.zeros((rows, width)), np.zeros((rows, width), np.uint8),
                   np.zeros(width, np.uint64), np.zeros(width, bool))

    def add(self, cols: LidarColumns) -> None:
        self.range_m[:, cols.measurement_id] = cols.range_m.T
        self.reflectivity[:, cols.measurement_id] = cols.reflectivity.T
        self.stamp_ns[cols.measurement_id] = cols.stamp_ns
        self.seen[cols.measurement_id] = True
        self.packets += 1

    @property
    def complete(self) -> bool:
        return bool(self.seen.all())


class FrameAssembler:
    """Complete frames from consecutive lidar packets: a frame ends when the frame id changes;
    partial ones (the capture's first and last, a lost packet) are left out."""

    def __init__(self, meta: OusterMeta):
        self.meta = meta
        self.current: Frame | None = None

    def push(self, cols: LidarColumns) -> Frame | None:
        """Add a packet's columns; returns the previous frame when these start a new one and
        it was complete."""
        done = None
        if self.current is not None and cols.frame_id != self.current.frame_id:
            done = self.finish()
        if self.current is None:
            self.current = Frame.empty(self.meta, cols.frame_id)
        self.current.add(cols)
        return done

    def finish(self) -> Frame | None:
        """The frame being filled, if complete; the assembler starts afresh."""
        frame, self.current = self.current, None
        return frame if frame is not None and frame.complete else None


class XyzLut:
    """Unit directions and beam offsets per pixel, in the sensor frame."""

    def __init__(self, meta: OusterMeta):
        cols = np.arange(meta.columns_per_frame)
        encoder = 2 * np.pi * (1.0 - cols / meta.columns_per_frame)
        theta = encoder[None, :] - meta.azimuth_rad[:, None]
        phi = meta.altitude_rad[:, None]
        direction = np.stack([np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi),
                              np.broadcast_to(np.sin(phi), theta.shape)], axis=-1)
        n = meta.beam_origin_mm * 1e-3
        offset = np.stack([n * np.cos(encoder), n * np.sin(encoder), np.zeros_like(encoder)],
                          axis=-1)
        offset = np.broadcast_to(offset[None], direction.shape) - n * direction
        R, t = meta.T_sensor_lidar[:3, :3], meta.T_sensor_lidar[:3, 3]
        self.direction = direction @ R.T
        self.offset = offset @ R.T + t

    def __call__(self, range_m: np.ndarray) -> np.ndarray:
        """(rows, columns, 3) float32 points; (0, 0, 0) where there is no return."""
        xyz = range_m[..., None] * self.direction + self.offset
        xyz[range_m <= 0] = 0.0
        return xyz.astype(np.float32)


@dataclass
class ImuSample:
    stamp_ns: int  # gyroscope time
    linear_acceleration: np.ndarray  # (3,) m/s^2
    angular_velocity: np.ndarray  # (3,) rad/s


def decode_imu_packet(payload: bytes, where: Path) -> ImuSample:
    if len(payload) != IMU_PACKET_BYTES:
        raise LogFormatError(f"{where}: an IMU packet of {len(payload)} bytes; mcl3d reads "
                             f"the LEGACY IMU profile ({IMU_PACKET_BYTES} bytes)")
    _sys, _accel_ts, gyro_ts = struct.unpack_from("<QQQ", payload, 0)
    values = np.frombuffer(payload, "<f4", count=6, offset=24).astype(np.float64)
    return ImuSample(int(gyro_ts), values[:3] * STANDARD_G, np.deg2rad(values[3:]))
