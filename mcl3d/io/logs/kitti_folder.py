"""A KITTI odometry sequence folder read as a log: `velodyne/NNNNNN.bin` scans stamped by
`times.txt`, with the ground-truth poses as lidar poses when the sequence has them.

Layout (the KITTI odometry benchmark): `NN/velodyne/000000.bin ...` (float32 x y z
reflectance per point, already motion-compensated, so no per-point time), `NN/times.txt`
(seconds since the sequence start, one line per scan), `NN/calib.txt` (`Tr:` velodyne to
camera 0, 3x4) and poses (camera 0 in the first camera frame, 3x4 per line) in
`NN/poses.txt`, `NN/poses/NN.txt`, `NN.txt` beside the folder or `../poses/NN.txt` of the
dataset. The lidar pose is T_map_lidar = Tr^-1 P Tr, so the map frame is the first scan's
lidar frame. Everything is checked when the folder is opened, so a broken folder fails
before any command writes output. Messages are ROS 2 objects, as the bag sources yield.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs import ros_types as rt
from mcl3d.io.logs.messages import PoseStamped
from mcl3d.io.logs.sources import TopicInfo

POINTS_TOPIC = "/velodyne_points"
GT_TOPIC = "/ground_truth"
LIDAR_FRAME = "velodyne"
MAP_FRAME = "map"
POINT_BYTES = 16  # float32 x y z reflectance
_MAX_TIME_S = 9.2e9  # integer nanoseconds hold times up to about 292 years


def is_kitti_folder(path: Path) -> bool:
    """A folder with `velodyne/` or `times.txt`: what this source reads (and names what is
    missing when one of them is)."""
    return path.is_dir() and ((path / "velodyne").is_dir() or (path / "times.txt").is_file())


def _numbers(path: Path, per_line: int, what: str) -> np.ndarray:
    """The non-blank lines of a text file as an (N, per_line) float64 array."""
    rows = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{path}: cannot read it ({exc})") from None
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            values = []
        if len(values) != per_line:
            raise LogFormatError(f"{path}: line {number} is not {what} "
                                 f"({per_line} number{'s' if per_line > 1 else ''})")
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, per_line)


def _homogeneous(row: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = row.reshape(3, 4)
    return T


def _velodyne_to_camera(folder: Path) -> np.ndarray:
    """T_cam0_velo from the `Tr:` line of calib.txt."""
    calib = folder / "calib.txt"
    if not calib.is_file():
        raise LogFormatError(f"{folder}: the poses are camera poses and need calib.txt (its "
                             "Tr: line, velodyne to camera) to become lidar poses; add the "
                             "sequence's calib.txt")
    try:
        lines = calib.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{calib}: cannot read it ({exc})") from None
    for line in lines:
        key, _, rest = line.partition(":")
        if key.strip() == "Tr":
            try:
                values = np.array([float(v) for v in rest.split()], dtype=np.float64)
            except ValueError:
                values = np.zeros(0)
            if values.size != 12 or not np.isfinite(values).all():
                raise LogFormatError(f"{calib}: the Tr: line does not hold 12 finite numbers")
            T_cam_velo = _homogeneous(values)
            if abs(np.linalg.det(T_cam_velo)) < 1e-9:
                raise LogFormatError(f"{calib}: the Tr: line is not a pose (its 3x3 part has "
                                     "no inverse)")
            return T_cam_velo
    raise LogFormatError(f"{calib}: no Tr: line (velodyne to camera 0, 12 numbers)")


def _poses_file(folder: Path) -> Path | None:
    """The first poses file of the candidates in the module docstring, or None."""
    name = folder.resolve().name
    candidates = [folder / "poses.txt", folder / "poses" / f"{name}.txt"]
    if name.isdigit():
        candidates += [folder.parent / f"{name}.txt",
                       folder.parent.parent / "poses" / f"{name}.txt"]
    return next((p for p in candidates if p.is_file()), None)


def _scan_files(folder: Path, count: int) -> list[Path]:
    """velodyne/000000.bin ... one per line of times.txt, each a whole number of points."""
    velodyne = folder / "velodyne"
    files = [velodyne / f"{i:06d}.bin" for i in range(count)]
    for path in files:
        if not path.is_file():
            raise LogFormatError(f"{path}: missing; times.txt has {count} lines, so scans "
                                 f"velodyne/000000.bin to {files[-1].name} are expected")
        size = path.stat().st_size
        if size % POINT_BYTES:
            raise LogFormatError(f"{path}: {size} bytes is not a multiple of {POINT_BYTES}; a "
                                 "KITTI .bin holds float32 x y z reflectance per point")
    extra = len(list(velodyne.glob("*.bin"))) - count
    if extra:
        raise LogFormatError(f"{velodyne}: {count + extra} .bin scans but times.txt has {count} "
                             "lines; one time per scan is needed")
    return files


class KittiFolderSource:
    """A KITTI odometry sequence folder as a log source (see the module docstring)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.format = "KITTI odometry folder"
        self.profile = "-"
        self.library = "-"
        for needed in ("velodyne", "times.txt"):
            if not (self.path / needed).exists():
                raise LogFormatError(f"{self.path / needed}: missing; a KITTI sequence folder "
                                     "holds velodyne/NNNNNN.bin scans and times.txt")
        times_s = _numbers(self.path / "times.txt", 1, "a time in seconds")[:, 0]
        if times_s.size == 0:
            raise LogFormatError(f"{self.path / 'times.txt'}: no times; one line per scan needed")
        if not (np.abs(times_s) < _MAX_TIME_S).all():  # NaN and inf included
            bad = int(np.flatnonzero(~(np.abs(times_s) < _MAX_TIME_S))[0])
            raise LogFormatError(f"{self.path / 'times.txt'}: time {bad + 1} is {times_s[bad]}, "
                                 "not a time in seconds")
        self.stamps_ns = np.rint(times_s * 1e9).astype(np.int64)
        self._files = _scan_files(self.path, len(times_s))
        self.T_map_lidar = self._lidar_poses(len(times_s))
        self.start_ns, self.end_ns = int(self.stamps_ns[0]), int(self.stamps_ns[-1])
        self.topics = {POINTS_TOPIC: TopicInfo(POINTS_TOPIC, rt.POINTCLOUD2, len(times_s))}
        if self.T_map_lidar is not None:
            self.topics[GT_TOPIC] = TopicInfo(GT_TOPIC, rt.POSE_STAMPED, len(times_s))
        self._store = rt.ros2_typestore()

    def _lidar_poses(self, count: int) -> np.ndarray | None:
        """(N, 4, 4) T_map_lidar from the camera poses, or None without a poses file."""
        poses_path = _poses_file(self.path)
        if poses_path is None:
            return None
        rows = _numbers(poses_path, 12, "a 3x4 pose")
        if len(rows) != count:
            raise LogFormatError(f"{poses_path}: {len(rows)} poses but times.txt has {count} "
                                 "lines; one pose per scan is needed")
        T_cam_velo = _velodyne_to_camera(self.path)
        T_velo_cam = np.linalg.inv(T_cam_velo)
        return np.stack([T_velo_cam @ _homogeneous(r) @ T_cam_velo for r in rows])

    def _header(self, index: int):
        types = self._store.types
        sec, nanosec = divmod(int(self.stamps_ns[index]), 1_000_000_000)
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id=LIDAR_FRAME)

    def _cloud(self, index: int):
        path = self._files[index]
        try:
            data = np.fromfile(path, dtype=np.uint8)
        except OSError as exc:
            raise LogFormatError(f"{path}: cannot read the scan ({exc})") from None
        if data.size % POINT_BYTES:
            raise LogFormatError(f"{path}: {data.size} bytes is not a multiple of {POINT_BYTES}")
        types = self._store.types
        fields = [types["sensor_msgs/msg/PointField"](name=name, offset=4 * k, datatype=7,
                                                       count=1)
                  for k, name in enumerate(("x", "y", "z", "intensity"))]
        n = data.size // POINT_BYTES
        return types[rt.POINTCLOUD2](
            header=self._header(index), height=1, width=n, fields=fields, is_bigendian=False,
            point_step=POINT_BYTES, row_step=n * POINT_BYTES, data=data, is_dense=True)

    def messages(self, topics: list[str], reverse: bool = False
                 ) -> Iterator[tuple[str, int, object]]:
        """(topic, stamp_ns, ROS 2 message) per scan, the scan before its pose."""
        order = range(len(self._files) - 1, -1, -1) if reverse else range(len(self._files))
        for index in order:
            stamp = int(self.stamps_ns[index])
            pair = [GT_TOPIC, POINTS_TOPIC] if reverse else [POINTS_TOPIC, GT_TOPIC]
            for topic in (t for t in pair if t in topics and t in self.topics):
                if topic == POINTS_TOPIC:
                    yield topic, stamp, self._cloud(index)
                else:
                    pose = PoseStamped(stamp, MAP_FRAME, self.T_map_lidar[index])
                    yield topic, stamp, rt.from_pose(self._store, pose)

    def close(self) -> None:
        """Nothing stays open between messages."""
