"""Raw log access: topics, counts and decoded ROS message objects, streamed in log-time order.

Two sources cover every supported format: `McapSource` (MCAP files, ROS 2 CDR or ROS 1
encoding, types registered from the schemas stored in the file) and `RosbagsSource`
(ROS 1 .bag files and ROS 2 bag folders, sqlite3 or MCAP, through rosbags' AnyReader).
Both (and `kitti_folder.KittiFolderSource`, `ouster_source.OusterPcapSource`) yield `rosbags`
message objects, so conversion to mcl3d dataclasses is shared; Livox CustomMsg scans of the
standard definition are decoded straight from their bytes instead (`livox.LivoxScan`).
Any failure of the underlying libraries becomes a `LogFormatError` naming the file, except
an MCAP damaged after its first message: like `mcap recover`, a cut one (a recorder killed
mid-chunk, an incomplete copy) is read up to the cut, and `damage` says how much was read;
damaged stretches in the middle (garbage, a bad CRC, zeros) are skipped, reading on at the
next intact chunk, and gathered in `skipped` (see `mcap_recovery.py`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.reader import make_reader
from mcap.records import Channel, Header, Message, Schema, Statistics
from mcap.summary import Summary
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from mcl3d.core.errors import LogFormatError, Mcl3dError
from mcl3d.io.logs import livox
from mcl3d.io.logs.faults import DamagedStretch, LogDamage
from mcl3d.io.logs.mcap_index import chunk_heads_agree, indexed_messages, lost_between
from mcl3d.io.logs.mcap_recovery import IntactRecords, Stretch
from mcl3d.io.logs.ros_types import normalize_type, ros2_typestore

MCAP_MAGIC = b"\x89MCAP0\r\n"
SUPPORTED = ("MCAP files (.mcap), ROS 1 .bag files, ROS 2 bag folders, KITTI odometry "
             "folders and Ouster .pcap files (with their metadata JSON)")
PCAP_MAGICS = (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\xa1\xb2\x3c\x4d")


@dataclass
class TopicInfo:
    topic: str
    msgtype: str  # normalized ROS 2 form, e.g. sensor_msgs/msg/PointCloud2
    count: int | None  # None when the log has no summary to tell
    decodable: bool = True  # a message definition is available
    handles: list = field(default_factory=list, repr=False)  # source-specific channel handles


@dataclass(frozen=True)
class StreamDamage:
    """Where a damaged MCAP stops being readable: the start of its first damaged record (whose
    whole records were still read), and the messages read per topic."""

    damaged_at_byte: int
    total_bytes: int
    messages_read: dict[str, int]
    detail: str  # what the reader met at the damage


def damage_notes(damage: StreamDamage | None, skipped: LogDamage) -> list[str]:
    """What a damaged log's format line says: where it is cut, how many stretches skipped."""
    notes = []
    if damage is not None:
        notes.append(f"truncated or damaged at byte {damage.damaged_at_byte:,}: read up to it")
    if skipped.stretches:
        n = len(skipped.stretches)
        notes.append(f"{n} damaged stretch{'es' * (n != 1)} skipped")
    return notes


def _corrupt(path: Path, exc: BaseException) -> LogFormatError:
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return LogFormatError(f"{path}: cannot read the log; it looks truncated or corrupt "
                          f"({detail[:160]}). Re-copy or re-record it.")


def open_source(path: Path):
    """The source for `path`, by what it is: bag folder, .bag file, or MCAP (checked by magic)."""
    path = Path(path)
    if not path.exists():
        raise LogFormatError(f"{path}: no such file or folder")
    if path.is_dir():
        if not (path / "metadata.yaml").exists():
            from mcl3d.io.logs import kitti_folder  # it builds on this module's TopicInfo

            if kitti_folder.is_kitti_folder(path):
                return kitti_folder.KittiFolderSource(path)
            raise LogFormatError(f"{path}: neither a ROS 2 bag folder (no metadata.yaml) nor a "
                                 f"KITTI sequence (no velodyne/ with times.txt); mcl3d reads "
                                 f"{SUPPORTED}")
        return RosbagsSource(path, "ROS 2 bag folder")
    if path.suffix == ".db3":
        return open_source(path.parent)
    with open(path, "rb") as f:
        magic = f.read(len(MCAP_MAGIC))
    if path.suffix.lower() == ".pcap" or magic[:4] in PCAP_MAGICS:
        from mcl3d.io.logs.ouster_source import OusterPcapSource  # it builds on this module

        return OusterPcapSource(path)
    if path.suffix == ".bag" or magic.startswith(b"#ROSBAG"):
        if not magic.startswith(b"#ROSBAG"):
            raise LogFormatError(f"{path}: not a ROS 1 bag (no #ROSBAG header); mcl3d reads "
                                 f"{SUPPORTED}")
        try:
            return RosbagsSource(path, "ROS 1 bag")
        except LogFormatError as unreadable:
            return _recovered_bag(path, unreadable)
    if magic != MCAP_MAGIC:
        raise LogFormatError(f"{path}: not an MCAP file (the file does not start with the MCAP "
                             f"magic bytes); mcl3d reads {SUPPORTED}")
    with open(path, "rb") as f:
        f.seek(max(path.stat().st_size - len(MCAP_MAGIC), 0))
        complete = f.read() == MCAP_MAGIC
    return McapSource(path, complete)


