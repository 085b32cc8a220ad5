"""Ouster lidar packets in a classic pcap file -> scans (PointCloud), without the Ouster SDK.

Supports firmware 2.x sensor metadata (JSON) with the `RNG15_RFL8_NIR8` ("low data rate")
and `RNG19_RFL8_SIG16_NIR16` ("single return") UDP profiles. A lidar packet holds a 32-byte
header, `columns_per_packet` columns (12-byte header: u64 timestamp ns, u16 measurement id,
u16 status; then one pixel per beam) and a 32-byte footer. Points are computed as in the
Ouster sensor documentation ("lidar range to XYZ") and returned in the **sensor frame**,
i.e. after `lidar_to_sensor_transform` (for OS1: 180° about z, then +36.18 mm up), metres.
Per-point times are the column timestamps relative to the scan's first column.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError, LogFormatError
from mcl3d.io.logs.messages import PointCloud

_PROFILES = {
    # profile: (bytes per pixel, range bits mask, range unit in mm)
    "RNG15_RFL8_NIR8": (4, 0x7FFF, 8.0),
    "RNG19_RFL8_SIG16_NIR16": (12, 0x7FFFF, 1.0),
}
_PACKET_HEADER = 32
_PACKET_FOOTER = 32
_COLUMN_HEADER = 12


@dataclass(frozen=True)
class OusterMeta:
    columns_per_frame: int
    columns_per_packet: int
    pixels_per_column: int
    profile: str
    altitude_rad: np.ndarray  # (rows,)
    azimuth_rad: np.ndarray  # (rows,)
    beam_origin_mm: float
    T_sensor_lidar: np.ndarray  # (4, 4), translation in metres
    udp_port_lidar: int

    @property
    def packet_size(self) -> int:
        pixel = _PROFILES[self.profile][0]
        return (_PACKET_HEADER + _PACKET_FOOTER
                + self.columns_per_packet * (_COLUMN_HEADER + self.pixels_per_column * pixel))


def read_metadata(path: Path) -> OusterMeta:
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
        fmt = meta["data_format"]
        profile = fmt.get("udp_profile_lidar", "RNG19_RFL8_SIG16_NIR16")
        if profile not in _PROFILES:
            raise InputError(f"{path}: UDP lidar profile {profile!r} is not supported "
                             f"(supported: {', '.join(_PROFILES)})")
        T = np.asarray(meta["lidar_to_sensor_transform"], dtype=np.float64).reshape(4, 4)
        T[:3, 3] *= 1e-3
        rows = int(fmt["pixels_per_column"])
        alt = np.deg2rad(np.asarray(meta["beam_altitude_angles"], dtype=np.float64))
        azi = np.deg2rad(np.asarray(meta["beam_azimuth_angles"], dtype=np.float64))
        if alt.shape != (rows,) or azi.shape != (rows,):
            raise InputError(f"{path}: {len(alt)} beam angles for {rows} pixels per column")
        return OusterMeta(int(fmt["columns_per_frame"]), int(fmt["columns_per_packet"]), rows,
                          profile, alt, azi, float(meta["lidar_origin_to_beam_origin_mm"]), T,
                          int(meta.get("udp_port_lidar", 7502)))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not readable as Ouster sensor metadata ({exc!r})") from exc


def _udp_payloads(path: Path, port: int):
    """(payload bytes) of every UDP datagram to `port` in a classic libpcap file."""
    data = Path(path).read_bytes()
    if len(data) < 24:
        raise LogFormatError(f"{path}: too short for a pcap file")
    magic = data[:4]
    if magic in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1"):
        endian = "<"
    elif magic in (b"\xa1\xb2\xc3\xd4", b"\xa1\xb2\x3c\x4d"):
        endian = ">"
    else:
        raise LogFormatError(f"{path}: not a classic pcap file (magic {magic.hex()}); pcapng "
                             f"is not supported, convert it with `editcap -F pcap`")
    linktype = struct.unpack(endian + "I", data[20:24])[0]
    if linktype != 1:
        raise LogFormatError(f"{path}: link type {linktype} is not Ethernet")
    off = 24
    while off + 16 <= len(data):
        incl = struct.unpack(endian + "I", data[off + 8:off + 12])[0]
        frame = data[off + 16:off + 16 + incl]
        off += 16 + incl
        if len(frame) < incl:
            raise LogFormatError(f"{path}: truncated packet record at byte {off - 16 - incl}")
        if len(frame) < 42 or frame[12:14] != b"\x08\x00":
            continue
        ihl = (frame[14] & 0x0F) * 4
        if frame[23] != 17:  # not UDP
            continue
        flags_frag = struct.unpack(">H", frame[20:22])[0]
        if flags_frag & 0x3FFF:
            raise LogFormatError(f"{path}: fragmented IP packets are not supported")
        udp = 14 + ihl
        dport, ulen = struct.unpack(">HH", frame[udp + 2:udp + 6])
        if dport == port:
            yield frame[udp + 8:udp + ulen]


def _xyz_lut(meta: OusterMeta) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (rows, cols, 3) and beam offsets (rows, cols, 3) in the lidar frame."""
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
    return direction, offset


