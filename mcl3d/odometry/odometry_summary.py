"""What an odometry run reports: the typed summary behind odometry_summary.json and the CLI's
table, and its accuracy against the log's ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from mcl3d.core.errors import Mcl3dError
from mcl3d.evaluation.metrics import Evaluation, evaluate
from mcl3d.io.logs.faults import LogFaults
from mcl3d.io.trajectory import Trajectory

RPE_DELTA_M = 1.0  # RPE pose pairs this far apart along the path


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

    def as_dict(self) -> dict:
        return {"scans": self.scans, "interrupted": self.interrupted,
                "keyframes": self.keyframes, "path_length_m": self.path_length_m,
                "ms_per_frame": self.ms_per_frame.as_dict(),
                "degenerate_frames": self.degenerate_frames, "notes": self.notes,
                "warnings": self.warnings, "num_warnings": self.num_warnings,
                "evaluation": evaluation_entry(self.accuracy, self.accuracy_error),
                "faults": self.faults.as_dict()}


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
            ("degenerate frames", str(s.degenerate_frames))]
    if s.accuracy is not None:
        ev = s.accuracy.evaluation
        rows.append(("ATE (first pose aligned)",
                     f"{ev.ate.translation_m.rmse:.3f} m RMSE, "
                     f"{ev.ate.rotation_deg.rmse:.2f} deg RMSE"))
        rows.append(("RPE per 1 m", f"{ev.rpe.translation_m.mean:.3f} m, "
                                    f"{ev.rpe.rotation_deg.mean:.2f} deg"))
        if s.accuracy.drift_percent is not None:
            rows.append(("end-point drift", f"{s.accuracy.drift_percent:.2f} % of "
                                            f"{s.accuracy.gt_path_length_m:.1f} m"))
    rows.append(("outputs", str(output_dir)))
    return rows
