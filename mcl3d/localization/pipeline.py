"""`mcl3d localize`: run the particle filter over a log against a TSDF map.

run() reads as its steps: check outputs -> load the map -> open the log and choose the motion
source -> initialize the particles -> filter every scan (with timing and progress) -> write
the trajectory (TUM + KITTI), the per-scan CSV, the effective config and optionally a
result MCAP -> summary (convergence, ATE against ground truth, ms per stage).
"""

from __future__ import annotations

import contextlib
import math
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import Field

from mcl3d.core import geometry
from mcl3d.core.config import Section
from mcl3d.core.errors import InputError, RunInterrupted, TopicError
from mcl3d.core.outputs import atomic_open, check_writable, output_folder
from mcl3d.localization.localizer import STAGES, EmptyScan, LocalizationResult, LocalizerConfig
from mcl3d.localization.motion_source import MotionSource, MotionSourceConfig

OUTPUT_FILES = {"tum": "trajectory.tum", "kitti": "trajectory.kitti", "csv": "scans.csv",
                "config": "config.yaml", "summary": "summary.json"}
NO_OVERLAP_SCANS = 10  # global init: give up when no scan matched the map by then
NO_OVERLAP_MATCH = 0.05


class LocalizeConfig(Section):
    """Everything `mcl3d localize` uses; saved as config.yaml beside the outputs."""

    localizer: LocalizerConfig = LocalizerConfig()
    motion_source: MotionSourceConfig = MotionSourceConfig()
    max_scans: int | None = Field(None, ge=1, description="stop after this many scans")
    result_particles: int = Field(2000, ge=1, description="particles per result-MCAP message")
    deskew: bool = Field(True, description="deskew scans with per-point times using the "
                                           "motion between scans (constant velocity)")


@dataclass
class Topics:
    points: str | None = None
    imu: str | None = None
    odom: str | None = None
    gt: str | None = None


@dataclass
class LocalizeRun:
    """What a run produced (also the data of the final summary table)."""

    results: list[LocalizationResult] = field(default_factory=list)
    motion_kinds: list[str] = field(default_factory=list)
    skipped_scans: int = 0
    warnings: list[str] = field(default_factory=list)
    motion_source: str = ""
    summary: dict = field(default_factory=dict)
    interrupted: bool = False
    gt: tuple | None = None  # (stamps_ns, T_map_lidar) when the log has ground truth
    height_band_m: list[float] | None = None  # the band global init used, when auto


def output_paths(out_dir: Path) -> dict[str, Path]:
    return {k: Path(out_dir) / name for k, name in OUTPUT_FILES.items()}


def check_outputs(out_dir: Path, force: bool, result_mcap: Path | None) -> dict[str, Path]:
    paths = output_paths(out_dir)
    for p in paths.values():
        check_writable(p, force)
    if result_mcap is not None:
        check_writable(Path(result_mcap), force)
    return paths


# --------------------------------------------------------------------------- setup
def _first_messages(reader, kinds: tuple[str, ...], imu_samples: int) -> dict:
    """The first scan / odometry message and the first `imu_samples` IMU messages."""
    firsts: dict = {"imu": []}
    wanted = {k for k in kinds if reader.topics.get(k)}
    for kind, msg in reader.messages(tuple(wanted)):
        if kind == "imu":
            if len(firsts["imu"]) < imu_samples:
                firsts["imu"].append(msg)
        else:
            firsts.setdefault(kind, msg)
        if all((k == "imu" and len(firsts["imu"]) >= imu_samples) or (k != "imu" and k in firsts)
               for k in wanted):
            break
    return firsts


def _extrinsic(reader, parent: str, child: str, what: str, warnings: list[str]) -> np.ndarray:
    if parent == child:
        return np.eye(4)
    try:
        return reader.static_transform(parent, child)
    except TopicError:
        warnings.append(f"no static transform {parent} -> {child} in the log; assuming the "
                        f"{what} frame equals the lidar frame")
        return np.eye(4)


