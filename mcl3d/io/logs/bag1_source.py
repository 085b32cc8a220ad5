"""A ROS 1 bag that rosbags cannot open (no index: the recorder was killed; or damaged), read
through its intact records (`bag1_recovery.py`) as a log source.

Opening walks the bag once to learn its connections, counts and time span; messages are then
streamed in file order (the order the recorder wrote them), decoded with the message
definitions the bag stores. `damage` says where a cut ends the readable part, `skipped` the
damaged stretches passed over, as for a damaged MCAP.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs import livox
from mcl3d.io.logs.bag1_recovery import BagConnection, BagMessage, IntactBagRecords, UnsoundRecord
from mcl3d.io.logs.faults import DamagedStretch, LogDamage
from mcl3d.io.logs.ros_types import normalize_type
from mcl3d.io.logs.sources import StreamDamage, TopicInfo, damage_notes


class RecoveredBagSource:
    """The readable part of a damaged ROS 1 bag (see the module docstring)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.profile = "ros1"
        self.library = "-"
        self._size = self.path.stat().st_size
        self.damage: StreamDamage | None = None
        self.skipped = LogDamage(self._size)
        self._connections: dict[int, BagConnection] = {}
        self._decoders: dict[int, Callable] = {}
        self.start_ns = self.end_ns = None
        self.last_log_ns: dict[str, int] = {}  # per topic, for `info`'s rates
        counts = self._index()
        self.topics: dict[str, TopicInfo] = {}
        for cid, conn in sorted(self._connections.items()):
            info = self.topics.setdefault(conn.topic, TopicInfo(
                conn.topic, normalize_type(conn.msgtype), 0, bool(conn.msgdef.strip())))
            info.count += counts.get(cid, 0)
            info.handles.append(cid)
        notes = ["no index: read record by record", *damage_notes(self.damage, self.skipped)]
        self.format = f"ROS 1 bag ({'; '.join(notes)})"

    def _walk(self) -> IntactBagRecords:
        """One pass over the records; damaged stretches are gathered in `skipped`."""
        return IntactBagRecords(self.path, lambda start, end: self.skipped.add(
            DamagedStretch(start, end, None)))

    def _index(self) -> dict[int, int]:
        counts: dict[int, int] = {}
        by_topic: dict[str, int] = {}
        walk = self._walk()
        try:
            for record in walk:
                if isinstance(record, BagConnection):
                    self._connections.setdefault(record.conn_id, record)
                    continue
                counts[record.conn_id] = counts.get(record.conn_id, 0) + 1
                conn = self._connections.get(record.conn_id)
                topic = conn.topic if conn else "?"
                by_topic[topic] = by_topic.get(topic, 0) + 1
                self.last_log_ns[topic] = max(self.last_log_ns.get(topic, 0), record.stamp_ns)
                first = record.stamp_ns if self.start_ns is None else self.start_ns
                self.start_ns = min(first, record.stamp_ns)
                self.end_ns = max(self.end_ns or 0, record.stamp_ns)
        except UnsoundRecord as exc:
            raise LogFormatError(f"{self.path}: cannot read the bag ({exc})") from None
        if not counts:
            raise LogFormatError(f"{self.path}: no message before the damage")
        if walk.cut_at is not None:
            self.damage = StreamDamage(walk.cut_at, self._size, by_topic, walk.detail)
        return counts

    def _decoder(self, conn_id: int) -> Callable:
        decode = self._decoders.get(conn_id)
        if decode is None:
            conn = self._connections[conn_id]
            name = normalize_type(conn.msgtype)
            store = get_typestore(Stores.EMPTY)
            try:
                store.register(get_types_from_msg(conn.msgdef, name))
            except Exception as exc:
                raise LogFormatError(f"{self.path}: the message definition of {conn.msgtype} "
                                     f"on {conn.topic} cannot be parsed ({exc})") from None
            fast = livox.fast_decoder(store.fielddefs, name, cdr=False)
            decode = fast or (lambda data: store.deserialize_ros1(data, name))
            self._decoders[conn_id] = decode
        return decode

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        """(topic, stamp_ns, decoded message) on `topics`, in file order, up to the damage."""
        if reverse:
            raise NotImplementedError("a bag without its index streams forward only")
        wanted = {cid for t in topics for cid in self.topics[t].handles}
        for record in self._walk():
            if not isinstance(record, BagMessage) or record.conn_id not in wanted:
                continue
            conn = self._connections[record.conn_id]
            try:
                msg = self._decoder(record.conn_id)(record.data)
            except LogFormatError:
                raise
            except Exception as exc:
                raise LogFormatError(f"{self.path}: a message on {conn.topic} at "
                                     f"{record.stamp_ns} ns cannot be decoded ({exc}); the bag "
                                     "is corrupt") from None
            yield conn.topic, record.stamp_ns, msg

    def close(self) -> None:
        """Nothing is held open between passes."""
