"""The per-scan record of a SLAM run: `SlamFrame`, what `MonteCarloSlam.step` returns, and
`SlamFrames`, every scan's record kept as NumPy columns for the run's outputs.

A run keeps every scan's result for its outputs (frames.csv, the trajectories, the summary,
the consistency check). As one `SlamFrame` object per scan that grew a 30-minute run by
~3.5 kB a scan; here each field is one column of fixed dtype (poses as 3x4 float64 rows, the
rigid bottom row implied), so a scan costs 814 bytes and adds no Python object. The columns
are allocated for the log's scan count when it is known (pages become resident as rows are
written) and grow by doubling otherwise: a doubling copies and frees the old columns, and
freed heap memory does not always go back to the system (10-14 MiB at 8,192 and 16,384
scans in the 30-minute soak). The rare ragged parts stay sparse: loop corrections (up to
`NEIGHBOURS` keyframes a scan, their relative poses in one growing array) and odometry
warnings (a list of (scan, text)).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from mcl3d.core.geometry import se3_inverse
from mcl3d.kernels.slam import NEIGHBOURS

STAGES = ("odometry", "preprocess", "predict", "correct", "weigh", "refine", "keyframe",
          "prune", "estimate")
INITIAL_ROWS = 1024  # rows allocated before the first doubling, when the count is unknown
MAX_RESERVED_ROWS = 1 << 20  # most rows reserved up front (814 MiB of address space)
POSES = ("T_world_lidar", "T_odom_lidar", "T_motion_lidar", "T_mean")
COLUMNS: dict[str, tuple[type, tuple[int, ...]]] = {  # name: (dtype, shape of one row)
    "stamp_ns": (np.int64, ()), "representative": (np.int32, ()), "ess": (np.float64, ()),
    "max_weight": (np.float64, ()), "hypotheses": (np.int32, ()),
    "looping": (np.int32, ()), "corrected": (np.int32, ()), "pruned": (np.int32, ()),
    "keyframe": (np.bool_, ()), "num_keyframes": (np.int32, ()), "elevator": (np.bool_, ()),
    "travel_m": (np.float64, ()), "timings_ms": (np.float64, (len(STAGES),)),
    "covariance": (np.float64, (6, 6)), "loop_keyframes": (np.int32, (NEIGHBOURS,)),
    **{name: (np.float64, (3, 4)) for name in POSES}}
RIGID_ROW = np.array([0.0, 0.0, 0.0, 1.0])


@dataclass
class SlamFrame:
    """One scan's result. The pose is the representative particle's (largest weight)."""

    stamp_ns: int
    T_world_lidar: np.ndarray
    T_odom_lidar: np.ndarray  # the odometry front-end's pose
    T_motion_lidar: np.ndarray  # the same plus the elevator motion it could not see
    representative: int
    ess: float
    max_weight: float
    hypotheses: int
    looping: int
    corrected: int
    pruned: int
    keyframe: bool
    num_keyframes: int
    elevator: bool
    travel_m: float
    odometry_warnings: list[str]
    timings_ms: dict[str, float] = field(default_factory=dict)
    # the cloud: weighted mean of the current poses and their 6x6 covariance in the tangent
    # at the mean (rotation first), as evaluation.consistency reads them
    T_mean: np.ndarray = field(default_factory=lambda: np.eye(4))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    # keyframes the representative took a loop correction toward on this scan, and its
    # pose relative to each of them in its own map (T_keyframe_lidar) after the scan
    loop_keyframes: tuple[int, ...] = ()
    loop_relative: tuple[np.ndarray, ...] = ()


def _rigid(rows: np.ndarray) -> np.ndarray:
    """(..., 3, 4) -> (..., 4, 4) with the bottom row [0 0 0 1]."""
    out = np.empty((*rows.shape[:-2], 4, 4))
    out[..., :3, :] = rows
    out[..., 3, :] = RIGID_ROW
    return out


class SlamFrames:
    """Every scan's `SlamFrame` as columns: `append(frame)`, `len()`, `frames[i]` (a
    `SlamFrame` again), each column of `COLUMNS` but the poses as an attribute (a view of the
    rows so far, e.g. `frames.ess`), the poses of `POSES` through `poses(name)` / `pose(name,
    i)` (4x4), and the sparse parts through `loops()` and `warnings`."""

    def __init__(self, initial_rows: int | None = None) -> None:
        """`initial_rows`: the scans expected (the log's count), else `INITIAL_ROWS`."""
        rows = min(max(initial_rows or INITIAL_ROWS, 1), MAX_RESERVED_ROWS)
        self._rows = 0
        self._data = {name: np.zeros((rows, *shape), dtype)
                      for name, (dtype, shape) in COLUMNS.items()}
        self._loop_relative = np.zeros((NEIGHBOURS, 3, 4))  # rows of all loops, in scan order
        self._loop_rows = 0
        self.warnings: list[tuple[int, str]] = []  # (scan, odometry warning), in scan order

    def __len__(self) -> int:
        return self._rows

    def __getattr__(self, name: str) -> np.ndarray:
        if name in COLUMNS and name not in POSES:
            return self.__dict__["_data"][name][:self._rows]
        raise AttributeError(f"{type(self).__name__} has no column {name!r}")

    def poses(self, name: str) -> np.ndarray:
        """(len, 4, 4) of one pose column of `POSES` (a new array)."""
        return _rigid(self._data[name][:self._rows])

    def pose(self, name: str, i: int) -> np.ndarray:
        return _rigid(self._data[name][:self._rows][i])

    def hung_off(self, T_keyframes: np.ndarray, keyframe_scans: list[int]) -> np.ndarray:
        """(scans, 4, 4): every scan hung off the keyframe before it (poses `T_keyframes`,
        made at scans `keyframe_scans`) by the odometry's motion since it; scans before the
        first keyframe keep `T_world_lidar`."""
        motion = self.poses("T_motion_lidar")
        poses = self.poses("T_world_lidar")
        scans = np.asarray(keyframe_scans, dtype=np.int64)
        before = np.searchsorted(scans, np.arange(len(self)), side="right") - 1
        hung = before >= 0
        T_world_motion = np.asarray(T_keyframes).reshape(-1, 4, 4) @ se3_inverse(motion[scans])
        poses[hung] = T_world_motion[before[hung]] @ motion[hung]
        return poses

    def append(self, frame: SlamFrame) -> None:
        """Add one scan's record (its loop keyframes: at most `NEIGHBOURS`)."""
        i = self._rows
        if i == len(self._data["stamp_ns"]):
            self._data = {name: _doubled(col) for name, col in self._data.items()}
        row = {name: getattr(frame, name) for name in COLUMNS}
        row["timings_ms"] = [frame.timings_ms.get(stage, 0.0) for stage in STAGES]
        loops = np.asarray(frame.loop_keyframes, np.int32)
        row["loop_keyframes"] = np.r_[loops, np.full(NEIGHBOURS - len(loops), -1, np.int32)]
        for name in POSES:
            row[name] = row[name][:3]
        for name, value in row.items():
            self._data[name][i] = value
        self._add_loop_relative(frame.loop_relative)
        self.warnings.extend((i, text) for text in frame.odometry_warnings)
        self._rows = i + 1

    def _add_loop_relative(self, relative: tuple[np.ndarray, ...]) -> None:
        end = self._loop_rows + len(relative)
        while end > len(self._loop_relative):
            self._loop_relative = _doubled(self._loop_relative)
        for k, T in enumerate(relative):
            self._loop_relative[self._loop_rows + k] = T[:3]
        self._loop_rows = end

    def loops(self) -> Iterator[tuple[int, tuple[int, ...], np.ndarray]]:
        """(scan, loop keyframes, their relative poses T_keyframe_lidar (k, 4, 4)) of every
        scan on which the representative took a loop correction, in scan order."""
        counts = (self.loop_keyframes >= 0).sum(axis=1)
        start = 0
        for i in np.flatnonzero(counts):
            k = int(counts[i])
            keyframes = tuple(int(j) for j in self.loop_keyframes[i, :k])
            yield int(i), keyframes, _rigid(self._loop_relative[start:start + k])
            start += k

    def __getitem__(self, i: int) -> SlamFrame:
        """Scan i's record as a `SlamFrame` (negative i counts from the end)."""
        i = range(self._rows)[i]
        col = {name: self._data[name][i] for name in COLUMNS}
        loops = [int(k) for k in col["loop_keyframes"] if k >= 0]
        start = int((self._data["loop_keyframes"][:i] >= 0).sum())
        return SlamFrame(
            int(col["stamp_ns"]), *(self.pose(name, i) for name in POSES[:3]),
            int(col["representative"]), float(col["ess"]), float(col["max_weight"]),
            int(col["hypotheses"]), int(col["looping"]), int(col["corrected"]),
            int(col["pruned"]), bool(col["keyframe"]), int(col["num_keyframes"]),
            bool(col["elevator"]), float(col["travel_m"]),
            [text for j, text in self.warnings if j == i],
            dict(zip(STAGES, col["timings_ms"].tolist(), strict=True)), self.pose("T_mean", i),
            col["covariance"].copy(), tuple(loops),
            tuple(_rigid(self._loop_relative[start:start + len(loops)])))


def _doubled(column: np.ndarray) -> np.ndarray:
    grown = np.zeros((2 * len(column), *column.shape[1:]), column.dtype)
    grown[:len(column)] = column
    return grown