def make_motion_source(reader, cfg: MotionSourceConfig, firsts: dict, lidar_frame: str,
                       warnings: list[str]) -> MotionSource:
    kind = cfg.source
    has_odom = "odom" in firsts
    has_imu = bool(firsts["imu"])
    if kind == "auto":
        kind = "odom" if has_odom else "imu" if has_imu else "constant_velocity"
        if kind == "constant_velocity":
            warnings.append("the log has no odometry and no IMU: using a constant-velocity "
                            "motion model with extra noise (pass --odom-topic/--imu-topic if "
                            "the log has them under other types)")
    elif kind == "odom" and not has_odom:
        raise TopicError(f"{reader.path}: --motion odom but the log has no odometry messages")
    elif kind == "imu" and not has_imu:
        raise TopicError(f"{reader.path}: --motion imu but the log has no IMU messages")
    T_base_lidar = R_lidar_imu = None
    if kind == "odom":
        T_base_lidar = _extrinsic(reader, firsts["odom"].child_frame_id, lidar_frame, "odometry",
                                  warnings)
    if kind == "imu":
        R_lidar_imu = _extrinsic(reader, lidar_frame, firsts["imu"][0].frame_id, "IMU",
                                 warnings)[:3, :3]
    return MotionSource(kind, cfg, T_base_lidar, R_lidar_imu)


def gravity_in_lidar(reader, firsts: dict, lidar_frame: str, warnings: list[str]):
    """Roll/pitch of the lidar from the first IMU samples, or None without an IMU."""
    from mcl3d.localization.initialization import gravity_roll_pitch

    if not firsts["imu"]:
        return None
    R = _extrinsic(reader, lidar_frame, firsts["imu"][0].frame_id, "IMU", warnings)[:3, :3]
    acc = np.stack([m.linear_acceleration for m in firsts["imu"]]) @ R.T
    return gravity_roll_pitch(acc)


def initial_pose(cfg: LocalizerConfig, gt) -> np.ndarray | None:
    init = cfg.init
    if init.mode == "pose":
        x, y, z, roll, pitch, yaw = init.pose
        return geometry.se3(geometry.rpy_to_rot(roll, pitch, yaw), [x, y, z])
    if init.mode == "gt":
        if gt is None:
            raise TopicError("--init gt needs a ground-truth topic in the log (ground_truth, "
                             "groundtruth or gt); pass --gt-topic or give --init \"x y z r p y\"")
        return gt[1][0]
    return None


# ---------------------------------------------------------------------------- run
def run(log_path: Path, map_path: Path, out_dir: Path, cfg: LocalizeConfig, *,
        topics: Topics | None = None, force: bool = False, result_mcap: Path | None = None,
        backend: str = "cpu", on_progress=None) -> LocalizeRun:
    """Localize every scan of the log; the output folder is removed again if nothing was
    written."""
    from mcl3d.localization.localizer import check_config

    check_config(cfg.localizer)
    with output_folder(out_dir):
        return _run(log_path, map_path, out_dir, cfg, topics, force, result_mcap, backend,
                    on_progress)


def _run(log_path, map_path, out_dir, cfg, topics, force, result_mcap, backend,
         on_progress) -> LocalizeRun:
    from mcl3d.core import runtime
    from mcl3d.maps.io import load_map

    paths = check_outputs(out_dir, force, result_mcap)
    info = runtime.init(backend)
    tsdf = load_map(Path(map_path), f16=False)
    try:
        out = _run_filter(log_path, tsdf, cfg, topics or Topics(), force, result_mcap,
                          on_progress)
    finally:
        tsdf.destroy()  # the map's device memory; the particles are small
    if not out.results:
        if out.interrupted:
            raise RunInterrupted("interrupted before the first scan was localized; nothing "
                                 "written")
        raise InputError(f"{log_path}: no scan could be localized ({out.skipped_scans} scans "
                         f"had fewer than 8 points in the range gate)")
    out.summary = summarize(out, out.gt, cfg, info)
    write_outputs(paths, out, cfg)
    if out.interrupted:
        raise RunInterrupted(f"interrupted after {len(out.results)} scans; the trajectory so far "
                             f"is in {paths['tum']}")
    return out


