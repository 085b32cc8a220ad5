"""What an odometry run reports: the typed summary behind odometry_summary.json and the CLI's
table, its warnings (a stretch of degenerate scans as one), and its accuracy against the log's
ground truth."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from mcl3d.core.errors import Mcl3dError, TrajectoryError
from mcl3d.evaluation.metrics import Evaluation, evaluate
from mcl3d.io.logs.faults import LogFaults
from mcl3d.io.trajectory import Trajectory
from mcl3d.odometry.lidar_odometry import OdometryFrame

RPE_DELTA_M = 1.0  # RPE pose pairs this far apart along the path
DEGENERATE = "degenerate "  # how lidar_odometry.degeneracy's warnings start


@dataclass(frozen=True)
class FrameTimesMs:
    """Wall time per frame (ms) over a run."""

    mean: float
    median: float
    max: float

    @classmethod
    def of(cls, ms: np.ndarray) -> FrameTimesMs:
        return cls(mean=float(ms.mean()), median=float(np.median(ms)), max=float(ms.max()))

    def as_dict(self) -> dict[str, float]:
        return {"mean": self.mean, "median": self.median, "max": self.max}


@dataclass(frozen=True)
class OdometryAccuracy:
    """ATE and RPE per metre after aligning the first poses, and the end-point drift."""

    evaluation: Evaluation
    drift_percent: float | None  # end-point error over the ground truth's path length
    gt_path_length_m: float

    def as_dict(self) -> dict:
        return {**self.evaluation.as_dict(), "drift_percent": self.drift_percent,
                "gt_path_length_m": self.gt_path_length_m}


@dataclass(frozen=True)
class DegenerateStretch:
    """Consecutive scans degenerate in the same block ("translation" or "rotation");
    `detail` is the first scan's warning (the score and the direction)."""

    block: str
    first_scan: int
    last_scan: int
    first_stamp_ns: int
    last_stamp_ns: int
    detail: str

    @property
    def scans(self) -> int:
        return self.last_scan - self.first_scan + 1

    def warning(self) -> str:
        if self.scans == 1:
            return f"scan {self.first_scan} ({self.first_stamp_ns * 1e-9:.3f} s): {self.detail}"
        return (f"scans {self.first_scan} to {self.last_scan} ({self.first_stamp_ns * 1e-9:.3f}"
                f" to {self.last_stamp_ns * 1e-9:.3f} s, {self.scans} scans): {self.detail} "
                "at the first")

    def as_dict(self) -> dict:
        return {"block": self.block, "first_scan": self.first_scan,
                "last_scan": self.last_scan, "scans": self.scans,
                "first_stamp_ns": self.first_stamp_ns, "last_stamp_ns": self.last_stamp_ns,
                "detail": self.detail}


def run_warnings(frames: Sequence[OdometryFrame]
                 ) -> tuple[list[str], list[DegenerateStretch]]:
    """The run's warnings in scan order, each naming its scan, and its degenerate stretches:
    a corridor degenerates scan after scan, and one warning per stretch keeps the others
    visible."""
    listed: list[tuple[int, str]] = []
    stretches: list[DegenerateStretch] = []
    open_: dict[str, tuple[int, str]] = {}  # block -> (first scan, its warning)

    def close(block: str, last: int) -> None:
        first, detail = open_.pop(block)
        stretch = DegenerateStretch(block, first, last, frames[first].stamp_ns,
                                    frames[last].stamp_ns, detail)
        stretches.append(stretch)
        listed.append((first, stretch.warning()))

    for i, frame in enumerate(frames):
        blocks = {}
        for w in frame.warnings:
            if w.startswith(DEGENERATE):
                blocks[w[len(DEGENERATE):].split(":")[0]] = w
            else:
                listed.append((i, f"scan {i} ({frame.stamp_ns * 1e-9:.3f} s): {w}"))
        for block in [b for b in open_ if b not in blocks]:
            close(block, i - 1)
        for block, w in blocks.items():
            open_.setdefault(block, (i, w))
    for block in list(open_):
        close(block, len(frames) - 1)
    listed.sort(key=lambda item: item[0])  # stable: a scan's own order kept
    stretches.sort(key=lambda st: st.first_scan)
    return [w for _, w in listed], stretches


