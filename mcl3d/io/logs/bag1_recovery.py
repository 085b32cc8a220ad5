"""A ROS 1 bag damaged part way, read as `rosbag reindex` reads it: record by record.

A recorder killed mid-write leaves a bag without its index (rosbags refuses it: "Bag is not
indexed") and often a cut last chunk. Here the bag is walked from its first record: chunks are
decompressed (streaming, so a cut chunk still gives the whole records written before the cut)
and their connection and message records yielded in file order; the cut ends the walk. A
stretch in the middle that does not parse (garbage, zeros) is skipped up to the next record
that is a whole chunk whose records all parse. ROS 1 bags carry no checksums, so a chunk is
trusted whole only when it decompresses to its stated size and every record in it parses.
"""

from __future__ import annotations

import bz2
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

import lz4.frame
from rosbags.rosbag1.reader import Header, ReaderError, RecordType

MAGIC = b"#ROSBAG V2.0\n"
_U32 = struct.Struct("<L")
_MAX_HEADER_BYTES = 1 << 16  # record headers hold a few short fields (connections: a few kB)
_SCAN_WINDOW = 1 << 20  # bytes searched at a time when resynchronising
_CHUNK_OP_FIELD = b"\x04\x00\x00\x00op=\x05"  # a record header's field saying "a chunk"
_MAX_CHUNK_HEADER = 96  # compression, op and size fields: a chunk header is ~45 bytes


@dataclass(frozen=True)
class BagConnection:
    conn_id: int
    topic: str
    msgtype: str  # as the bag writes it, e.g. sensor_msgs/PointCloud2
    msgdef: str  # the full message definition text, dependencies included


@dataclass(frozen=True)
class BagMessage:
    conn_id: int
    stamp_ns: int
    data: bytes


class UnsoundRecord(ValueError):
    """Bytes that do not parse as the record their header says (damage, or not a record)."""


def _header(src: BinaryIO) -> Header:
    head = src.read(4)
    if len(head) < 4:
        raise UnsoundRecord("the file ends inside a record")
    size = _U32.unpack(head)[0]
    if size > _MAX_HEADER_BYTES:
        raise UnsoundRecord(f"a record header of {size} bytes")
    try:
        return Header.read(BytesIO(head + src.read(size)))
    except ReaderError as exc:
        raise UnsoundRecord(str(exc)) from None


def _data(src: BinaryIO, limit: int) -> bytes:
    head = src.read(4)
    if len(head) < 4:
        raise UnsoundRecord("the file ends inside a record")
    size = _U32.unpack(head)[0]
    if size > limit:
        raise UnsoundRecord(f"a record of {size:,} bytes where {limit:,} remain")
    data = src.read(size)
    if len(data) != size:
        raise UnsoundRecord("the file ends inside a record")
    return data


def _op(header: Header) -> int:
    try:
        return header.get_uint8("op")
    except ReaderError as exc:
        raise UnsoundRecord(str(exc)) from None


def _inner(header: Header, data: bytes) -> BagConnection | BagMessage | None:
    """The connection or message a record holds; None for records a reader does not need."""
    op = _op(header)
    try:
        if op == RecordType.MSGDATA:
            return BagMessage(header.get_uint32("conn"), header.get_time("time"), data)
        if op == RecordType.CONNECTION:
            described = Header.read(BytesIO(_U32.pack(len(data)) + data))
            return BagConnection(header.get_uint32("conn"), header.get_string("topic"),
                                 described.get_string("type"),
                                 described.get_string("message_definition"))
    except ReaderError as exc:
        raise UnsoundRecord(str(exc)) from None
    if op not in RecordType.__members__.values():
        raise UnsoundRecord(f"a record of unknown type {op}")
    return None


def _decompress(compression: str, data: bytes) -> bytes:
    """All that streams out of `data` (a cut chunk gives what was written before the cut)."""
    if compression == "none":
        return data
    if compression == "bz2":
        return bz2.BZ2Decompressor().decompress(data)
    if compression == "lz4":
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    raise UnsoundRecord(f"chunk compression {compression!r}")