def _run_filter(log_path: Path, tsdf, cfg: LocalizeConfig, topics: Topics, force: bool,
                result_mcap: Path | None, on_progress) -> LocalizeRun:
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.localization.initialization import auto_band
    from mcl3d.localization.localizer import Localizer

    out = LocalizeRun()
    with LogReader(Path(log_path), points_topic=topics.points, imu_topic=topics.imu,
                   odom_topic=topics.odom, gt_topic=topics.gt) as reader:
        reader.require("points")
        n_scans = reader.count("points")
        gt = reader.ground_truth() if reader.topics.gt else None
        firsts = _first_messages(reader, ("points", "imu", "odom"), cfg.localizer.init.imu_samples)
        if "points" not in firsts:
            raise InputError(f"{log_path}: the point-cloud topic {reader.topics.points} has no "
                             f"messages")
        lidar_frame = firsts["points"].frame_id
        source = make_motion_source(reader, cfg.motion_source, firsts, lidar_frame, out.warnings)
        out.motion_source = source.kind
        roll_pitch = (gravity_in_lidar(reader, firsts, lidar_frame, out.warnings)
                      if cfg.localizer.init.mode == "global" else None)
        loc_cfg = cfg.localizer
        if loc_cfg.init.mode == "global" and loc_cfg.init.height_band_m == "auto":
            band = auto_band(loc_cfg.init, firsts["points"].points, roll_pitch)
            out.height_band_m = band
            loc_cfg = loc_cfg.model_copy(deep=True)
            loc_cfg.init.height_band_m = band
        loc = Localizer(tsdf, loc_cfg, imu_roll_pitch=roll_pitch)
        T0 = initial_pose(cfg.localizer, gt)
        if T0 is None:
            loc.init_global()
        else:
            loc.init_pose(T0, cfg.localizer.init.std)
        total = min(n_scans, cfg.max_scans or n_scans)
        writer_ctx = _result_writer(result_mcap, force)
        with writer_ctx as writer:
            try:
                _filter(reader, loc, source, cfg, out, total, writer, on_progress)
            except KeyboardInterrupt:
                out.interrupted = True
        out.gt = gt
    return out


def _result_writer(path: Path | None, force: bool):
    if path is None:
        return contextlib.nullcontext(None)
    from mcl3d.io.logs.writer import LogWriter

    return LogWriter(Path(path), force=force)


def _filter(reader, loc, source: MotionSource, cfg: LocalizeConfig, out: LocalizeRun,
            total: int, writer, on_progress) -> None:
    pending: deque = deque()
    state = {"prev_ns": None, "done": 0, "best_match": 0.0}
    kinds = ("points", *(k for k in ("odom", "imu") if source.kind == k))
    for kind, msg in reader.messages(kinds):
        if kind == "odom":
            source.add_odometry(msg.stamp_ns, msg.T_frame_child)
        elif kind == "imu":
            source.add_imu(msg.stamp_ns, msg.angular_velocity)
        else:
            pending.append(msg)
        while pending and source.covers(pending[0].stamp_ns):
            if _process(pending.popleft(), loc, source, cfg, out, state, writer, on_progress,
                        total):
                return
    while pending:
        if _process(pending.popleft(), loc, source, cfg, out, state, writer, on_progress, total):
            return


