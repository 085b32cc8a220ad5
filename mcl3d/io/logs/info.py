"""`mcl3d info`: what a log holds, like `ros2 bag info`, computed without reading it all.

Counts, start/end and duration come from the log's summary (MCAP statistics, bag indexes).
Frame ids come from the first few messages of each topic; cloud layouts and valid-point
counts from decoding at most `max_scans` scans per cloud topic; topic rates from each
topic's first and last message times (MCAP; bags use the log's end time).

`LogInfo.as_dict()` gives the same facts for scripts (`mcl3d info --json`), under the keys
documented in docs/json-output.md (schema `mcl3d.info/1`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from mcl3d.core.errors import Mcl3dError
from mcl3d.io.logs import livox
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.pointcloud2 import DATATYPE_NAMES, time_field_name
from mcl3d.io.logs.reader import KINDS, LogReader, standard_fields

MAX_SCANS = 3
FRAME_SAMPLES = 3
SCHEMA = "mcl3d.info/1"  # bump the number when a key changes meaning or goes away


def iso_utc(stamp_ns: int | None) -> str | None:
    """A stamp as ISO 8601 UTC with all nine digits of its nanoseconds."""
    if stamp_ns is None:
        return None
    when = datetime.fromtimestamp(stamp_ns // 1_000_000_000, tz=timezone.utc)
    return f"{when:%Y-%m-%dT%H:%M:%S}.{stamp_ns % 1_000_000_000:09d}Z"


@dataclass
class CloudInfo:
    fields: list[tuple[str, str, int]]  # (name, datatype name, count)
    height: int
    width: int
    scans_decoded: int
    valid_min: int
    valid_mean: float
    valid_max: int
    time_field: str | None
    time_span_s: float | None  # max per-point time minus min, over the decoded scans

    @property
    def organized(self) -> bool:
        return self.height > 1

    def as_dict(self) -> dict:
        return {"organized": self.organized, "height": self.height, "width": self.width,
                "fields": [{"name": n, "datatype": t, "count": c} for n, t, c in self.fields],
                "time_field": self.time_field, "time_span_s": self.time_span_s,
                "scans_decoded": self.scans_decoded,
                "valid_points": {"min": self.valid_min, "mean": self.valid_mean,
                                 "max": self.valid_max}}


@dataclass
class TopicSummary:
    topic: str
    msgtype: str
    count: int | None
    rate_hz: float | None
    frame_ids: list[str] = field(default_factory=list)
    cloud: CloudInfo | None = None

    def as_dict(self) -> dict:
        return {"name": self.topic, "type": self.msgtype, "count": self.count,
                "rate_hz": self.rate_hz, "frame_ids": list(self.frame_ids),
                "cloud": self.cloud.as_dict() if self.cloud else None}


@dataclass
class TopicChoice:
    """The topic mcl3d would use for one kind, or the problem that stops it choosing."""

    topic: str | None
    problem: str | None = None  # e.g. several candidates: which ones
    setting: str | None = None  # the request setting that resolves the problem

    def as_dict(self) -> dict:
        return {"topic": self.topic, "problem": self.problem, "setting": self.setting}


@dataclass
class LogInfo:
    path: Path
    format: str
    profile: str
    library: str
    size_bytes: int
    start_ns: int | None
    end_ns: int | None
    topics: list[TopicSummary]
    selection: dict[str, TopicChoice]  # kind (points, imu, odom, gt) -> its topic

    @property
    def duration_s(self) -> float | None:
        if self.start_ns is None or self.end_ns is None:
            return None
        return (self.end_ns - self.start_ns) * 1e-9

    @property
    def message_count(self) -> int:
        return sum(t.count or 0 for t in self.topics)

    def as_dict(self) -> dict:
        """The facts of the tables as plain JSON types (docs/json-output.md)."""
        return {"schema": SCHEMA, "path": str(self.path), "format": self.format,
                "profile": self.profile, "library": self.library,
                "size_bytes": self.size_bytes,
                "start_ns": self.start_ns, "start_utc": iso_utc(self.start_ns),
                "end_ns": self.end_ns, "end_utc": iso_utc(self.end_ns),
                "duration_ns": None if self.duration_s is None else self.end_ns - self.start_ns,
                "duration_s": self.duration_s, "message_count": self.message_count,
                "topics": [t.as_dict() for t in self.topics],
                "selection": {kind: c.as_dict() for kind, c in self.selection.items()}}


def _size(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


def _layout(msg, msgtype: str, cloud) -> tuple[list[tuple[str, str, int]], int, int]:
    """(fields, height, width) of a scan message as it is in the log."""
    if msgtype in livox.CUSTOM_MSG_TYPES:
        return [(name, kind, 1) for name, kind in livox.POINT_LAYOUT], 1, cloud.width
    return ([(f.name, DATATYPE_NAMES.get(int(f.datatype), f"type{f.datatype}"), int(f.count))
             for f in msg.fields], int(msg.height), int(msg.width))


def _cloud_info(reader: LogReader, topic: str, max_scans: int) -> tuple[CloudInfo, set[str],
                                                                          int | None]:
    """Layout and valid-point counts from the first `max_scans` scans of a cloud topic."""
    valid, frames, spans, first_ns, layout = [], set(), [], None, None
    for index, (_topic, log_ns, msg) in enumerate(reader.source.messages([topic]), start=1):
        if first_ns is None:
            first_ns = log_ns
        msgtype = reader.all_topics[topic].msgtype
        with standard_fields(reader.path, topic, msgtype):
            cloud = rt.to_scan(msg, msgtype, f"{reader.path} topic {topic} message {index}")
            layout = layout or _layout(msg, msgtype, cloud)
        valid.append(len(cloud.points))
        frames.add(cloud.frame_id)
        if cloud.times_s is not None and len(cloud.times_s):
            spans.append(float(cloud.times_s.max() - cloud.times_s.min()))
        if index >= max_scans:
            break
    fields, height, width = layout if layout else ([], 0, 0)
    info = CloudInfo(fields=fields, height=height, width=width, scans_decoded=len(valid),
                     valid_min=min(valid, default=0), valid_max=max(valid, default=0),
                     valid_mean=float(np.mean(valid)) if valid else 0.0,
                     time_field=time_field_name([f[0] for f in fields]),
                     time_span_s=max(spans) if spans else None)
    return info, frames, first_ns


def _frames_and_first(reader: LogReader, topic: str) -> tuple[set[str], int | None]:
    frames, first_ns = set(), None
    try:
        for index, (_topic, log_ns, msg) in enumerate(reader.source.messages([topic]), start=1):
            if first_ns is None:
                first_ns = log_ns
            header = getattr(msg, "header", None)
            if header is not None and hasattr(header, "frame_id"):
                frames.add(header.frame_id)
            for tf in getattr(msg, "transforms", None) or []:
                frames.add(f"{tf.header.frame_id}->{tf.child_frame_id}")
            if index >= FRAME_SAMPLES:
                break
    except Mcl3dError:  # an undecodable side topic (custom type, no schema) is only described
        return frames, first_ns
    return frames, first_ns


def _last_ns(reader: LogReader, topic: str) -> int | None:
    known = getattr(reader.source, "last_log_ns", {})  # sources that index themselves on opening
    if topic in known:
        return known[topic]
    try:
        for _topic, log_ns, _msg in reader.source.messages([topic], reverse=True):
            return log_ns
    except (NotImplementedError, Mcl3dError):
        return None
    return None


def log_info(path: Path, *, max_scans: int = MAX_SCANS, points_topic: str | None = None,
             imu_topic: str | None = None, odom_topic: str | None = None,
             gt_topic: str | None = None) -> LogInfo:
    """Describe a log (see module docstring); decodes at most `max_scans` scans per cloud topic."""
    path = Path(path)
    with LogReader(path, points_topic=points_topic, imu_topic=imu_topic, odom_topic=odom_topic,
                   gt_topic=gt_topic) as reader:
        src = reader.source
        topics = []
        for name, tinfo in reader.all_topics.items():
            summary = TopicSummary(name, tinfo.msgtype, tinfo.count, None)
            if not tinfo.decodable:
                frames, first = set(), None
            elif tinfo.msgtype in rt.POINT_TYPES:
                summary.cloud, frames, first = _cloud_info(reader, name, max_scans)
            else:
                frames, first = _frames_and_first(reader, name)
            summary.frame_ids = sorted(frames)
            last = _last_ns(reader, name) if tinfo.decodable else None
            if last is None:
                last = src.end_ns
            if first is not None and last is not None and last > first and (tinfo.count or 0) > 1:
                summary.rate_hz = (tinfo.count - 1) * 1e9 / (last - first)
            topics.append(summary)
        selection = {}
        for kind in KINDS:
            problem = reader.problems.get(kind)
            selection[kind] = TopicChoice(reader.topics.get(kind)) if problem is None else (
                TopicChoice(None, str(problem).removeprefix(f"{path}: "), problem.setting))
        return LogInfo(path=path, format=src.format, profile=src.profile, library=src.library,
                       size_bytes=_size(path), start_ns=src.start_ns, end_ns=src.end_ns,
                       topics=topics, selection=selection)
