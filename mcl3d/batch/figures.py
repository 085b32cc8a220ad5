"""A batch run's key figures: the numbers its row holds, taken from the summary JSON its
command wrote (and, where the summary lacks one, from its trajectory and the log's ground
truth). Keys carry their units; a figure that needs ground truth is None without it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mcl3d.batch.manifest import SuccessCriterion
from mcl3d.core import geometry
from mcl3d.core.errors import Mcl3dError
from mcl3d.io.trajectory import Trajectory

RPE_DELTA_M = 1.0  # as the odometry summary's RPE: pose pairs 1 m apart along the path


def _read(folder: Path, name: str) -> dict:
    return json.loads((Path(folder) / name).read_text())


def _get(entry: dict | None, *keys: str):
    """entry[k1][k2]...; None when any level is missing (no ground truth, an error)."""
    for key in keys:
        if not isinstance(entry, dict) or key not in entry:
            return None
        entry = entry[key]
    return entry


def localize(folder: Path, result, success: SuccessCriterion) -> dict:
    """Convergence, ATE and success (the last scans within tolerance of the truth)."""
    s = _read(folder, "summary.json")
    final_m, final_deg, ok = _tail_check(result, success)
    return {"scans": s["scans"], "converged": s["converged_at_scan"] is not None,
            "converged_at_scan": s["converged_at_scan"],
            "converged_after_s": s["converged_after_s"], "final_state": s["final_state"],
            "success": ok, "final_error_m": final_m, "final_error_deg": final_deg,
            "ate_m": _get(s, "ate_all", "translation_rmse_m"),
            "ate_after_convergence_m": _get(s, "ate_after_convergence", "translation_rmse_m"),
            "ms_per_scan": s["ms_per_update"]["total"]}


def _tail_check(result, success: SuccessCriterion
                ) -> tuple[float | None, float | None, bool | None]:
    """(final error m, final error deg, every one of the last scans within tolerance), all
    None without ground truth covering the scans."""
    if result.gt is None:
        return None, None, None
    gt = Trajectory.from_ns(*result.gt)
    stamps = np.array(result.stamps_ns) * 1e-9
    inside = (stamps >= gt.stamps_s[0]) & (stamps <= gt.stamps_s[-1])
    if not inside.any():
        return None, None, None
    est = np.stack([r.T_map_lidar for r in result.results])[inside]
    ref = gt.interpolate_poses(stamps[inside])
    d = np.linalg.norm(ref[:, :3, 3] - est[:, :3, 3], axis=1)
    a = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    good = (d < success.tolerance_m) & (a < success.tolerance_deg)
    ok = bool(len(good) >= success.tail_scans and good[-success.tail_scans:].all())
    return float(d[-1]), float(a[-1]), ok


def odometry(folder: Path) -> dict:
    s = _read(folder, "odometry_summary.json")
    ev = s["evaluation"]
    return {"scans": s["scans"], "keyframes": s["keyframes"],
            "path_length_m": s["path_length_m"], "ms_per_scan": s["ms_per_frame"]["median"],
            "ate_m": _get(ev, "ate", "translation_m", "rmse"),
            "rpe_m": _get(ev, "rpe", "translation_m", "mean"),
            "drift_percent": _get(ev, "drift_percent")}


def slam(folder: Path, log: Path, gt_topic: str | None) -> dict:
    """ATE of SLAM, of its online estimate and of its odometry front-end (SE(3)-aligned, as
    the summary), the RPE per metre of the SLAM trajectory (the summary has none), the loop
    corrections and the share of scans with the truth inside the cloud's 95% region."""
    s = _read(folder, "slam_summary.json")
    ev, loops = s["evaluation"], s["loops"]
    return {"scans": s["scans"], "keyframes": s["keyframes"],
            "path_length_m": s["path_length_m"], "ms_per_scan": s["ms_per_frame"]["median"],
            "ate_m": _get(ev, "slam", "ate_m"), "ate_online_m": _get(ev, "online", "ate_m"),
            "ate_odometry_m": _get(ev, "odometry", "ate_m"),
            "rpe_m": _slam_rpe_m(Path(folder) / "slam.tum", log, gt_topic)
            if _get(ev, "slam") is not None else None,
            "loops_accepted": _get(loops, "accepted"), "loops_wrong": _get(loops, "wrong"),
            "consistency_95": _get(s, "consistency", "fraction_95"),
            "final_hypotheses": s["final_hypotheses"]}


def _slam_rpe_m(tum: Path, log: Path, gt_topic: str | None) -> float | None:
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import read_tum

    with LogReader(log, gt_topic=gt_topic) as reader:
        gt = Trajectory.from_ns(*reader.ground_truth())
    try:
        ev = evaluate(gt, read_tum(tum), alignment="se3", rpe_delta=RPE_DELTA_M, rpe_unit="m")
    except Mcl3dError:  # too short a path for one RPE pair, stamps that do not associate
        return None
    rpe_m = float(ev.rpe.translation_m.mean)
    return rpe_m if np.isfinite(rpe_m) else None


def build_map(result) -> dict:
    return {"scans": result.n_scans, "points": result.n_points,
            "map_bytes": result.stats.file_bytes, "build_s": result.seconds}
