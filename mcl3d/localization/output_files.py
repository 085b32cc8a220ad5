"""The files a `localize` run writes: trajectory (TUM + KITTI), the per-scan CSV, the
effective config, summary.json and a picture of the run, each atomically."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from mcl3d.core import geometry
from mcl3d.core.checkpoint import write_checkpoint_summary
from mcl3d.core.config import Section, save
from mcl3d.core.outputs import atomic_open, check_writable
from mcl3d.evaluation.run_plots import LOCALIZE_PICTURE, localize_figure, write_png
from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum
from mcl3d.localization.localization_summary import LocalizeSummary
from mcl3d.localization.state import STAGES, ScanRecord

OUTPUT_FILES = {"tum": "trajectory.tum", "kitti": "trajectory.kitti", "csv": "scans.csv",
                "config": "config.yaml", "summary": "summary.json", "picture": LOCALIZE_PICTURE}
CSV_HEADER = ("stamp_s,x,y,z,qx,qy,qz,qw,var_rx,var_ry,var_rz,var_x,var_y,var_z,ess,"
              "n_particles,state,hypotheses,places,match_ratio,mean_log_likelihood,n_points,resampled,"
              "reseeded,motion," + ",".join(f"ms_{s}" for s in STAGES) + ",ms_total")


def output_paths(out_dir: Path) -> dict[str, Path]:
    return {k: Path(out_dir) / name for k, name in OUTPUT_FILES.items()}


def check_outputs(out_dir: Path, force: bool, result_mcap: Path | None) -> dict[str, Path]:
    """The output paths, after checking that none would be overwritten unasked."""
    paths = output_paths(out_dir)
    for p in paths.values():
        check_writable(p, force)
    if result_mcap is not None:
        check_writable(Path(result_mcap), force)
    return paths


def _csv_row(r: ScanRecord, motion: str) -> str:
    t, q = geometry.tq_from_se3(r.T_map_lidar)
    ms = [r.timings_ms[s] for s in STAGES]
    row = [f"{r.stamp_s:.9f}", *(f"{v:.6f}" for v in t), *(f"{v:.7f}" for v in q),
           *(f"{v:.3e}" for v in r.variances), f"{r.ess:.1f}",
           str(r.n_particles), r.state.value, str(len(r.hypotheses)), str(r.places),
           f"{r.match_ratio:.4f}",
           f"{r.mean_log_likelihood:.4f}", str(r.n_points), str(int(r.resampled)),
           r.reseeded or "-", motion, *(f"{v:.2f}" for v in ms), f"{sum(ms):.2f}"]
    return ",".join(row)


def write_outputs(paths: dict[str, Path], results: list[ScanRecord],
                  motion_kinds: list[str], summary: LocalizeSummary, cfg: Section,
                  stamps_ns: list[int] | None = None, map_points: np.ndarray | None = None,
                  gt: Trajectory | None = None, map_cell_m: float = 0.0) -> None:
    """Every output; `stamps_ns` are the results' exact stamps, for the trajectory files;
    `map_points` (map frame, `map_cell_m` apart) and the ground truth `gt` go into the
    picture."""
    poses = np.stack([r.T_map_lidar for r in results])
    traj = (Trajectory(np.array([r.stamp_s for r in results]), poses) if stamps_ns is None
            else Trajectory.from_ns(stamps_ns, poses))
    write_tum(paths["tum"], traj)
    write_kitti(paths["kitti"], traj)
    with atomic_open(paths["csv"]) as f:
        f.write(CSV_HEADER + "\n")
        for r, motion in zip(results, motion_kinds, strict=True):
            f.write(_csv_row(r, motion) + "\n")
    save(cfg, paths["config"])
    with atomic_open(paths["summary"]) as f:
        json.dump(summary.to_json(), f, indent=2, default=_json_default)
    points = np.zeros((0, 3)) if map_points is None else map_points
    write_png(paths["picture"], localize_figure(results, points, gt, map_cell_m))


def write_checkpoint(paths: dict[str, Path], out) -> None:
    """The trajectory so far of a run under way (`out`: its `LocalizeResult`) and the cheap
    part of its summary, marked as a checkpoint; the final outputs replace them."""
    if not out.results:
        return
    traj = Trajectory.from_ns(out.stamps_ns, np.stack([r.T_map_lidar for r in out.results]))
    write_tum(paths["tum"], traj)
    write_kitti(paths["kitti"], traj)
    write_checkpoint_summary(paths["summary"], {
        "scans": len(out.results), "skipped_scans": out.skipped_scans,
        "motion_source": out.motion_source, "final_state": out.results[-1].state.value,
        "warnings": out.warnings, "faults": out.faults.as_dict()})


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    raise TypeError(f"not JSON serializable: {type(value)}")
