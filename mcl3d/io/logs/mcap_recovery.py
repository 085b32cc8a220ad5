"""The intact records of a damaged MCAP, read as `mcap recover` reads them.

Two kinds of damage. A cut (a recorder killed mid-chunk, an incomplete copy) leaves the cut
chunk's header and the start of its compressed records, which a streaming decompressor turns
into the records written before the cut; a chunk holds a few MB, so without this a cut could
lose several seconds of scans. A damaged stretch in the middle (garbage written over bytes, a
chunk whose CRC fails, a zeroed stretch) is skipped: reading resynchronises at the next record
that is a whole, sound chunk (it decompresses to its stated size and its CRC checks), and the
messages the stretch held are counted from the message indexes written after the lost chunk,
where they survive. A chunk is used whole or not at all: records decoded from a damaged one
could be garbage that happens to parse.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Header, Message, Schema

MAGIC_BYTES = 8
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_FIXED = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_INDEX_HEAD = struct.Struct("<HI")  # message index: channel id, bytes of (log time, offset) pairs
_COMPRESSIONS = {b"": "", b"zstd": "zstd", b"lz4": "lz4"}
_MAX_CHUNK_BYTES = 1 << 32  # larger stated sizes are garbage, not a chunk
_SCAN_WINDOW = 1 << 20  # bytes searched at a time when resynchronising
_HEAD_BYTES = _RECORD_HEAD.size + _CHUNK_FIXED.size + 4 + 8  # a chunk record up to its records
_INNER = {Opcode.CHANNEL: Channel, Opcode.SCHEMA: Schema}
_DATA = {Opcode.HEADER: Header, **_INNER}
_SKIPPED = {Opcode.MESSAGE_INDEX, Opcode.ATTACHMENT, Opcode.METADATA, Opcode.CHUNK_INDEX,
            Opcode.ATTACHMENT_INDEX, Opcode.METADATA_INDEX, Opcode.STATISTICS,
            Opcode.SUMMARY_OFFSET}
_END = {Opcode.DATA_END, Opcode.FOOTER}


class UnsoundRecord(ValueError):
    """A record that does not parse as what its head says (damage, or not a record at all)."""


@dataclass(frozen=True)
class Stretch:
    """Damaged bytes skipped, and the messages they held per channel id (None: unknown)."""

    start_byte: int
    end_byte: int
    lost_by_channel: dict[int, int] | None


def _decompressed(compression: str, data: bytes) -> bytes:
    """Streaming decompression: a garbage stated size never sizes a buffer."""
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    if compression == "lz4":
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    return data


def _inner_records(data: bytes) -> list:
    """The schemas, channels and messages of a chunk's decompressed records."""
    records, pos = [], 0
    while pos < len(data):
        if pos + _RECORD_HEAD.size > len(data):
            raise UnsoundRecord("a record head runs past the end of its chunk")
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        end = pos + _RECORD_HEAD.size + length
        if end > len(data):
            raise UnsoundRecord("a record runs past the end of its chunk")
        stream = ReadDataStream(BytesIO(data[pos + _RECORD_HEAD.size:end]))
        if opcode == Opcode.MESSAGE:
            records.append(Message.read(stream, length))
        elif opcode in _INNER:
            records.append(_INNER[opcode].read(stream))
        pos = end
    return records


def chunk_records(body: bytes) -> list:
    """The records of a chunk record's body; UnsoundRecord unless the chunk is whole and sound
    (known compression, its stated sizes, its CRC where it has one)."""
    try:
        start, end, size, crc, name_len = _CHUNK_FIXED.unpack_from(body)
        name_end = _CHUNK_FIXED.size + name_len
        compression = _COMPRESSIONS.get(bytes(body[_CHUNK_FIXED.size:name_end]))
        (records_len,) = struct.unpack_from("<Q", body, name_end)
    except struct.error:
        raise UnsoundRecord("a chunk shorter than its head") from None
    if compression is None or start > end or size > _MAX_CHUNK_BYTES:
        raise UnsoundRecord("a chunk head with impossible fields")
    if name_end + 8 + records_len > len(body):
        raise UnsoundRecord("a chunk whose records run past its end")
    try:
        data = _decompressed(compression, body[name_end + 8:name_end + 8 + records_len])
    except Exception as exc:  # zstandard and lz4 raise their own types on garbage
        raise UnsoundRecord(f"a chunk that does not decompress ({exc})") from None
    if len(data) != size or (crc and zlib.crc32(data) != crc):
        raise UnsoundRecord("a chunk whose records fail their size or CRC check")
    try:
        return _inner_records(data)
    except UnsoundRecord:
        raise
    except Exception as exc:  # mcap's record parsers on bytes that are not what they say
        raise UnsoundRecord(f"a chunk record that does not parse ({exc})") from None


