"""Streaming log reader: scans, IMU, odometry, ground truth and static transforms.

Reads MCAP (ROS 2 CDR or ROS 1 encoding), ROS 1 .bag files, ROS 2 bag folders, KITTI
odometry folders and Ouster .pcap files; memory stays flat because messages are decoded one
at a time. Scans are sensor_msgs/PointCloud2 or Livox CustomMsg (`livox.py`). Topics
are chosen per CONVENTIONS §3: by message type when exactly one topic has it, ground truth
by name (ground_truth, groundtruth, gt); otherwise a `TopicError` lists the candidates and
the option to pass.
Messages with faults (a repeated or backwards stamp, NaN/inf, an empty scan) are dropped and
counted in `faults` (see `faults.py`), as is a log damaged part way (read up to the damage)
or in its middle (the damaged stretches skipped, counted as passes meet them).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcl3d.core.errors import LogFormatError, TopicError
from mcl3d.core.geometry import se3_inverse
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.faults import FaultFilter, LogFaults, LogTruncation
from mcl3d.io.logs.messages import PointCloud, Transform
from mcl3d.io.logs.sources import TopicInfo, open_source

KINDS = ("points", "imu", "odom", "gt")
GT_NAMES = ("ground_truth", "groundtruth", "gt")
_KIND_TYPES = {"points": rt.POINT_TYPES, "imu": (rt.IMU,), "odom": (rt.ODOMETRY,),
               "gt": rt.GT_TYPES}
_KIND_WORDS = {"points": "point cloud (sensor_msgs/PointCloud2 or Livox CustomMsg)",
               "imu": "IMU (sensor_msgs/Imu)",
               "odom": "odometry (nav_msgs/Odometry)",
               "gt": "ground-truth (PoseStamped, PoseWithCovarianceStamped or Odometry named "
                     "ground_truth, groundtruth or gt)"}


@dataclass
class TopicSelection:
    """The topic used for each kind of data; None when the log has none (or it is ambiguous,
    in which case using that kind raises the TopicError in `problems`)."""

    points: str | None
    imu: str | None
    odom: str | None
    gt: str | None

    def get(self, kind: str) -> str | None:
        return getattr(self, kind)


@contextmanager
def standard_fields(path: Path, topic: str, msgtype: str) -> Iterator[None]:
    """Converting a message that lacks a field of its type or holds one of another type (the
    log's definition of the type is damaged or not the standard one) raises a LogFormatError
    naming the topic, instead of a traceback."""
    try:
        yield
    except (AttributeError, TypeError, ValueError, KeyError, IndexError) as exc:
        raise LogFormatError(f"{path}: a message on {topic} does not hold the fields of "
                             f"{rt.short_type(msgtype)} ({type(exc).__name__}: {exc}); the "
                             "log's definition of that type is damaged or not the standard "
                             "one") from None


def _is_gt_name(topic: str) -> bool:
    last = topic.strip("/").split("/")[-1].lower() if topic.strip("/") else ""
    return last in GT_NAMES


class LogReader:
    """Context manager over one log; see the module docstring."""

    def __init__(self, path: Path, *, points_topic: str | None = None,
                 imu_topic: str | None = None, odom_topic: str | None = None,
                 gt_topic: str | None = None):
        self.path = Path(path)
        self._source = open_source(self.path)
        self.faults = LogFaults()  # messages dropped for faults, over every pass
        try:
            self.problems: dict[str, TopicError] = {}
            chosen = {"points": points_topic, "imu": imu_topic, "odom": odom_topic,
                      "gt": gt_topic}
            selected = {kind: self._select(kind, chosen[kind], chosen) for kind in KINDS}
            self.topics = TopicSelection(**selected)
            self.faults.truncation = self._truncation()
            self.faults.damage = getattr(self._source, "skipped", None)
            if self.faults.damage is not None:
                self.faults.damage.points_topic = self.topics.points
        except BaseException:
            self._source.close()
            raise

    # ---- topic selection ----

    @property
    def all_topics(self) -> dict[str, TopicInfo]:
        return self._source.topics

    @property
    def source(self):
        """The underlying source (format, profile, library, start_ns, end_ns, topics)."""
        return self._source

    def _topic_list(self) -> str:
        return ", ".join(f"{t} ({rt.short_type(i.msgtype)})" for t, i in self.all_topics.items()
                         ) or "none"

    def _select(self, kind: str, explicit: str | None, chosen: dict) -> str | None:
        types = _KIND_TYPES[kind]
        setting = f"{kind}_topic"
        if explicit is not None:
            info = self.all_topics.get(explicit)
            if info is None:
                raise TopicError(f"{self.path}: {_KIND_WORDS[kind]} topic {explicit} is not in "
                                 f"the log; topics: {self._topic_list()}", setting=setting)
            if info.msgtype not in types:
                raise TopicError(f"{self.path}: {_KIND_WORDS[kind]} topic {explicit} holds "
                                 f"{rt.short_type(info.msgtype)}, not "
                                 f"{' or '.join(rt.short_type(t) for t in types)}",
                                 setting=setting)
            return explicit
        candidates = [t for t, i in self.all_topics.items() if i.msgtype in types]
        if kind == "gt":
            candidates = [t for t in candidates if _is_gt_name(t)]
        if kind == "odom":  # an Odometry-typed ground truth is not odometry
            gt = chosen["gt"] or next((t for t in candidates if _is_gt_name(t)), None)
            candidates = [t for t in candidates if t != gt and not _is_gt_name(t)]
        if len(candidates) == 1:
            return candidates[0]
        if len(candidates) > 1:
            self.problems[kind] = TopicError(
                f"{self.path}: {len(candidates)} {_KIND_WORDS[kind]} topics "
                f"({', '.join(candidates)}); choose one", setting=setting)
        return None

    def _truncation(self) -> LogTruncation | None:
        damage = getattr(self._source, "damage", None)
        if damage is None:
            return None
        scans = damage.messages_read.get(self.topics.points, 0)
        return LogTruncation(damage.damaged_at_byte, damage.total_bytes, scans)

    def require(self, kind: str) -> str:
        """The topic for `kind`, or a TopicError saying why there is none and what to pass."""
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")
        if kind in self.problems:
            raise self.problems[kind]
        topic = self.topics.get(kind)
        if topic is None:
            raise TopicError(f"{self.path}: no {_KIND_WORDS[kind]} topic in the log (topics: "
                             f"{self._topic_list()}); choose one", setting=f"{kind}_topic")
        return topic

    # ---- reading ----

    def messages(self, kinds=KINDS) -> Iterator[tuple[str, object]]:
        """(kind, message) in log-time order for the kinds present, messages with faults
        left out (and counted in `faults`); ambiguous kinds raise."""
        for kind in kinds:
            if kind in self.problems:
                raise self.problems[kind]
        by_topic: dict[str, list[str]] = {}
        for kind in kinds:
            topic = self.topics.get(kind)
            if topic is not None:
                by_topic.setdefault(topic, []).append(kind)
        if not by_topic:
            return
        counters = dict.fromkeys(by_topic, 0)
        sound = FaultFilter(self.faults)
        for topic, _log_ns, msg in self._source.messages(list(by_topic)):
            counters[topic] += 1
            for kind in by_topic[topic]:
                with standard_fields(self.path, topic, self.all_topics[topic].msgtype):
                    converted = self._convert(kind, topic, msg, counters[topic])
                if sound.keep(kind, converted):
                    yield kind, converted

    def _convert(self, kind: str, topic: str, msg, index: int):
        msgtype = self.all_topics[topic].msgtype
        if kind == "points":
            return rt.to_scan(msg, msgtype, f"{self.path} topic {topic} message {index}")
        if kind == "imu":
            return rt.to_imu(msg)
        if kind == "odom":
            return rt.to_odometry(msg)
        return rt.to_pose(msg, msgtype)

    def scans(self) -> Iterator[PointCloud]:
        """Every sound scan on the point-cloud topic, decoded, in log-time order."""
        self.require("points")
        for _kind, cloud in self.messages(("points",)):
            yield cloud

    def count(self, kind: str) -> int:
        """Number of messages of `kind` (0 when absent), from the summary when present."""
        if kind in self.problems:
            raise self.problems[kind]
        topic = self.topics.get(kind)
        if topic is None:
            return 0
        count = self.all_topics[topic].count
        if count is None:
            count = sum(1 for _ in self._source.messages([topic]))
        return count

    def _tf_topics(self) -> list[str]:
        return [t for t, i in self.all_topics.items() if i.msgtype == rt.TF_MESSAGE]

    def static_transforms(self) -> list[Transform]:
        """Transforms on /tf_static, plus /tf transforms whose value never changes in the log."""
        tf_topics = self._tf_topics()
        if not tf_topics:
            return []
        static: dict[tuple[str, str], Transform] = {}
        dynamic: dict[tuple[str, str], Transform | None] = {}
        for topic, _log_ns, msg in self._source.messages(tf_topics):
            is_static = topic.rstrip("/").endswith("tf_static")
            with standard_fields(self.path, topic, rt.TF_MESSAGE):
                transforms = rt.to_transforms(msg)
            for tf in transforms:
                key = (tf.parent_frame, tf.child_frame)
                if is_static:
                    static[key] = tf
                elif key not in dynamic:
                    dynamic[key] = tf
                elif dynamic[key] is not None and not np.allclose(
                        dynamic[key].T_parent_child, tf.T_parent_child, rtol=0, atol=1e-9):
                    dynamic[key] = None
        for key, tf in dynamic.items():
            if tf is not None and key not in static:
                static[key] = tf
        return list(static.values())

    def static_transform(self, parent: str, child: str) -> np.ndarray:
        """T_parent_child composed from static transforms (either direction), or TopicError."""
        edges: dict[str, list[tuple[str, np.ndarray]]] = {}
        for tf in self.static_transforms():
            edges.setdefault(tf.parent_frame, []).append((tf.child_frame, tf.T_parent_child))
            edges.setdefault(tf.child_frame, []).append((tf.parent_frame,
                                                         se3_inverse(tf.T_parent_child)))
        reached = {parent: np.eye(4)}
        frontier = [parent]
        while frontier and child not in reached:
            frame = frontier.pop()
            for nxt, T in edges.get(frame, []):
                if nxt not in reached:
                    reached[nxt] = reached[frame] @ T
                    frontier.append(nxt)
        if child not in reached:
            raise TopicError(f"{self.path}: no static transform chain from {parent!r} to "
                             f"{child!r} in /tf_static or /tf (frames: "
                             f"{', '.join(sorted(edges)) or 'none'})")
        return reached[child]

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns (N,) int64, T_map_lidar (N, 4, 4)) from the ground-truth topic.

        The poses are taken as published (CONVENTIONS §3: /ground_truth is the lidar pose).
        """
        self.require("gt")
        stamps, poses = [], []
        for _kind, pose in self.messages(("gt",)):
            stamps.append(pose.stamp_ns)
            poses.append(pose.T)
        if not stamps:
            raise TopicError(f"{self.path}: ground-truth topic {self.topics.gt} has no messages")
        return np.asarray(stamps, dtype=np.int64), np.stack(poses)

    # ---- context manager ----

    def close(self) -> None:
        self._source.close()

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
