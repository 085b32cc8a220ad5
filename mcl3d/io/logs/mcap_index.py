"""Messages of a complete MCAP through its summary's chunk indexes, in log-time order (as
mcap's SeekingReader reads them), each chunk checked whole (sizes, CRC) before its records are
used: a damaged chunk is skipped and reported with the messages its message indexes say it
held, so one bad chunk in the middle of a recording costs that chunk, not the run.
"""

from __future__ import annotations

import heapq
import itertools
import os
import struct
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.records import Message
from mcap.summary import Summary

from mcl3d.io.logs.mcap_recovery import (
    Stretch,
    UnsoundRecord,
    chunk_at,
    message_index_counts,
)

_CHUNK_HEAD = struct.Struct("<BQQQQ")  # opcode, length, message start, end, uncompressed size


def chunk_heads_agree(f: BinaryIO, summary: Summary, size: int) -> bool:
    """Whether every chunk index points at a chunk record whose head says what the index says
    (one small read per chunk); false when the summary points into damage."""
    for ci in summary.chunk_indexes:
        if ci.chunk_start_offset + ci.chunk_length > size:
            return False
        f.seek(ci.chunk_start_offset)
        head = f.read(_CHUNK_HEAD.size)
        if len(head) < _CHUNK_HEAD.size:
            return False
        opcode, length, start, end, uncompressed = _CHUNK_HEAD.unpack(head)
        if (opcode != Opcode.CHUNK or length + 9 != ci.chunk_length
                or (start, end) != (ci.message_start_time, ci.message_end_time)
                or uncompressed != ci.uncompressed_size):
            return False
    return True


def _lost_chunk(f: BinaryIO, ci) -> Stretch:
    """A chunk that failed its checks: its bytes and message indexes, and the messages those
    say it held (None when they are damaged too)."""
    end = ci.chunk_start_offset + ci.chunk_length
    lost = (message_index_counts(f, end, end + ci.message_index_length)
            if ci.message_index_length else None)
    return Stretch(ci.chunk_start_offset, end + ci.message_index_length, lost)


def indexed_messages(f: BinaryIO, summary: Summary, size: int, channel_ids: set[int],
                     reverse: bool, on_stretch: Callable[[Stretch], None]
                     ) -> Iterator[Message]:
    """Messages on `channel_ids` in log-time order (reversed with `reverse`; ties in file
    order), chunk by chunk as their time ranges come up; a damaged chunk goes to
    `on_stretch`; UnsoundRecord when every chunk read is damaged. Each chunk is read in one
    seek and read, so passes may share `f`."""
    sign = -1 if reverse else 1
    heap: list[tuple] = []
    for n, ci in enumerate(summary.chunk_indexes):
        if ci.message_index_offsets and not channel_ids & ci.message_index_offsets.keys():
            continue
        first = -ci.message_end_time if reverse else ci.message_start_time
        heap.append((first, 0, n, ci))  # 0: a chunk opens before messages of its time
    ahead = ChunksAhead(f.fileno(), size, [item[3] for item in sorted(heap)])
    heapq.heapify(heap)
    order = itertools.count()
    sound = damaged = 0
    try:
        while heap:
            _time, is_message, _n, item = heapq.heappop(heap)
            if is_message:
                yield item
                continue
            try:
                records = ahead.next_chunk()
            except UnsoundRecord:
                on_stretch(_lost_chunk(f, item))
                damaged += 1
                continue
            sound += 1
            for record in records:
                if isinstance(record, Message) and record.channel_id in channel_ids:
                    heapq.heappush(heap, (sign * record.log_time, 1, sign * next(order),
                                          record))
    finally:
        ahead.close()
    if damaged and not sound:
        raise UnsoundRecord(f"all {damaged} chunks holding these topics are damaged")


class ChunksAhead:
    """The records of chunks in the order they will be opened, the next one read, checked and
    decompressed on a thread while the caller decodes this one's messages (decompression and
    CRC release the GIL: in build-map's first pass they were half of the time a scan)."""

    def __init__(self, fd: int, size: int, chunks: list):
        self._read = lambda at, n: os.pread(fd, n, at)
        self._size = size
        self._chunks = iter(chunks)
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mcap-chunks")
        self._next = self._submit()

    def _submit(self) -> Future | None:
        ci = next(self._chunks, None)
        if ci is None:
            return None
        return self._pool.submit(chunk_at, self._read, ci.chunk_start_offset, self._size)

    def next_chunk(self) -> list:
        """The next chunk's records, or UnsoundRecord; starts reading the one after."""
        current, self._next = self._next, self._submit()
        return current.result()[0]

    def close(self) -> None:
        """Stop reading ahead; waits for a read in flight (the caller may close the file)."""
        self._pool.shutdown(wait=True, cancel_futures=True)


def lost_between(f: BinaryIO, summary: Summary, start: int, stop: int) -> dict[int, int] | None:
    """Messages per channel id of the chunks the summary places in bytes [start, stop), from
    their message indexes; None when the summary places none there or an index is damaged."""
    lost: dict[int, int] = {}
    inside = [ci for ci in summary.chunk_indexes if start <= ci.chunk_start_offset < stop]
    for ci in inside:
        counts = _lost_chunk(f, ci).lost_by_channel
        if counts is None:
            return None
        for cid, n in counts.items():
            lost[cid] = lost.get(cid, 0) + n
    return lost if inside else None