def read_chunk(f: BinaryIO, offset: int, size: int) -> tuple[list, int]:
    """(records, end byte) of the chunk record at `offset` of a `size`-byte file, or
    UnsoundRecord."""

    def read(at: int, n: int) -> bytes:
        f.seek(at)
        return f.read(n)

    return chunk_at(read, offset, size)


def chunk_at(read: Callable[[int, int], bytes], offset: int, size: int) -> tuple[list, int]:
    """read_chunk through `read(offset, n)` (os.pread: no shared file position, so another
    thread may read ahead)."""
    head = read(offset, _RECORD_HEAD.size)
    if len(head) < _RECORD_HEAD.size:
        raise UnsoundRecord("the file ends inside a record head")
    opcode, length = _RECORD_HEAD.unpack(head)
    end = offset + _RECORD_HEAD.size + length
    if opcode != Opcode.CHUNK or end > size:
        raise UnsoundRecord("not a whole chunk record")
    return chunk_records(read(offset + _RECORD_HEAD.size, length)), end


def _plausible_chunk_head(buf: bytes, i: int, offset: int, size: int) -> bool:
    """Whether the bytes at buf[i] (file byte `offset`) start a chunk record whose fields agree
    with each other: cheap, so garbage is ruled out before any decompression."""
    if i + _HEAD_BYTES > len(buf) and offset + _HEAD_BYTES <= size:
        return False
    try:
        _, length = _RECORD_HEAD.unpack_from(buf, i)
        start, end, usize, _crc, name_len = _CHUNK_FIXED.unpack_from(buf, i + _RECORD_HEAD.size)
        name_at = i + _RECORD_HEAD.size + _CHUNK_FIXED.size
        if name_len > 4 or buf[name_at:name_at + name_len] not in _COMPRESSIONS:
            return False
        (records_len,) = struct.unpack_from("<Q", buf, name_at + name_len)
    except struct.error:
        return False
    return (start <= end and usize <= _MAX_CHUNK_BYTES
            and length == _CHUNK_FIXED.size + name_len + 8 + records_len
            and offset + _RECORD_HEAD.size + length <= size)


def next_chunk(f: BinaryIO, start: int, size: int) -> int | None:
    """The first byte at or after `start` where a whole, sound chunk record begins."""
    pos = start
    while pos < size:
        f.seek(pos)
        buf = f.read(_SCAN_WINDOW + _HEAD_BYTES)
        limit = min(_SCAN_WINDOW, len(buf))
        i = buf.find(bytes([Opcode.CHUNK]), 0, limit)
        while i >= 0:
            if _plausible_chunk_head(buf, i, pos + i, size):
                try:
                    read_chunk(f, pos + i, size)
                    return pos + i
                except UnsoundRecord:
                    pass
            i = buf.find(bytes([Opcode.CHUNK]), i + 1, limit)
        pos += _SCAN_WINDOW
    return None


def message_index_counts(f: BinaryIO, start: int, stop: int) -> dict[int, int] | None:
    """Messages per channel id in the message index records filling bytes [start, stop), as a
    chunk is followed by them; None unless they fill exactly that span and all parse."""
    if not 0 <= start < stop or stop - start > 64 * _SCAN_WINDOW:
        return None
    f.seek(start)
    data = f.read(stop - start)
    counts, pos = {}, 0
    while pos < len(data):
        if pos + _RECORD_HEAD.size + _INDEX_HEAD.size > len(data):
            return None
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        channel_id, pairs_len = _INDEX_HEAD.unpack_from(data, pos + _RECORD_HEAD.size)
        if opcode != Opcode.MESSAGE_INDEX or length != _INDEX_HEAD.size + pairs_len \
                or pairs_len % 16:
            return None
        counts[channel_id] = counts.get(channel_id, 0) + pairs_len // 16
        pos += _RECORD_HEAD.size + length
    return counts if pos == len(data) else None