def chunk_records(header: Header, stored: bytes, whole: bool) -> list:
    """The records of a chunk. `whole`: the chunk must decompress to its stated size and parse
    to its end; otherwise (a cut chunk) the whole records before the cut are kept."""
    try:
        compression, size = header.get_string("compression"), header.get_uint32("size")
        raw = _decompress(compression, stored)
    except (ReaderError, OSError, RuntimeError, EOFError, ValueError) as exc:
        if whole:
            raise UnsoundRecord(f"a chunk that does not decompress ({exc})") from None
        return []
    if whole and len(raw) != size:
        raise UnsoundRecord(f"a chunk of {len(raw):,} bytes that states {size:,}")
    src, records = BytesIO(raw), []
    while src.tell() < len(raw):
        try:
            inner_header = _header(src)
            record = _inner(inner_header, _data(src, len(raw) - src.tell()))
        except UnsoundRecord:
            if whole:
                raise
            break
        if record is not None:
            records.append(record)
    return records


def _record_at(f: BinaryIO, pos: int, size: int, whole: bool) -> tuple[list, int]:
    """The connections and messages of the record at `pos`, and where the next one starts.
    A chunk running past the end is a cut (its whole records kept) unless `whole` is asked or
    a sound chunk follows it (then its stated size is damage, not a cut)."""
    f.seek(pos)
    header = _header(f)
    if _op(header) != RecordType.CHUNK:
        data = _data(f, size - f.tell() - 4)
        record = _inner(header, data)
        return ([record] if record is not None else []), f.tell()
    head = f.read(4)
    if len(head) < 4:
        raise UnsoundRecord("the file ends inside a chunk")
    stated = _U32.unpack(head)[0]
    data_at = f.tell()
    stored = f.read(stated)
    cut = len(stored) < stated
    if cut and (whole or next_chunk(f, pos + 1, size) is not None):
        raise UnsoundRecord("a chunk running past the end of the file")
    return chunk_records(header, stored, whole=not cut), data_at + stated


def _chunk_starts(window: bytes, match: int) -> Iterator[int]:
    """Where a record whose header holds the chunk op field at `match` could start."""
    for start in range(max(match - _MAX_CHUNK_HEADER, 0), match - 3):
        end = start + 4 + _U32.unpack_from(window, start)[0]
        if match + len(_CHUNK_OP_FIELD) <= end <= start + 4 + _MAX_CHUNK_HEADER:
            yield start


def next_chunk(f: BinaryIO, start: int, size: int) -> int | None:
    """The byte of the next record after `start` that is a whole, sound chunk."""
    at = start
    while at < size:
        base = max(at - _MAX_CHUNK_HEADER, start)
        f.seek(base)
        window = f.read(_SCAN_WINDOW + _MAX_CHUNK_HEADER)
        match = window.find(_CHUNK_OP_FIELD, at - base)
        while match >= 0:
            for begin in _chunk_starts(window, match):
                try:
                    _record_at(f, base + begin, size, whole=True)
                    return base + begin
                except UnsoundRecord:
                    pass
            match = window.find(_CHUNK_OP_FIELD, match + 1)
        at = base + _SCAN_WINDOW
    return None


class IntactBagRecords:
    """Iterates the connections and messages of a ROS 1 bag in file order, past damaged
    stretches (each reported to `on_stretch(start_byte, end_byte)`), up to the end or a cut:
    then `cut_at` is the cut record's first byte and `detail` what was met there."""

    def __init__(self, path: Path, on_stretch: Callable[[int, int], None]):
        self.path = path
        self.on_stretch = on_stretch
        self.cut_at: int | None = None
        self.detail = ""

    def __iter__(self) -> Iterator[BagConnection | BagMessage]:
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                raise UnsoundRecord("no '#ROSBAG V2.0' magic line")
            pos = len(MAGIC)
            while pos < size:
                try:
                    records, following = _record_at(f, pos, size, whole=False)
                except UnsoundRecord as exc:
                    resume = next_chunk(f, pos + 1, size)
                    if resume is None:
                        self.cut_at, self.detail = pos, str(exc)
                        return
                    self.on_stretch(pos, resume)
                    pos = resume
                    continue
                yield from records
                if following > size:
                    self.cut_at, self.detail = pos, "the file ends inside a chunk"
                    return
                pos = following