def _recovered_bag(path: Path, unreadable: LogFormatError):
    """A ROS 1 bag rosbags cannot open (no index, damage), read record by record; when not even
    that finds a message, rosbags' own reason stands."""
    from mcl3d.io.logs.bag1_source import RecoveredBagSource  # it builds on this module

    try:
        return RecoveredBagSource(path)
    except LogFormatError:
        raise unreadable from None


class McapSource:
    """An MCAP file, read through its summary and chunk indexes (chunk by chunk, each checked);
    one that does not end with the MCAP magic bytes (truncated), or whose summary is damaged or
    points into damage, is streamed, past damaged stretches, up to its end or its cut."""

    def __init__(self, path: Path, complete: bool = True):
        self.path = path
        self._file = open(path, "rb")  # noqa: SIM115 (closed by close())
        self._size = path.stat().st_size
        self.damage: StreamDamage | None = None
        self.skipped = LogDamage(self._size)  # damaged stretches met so far, over every pass
        self._reader = None
        self._distrusted: Summary | None = None  # a summary pointing into damage
        summary = None
        try:
            if complete:
                header, summary = self._indexed_summary()
            if summary is None or not summary.channels or summary.statistics is None:
                header, summary = self._scan_summary()
        except Mcl3dError:
            self.close()
            raise
        except Exception as exc:
            self.close()
            raise _corrupt(path, exc) from None
        self.profile = header.profile or "-"
        self.library = header.library or "-"
        self._decoders: dict[int, Callable] = {}
        self._indexed = self._reader is not None and bool(summary.chunk_indexes)
        self._summary = summary
        self._schemas = summary.schemas
        self._channels = summary.channels
        stats = summary.statistics
        counts = stats.channel_message_counts if stats else {}
        self.start_ns = stats.message_start_time if stats else None
        self.end_ns = stats.message_end_time if stats else None
        self.topics: dict[str, TopicInfo] = {}
        for cid, ch in sorted(self._channels.items()):
            schema = self._schemas.get(ch.schema_id)
            msgtype = normalize_type(schema.name) if schema else "(no schema)"
            info = self.topics.get(ch.topic)
            if info is None:
                info = self.topics[ch.topic] = TopicInfo(ch.topic, msgtype, 0 if stats else None,
                                                         schema is not None)
            elif info.msgtype != msgtype:
                info.msgtype = f"{info.msgtype} | {msgtype}"
            info.handles.append(cid)
            if stats:
                info.count += counts.get(cid, 0)

    @property
    def format(self) -> str:
        """The format, with the damage met so far."""
        return f"MCAP ({'; '.join([self.profile, *damage_notes(self.damage, self.skipped)])})"

    def _indexed_summary(self) -> tuple[Header | None, Summary | None]:
        """Header and summary of a complete file, read through its footer; no summary when it
        is damaged or its chunk indexes point into damage (the file is then streamed)."""
        try:
            self._reader = make_reader(self._file)
            header = self._reader.get_header()
            summary = self._reader.get_summary()
        except Exception:  # a damaged header, footer or summary: the data section may be whole
            self._reader = None
            return None, None
        if summary is not None and not chunk_heads_agree(self._file, summary, self._size):
            self._reader, self._distrusted = None, summary  # it still counts what is lost
            return None, None
        return header, summary

    def _note_stretch(self, stretch: Stretch, channels: dict[int, str]) -> None:
        """A damaged stretch, its messages lost counted by topic (the channels seen so far)."""
        summaries = [getattr(self, "_channels", {}),
                     self._distrusted.channels if self._distrusted else {}]
        known = {cid: ch.topic for chans in summaries for cid, ch in chans.items()}
        by_channel = stretch.lost_by_channel
        if by_channel is None and self._distrusted is not None:
            by_channel = lost_between(self._file, self._distrusted, stretch.start_byte,
                                      stretch.end_byte)
        lost = None
        if by_channel is not None:
            lost = {}
            for cid, n in by_channel.items():
                topic = channels.get(cid) or known.get(cid, "?")
                lost[topic] = lost.get(topic, 0) + n
        self.skipped.add(DamagedStretch(stretch.start_byte, stretch.end_byte, lost))

    def _records(self) -> Iterator[object]:
        """The records in file order, past damaged stretches (gathered in `skipped`), up to the
        end or a cut (then the whole records of the cut chunk); a cut is recorded in `damage`,
        or raised when no message comes before it. Each pass has its own file handle: passes
        may nest (static transforms read during a scan pass)."""
        counts, channels = {}, {}

        def seen(record) -> None:
            if isinstance(record, Channel):
                channels[record.id] = record.topic
            elif isinstance(record, Message):
                topic = channels.get(record.channel_id, "?")
                counts[topic] = counts.get(topic, 0) + 1

        intact = IntactRecords(self.path, lambda s: self._note_stretch(s, channels))
        for record in intact:
            seen(record)
            yield record
        if intact.cut_at is not None:
            if not counts:
                raise LogFormatError(f"{self.path}: the log is truncated or damaged before its "
                                     f"first message ({intact.detail[:160]}); nothing in it can "
                                     "be read. Re-copy or re-record it.")
            self.damage = StreamDamage(intact.cut_at, self._size, counts, intact.detail)

    def _scan_summary(self) -> tuple[Header, Summary]:
        """A log without a (complete) summary: one streaming pass to learn channels and counts."""
        header, summary = Header(profile="", library=""), Summary()
        stats = Statistics(message_count=0, schema_count=0, channel_count=0,
                           attachment_count=0, metadata_count=0, chunk_count=0,
                           message_start_time=0, message_end_time=0, channel_message_counts={})
        for record in self._records():
            if isinstance(record, Header):
                header = record
            elif isinstance(record, Schema):
                summary.schemas[record.id] = record
            elif isinstance(record, Channel):
                summary.channels[record.id] = record
            elif isinstance(record, Message):
                counts = stats.channel_message_counts
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                if stats.message_count == 0 or record.log_time < stats.message_start_time:
                    stats.message_start_time = record.log_time
                stats.message_end_time = max(stats.message_end_time, record.log_time)
                stats.message_count += 1
        if self.damage is not None or self.skipped.stretches:
            self._reader = None  # its indexes would lead into the damage
        summary.statistics = stats
        return header, summary

    def _streamed(self, topics: list[str]) -> Iterator[tuple[object, Message]]:
        """(channel, message) on `topics` in file order, up to the damage."""
        wanted = set(topics)
        for record in self._records():
            if isinstance(record, Message):
                channel = self._channels.get(record.channel_id)
                if channel is not None and channel.topic in wanted:
                    yield channel, record

    def _decoder(self, channel_id: int) -> Callable:
        decode = self._decoders.get(channel_id)
        if decode is None:
            decode = self._decoders[channel_id] = self._make_decoder(channel_id)
        return decode

    def _make_decoder(self, channel_id: int) -> Callable:
        ch = self._channels[channel_id]
        schema = self._schemas.get(ch.schema_id)
        if schema is None:
            raise LogFormatError(f"{self.path}: topic {ch.topic} has no schema; cannot decode it")
        name = normalize_type(schema.name)
        text = schema.data.decode("utf-8", errors="replace")
        store = get_typestore(Stores.EMPTY)
        try:
            if schema.encoding in ("ros2msg", "ros1msg"):
                store.register(get_types_from_msg(text, name))
            elif schema.encoding == "ros2idl":
                sep = "=" * 80 + "\n"
                for part in text.split(sep):
                    idl = part.split("\n", 1)[1] if part.startswith("IDL: ") else part
                    if idl.strip():
                        store.register(get_types_from_idl(idl))
            else:
                raise LogFormatError(f"{self.path}: topic {ch.topic} uses schema encoding "
                                     f"{schema.encoding!r}; mcl3d reads ros1msg, ros2msg, ros2idl")
        except Mcl3dError:
            raise
        except Exception as exc:
            raise LogFormatError(f"{self.path}: the message definition of {schema.name} on "
                                 f"{ch.topic} cannot be parsed ({exc})") from None
        if ch.message_encoding not in ("cdr", "ros1"):
            raise LogFormatError(f"{self.path}: topic {ch.topic} uses message encoding "
                                 f"{ch.message_encoding!r}; mcl3d reads cdr (ROS 2) and ros1")
        cdr = ch.message_encoding == "cdr"
        fast = livox.fast_decoder(store.fielddefs, name, cdr)
        if fast is not None:
            return fast
        if cdr:
            return lambda data: store.deserialize_cdr(data, name)
        return lambda data: store.deserialize_ros1(data, name)

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        """(topic, log_time_ns, decoded message) for `topics`, in log-time order (in file order
        for an MCAP without chunk indexes)."""
        if reverse and not self._indexed:
            raise NotImplementedError("reverse reading needs an MCAP with chunk indexes")
        try:
            if not self._indexed:
                it = self._streamed(topics)
            else:
                ids = {cid for cid, ch in self._channels.items() if ch.topic in topics}
                it = ((self._channels[m.channel_id], m) for m in indexed_messages(
                    self._file, self._summary, self._size, ids, reverse,
                    lambda s: self._note_stretch(s, {})))
            for channel, message in it:
                decode = self._decoder(channel.id)
                try:
                    msg = decode(message.data)
                except Exception as exc:
                    raise LogFormatError(f"{self.path}: a message on {channel.topic} at log time "
                                         f"{message.log_time} ns cannot be decoded as its "
                                         f"schema says ({exc}); the log is corrupt") from None
                yield channel.topic, message.log_time, msg
        except Mcl3dError:
            raise
        except Exception as exc:
            raise _corrupt(self.path, exc) from None

    def close(self) -> None:
        self._file.close()


