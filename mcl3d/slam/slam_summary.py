"""What a SLAM run reports: the typed summary behind slam_summary.json and the CLI's table,
and the accuracy of its trajectories against the log's ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcl3d.core.errors import Mcl3dError
from mcl3d.core.geometry import se3_inverse
from mcl3d.evaluation.consistency import Consistency, align_start, consistency
from mcl3d.evaluation.metrics import evaluate
from mcl3d.evaluation.run_plots import SLAM_PICTURE
from mcl3d.io.logs.faults import LogFaults
from mcl3d.io.trajectory import Trajectory
from mcl3d.mapping.pipeline import format_bytes
from mcl3d.odometry.odometry_summary import FrameTimesMs, evaluation_entry
from mcl3d.slam.frame_store import STAGES
from mcl3d.slam.monte_carlo_slam import MonteCarloSlam

MAX_LISTED_WARNINGS = 100  # the summary lists this many, and counts them all
WARM_UP_FRAMES = 3  # the first scans include compiling each kernel: left out of the timings
MIN_POSES_FOR_ALIGNMENT = 3  # an SE(3) alignment needs this many poses
WRONG_LOOP_M = 2.0  # a loop is wrong when it places the scan this far from where it is


@dataclass(frozen=True)
class AteRmse:
    """ATE RMSE after an SE(3) alignment (as `evo_ape -a`)."""

    ate_m: float
    ate_deg: float


@dataclass(frozen=True)
class SlamAccuracy:
    slam: AteRmse  # the representative's trajectory, placed by its corrected keyframes
    online: AteRmse  # the representative of each scan as chosen when the scan came
    odometry: AteRmse  # the odometry front-end alone

    def as_dict(self) -> dict:
        return {name: {"ate_m": ate.ate_m, "ate_deg": ate.ate_deg}
                for name, ate in (("slam", self.slam), ("online", self.online),
                                  ("odometry", self.odometry))}


@dataclass(frozen=True)
class LoopCheck:
    """The representative's loop corrections against the ground truth."""

    accepted: int  # scans on which the representative took a loop correction
    wrong: int  # ... that left its pose relative to a loop keyframe > WRONG_LOOP_M off the
    # true relative pose (the scan matched to another row of trees, another floor)
    worst_m: float  # the largest such error over the accepted scans
    farthest_m: float  # the largest true distance between a loop keyframe and its scan
    edges_wrong: int = 0  # loop edges in the written map > WRONG_LOOP_M off
    edges_worst_m: float = 0.0  # the largest error of a loop edge in the written map
    misplaced: int = 0  # wrong ones off against every loop keyframe: the scan put in the
    # wrong place (the others were right against one, off against a keyframe held misplaced)

    def as_dict(self) -> dict:
        return {"accepted": self.accepted, "wrong": self.wrong, "worst_error_m": self.worst_m,
                "farthest_keyframe_m": self.farthest_m, "wrong_if_off_by_m": WRONG_LOOP_M,
                "edges_wrong": self.edges_wrong, "edges_worst_error_m": self.edges_worst_m,
                "misplaced": self.misplaced}


@dataclass(frozen=True)
class SlamSummary:
    """One run in numbers; `as_dict` is slam_summary.json."""

    scans: int
    interrupted: bool
    particles: int
    keyframes: int  # kept at the end (at most keyframes.capacity)
    path_length_m: float  # of the odometry
    loop_frames: int  # scans on which some particle saw a loop
    corrected_frames: int  # scans on which some particle took a loop correction
    pruned_total: int
    elevator_frames: int
    final_hypotheses: int
    final_ess: float
    ms_per_frame: FrameTimesMs
    ms_per_stage: dict[str, float]  # mean per scan, by stage of `STAGES`
    particle_state_bytes: int
    notes: list[str]
    odometry_warnings: list[str]  # the first ones, each naming its scan
    num_odometry_warnings: int
    accuracy: SlamAccuracy | None  # None without ground truth
    accuracy_error: str | None = None  # why the accuracy could not be computed
    faults: LogFaults = field(default_factory=LogFaults)  # the log's messages dropped
    # with ground truth: how often the truth lay inside the cloud's 95% region, and the
    # representative's loop corrections that matched a keyframe truly elsewhere
    consistency: Consistency | None = None
    loop_check: LoopCheck | None = None
    keyframes_made: int = 0  # over the run; beyond the capacity each replaced a kept one
    # keyframe pairs the representative closed a loop over (trajectory.loop_graph): registered,
    # of them in the final representative's map (the written map's pose graph), and those
    # whose registration failed its checks
    loop_edges_registered: int = 0
    loop_edges_in_map: int = 0
    loop_edges_rejected: int = 0

    def as_dict(self) -> dict:
        return {
            "scans": self.scans, "interrupted": self.interrupted,
            "particles": self.particles, "keyframes": self.keyframes,
            "keyframes_made": self.keyframes_made,
            "path_length_m": self.path_length_m, "loop_frames": self.loop_frames,
            "corrected_frames": self.corrected_frames, "pruned_total": self.pruned_total,
            "elevator_frames": self.elevator_frames,
            "final_hypotheses": self.final_hypotheses, "final_ess": self.final_ess,
            "ms_per_frame": self.ms_per_frame.as_dict(), "ms_per_stage": self.ms_per_stage,
            "particle_state_bytes": self.particle_state_bytes, "notes": self.notes,
            "odometry_warnings": self.odometry_warnings,
            "num_odometry_warnings": self.num_odometry_warnings,
            "evaluation": evaluation_entry(self.accuracy, self.accuracy_error),
            "consistency": None if self.consistency is None else self.consistency.as_dict(),
            "loops": None if self.loop_check is None else self.loop_check.as_dict(),
            "loop_edges": {"registered": self.loop_edges_registered,
                           "in_map": self.loop_edges_in_map,
                           "rejected": self.loop_edges_rejected},
            "faults": self.faults.as_dict()}


