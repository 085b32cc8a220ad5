"""The intact records of a damaged MCAP chunk: a recorder killed mid-chunk leaves the chunk's
header and the start of its compressed records, which a streaming decompressor turns into the
records written before the cut (as `mcap recover` does). A chunk holds a few MB, so without
this a cut could lose several seconds of scans.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Message, Schema

_CHUNK_FIXED = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_RECORDS = {Opcode.CHANNEL: Channel, Opcode.SCHEMA: Schema}


def _decompressed_prefix(compression: str, data: bytes) -> bytes:
    """As much of the chunk's records as the (possibly cut) compressed bytes hold."""
    if compression == "":
        return data
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    if compression == "lz4":
        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    return b""


def partial_chunk_records(path: Path, offset: int) -> Iterator[object]:
    """The whole records (schemas, channels, messages) of the chunk starting at `offset`, up to
    its damage; nothing when no chunk starts there or it cannot be read at all."""
    with open(path, "rb") as f:
        f.seek(offset)
        head = f.read(9 + _CHUNK_FIXED.size)
        if len(head) < 9 + _CHUNK_FIXED.size or head[0] != Opcode.CHUNK:
            return
        *_, uncompressed_size, _crc, name_len = _CHUNK_FIXED.unpack_from(head, 9)
        compression = f.read(name_len).decode("utf-8", errors="replace")
        f.read(8)  # the records' length, as written before the cut
        compressed = f.read(int(uncompressed_size) + 1024)  # never more than the chunk
    try:
        data = _decompressed_prefix(compression, compressed)
    except Exception:
        return
    pos = 0
    while pos + 9 <= len(data):
        opcode, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        body = data[pos + 9:pos + 9 + length]
        if len(body) < length:
            return
        pos += 9 + length
        stream = ReadDataStream(BytesIO(body))
        try:
            if opcode == Opcode.MESSAGE:
                yield Message.read(stream, length)
            elif opcode in _RECORDS:
                yield _RECORDS[opcode].read(stream)
        except Exception:
            return