def _bag2_storage(folder: Path) -> str:
    """The storage plugin a ROS 2 bag folder declares (sqlite3, mcap)."""
    try:
        meta = yaml.safe_load((folder / "metadata.yaml").read_text())
        return str(meta["rosbag2_bagfile_information"]["storage_identifier"])
    except Exception:
        return "unknown storage"


class RosbagsSource:
    """A ROS 1 .bag file or a ROS 2 bag folder, through rosbags' AnyReader."""

    def __init__(self, path: Path, kind: str):
        self.path = path
        self.format = kind
        self.library = "-"
        try:
            self._reader = AnyReader([path], default_typestore=ros2_typestore())
            self._reader.open()
        except Exception as exc:
            raise _corrupt(path, exc) from None
        r = self._reader
        self.profile = "ros1" if not r.is2 else "ros2"
        self.skipped = LogDamage(path.stat().st_size) if not r.is2 else None
        if r.is2:
            self.format = f"{kind} ({_bag2_storage(path)})"
        self.start_ns = r.start_time if r.message_count else None
        self.end_ns = r.end_time if r.message_count else None
        self.topics = {}
        for name, info in sorted(r.topics.items()):
            msgtype = normalize_type(info.msgtype) if info.msgtype else "(mixed types)"
            self.topics[name] = TopicInfo(name, msgtype, info.msgcount, info.msgtype is not None,
                                          list(info.connections))

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        if reverse:
            raise NotImplementedError("rosbags sources stream forward only")
        conns = [c for t in topics for c in self.topics[t].handles]
        fast = {c.msgtype: livox.fast_decoder(self._reader.typestore.fielddefs, c.msgtype,
                                              self._reader.is2) for c in conns}
        last_ns = None
        try:
            for conn, stamp, raw in self._reader.messages(connections=conns):
                try:
                    decode = fast[conn.msgtype]
                    msg = (decode(raw) if decode is not None
                           else self._reader.deserialize(raw, conn.msgtype))
                except Exception as exc:
                    raise LogFormatError(f"{self.path}: a message on {conn.topic} at {stamp} ns "
                                         f"cannot be decoded ({exc}); the bag is corrupt") from None
                last_ns = stamp
                yield conn.topic, stamp, msg
        except Mcl3dError:
            raise
        except Exception as exc:
            if self.skipped is None:
                raise _corrupt(self.path, exc) from None
            yield from self._after_damage(topics, last_ns, _corrupt(self.path, exc))

    def _after_damage(self, topics: list[str], last_ns: int | None, unreadable: LogFormatError
                      ) -> Iterator[tuple[str, int, object]]:
        """A ROS 1 bag whose index is whole but a chunk is not: the messages after `last_ns`
        (the last one read in time order), read record by record past the damage."""
        recovered = _recovered_bag(self.path, unreadable)
        for stretch in recovered.skipped.stretches.values():
            self.skipped.add(DamagedStretch(stretch.start_byte, stretch.end_byte,
                                            self._indexed_between(stretch)))
        for topic, stamp, msg in recovered.messages(topics):
            if last_ns is None or stamp > last_ns:
                yield topic, stamp, msg

    def _indexed_between(self, stretch: DamagedStretch) -> dict[str, int]:
        """Messages per topic the bag's (whole) index places in the chunks of `stretch`."""
        lost: dict[str, int] = {}
        for bag in self._reader.readers:
            for conn in bag.connections:
                n = sum(stretch.start_byte <= entry.chunk_pos < stretch.end_byte
                        for entry in bag.indexes.get(conn.id, ()))
                if n:
                    lost[conn.topic] = lost.get(conn.topic, 0) + n
        return lost

    def close(self) -> None:
        self._reader.close()