def summarize(slam: MonteCarloSlam, trajectories: dict[str, Trajectory],
              gt: Trajectory | None, notes: list[str], interrupted: bool,
              faults: LogFaults | None = None) -> SlamSummary:
    """The summary of a run; `trajectories` are "slam", "online" and "odometry"; `faults`
    the log's messages dropped."""
    frames = slam.frames
    timings = frames.timings_ms[WARM_UP_FRAMES:] if len(frames) > WARM_UP_FRAMES else (
        frames.timings_ms)
    ms = {s: float(np.mean(timings[:, k].copy())) for k, s in enumerate(STAGES)}
    totals = np.zeros(len(timings))
    for k in range(len(STAGES)):  # stage by stage, as a sum over each scan's stages
        totals = totals + timings[:, k]
    warnings = [f"scan {i}: {w}" for i, w in frames.warnings]
    accuracy, accuracy_error = _evaluate(trajectories, gt)
    cloud, loop_check = _check_against_truth(slam, gt)
    return SlamSummary(
        scans=len(frames), interrupted=interrupted, particles=slam.cfg.particles,
        keyframes=slam.particles.num_keyframes,
        path_length_m=trajectories["odometry"].path_length_m(),
        loop_frames=int(np.count_nonzero(frames.looping > 0)),
        corrected_frames=int(np.count_nonzero(frames.corrected > 0)),
        pruned_total=int(frames.pruned.sum(dtype=np.int64)),
        elevator_frames=int(np.count_nonzero(frames.elevator)),
        final_hypotheses=int(frames.hypotheses[-1]), final_ess=float(frames.ess[-1]),
        ms_per_frame=FrameTimesMs.of(totals), ms_per_stage=ms,
        particle_state_bytes=slam.particles.state_bytes(), notes=notes,
        odometry_warnings=warnings[:MAX_LISTED_WARNINGS], num_odometry_warnings=len(warnings),
        accuracy=accuracy, accuracy_error=accuracy_error, faults=faults or LogFaults(),
        consistency=cloud, loop_check=loop_check, keyframes_made=len(slam.keyframe_frames),
        loop_edges_registered=len(slam.loop_edges.registered()),
        loop_edges_in_map=len(slam.map_loop_edges()),
        loop_edges_rejected=slam.loop_edges.rejected)


def _check_against_truth(slam: MonteCarloSlam, gt: Trajectory | None
                         ) -> tuple[Consistency | None, LoopCheck | None]:
    """The cloud's consistency over the scans the ground truth covers (aligned at the first
    of them: SLAM's world is its first pose's frame), and the representative's loops."""
    if gt is None:
        return None, None
    frames = slam.frames
    stamps_s = frames.stamp_ns * 1e-9
    covered = np.flatnonzero((stamps_s >= gt.stamps_s[0]) & (stamps_s <= gt.stamps_s[-1]))
    if len(covered) < MIN_POSES_FOR_ALIGNMENT:
        return None, None
    T_means = frames.poses("T_mean")[covered]
    truth = align_start(gt.interpolate_poses(stamps_s[covered]), T_means[0])
    cloud = consistency(T_means, frames.covariance[covered], truth)
    true_at = dict(zip(covered.tolist(), truth, strict=True))
    accepted = wrong = misplaced = 0
    worst = farthest = 0.0
    for i, loop_keyframes, loop_relative in frames.loops():
        kf_frames = [slam.keyframe_frames[k] for k in loop_keyframes]
        if i not in true_at or any(j not in true_at for j in kf_frames):
            continue
        true_rel = [se3_inverse(true_at[j]) @ true_at[i] for j in kf_frames]
        offs = [float(np.linalg.norm((se3_inverse(T) @ E)[:3, 3]))
                for T, E in zip(true_rel, loop_relative, strict=True)]
        accepted += 1
        wrong += max(offs) > WRONG_LOOP_M
        misplaced += min(offs) > WRONG_LOOP_M
        worst = max(worst, *offs)
        farthest = max(farthest, *(float(np.linalg.norm(T[:3, 3])) for T in true_rel))
    edge_errors = []
    for e in slam.map_loop_edges():
        i, j = slam.keyframe_frames[e.source], slam.keyframe_frames[e.target]
        if i in true_at and j in true_at:
            T_true = se3_inverse(true_at[j]) @ true_at[i]
            edge_errors.append(float(np.linalg.norm((se3_inverse(T_true)
                                                     @ e.T_target_source)[:3, 3])))
    return cloud, LoopCheck(accepted, wrong, worst, farthest,
                            sum(off > WRONG_LOOP_M for off in edge_errors),
                            max(edge_errors, default=0.0), misplaced)