def read_ouster_pcap(pcap: Path, metadata: Path) -> list[PointCloud]:
    """Every complete frame of the pcap as a PointCloud in the sensor frame (metres).

    `fields` holds `reflectivity`, `row` and `column` per point; height/width give the
    organized layout (rows x columns) before invalid returns were dropped.
    """
    meta = read_metadata(metadata)
    pixel, mask, unit_mm = _PROFILES[meta.profile]
    rows, width = meta.pixels_per_column, meta.columns_per_frame
    col_bytes = _COLUMN_HEADER + rows * pixel
    frames: dict[int, dict] = {}
    for payload in _udp_payloads(pcap, meta.udp_port_lidar):
        if len(payload) != meta.packet_size:
            raise LogFormatError(f"{pcap}: lidar packet of {len(payload)} bytes; the metadata "
                                 f"({meta.profile}) says {meta.packet_size}")
        frame_id = struct.unpack("<H", payload[2:4])[0]
        body = np.frombuffer(payload, np.uint8, offset=_PACKET_HEADER,
                             count=meta.columns_per_packet * col_bytes)
        body = body.reshape(meta.columns_per_packet, col_bytes)
        head = body[:, :_COLUMN_HEADER].copy()
        stamp = head[:, 0:8].view("<u8")[:, 0]
        mid = head[:, 8:10].view("<u2")[:, 0]
        status = head[:, 10:12].view("<u2")[:, 0]
        pixels = body[:, _COLUMN_HEADER:].reshape(meta.columns_per_packet, rows, pixel)
        rng = pixels[:, :, 0:4].copy().view("<u4")[..., 0] if pixel >= 4 else None
        rng = (rng & mask).astype(np.float64) * unit_mm * 1e-3
        refl = pixels[:, :, 2] if meta.profile == "RNG15_RFL8_NIR8" else pixels[:, :, 4]
        f = frames.setdefault(frame_id, {
            "range": np.zeros((rows, width)), "refl": np.zeros((rows, width), np.uint8),
            "stamp": np.zeros(width, np.uint64), "seen": np.zeros(width, bool)})
        ok = ((status & 1) == 1) & (mid < width)
        f["range"][:, mid[ok]] = rng[ok].T
        f["refl"][:, mid[ok]] = refl[ok].T
        f["stamp"][mid[ok]] = stamp[ok]
        f["seen"][mid[ok]] = True
    if not frames:
        raise LogFormatError(f"{pcap}: no Ouster lidar packets on UDP port {meta.udp_port_lidar}")
    direction, offset = _xyz_lut(meta)
    R, t = meta.T_sensor_lidar[:3, :3], meta.T_sensor_lidar[:3, 3]
    clouds = []
    for frame_id in sorted(frames):
        f = frames[frame_id]
        if not f["seen"].all():
            continue  # partial frame at the start or end of the capture
        r = f["range"]
        xyz = r[..., None] * direction + offset
        valid = r > 0
        row, col = np.nonzero(valid)
        pts = xyz[valid] @ R.T + t
        stamps = f["stamp"].astype(np.int64)
        stamp0 = int(stamps.min())
        times = ((stamps[col] - stamp0) * 1e-9).astype(np.float32)
        clouds.append(PointCloud(
            stamp_ns=stamp0, frame_id="os_sensor", points=pts.astype(np.float32),
            times_s=times, fields={"reflectivity": f["refl"][valid], "row": row.astype(np.int32),
                                   "column": col.astype(np.int32)},
            n_dropped=int((~valid).sum()), height=rows, width=width))
    if not clouds:
        raise LogFormatError(f"{pcap}: no complete frame ({width} columns) in the capture")
    return clouds
