"""Trajectories: timestamped `T_world_sensor` poses, TUM and KITTI files, SE(3) interpolation.

TUM rows are exactly `t x y z qx qy qz qw` (8 space-separated columns, no trailing
delimiter) so that every file we write loads in `evo_ape tum` unchanged. KITTI rows are the
12 numbers of the row-major 3x4 `[R|t]`; they carry no stamps. Stamps known as integer
nanoseconds (from a log, or parsed exactly from a TUM file's decimal text) are kept as such,
written back exactly and compared exactly (CONVENTIONS §6).
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from mcl3d.core.errors import TrajectoryError
from mcl3d.core.geometry import interpolate_se3, rot_to_quat, se3_from_tq
from mcl3d.core.outputs import atomic_open
from mcl3d.io.logs.faults import format_stamp

TUM_COLUMNS = "t x y z qx qy qz qw"
FORMATS = ("auto", "tum", "kitti")
_ROTATION_TOL = 1e-3    # |RᵀR − I| allowed in KITTI rows printed with few digits
_QUAT_NORM_TOL = 1e-2   # |‖q‖ − 1| allowed in TUM rows printed with few digits


@dataclass(eq=False)
class Trajectory:
    """Poses `T_world_sensor` (N, 4, 4) at strictly increasing stamps (N,) in seconds, and
    the same stamps in integer ns when they are known exactly.

    Compared by identity (eq=False): `==` on arrays has no single truth value.
    """

    stamps_s: np.ndarray
    poses: np.ndarray
    stamps_ns: np.ndarray | None = None  # (N,) int64, exact; None when only seconds are known

    @classmethod
    def from_ns(cls, stamps_ns, poses) -> Trajectory:
        """A trajectory at integer-ns stamps (seconds as `stamps_ns * 1e-9`)."""
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        return cls(stamps_ns * 1e-9, poses, stamps_ns)

    def __post_init__(self) -> None:
        self.stamps_s = np.asarray(self.stamps_s, dtype=np.float64)
        self.poses = np.asarray(self.poses, dtype=np.float64)
        n = self.stamps_s.shape[0] if self.stamps_s.ndim == 1 else -1
        if n < 0 or self.poses.shape != (n, 4, 4):
            raise TrajectoryError(
                f"a trajectory needs stamps of shape (N,) and poses of shape (N, 4, 4); "
                f"got {self.stamps_s.shape} and {self.poses.shape}")
        if not (np.isfinite(self.stamps_s).all() and np.isfinite(self.poses).all()):
            raise TrajectoryError("trajectory stamps or poses contain NaN or inf")
        bad = np.flatnonzero(np.diff(self.stamps_s) <= 0)
        if bad.size:
            i = int(bad[0])
            raise TrajectoryError(
                f"trajectory stamps must be strictly increasing: stamp {i + 1} "
                f"({self.stamps_s[i + 1]:.9f} s) does not come after stamp {i} "
                f"({self.stamps_s[i]:.9f} s)")
        if self.stamps_ns is not None:
            self.stamps_ns = np.asarray(self.stamps_ns, dtype=np.int64)
            if self.stamps_ns.shape != self.stamps_s.shape:
                raise TrajectoryError(f"a trajectory needs as many ns stamps as poses; got "
                                      f"{self.stamps_ns.shape} for {n}")

    def range_ns(self) -> tuple[int, int]:
        """(first, last) stamp in integer ns: exact when known, else rounded from seconds."""
        if self.stamps_ns is not None:
            return int(self.stamps_ns[0]), int(self.stamps_ns[-1])
        return round(float(self.stamps_s[0]) * 1e9), round(float(self.stamps_s[-1]) * 1e9)

    def __len__(self) -> int:
        return int(self.stamps_s.shape[0])

    def positions(self) -> np.ndarray:
        """(N, 3) sensor positions in the world frame."""
        return self.poses[:, :3, 3].copy()

    def path_length_m(self) -> float:
        """Travelled distance: the sum of straight segments between consecutive positions."""
        return float(np.linalg.norm(np.diff(self.poses[:, :3, 3], axis=0), axis=1).sum())

    def interpolate_poses(self, stamps_s) -> np.ndarray:
        """(M, 4, 4) poses at any stamps inside the covered range (unsorted and repeated ok).

        Deskewing needs this form: per-point times are neither sorted nor unique.
        """
        query = np.atleast_1d(np.asarray(stamps_s, dtype=np.float64))
        if query.ndim != 1:
            raise TrajectoryError(f"interpolation stamps must be 1-D, got shape {query.shape}")
        if len(self) == 0:
            raise TrajectoryError("cannot interpolate an empty trajectory")
        t0, t1 = self.stamps_s[0], self.stamps_s[-1]
        outside = np.flatnonzero(~((query >= t0) & (query <= t1)))
        if outside.size:
            bad = query[outside[0]]
            raise TrajectoryError(
                f"stamp {bad:.9f} s (index {int(outside[0])}) is outside the trajectory's "
                f"range {t0:.9f}..{t1:.9f} s; poses are only interpolated, never extrapolated")
        if len(self) == 1:
            return np.repeat(self.poses, query.shape[0], axis=0)
        i = np.clip(np.searchsorted(self.stamps_s, query, side="right") - 1, 0, len(self) - 2)
        alpha = (query - self.stamps_s[i]) / (self.stamps_s[i + 1] - self.stamps_s[i])
        return interpolate_se3(self.poses[i], self.poses[i + 1], alpha)

    def interpolate(self, stamps_s) -> Trajectory:
        """The trajectory resampled at strictly increasing stamps inside the covered range."""
        stamps = np.atleast_1d(np.asarray(stamps_s, dtype=np.float64))
        return Trajectory(stamps, self.interpolate_poses(stamps))


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of every non-blank, non-comment line; text errors name the file."""
    path = Path(path)
    if not path.exists():
        raise TrajectoryError(f"{path}: trajectory file not found")
    if not path.is_file():
        raise TrajectoryError(f"{path}: is not a file (expected a TUM or KITTI trajectory)")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise TrajectoryError(
            f"{path}: is not a text trajectory file (byte {exc.start} is not UTF-8); "
            f"expected TUM ({TUM_COLUMNS}) or KITTI (12 numbers per line)") from None
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot be read ({exc.strerror})") from None
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.append((number, stripped.split()))
    if not rows:
        raise TrajectoryError(f"{path}: contains no poses (only blank or # comment lines)")
    return rows