@dataclass(frozen=True)
class OdometrySummary:
    """One run in numbers; `as_dict` is odometry_summary.json."""

    scans: int
    interrupted: bool
    keyframes: int
    path_length_m: float
    ms_per_frame: FrameTimesMs  # the first frame (kernel compilation) left out
    degenerate_frames: int
    notes: list[str]
    warnings: list[str]  # the first ones, each naming its scan
    num_warnings: int
    accuracy: OdometryAccuracy | None  # None without ground truth
    accuracy_error: str | None = None  # why the accuracy could not be computed
    faults: LogFaults = field(default_factory=LogFaults)  # the log's messages dropped
    degenerate_stretches: list[DegenerateStretch] = field(default_factory=list)
    redeskewed_frames: int = 0  # deskewed with the registered motion and registered again

    def as_dict(self) -> dict:
        return {"scans": self.scans, "interrupted": self.interrupted,
                "keyframes": self.keyframes, "path_length_m": self.path_length_m,
                "ms_per_frame": self.ms_per_frame.as_dict(),
                "degenerate_frames": self.degenerate_frames,
                "redeskewed_frames": self.redeskewed_frames, "notes": self.notes,
                "warnings": self.warnings, "num_warnings": self.num_warnings,
                "evaluation": evaluation_entry(self.accuracy, self.accuracy_error),
                "faults": self.faults.as_dict(),
                "degenerate_stretches": [st.as_dict() for st in self.degenerate_stretches]}


class Accuracy(Protocol):
    """A pipeline's accuracy against ground truth, as JSON-ready numbers."""

    def as_dict(self) -> dict: ...


def evaluation_entry(accuracy: Accuracy | None, error: str | None) -> dict | None:
    """A summary's "evaluation": the accuracy's numbers, {"error": why} when it could not be
    computed, None without ground truth."""
    if error is not None:
        return {"error": error}
    return None if accuracy is None else accuracy.as_dict()


def evaluate_odometry(est: Trajectory, gt: Trajectory | None
                      ) -> tuple[OdometryAccuracy | None, str | None]:
    """(accuracy, None), or (None, why not) when the trajectories do not associate; (None,
    None) without ground truth or with fewer than two poses."""
    if gt is None or len(est) < 2:
        return None, None
    try:
        ev = evaluate(gt, est, alignment="origin", rpe_delta=RPE_DELTA_M, rpe_unit="m")
    except TrajectoryError as exc:
        if exc.setting != "rpe_delta":
            return None, str(exc)
        # a path shorter than RPE_DELTA_M has no pairs 1 m apart: RPE per frame, ATE kept
        ev = evaluate(gt, est, alignment="origin", rpe_delta=1, rpe_unit="frames")
    except Mcl3dError as exc:
        return None, str(exc)
    ref, aligned = ev.association.ref_poses, ev.est_aligned_poses
    length = Trajectory(ev.association.est_stamps_s, ref).path_length_m()
    end_error = float(np.linalg.norm(ref[-1, :3, 3] - aligned[-1, :3, 3]))
    return OdometryAccuracy(ev, 100.0 * end_error / length if length > 0 else None, length), None


def summary_rows(summary: OdometrySummary, backend: str, output_dir: Path
                 ) -> list[tuple[str, str]]:
    """The rows (what, value) of the end-of-run table; `backend` says what ran it."""
    s, ms = summary, summary.ms_per_frame
    rows = [("scans", f"{s.scans} ({s.keyframes} keyframes)"), ("backend", backend),
            ("path length", f"{s.path_length_m:.2f} m"),
            ("ms per frame", f"{ms.mean:.1f} mean, {ms.median:.1f} median"),
            ("degenerate frames", str(s.degenerate_frames)),
            ("deskewed again", f"{s.redeskewed_frames} scans (registered motion off the "
                               "predicted)")]
    if s.accuracy is not None:
        ev = s.accuracy.evaluation
        rows.append(("ATE (first pose aligned)",
                     f"{ev.ate.translation_m.rmse:.3f} m RMSE, "
                     f"{ev.ate.rotation_deg.rmse:.2f} deg RMSE"))
        rows.append((f"RPE per {ev.rpe.delta:g} {ev.rpe.unit}",
                     f"{ev.rpe.translation_m.mean:.3f} m, {ev.rpe.rotation_deg.mean:.2f} deg"))
        if s.accuracy.drift_percent is not None:
            rows.append(("end-point drift", f"{s.accuracy.drift_percent:.2f} % of "
                                            f"{s.accuracy.gt_path_length_m:.1f} m"))
    rows.append(("outputs", str(output_dir)))
    return rows