def _process(scan, loc, source: MotionSource, cfg: LocalizeConfig, out: LocalizeRun,
             state: dict, writer, on_progress, total: int) -> bool:
    """Filter one scan; True when the run should stop (max_scans reached)."""
    prev = state["prev_ns"]
    if prev is not None and scan.stamp_ns <= prev:
        out.warnings.append(f"scan at {scan.stamp_ns} ns does not come after the previous "
                            f"one; skipped")
        out.skipped_scans += 1
        return False
    motion = source.motion(prev, scan.stamp_ns) if prev is not None else None
    twist = None
    if motion is not None and cfg.deskew and scan.times_s is not None:
        twist = geometry.se3_log(motion.T_prev_curr) / max((scan.stamp_ns - prev) * 1e-9, 1e-6)
    try:
        result = loc.step(scan.points, None if motion is None else motion.T_prev_curr,
                          scan.stamp_ns * 1e-9, (0.0, 0.0) if motion is None else motion.extra_std,
                          scan.times_s, twist)
    except EmptyScan:
        out.skipped_scans += 1
        return False
    state["prev_ns"] = scan.stamp_ns
    out.results.append(result)
    out.motion_kinds.append("none" if motion is None else motion.kind)
    source.add_estimate(scan.stamp_ns, result.T_map_lidar, result.state == "converged")
    state["best_match"] = max(state["best_match"], result.match_ratio)
    if (cfg.localizer.init.mode == "global" and len(out.results) >= NO_OVERLAP_SCANS
            and state["best_match"] < NO_OVERLAP_MATCH):
        raise InputError(
            f"after {len(out.results)} scans no particle's scan matches the map (best match "
            f"ratio {state['best_match']:.2f}): the map and the log are from different places "
            f"or frames; check --map")
    if writer is not None:
        _write_result(writer, scan, result, loc, cfg)
    if on_progress is not None:
        on_progress(result, len(out.results), total)
    return cfg.max_scans is not None and len(out.results) >= cfg.max_scans


def _write_result(writer, scan, result: LocalizationResult, loc, cfg: LocalizeConfig) -> None:
    from mcl3d.io.logs.messages import PointCloud, PoseStamped

    stamp = scan.stamp_ns
    writer.write_pose("/localization/pose", PoseStamped(stamp, "map", result.T_map_lidar))
    sample = loc.last_sample_positions[:cfg.result_particles]
    writer.write_points("/localization/particles", PointCloud(stamp, "map", sample, None))
    aligned = geometry.transform_points(result.T_map_lidar, scan.points).astype(np.float32)
    writer.write_points("/localization/scan", PointCloud(stamp, "map", aligned, None))


# ------------------------------------------------------------------------ outputs
def summarize(out: LocalizeRun, gt, cfg: LocalizeConfig, info) -> dict:
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.trajectory import Trajectory

    res = out.results
    stamps = np.array([r.stamp_s for r in res])
    states = [r.state for r in res]
    conv = next((i for i, s in enumerate(states) if s == "converged"), None)
    warm = res[1:] or res  # the first update also compiles the kernels (Taichi's JIT)
    stages = {s: float(np.mean([r.timings_ms[s] for r in warm])) for s in STAGES}
    if conv is None and cfg.localizer.init.mode == "global":
        out.warnings.append(
            f"global localization did not converge in {len(res)} scans: the log may be from "
            f"a place the map does not hold (check --map), or the map is ambiguous for this "
            f"stretch of log (try more --particles or a longer log)")
    summary = {
        "scans": len(res), "skipped_scans": out.skipped_scans, "interrupted": out.interrupted,
        "backend": info.backend, "device": info.device, "motion_source": out.motion_source,
        "particles": cfg.localizer.particles, "points": cfg.localizer.sensor.points,
        "init": cfg.localizer.init.mode,
        "height_band_m": out.height_band_m,
        "converged_at_scan": conv,
        "converged_after_s": None if conv is None else float(stamps[conv] - stamps[0]),
        "converged_fraction": float(np.mean([s == "converged" for s in states])),
        "final_state": states[-1],
        "ms_per_update": {**stages, "total": float(sum(stages.values()))},
        "warnings": out.warnings,
    }
    if gt is not None and len(res) >= 2:
        gt_traj = Trajectory(gt[0] * 1e-9, gt[1])
        est = Trajectory(stamps, np.stack([r.T_map_lidar for r in res]))
        inside = (stamps >= gt_traj.stamps_s[0]) & (stamps <= gt_traj.stamps_s[-1])
        if inside.sum() >= 2:
            ref = Trajectory(stamps[inside], gt_traj.interpolate_poses(stamps[inside]))
            errs = _errors(ref.poses, est.poses[inside])
            summary["ate_all"] = errs
            start = conv if conv is not None else len(res)
            after = inside & (np.arange(len(res)) >= start)
            if after.sum() >= 1:
                summary["ate_after_convergence"] = _errors(
                    ref.poses[after[inside]], est.poses[after])
            with contextlib.suppress(Exception):
                summary["ate_rmse_m_evo"] = float(
                    evaluate(ref, Trajectory(stamps[inside], est.poses[inside]),
                             max_diff_s=1e-3).ate.translation_m.rmse)
    return summary