def _numbers(path: Path, rows: list[tuple[int, list[str]]], columns: int,
             layout: str) -> np.ndarray:
    """The rows as an (N, columns) float array; names the first bad line and what is wrong."""
    for number, tokens in rows:
        if len(tokens) != columns:
            hint = " (columns are separated by spaces, not commas)" if "," in tokens[0] else ""
            raise TrajectoryError(
                f"{path}: line {number} has {len(tokens)} column{'s' * (len(tokens) != 1)}, "
                f"{layout}{hint}")
    try:
        values = np.array([tokens for _, tokens in rows], dtype=np.float64)
    except ValueError:
        for number, tokens in rows:
            for token in tokens:
                try:
                    float(token)
                except ValueError:
                    raise TrajectoryError(
                        f"{path}: line {number}: {token!r} is not a number") from None
        raise
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise TrajectoryError(f"{path}: line {rows[bad[0]][0]} contains NaN or inf")
    return values


def _check_stamps(path: Path, rows, stamps_s: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(stamps_s) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise TrajectoryError(
            f"{path}: line {rows[i][0]} has stamp {stamps_s[i]:.9f} s, not after the previous "
            f"line's {stamps_s[i - 1]:.9f} s; stamps must be strictly increasing")


def read_tum(path) -> Trajectory:
    """A TUM file: exactly 8 columns `t x y z qx qy qz qw`; # comments and blank lines ok."""
    path = Path(path)
    rows = _data_lines(path)
    values = _numbers(path, rows, 8, f"TUM needs 8: {TUM_COLUMNS}")
    norms = np.linalg.norm(values[:, 4:8], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        i = int(bad[0])
        raise TrajectoryError(
            f"{path}: line {rows[i][0]} has a quaternion of norm {norms[i]:.6g}, not 1; "
            f"TUM columns are {TUM_COLUMNS}")
    _check_stamps(path, rows, values[:, 0])
    return Trajectory(values[:, 0], se3_from_tq(values[:, 1:4], values[:, 4:8]),
                      _stamps_ns(path, rows))


def _stamps_ns(path: Path, rows: list[tuple[int, list[str]]]) -> np.ndarray | None:
    """The first column's stamps in integer ns, exactly from their decimal text; None when one
    does not fit in int64 ns (the seconds then stand alone)."""
    try:
        stamps = [int(Decimal(tokens[0]).scaleb(9).to_integral_value()) for _, tokens in rows]
        ns = np.array(stamps, dtype=np.int64)
    except (InvalidOperation, OverflowError):
        return None
    return ns if (np.diff(ns) > 0).all() else None


def _stamp_text(traj: Trajectory) -> list[str]:
    """'%.9f' stamps; integer-ns ones exactly, not through a float."""
    if traj.stamps_ns is None:
        return [f"{t:.9f}" for t in traj.stamps_s]
    return [format_stamp(int(t)) for t in traj.stamps_ns]


def _tum_text(traj: Trajectory) -> str:
    rows = np.column_stack((traj.positions(), rot_to_quat(traj.poses[:, :3, :3])))
    return f"# {TUM_COLUMNS}\n" + "".join(
        stamp + " " + " ".join(f"{v:.9f}" for v in row) + "\n"
        for stamp, row in zip(_stamp_text(traj), rows, strict=True))


def write_tum(path, traj: Trajectory) -> None:
    """Write `t x y z qx qy qz qw` rows, all '%.9f' (ns, nm, 1e-9 rad), atomically."""
    text = _tum_text(traj)
    with atomic_open(Path(path), "w") as f:
        f.write(text)


def read_kitti(path, stamps_s=None) -> Trajectory:
    """A KITTI pose file (12 numbers per line, row-major 3x4); stamps 0..N-1 s unless given."""
    path = Path(path)
    rows = _data_lines(path)
    values = _numbers(path, rows, 12, "KITTI needs 12: the row-major 3x4 pose [R|t]")
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = values.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    R = poses[:, :3, :3]
    error = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > _ROTATION_TOL) | (np.linalg.det(R) <= 0))
    if bad.size:
        raise TrajectoryError(
            f"{path}: line {rows[bad[0]][0]} is not a rigid pose (its 3x3 part is not a "
            f"rotation); KITTI rows are r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz")
    if stamps_s is None:
        stamps = np.arange(len(rows), dtype=np.float64)
    else:
        stamps = np.asarray(stamps_s, dtype=np.float64)
        if stamps.shape != (len(rows),):
            raise TrajectoryError(
                f"{path}: has {len(rows)} poses but {stamps.size} stamps were given")
    return Trajectory(stamps, poses)


def write_kitti(path, traj: Trajectory) -> None:
    """Write the 12 numbers of each row-major 3x4 pose ('%.9f'), atomically; stamps are lost."""
    rows = traj.poses[:, :3, :].reshape(-1, 12)
    text = "".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in rows)
    with atomic_open(Path(path), "w") as f:
        f.write(text)


def detect_format(path) -> str:
    """'tum' or 'kitti' from the column count of the first data line."""
    path = Path(path)
    number, tokens = _data_lines(path)[0]
    if len(tokens) == 8:
        return "tum"
    if len(tokens) == 12:
        return "kitti"
    raise TrajectoryError(
        f"{path}: line {number} has {len(tokens)} columns; a trajectory needs 8 "
        f"(TUM: {TUM_COLUMNS}) or 12 (KITTI: row-major 3x4 pose)")


def read_trajectory(path, fmt: str = "auto") -> Trajectory:
    """Read a TUM or KITTI file; `auto` decides by the number of columns."""
    if fmt not in FORMATS:
        raise TrajectoryError(f"unknown trajectory format {fmt!r}; use one of {', '.join(FORMATS)}")
    if fmt == "auto":
        fmt = detect_format(path)
    return read_tum(path) if fmt == "tum" else read_kitti(path)