def _partial_chunk_records(f: BinaryIO, offset: int, size: int) -> Iterator[object]:
    """The whole records of a chunk cut by the end of the file, up to the cut (none when the
    chunk at `offset` is not cut but damaged: its records could be garbage)."""
    f.seek(offset)
    head = f.read(_RECORD_HEAD.size + _CHUNK_FIXED.size)
    if len(head) < _RECORD_HEAD.size + _CHUNK_FIXED.size or head[0] != Opcode.CHUNK:
        return
    if offset + _RECORD_HEAD.size + _RECORD_HEAD.unpack_from(head)[1] <= size:
        return
    *_, uncompressed_size, _crc, name_len = _CHUNK_FIXED.unpack_from(head, _RECORD_HEAD.size)
    compression = _COMPRESSIONS.get(f.read(name_len))
    f.read(8)  # the records' length, as written before the cut
    compressed = f.read(min(int(uncompressed_size), _MAX_CHUNK_BYTES) + 1024)
    if compression is None:
        return
    try:
        data = _decompressed(compression, compressed)
    except Exception:  # nothing decompresses: nothing of the chunk survives
        return
    pos = 0
    while pos + _RECORD_HEAD.size <= len(data):
        _opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        end = pos + _RECORD_HEAD.size + length
        if end > len(data):
            return
        try:
            yield from _inner_records(data[pos:end])
        except Exception:  # the cut runs through this record
            return
        pos = end


class IntactRecords:
    """The data section's records in file order (header, schemas, channels, messages, those
    inside chunks included), read past damaged stretches (each reported to `on_stretch`) up to
    the data's end, or to an unreadable tail: `cut_at` is then where it starts, `detail` what
    was met there. Each iteration has its own file handle: passes may nest."""

    def __init__(self, path: Path, on_stretch: Callable[[Stretch], None]) -> None:
        self.path = path
        self._on_stretch = on_stretch
        self.cut_at: int | None = None
        self.detail = ""

    def __iter__(self) -> Iterator[object]:
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            pos = trusted = MAGIC_BYTES
            while pos < size:
                try:
                    records, end, sound = self._record_at(f, pos, size)
                except UnsoundRecord as exc:
                    pos = yield from self._past_damage(f, pos, trusted, size, str(exc))
                    if pos is None:
                        return
                    trusted = pos
                    continue
                if records is None:
                    return
                yield from records
                pos = end
                if sound:
                    trusted = end
            self.cut_at, self.detail = size, "the file ends before the data section does"

    @staticmethod
    def _record_at(f: BinaryIO, pos: int, size: int) -> tuple[list | None, int, bool]:
        """(records, end byte, checked) of the record at `pos`: records is None at the data's
        end; checked says the record was checked whole (a chunk, by its sizes and CRC)."""
        f.seek(pos)
        head = f.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            raise UnsoundRecord(f"the file ends inside a record head at byte {pos:,}")
        opcode, length = _RECORD_HEAD.unpack(head)
        end = pos + _RECORD_HEAD.size + length
        if end > size:
            raise UnsoundRecord(f"a record at byte {pos:,} runs past the end of the file")
        if opcode == Opcode.CHUNK:
            return read_chunk(f, pos, size)[0], end, True
        if opcode in _END:
            return None, end, False
        if opcode in _SKIPPED:
            return [], end, False
        if opcode != Opcode.MESSAGE and opcode not in _DATA:
            raise UnsoundRecord(f"a corrupt record (opcode {opcode:#04x}) at byte {pos:,}")
        stream = ReadDataStream(BytesIO(f.read(length)))
        try:
            record = (Message.read(stream, length) if opcode == Opcode.MESSAGE
                      else _DATA[opcode].read(stream))
        except Exception as exc:  # mcap's parsers on bytes that are not what they say
            raise UnsoundRecord(f"a corrupt record at byte {pos:,} ({exc})") from None
        return [record], end, opcode == Opcode.HEADER

    def _past_damage(self, f: BinaryIO, pos: int, trusted: int, size: int, detail: str):
        """Resynchronise after damage met at `pos` (the last sound record ended at `trusted`):
        the byte to read on from, or None when no sound chunk follows (then the records of a
        chunk cut by the end of the file)."""
        resume = next_chunk(f, trusted, size)
        if resume is not None:
            start = pos if pos < resume else trusted
            self._on_stretch(Stretch(start, resume, self._lost(f, start, resume, size)))
            return resume
        self.cut_at, self.detail = pos, detail
        yield from _partial_chunk_records(f, pos, size)
        return None

    @staticmethod
    def _lost(f: BinaryIO, start: int, stop: int, size: int) -> dict[int, int] | None:
        """Messages per channel in a skipped stretch that is one chunk with its message
        indexes (their counts), None when that cannot be told."""
        f.seek(start)
        head = f.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            return None
        opcode, length = _RECORD_HEAD.unpack(head)
        chunk_end = start + _RECORD_HEAD.size + length
        if opcode != Opcode.CHUNK or chunk_end >= stop:
            return None
        return message_index_counts(f, chunk_end, stop)
