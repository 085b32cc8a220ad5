"""The end-of-run summary of `localize`: one typed `LocalizeSummary`, written as
summary.json and shown as the CLI's table (`summary_rows`)."""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core import geometry
from mcl3d.evaluation.metrics import evaluate
from mcl3d.evaluation.run_plots import LOCALIZE_PICTURE
from mcl3d.io.logs.faults import LogFaults
from mcl3d.io.trajectory import Trajectory
from mcl3d.localization.state import STAGES, FilterState, ScanRecord

OPTIONAL_KEYS = ("ate_all", "ate_after_convergence", "ate_rmse_m_evo")  # only with ground truth


@dataclass(frozen=True)
class GroundTruthErrors:
    """Errors of estimated poses against the ground truth at the same stamps."""

    translation_rmse_m: float
    translation_max_m: float
    rotation_rmse_deg: float
    rotation_max_deg: float
    poses: int


@dataclass
class LocalizeSummary:
    scans: int
    skipped_scans: int
    interrupted: bool
    backend: str
    device: str
    motion_source: str
    particles: int
    points: int
    init: str  # global | pose | gt
    height_band_m: list[float] | None  # the band global init used, when auto
    converged_at_scan: int | None
    converged_after_s: float | None
    converged_fraction: float
    final_state: str
    ms_per_update: dict[str, float]  # warm mean per stage, and "total"
    warnings: list[str]
    ate_all: GroundTruthErrors | None = None
    ate_after_convergence: GroundTruthErrors | None = None
    ate_rmse_m_evo: float | None = None  # ATE as evo computes it, a cross-check
    faults: LogFaults = field(default_factory=LogFaults)  # the log's messages dropped
    preset: str = "default"  # the --preset the settings started from
    claim_checks: dict = field(default_factory=dict)  # convergence checks: runs, ms, withheld

    def to_json(self) -> dict:
        """summary.json's content: the fields, without the ground-truth ones when absent."""
        d = {**asdict(self), "faults": self.faults.as_dict()}
        for key in OPTIONAL_KEYS:
            if d[key] is None:
                del d[key]
        return d


def _errors(ref: np.ndarray, est: np.ndarray) -> GroundTruthErrors:
    d = np.linalg.norm(ref[:, :3, 3] - est[:, :3, 3], axis=1)
    ang = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    return GroundTruthErrors(translation_rmse_m=float(np.sqrt(np.mean(d**2))),
                      translation_max_m=float(d.max()),
                      rotation_rmse_deg=float(np.sqrt(np.mean(ang**2))),
                      rotation_max_deg=float(ang.max()), poses=len(d))


def summarize(res: list[ScanRecord], summary: LocalizeSummary, gt) -> None:
    """Add the errors against the ground truth `gt` (stamps ns, poses) to `summary`: over all
    scans, and from the scan the filter converged on."""
    if gt is None or len(res) < 2:
        return
    stamps = np.array([r.stamp_s for r in res])
    gt_traj = Trajectory(gt[0] * 1e-9, gt[1])
    est = Trajectory(stamps, np.stack([r.T_map_lidar for r in res]))
    inside = (stamps >= gt_traj.stamps_s[0]) & (stamps <= gt_traj.stamps_s[-1])
    if inside.sum() < 2:
        return
    ref = Trajectory(stamps[inside], gt_traj.interpolate_poses(stamps[inside]))
    summary.ate_all = _errors(ref.poses, est.poses[inside])
    conv = summary.converged_at_scan
    start = conv if conv is not None else len(res)
    after = inside & (np.arange(len(res)) >= start)
    if after.sum() >= 1:
        summary.ate_after_convergence = _errors(ref.poses[after[inside]], est.poses[after])
    with contextlib.suppress(Exception):
        summary.ate_rmse_m_evo = float(
            evaluate(ref, Trajectory(stamps[inside], est.poses[inside]),
                     max_diff_s=1e-3).ate.translation_m.rmse)


def convergence(res: list[ScanRecord]) -> tuple[int | None, float | None, float]:
    """(first converged scan, seconds after the first scan, share of converged scans)."""
    states = [r.state for r in res]
    conv = next((i for i, s in enumerate(states) if s == FilterState.CONVERGED), None)
    after_s = None if conv is None else float(res[conv].stamp_s - res[0].stamp_s)
    return conv, after_s, float(np.mean([s == FilterState.CONVERGED for s in states]))


def stage_means(res: list[ScanRecord]) -> dict[str, float]:
    """Mean ms per stage and in total, warm: the first update also compiles the kernels."""
    warm = res[1:] or res
    stages = {s: float(np.mean([r.timings_ms[s] for r in warm])) for s in STAGES}
    return {**stages, "total": float(sum(stages.values()))}


def summary_rows(s: LocalizeSummary, out_dir) -> list[tuple[str, str]]:
    """Rows of the end-of-run summary table (what `mcl3d localize` and the demo print)."""
    rows = [("scans", f"{s.scans} ({s.skipped_scans} skipped)"),
            ("backend", f"{s.backend} ({s.device})"),
            ("particles x points", f"{s.particles:,} x {s.points}"),
            ("init / motion", f"{s.init} / {s.motion_source}"),
            ("converged", "never" if s.converged_at_scan is None else
             f"at scan {s.converged_at_scan} ({s.converged_after_s:.1f} s)"),
            ("final state", s.final_state)]
    for e, label in ((s.ate_all, "ATE all scans"),
                     (s.ate_after_convergence, "ATE after convergence")):
        if e is not None:
            rows.append((label, f"{e.translation_rmse_m:.3f} m RMSE (max "
                                f"{e.translation_max_m:.3f}), {e.rotation_rmse_deg:.2f} "
                                f"deg RMSE (max {e.rotation_max_deg:.2f})"))
    checks = s.claim_checks
    if checks.get("runs"):
        rows.append(("convergence checks", f"{checks['runs']} ({checks['ms_per_run']:.0f} ms "
                                           f"each), {checks['withheld']} claims withheld"))
    ms = s.ms_per_update
    rows.append(("ms per update (warm)", f"{ms['total']:.1f} = " + " + ".join(
        f"{k} {v:.1f}" for k, v in ms.items() if k != "total")))
    rows.append(("outputs", str(out_dir)))
    rows.append(("picture", str(Path(out_dir) / LOCALIZE_PICTURE)))
    return rows