def _evaluate(trajectories: dict[str, Trajectory], gt: Trajectory | None
              ) -> tuple[SlamAccuracy | None, str | None]:
    """(accuracy, None), or (None, why not); (None, None) without ground truth or with too
    few poses."""
    if gt is None:
        return None, None
    ates = {}
    for name, est in trajectories.items():
        if len(est) < MIN_POSES_FOR_ALIGNMENT:
            return None, None
        try:
            ev = evaluate(gt, est, alignment="se3", rpe_delta=1, rpe_unit="frames")  # ATE only
        except Mcl3dError as exc:
            return None, str(exc)
        ates[name] = AteRmse(ev.ate.translation_m.rmse, ev.ate.rotation_deg.rmse)
    return SlamAccuracy(**ates), None


def summary_rows(summary: SlamSummary, backend: str, output_dir: Path,
                 tsdf: Path | None = None) -> list[tuple[str, str]]:
    """The rows (what, value) of the end-of-run table; `backend` says what ran it, `tsdf` is
    the TSDF map built from the result, if any."""
    s, ms = summary, summary.ms_per_frame
    stages = ", ".join(f"{k} {v:.0f}" for k, v in s.ms_per_stage.items() if v >= 0.5)
    kept = (f"{s.keyframes} keyframes" if s.keyframes_made <= s.keyframes
            else f"{s.keyframes_made} keyframes, {s.keyframes} kept")
    rows = [("scans", f"{s.scans} ({kept}, {s.path_length_m:.1f} m)"),
            ("particles", f"{s.particles:,} ({format_bytes(s.particle_state_bytes)} "
                          "of particle state)"),
            ("backend", backend),
            ("ms per frame", f"{ms.mean:.0f} mean, {ms.median:.0f} median"),
            ("ms per stage", stages),
            ("loops", f"{s.loop_frames} scans saw a loop, {s.corrected_frames} corrected"),
            ("pruned", f"{s.pruned_total:,} particles"),
            ("hypotheses at the end", f"{s.final_hypotheses} (ESS {s.final_ess:.0f})")]
    if s.elevator_frames:
        rows.append(("elevator", f"{s.elevator_frames} scans"))
    if s.loop_edges_registered + s.loop_edges_rejected:
        rows.append(("loop edges", f"{s.loop_edges_registered} keyframe pairs registered "
                     f"({s.loop_edges_in_map} in the final map), {s.loop_edges_rejected} "
                     "rejected"))
    if s.loop_check is not None:
        rows.append(("loops vs truth", f"{s.loop_check.accepted} scans corrected by the "
                     f"representative, {s.loop_check.wrong} wrong (> {WRONG_LOOP_M:.0f} m "
                     f"off the truth against a loop keyframe; {s.loop_check.misplaced} "
                     "against every one)"))
        if s.loop_edges_in_map:
            rows.append(("loop edges vs truth", f"{s.loop_check.edges_wrong} wrong, worst "
                         f"{s.loop_check.edges_worst_m:.3f} m off"))
    if s.consistency is not None:
        axes = ", ".join(f"{a} {100 * f:.0f}%" for a, f in s.consistency.axes.items())
        rows.append(("consistency", f"truth inside the cloud's 95% region in "
                     f"{100 * s.consistency.fraction:.1f}% of {s.consistency.scans} scans "
                     f"(within each axis's 95%: {axes})"))
    if s.accuracy is not None:
        for ate, label in ((s.accuracy.slam, "ATE SLAM"), (s.accuracy.online, "ATE online"),
                           (s.accuracy.odometry, "ATE odometry only")):
            rows.append((label, f"{ate.ate_m:.3f} m, {ate.ate_deg:.2f} deg "
                                "RMSE (SE(3)-aligned)"))
    if tsdf is not None:
        rows.append(("TSDF map", str(tsdf)))
    rows.append(("outputs", str(output_dir)))
    rows.append(("picture", str(Path(output_dir) / SLAM_PICTURE)))
    return rows
