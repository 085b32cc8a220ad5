"""Raw log access: topics, counts and decoded ROS message objects, streamed in log-time order.

Two sources cover every supported format: `McapSource` (MCAP files, ROS 2 CDR or ROS 1
encoding, types registered from the schemas stored in the file) and `RosbagsSource`
(ROS 1 .bag files and ROS 2 bag folders, sqlite3 or MCAP, through rosbags' AnyReader).
Both yield `rosbags` message objects, so conversion to mcl3d dataclasses is shared.
Any failure of the underlying libraries becomes a `LogFormatError` naming the file.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Statistics
from mcap.summary import Summary
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from mcl3d.core.errors import LogFormatError, Mcl3dError
from mcl3d.io.logs.ros_types import normalize_type, ros2_typestore

MCAP_MAGIC = b"\x89MCAP0\r\n"
SUPPORTED = "MCAP files (.mcap), ROS 1 .bag files and ROS 2 bag folders"


@dataclass
class TopicInfo:
    topic: str
    msgtype: str  # normalized ROS 2 form, e.g. sensor_msgs/msg/PointCloud2
    count: int | None  # None when the log has no summary to tell
    decodable: bool = True  # a message definition is available
    handles: list = field(default_factory=list, repr=False)  # source-specific channel handles


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
            raise LogFormatError(f"{path}: folder without metadata.yaml is not a ROS 2 bag; "
                                 f"mcl3d reads {SUPPORTED}")
        return RosbagsSource(path, "ROS 2 bag folder")
    if path.suffix == ".db3":
        return open_source(path.parent)
    with open(path, "rb") as f:
        magic = f.read(len(MCAP_MAGIC))
    if path.suffix == ".bag" or magic.startswith(b"#ROSBAG"):
        if not magic.startswith(b"#ROSBAG"):
            raise LogFormatError(f"{path}: not a ROS 1 bag (no #ROSBAG header); mcl3d reads "
                                 f"{SUPPORTED}")
        return RosbagsSource(path, "ROS 1 bag")
    if magic != MCAP_MAGIC:
        raise LogFormatError(f"{path}: not an MCAP file (the file does not start with the MCAP "
                             f"magic bytes); mcl3d reads {SUPPORTED}")
    with open(path, "rb") as f:
        f.seek(max(path.stat().st_size - len(MCAP_MAGIC), 0))
        if f.read() != MCAP_MAGIC:
            raise LogFormatError(f"{path}: the MCAP file is truncated (it does not end with the "
                                 "MCAP magic bytes: an interrupted recording or an incomplete "
                                 "copy); re-copy it, or repair it with `mcap recover`")
    return McapSource(path)


class McapSource:
    """An MCAP file, read through its summary and chunk indexes (streamed chunk by chunk)."""

    def __init__(self, path: Path):
        self.path = path
        self._file = open(path, "rb")  # noqa: SIM115 (closed by close())
        try:
            self._reader = make_reader(self._file)
            header = self._reader.get_header()
            summary = self._reader.get_summary()
        except Mcl3dError:
            self.close()
            raise
        except Exception as exc:
            self.close()
            raise _corrupt(path, exc) from None
        self.profile = header.profile or "-"
        self.library = header.library or "-"
        self.format = f"MCAP ({self.profile})"
        self._decoders: dict[int, Callable] = {}
        self._indexed = summary is not None and bool(summary.chunk_indexes)
        if summary is None or not summary.channels or summary.statistics is None:
            summary = self._scan_summary()
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

    def _scan_summary(self):
        """A log without a (complete) summary: one streaming pass to learn channels and counts."""
        summary = Summary()
        stats = Statistics(message_count=0, schema_count=0, channel_count=0,
                           attachment_count=0, metadata_count=0, chunk_count=0,
                           message_start_time=0, message_end_time=0, channel_message_counts={})
        self._file.seek(0)
        try:
            for schema, channel, message in NonSeekingReader(self._file).iter_messages():
                if schema is not None:
                    summary.schemas[schema.id] = schema
                summary.channels[channel.id] = channel
                counts = stats.channel_message_counts
                counts[channel.id] = counts.get(channel.id, 0) + 1
                if stats.message_count == 0 or message.log_time < stats.message_start_time:
                    stats.message_start_time = message.log_time
                stats.message_end_time = max(stats.message_end_time, message.log_time)
                stats.message_count += 1
        except Exception as exc:
            raise _corrupt(self.path, exc) from None
        summary.statistics = stats
        return summary

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
        if ch.message_encoding == "cdr":
            return lambda data: store.deserialize_cdr(data, name)
        if ch.message_encoding == "ros1":
            return lambda data: store.deserialize_ros1(data, name)
        raise LogFormatError(f"{self.path}: topic {ch.topic} uses message encoding "
                             f"{ch.message_encoding!r}; mcl3d reads cdr (ROS 2) and ros1")

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        """(topic, log_time_ns, decoded message) for `topics`, in log-time order (in file order
        for an MCAP without chunk indexes)."""
        if reverse and not self._indexed:
            raise NotImplementedError("reverse reading needs an MCAP with chunk indexes")
        try:
            it = self._reader.iter_messages(topics=topics, log_time_order=True, reverse=reverse)
            for _schema, channel, message in it:
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
        try:
            for conn, stamp, raw in self._reader.messages(connections=conns):
                try:
                    msg = self._reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    raise LogFormatError(f"{self.path}: a message on {conn.topic} at {stamp} ns "
                                         f"cannot be decoded ({exc}); the bag is corrupt") from None
                yield conn.topic, stamp, msg
        except Mcl3dError:
            raise
        except Exception as exc:
            raise _corrupt(self.path, exc) from None

    def close(self) -> None:
        self._reader.close()
