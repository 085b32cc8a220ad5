"""An Ouster `.pcap` recording with its sensor metadata JSON, read as a log.

The metadata is the JSON beside the pcap with the same stem; else the one whose stem the
pcap's name starts with (`OS-1-128_1024x10.json` for `OS-1-128_1024x10_run3.pcap`, the
longest such); else the only `.json` in the folder. Topics are what ouster-ros publishes:
`/ouster/points` (organized PointCloud2 in the sensor frame `os_sensor`, zero points for no
return, fields `t` (u32 ns after the frame's first column, whose time stamps the scan),
`reflectivity`, `ring`), `/ouster/imu` (`os_imu` frame, LEGACY IMU profile) and `/tf_static`
(`os_sensor` -> `os_imu`, the JSON's `imu_to_sensor_transform`). Packets are decoded as they
are read: memory holds one frame. A scan is logged when its frame ends, after the IMU samples
up to its last column, as a driver would publish it.

Opening reads the pcap once to count frames and IMU samples and to check that the metadata
fits the packets (another sensor's JSON stops here, with one line); a pcap cut inside a
record (an interrupted capture or copy) is read up to the cut, like a damaged MCAP.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.messages import Imu, PointCloud, Transform
from mcl3d.io.logs.ouster_pcap import (
    FrameAssembler,
    OusterMeta,
    PcapPackets,
    XyzLut,
    decode_imu_packet,
    decode_lidar_packet,
    read_metadata,
)
from mcl3d.io.logs.sources import StreamDamage, TopicInfo

POINTS_TOPIC = "/ouster/points"
IMU_TOPIC = "/ouster/imu"
TF_TOPIC = "/tf_static"
SENSOR_FRAME = "os_sensor"
IMU_FRAME = "os_imu"


def find_metadata(pcap: Path) -> Path:
    """The sensor metadata JSON of `pcap` (module docstring), or LogFormatError saying why."""
    same = pcap.with_suffix(".json")
    if same.is_file():
        return same
    candidates = sorted(pcap.parent.glob("*.json"))
    prefixed = [j for j in candidates if pcap.stem.startswith(j.stem)]
    if prefixed:
        return max(prefixed, key=lambda j: len(j.stem))
    if len(candidates) == 1:
        return candidates[0]
    found = (f"the folder holds {len(candidates)} .json files "
             f"({', '.join(j.name for j in candidates)}) and none is named after it"
             if candidates else "there is no .json beside it")
    raise LogFormatError(f"{pcap}: an Ouster pcap needs the sensor metadata JSON saved with "
                         f"the recording, but {found}; put it beside the pcap as {same.name}")


class OusterPcapSource:
    """An Ouster pcap and its metadata as a log source (see the module docstring)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.meta: OusterMeta = read_metadata(find_metadata(self.path))
        self.profile = "-"
        self.library = "-"
        self._store = rt.ros2_typestore()
        self._lut: XyzLut | None = None
        self.damage: StreamDamage | None = None
        self.last_log_ns: dict[str, int] = {}  # per topic, for `info`'s rates
        n_frames, n_imu, first_ns, last_ns = self._index()
        self.format = (f"Ouster pcap ({self.meta.sensor}, {self.meta.profile}; metadata "
                       f"{self.meta.path.name})")
        if self.damage is not None:
            self.format += f" cut at byte {self.damage.damaged_at_byte:,}: read up to it"
        self.start_ns, self.end_ns = first_ns, last_ns
        self.topics = {POINTS_TOPIC: TopicInfo(POINTS_TOPIC, rt.POINTCLOUD2, n_frames)}
        if n_imu:
            self.topics[IMU_TOPIC] = TopicInfo(IMU_TOPIC, rt.IMU, n_imu)
            self.topics[TF_TOPIC] = TopicInfo(TF_TOPIC, rt.TF_MESSAGE, 1)

    def _index(self) -> tuple[int, int, int, int]:
        """(frames, IMU samples, first and last log time) in one pass; checks the metadata."""
        counts = {"points": 0, "imu": 0}
        first = last = None
        packets = PcapPackets(self.path)
        topic = {"points": POINTS_TOPIC, "imu": IMU_TOPIC}
        for kind, log_ns, _item in self._events(packets):
            counts[kind] += 1
            self.last_log_ns[topic[kind]] = log_ns
            first = log_ns if first is None else min(first, log_ns)
            last = log_ns if last is None else max(last, log_ns)
        if counts["points"] == 0:
            raise LogFormatError(f"{self.path}: no complete Ouster frame ({self.meta.sensor}, "
                                 f"{self.meta.columns_per_frame} columns) in the lidar packets "
                                 f"to UDP port {self.meta.udp_port_lidar}; check that "
                                 f"{self.meta.path.name} is the metadata of this recording")
        if packets.cut_at_byte is not None:
            self.damage = StreamDamage(packets.cut_at_byte, packets.size,
                                       {POINTS_TOPIC: counts["points"], IMU_TOPIC: counts["imu"]},
                                       "the capture ends inside a packet record")
        return counts["points"], counts["imu"], first, last

    def _events(self, packets: PcapPackets) -> Iterator[tuple[str, int, object]]:
        """("points", log ns, Frame) and ("imu", stamp ns, ImuSample) in log order."""
        meta = self.meta
        assembler = FrameAssembler(meta)
        waiting: deque = deque()
        for port, payload in packets:
            if port == meta.udp_port_lidar:
                frame = assembler.push(decode_lidar_packet(meta, payload, self.path))
                if frame is not None:
                    yield from self._publish(frame, waiting)
            elif port == meta.udp_port_imu:
                waiting.append(decode_imu_packet(payload, self.path))
        frame = assembler.finish()
        if frame is not None:
            yield from self._publish(frame, waiting)
        while waiting:
            sample = waiting.popleft()
            yield "imu", sample.stamp_ns, sample

    @staticmethod
    def _publish(frame, waiting: deque) -> Iterator[tuple[str, int, object]]:
        end_ns = int(frame.stamp_ns.max())
        while waiting and waiting[0].stamp_ns <= end_ns:
            sample = waiting.popleft()
            yield "imu", sample.stamp_ns, sample
        yield "points", end_ns, frame

    def _cloud(self, frame) -> PointCloud:
        """The frame as ouster-ros publishes it: organized, zeros where there is no return."""
        if self._lut is None:
            self._lut = XyzLut(self.meta)
        rows, width = frame.range_m.shape
        stamp0 = int(frame.stamp_ns.min())
        t_ns = (frame.stamp_ns - np.uint64(stamp0)).astype(np.uint32)
        fields = {"t": np.broadcast_to(t_ns, (rows, width)).ravel(),
                  "reflectivity": frame.reflectivity.ravel(),
                  "ring": np.repeat(np.arange(rows, dtype=np.uint16), width)}
        return PointCloud(stamp0, SENSOR_FRAME, self._lut(frame.range_m).reshape(-1, 3), None,
                          fields, 0, rows, width)

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        """(topic, log time ns, ROS 2 message) for `topics`, in log order."""
        if reverse:
            raise NotImplementedError("an Ouster pcap is read forward only")
        if TF_TOPIC in topics and TF_TOPIC in self.topics:
            tf = Transform(self.start_ns, SENSOR_FRAME, IMU_FRAME, self.meta.T_sensor_imu)
            yield TF_TOPIC, self.start_ns, rt.from_transforms(self._store, [tf])
        want_points, want_imu = POINTS_TOPIC in topics, IMU_TOPIC in topics
        if not (want_points or want_imu):
            return
        for kind, log_ns, item in self._events(PcapPackets(self.path)):
            if kind == "points" and want_points:
                yield POINTS_TOPIC, log_ns, rt.from_pointcloud(
                    self._store, self._cloud(item), f"{self.path} frame {item.frame_id}")
            elif kind == "imu" and want_imu:
                imu = Imu(item.stamp_ns, IMU_FRAME, item.angular_velocity,
                          item.linear_acceleration)
                yield IMU_TOPIC, log_ns, rt.from_imu(self._store, imu)

    def close(self) -> None:
        """Nothing stays open between messages."""