def summary_rows(s: dict, out_dir: Path) -> list[tuple[str, str]]:
    """Rows of the end-of-run summary table (what `mcl3d localize` and the demo print)."""
    rows = [("scans", f"{s['scans']} ({s['skipped_scans']} skipped)"),
            ("backend", f"{s['backend']} ({s['device']})"),
            ("particles x points", f"{s['particles']:,} x {s['points']}"),
            ("init / motion", f"{s['init']} / {s['motion_source']}"),
            ("converged", "never" if s["converged_at_scan"] is None else
             f"at scan {s['converged_at_scan']} ({s['converged_after_s']:.1f} s)"),
            ("final state", s["final_state"])]
    for key, label in (("ate_all", "ATE all scans"),
                       ("ate_after_convergence", "ATE after convergence")):
        if key in s:
            e = s[key]
            rows.append((label, f"{e['translation_rmse_m']:.3f} m RMSE (max "
                                f"{e['translation_max_m']:.3f}), {e['rotation_rmse_deg']:.2f} "
                                f"deg RMSE (max {e['rotation_max_deg']:.2f})"))
    ms = s["ms_per_update"]
    rows.append(("ms per update (warm)", f"{ms['total']:.1f} = " + " + ".join(
        f"{k} {v:.1f}" for k, v in ms.items() if k != "total")))
    rows.append(("outputs", str(out_dir)))
    return rows


def _errors(ref: np.ndarray, est: np.ndarray) -> dict:
    d = np.linalg.norm(ref[:, :3, 3] - est[:, :3, 3], axis=1)
    ang = np.degrees(geometry.rotation_angle(np.swapaxes(ref[:, :3, :3], 1, 2) @ est[:, :3, :3]))
    return {"translation_rmse_m": float(np.sqrt(np.mean(d**2))),
            "translation_max_m": float(d.max()),
            "rotation_rmse_deg": float(np.sqrt(np.mean(ang**2))),
            "rotation_max_deg": float(ang.max()), "poses": len(d)}


CSV_HEADER = ("stamp_s,x,y,z,qx,qy,qz,qw,var_rx,var_ry,var_rz,var_x,var_y,var_z,ess,"
              "n_particles,state,hypotheses,match_ratio,mean_log_likelihood,n_points,resampled,"
              "reseeded,motion," + ",".join(f"ms_{s}" for s in STAGES) + ",ms_total")


def write_outputs(paths: dict[str, Path], out: LocalizeRun, cfg: LocalizeConfig) -> None:
    import json

    from mcl3d.core.config import save
    from mcl3d.io.trajectory import Trajectory, write_kitti, write_tum

    res = out.results
    traj = Trajectory(np.array([r.stamp_s for r in res]), np.stack([r.T_map_lidar for r in res]))
    write_tum(paths["tum"], traj)
    write_kitti(paths["kitti"], traj)
    with atomic_open(paths["csv"]) as f:
        f.write(CSV_HEADER + "\n")
        for r, motion in zip(res, out.motion_kinds, strict=True):
            t, q = geometry.tq_from_se3(r.T_map_lidar)
            ms = [r.timings_ms[s] for s in STAGES]
            row = [f"{r.stamp_s:.9f}", *(f"{v:.6f}" for v in t), *(f"{v:.7f}" for v in q),
                   *(f"{v:.3e}" for v in np.diag(r.covariance)), f"{r.ess:.1f}",
                   str(r.n_particles), r.state, str(len(r.hypotheses)), f"{r.match_ratio:.4f}",
                   f"{r.mean_log_likelihood:.4f}", str(r.n_points), str(int(r.resampled)),
                   r.reseeded or "-", motion, *(f"{v:.2f}" for v in ms), f"{sum(ms):.2f}"]
            f.write(",".join(row) + "\n")
    save(cfg, paths["config"])
    with atomic_open(paths["summary"]) as f:
        json.dump(out.summary, f, indent=2, default=_json_default)


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    raise TypeError(f"not JSON serializable: {type(value)}")
