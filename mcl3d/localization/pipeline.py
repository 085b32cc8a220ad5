"""`mcl3d localize`: run the particle filter over a log against a TSDF map.

`run(request, on_progress=None) -> LocalizeResult` reads as its steps: check outputs -> load
the map -> open the log and choose the motion source -> initialize the particles -> filter
every scan (with timing and progress) -> write the trajectory (TUM + KITTI), the per-scan
CSV, the effective config, a picture of the run (localize.png) and optionally a result MCAP
-> summary (convergence, ATE against ground truth, ms per stage). Every
`CHECKPOINT_INTERVAL_S` of wall time the trajectory so far and a summary marked as a
checkpoint are written, so a crash keeps them; the final outputs replace them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import Field

from mcl3d.core import geometry, runtime
from mcl3d.core.checkpoint import Checkpointer
from mcl3d.core.config import Section
from mcl3d.core.errors import InputError, RunInterrupted
from mcl3d.core.outputs import output_folder
from mcl3d.core.progress import Progress, ProgressCallback, report
from mcl3d.io.foxglove_results import open_results
from mcl3d.io.logs.faults import LogFaults
from mcl3d.io.logs.plausibility import check_scans
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory
from mcl3d.localization.initialization import auto_band
from mcl3d.localization.localization_config import LocalizerConfig, check_config
from mcl3d.localization.localization_summary import (
    LocalizeSummary,
    convergence,
    stage_means,
    summarize,
)
from mcl3d.localization.localizer import Localizer
from mcl3d.localization.log_inputs import (
    first_messages,
    gravity_in_lidar,
    initial_pose,
    make_motion_source,
)
from mcl3d.localization.motion_source import MotionSource, MotionSourceConfig
from mcl3d.localization.output_files import check_outputs, write_checkpoint, write_outputs
from mcl3d.localization.result_view import LocalizeView
from mcl3d.localization.sensor_model import MIN_SCAN_POINTS
from mcl3d.localization.state import EmptyScan, FilterState, LocalizationResult, ScanRecord
from mcl3d.maps.map_file import load_map
from mcl3d.maps.tsdf import surface_points

NO_OVERLAP_SCANS = 10  # global init: give up when no scan matched the map by then
NO_OVERLAP_MATCH = 0.05
MEASURED_KINDS = ("odom", "imu")  # motion sources that measure the sweep's own motion
PROGRESS_STAGE = "localize"


class LocalizeConfig(Section):
    """Everything `mcl3d localize` uses; saved as config.yaml beside the outputs."""

    localizer: LocalizerConfig = LocalizerConfig()
    motion_source: MotionSourceConfig = MotionSourceConfig()
    max_scans: int | None = Field(None, ge=1, description="stop after this many scans")
    result_particles: int = Field(5000, ge=1, le=5000,
                                  description="particles per result-MCAP/live message")
    deskew: bool = Field(True, description="deskew scans with per-point times using the "
                                           "motion between scans (constant velocity)")


@dataclass
class Topics:
    points: str | None = None
    imu: str | None = None
    odom: str | None = None
    gt: str | None = None


@dataclass(frozen=True)
class LocalizeRequest:
    log: Path
    map: Path  # the TSDF map (.tsdf)
    output_dir: Path
    config: LocalizeConfig = field(default_factory=LocalizeConfig)
    topics: Topics = field(default_factory=Topics)
    force: bool = False  # overwrite existing outputs
    result_mcap: Path | None = None  # also write the Foxglove result log here
    live_port: int | None = None  # serve the same messages live on this port (None: off)
    backend: str = "cpu"
    preset: str = "default"  # the named preset the config started from (recorded only)


@dataclass
class LocalizeResult:
    """What a run produced; `summary` is also summary.json and the CLI's table."""

    results: list[ScanRecord] = field(default_factory=list)  # per scan, what outputs need
    stamps_ns: list[int] = field(default_factory=list)  # the results' scan stamps, exact
    motion_kinds: list[str] = field(default_factory=list)
    skipped_scans: int = 0
    warnings: list[str] = field(default_factory=list)
    motion_source: str = ""
    summary: LocalizeSummary | None = None
    interrupted: bool = False
    gt: tuple | None = None  # (stamps_ns, T_map_lidar) when the log has ground truth
    height_band_m: list[float] | None = None  # the band global init used, when auto
    faults: LogFaults = field(default_factory=LogFaults)  # the log's messages dropped
    claim_checks: dict = field(default_factory=dict)  # the convergence checks' counts, ms


def run(request: LocalizeRequest, on_progress: ProgressCallback | None = None
        ) -> LocalizeResult:
    """Localize every scan of the log; the output folder is removed again if nothing was
    written."""
    check_config(request.config.localizer)
    with output_folder(request.output_dir):
        return _run(request, on_progress)


def _run(req: LocalizeRequest, on_progress: ProgressCallback | None) -> LocalizeResult:
    paths = check_outputs(req.output_dir, req.force, req.result_mcap)
    info = runtime.init(req.backend)
    tsdf = load_map(Path(req.map), f16=False)
    try:
        map_points = surface_points(tsdf.geometry, tsdf.blocks())  # the picture, the map shown
        out = _run_filter(req, tsdf, paths, map_points, on_progress)
    finally:
        tsdf.destroy()  # the map's device memory; the particles are small
    if not out.results:
        if out.interrupted:
            raise RunInterrupted("interrupted before the first scan was localized; nothing "
                                 "written")
        raise InputError(f"{req.log}: no scan could be localized ({out.skipped_scans} scans "
                         f"had fewer than {MIN_SCAN_POINTS} points in the range gate)")
    out.summary = _summary(out, req.config, info)
    out.summary.preset = req.preset
    write_outputs(paths, out.results, out.motion_kinds, out.summary, req.config, out.stamps_ns,
                  map_points, None if out.gt is None else Trajectory.from_ns(*out.gt),
                  tsdf.voxel_size_m)
    if out.interrupted:
        raise RunInterrupted(f"interrupted after {len(out.results)} scans; the trajectory so far "
                             f"is in {paths['tum']}")
    return out


def _run_filter(req: LocalizeRequest, tsdf, paths: dict[str, Path], map_points: np.ndarray,
                on_progress) -> LocalizeResult:
    cfg, topics = req.config, req.topics
    out = LocalizeResult()
    with LogReader(Path(req.log), points_topic=topics.points, imu_topic=topics.imu,
                   odom_topic=topics.odom, gt_topic=topics.gt) as reader:
        out.faults = reader.faults
        reader.require("points")
        check_scans(reader, req.log, needs_3d=False)
        n_scans = reader.count("points")
        out.gt = reader.ground_truth() if reader.topics.gt else None
        firsts = first_messages(reader, ("points", "imu", "odom"), cfg.localizer.init.imu_samples)
        if "points" not in firsts:
            dropped = "; ".join(reader.faults.warnings())
            raise InputError(f"{req.log}: the point-cloud topic {reader.topics.points} has no "
                             f"usable scans" + (f": {dropped}" if dropped else ""))
        lidar_frame = firsts["points"].frame_id
        source = make_motion_source(reader, cfg.motion_source, firsts, lidar_frame, out.warnings)
        out.motion_source = source.kind
        loc = _start_localizer(reader, tsdf, cfg.localizer, firsts, out)
        total = min(n_scans, cfg.max_scans or n_scans)
        with open_results(req.result_mcap, req.live_port, req.force, "localize") as pub:
            view = None if pub is None else LocalizeView(pub, out.gt)
            if pub is not None:
                pub.publish_map(firsts["points"].stamp_ns, map_points)
            loop = _ScanLoop(loc, source, cfg, out, total, view, on_progress)
            loop.checkpoint = Checkpointer(lambda: write_checkpoint(paths, out))
            try:
                loop.run(reader)
            except KeyboardInterrupt:
                out.interrupted = True
    out.claim_checks = loc.claim_check.stats()
    return out


def _start_localizer(reader, tsdf, cfg: LocalizerConfig, firsts: dict,
                     out: LocalizeResult) -> Localizer:
    """The filter with its particles placed: globally (in the auto height band, levelled by
    the IMU's gravity) or around the initial pose."""
    lidar_frame = firsts["points"].frame_id
    roll_pitch = (gravity_in_lidar(reader, firsts, lidar_frame, out.warnings)
                  if cfg.init.mode == "global" else None)
    loc_cfg = cfg
    if cfg.init.mode == "global" and cfg.init.height_band_m == "auto":
        band = auto_band(cfg.init, firsts["points"].points, roll_pitch)
        out.height_band_m = band
        loc_cfg = cfg.model_copy(deep=True)
        loc_cfg.init.height_band_m = band
    loc = Localizer(tsdf, loc_cfg, imu_roll_pitch=roll_pitch)
    T0 = initial_pose(cfg, out.gt)
    if T0 is None:
        loc.init_global()
    else:
        loc.init_pose(T0, cfg.init.std_m_rad)
    return loc


class _ScanLoop:
    """Feeds the log's messages to the motion source and each scan, once the motion
    source covers its stamp, to the filter."""

    def __init__(self, loc: Localizer, source: MotionSource, cfg: LocalizeConfig,
                 out: LocalizeResult, total: int, view: LocalizeView | None, on_progress):
        self.loc, self.source, self.cfg, self.out = loc, source, cfg, out
        self.total, self.view, self.on_progress = total, view, on_progress
        loc.shown_particles = cfg.result_particles if view is not None else 0
        self.prev_ns: int | None = None
        self.best_match = 0.0
        self.checkpoint: Checkpointer | None = None  # writes the outputs so far now and then

    def run(self, reader) -> None:
        pending: deque = deque()
        kinds = ("points", *(k for k in ("odom", "imu") if self.source.kind == k))
        for kind, msg in reader.messages(kinds):
            if kind == "odom":
                self.source.add_odometry(msg.stamp_ns, msg.T_frame_child)
            elif kind == "imu":
                self.source.add_imu(msg.stamp_ns, msg.angular_velocity)
            else:
                pending.append(msg)
            while pending and self.source.covers(_sweep_ns(pending[0])[1]):
                if self.process(pending.popleft()):
                    return
        while pending:
            if self.process(pending.popleft()):
                return

    def process(self, scan) -> bool:
        """Filter one scan; True when the run should stop (max_scans reached)."""
        out, prev = self.out, self.prev_ns  # the reader drops scans whose stamp goes back
        motion = self.source.motion(prev, scan.stamp_ns) if prev is not None else None
        twist = None
        if motion is not None and self.cfg.deskew and scan.times_s is not None:
            twist = self._sweep_twist(scan, prev, motion.T_prev_curr)
        try:
            result = self.loc.step(scan.points, None if motion is None else motion.T_prev_curr,
                                   scan.stamp_ns * 1e-9,
                                   (0.0, 0.0) if motion is None else motion.extra_std,
                                   scan.times_s, twist)
        except EmptyScan:
            out.skipped_scans += 1
            return False
        self.prev_ns = scan.stamp_ns
        out.results.append(ScanRecord.of(result))
        out.stamps_ns.append(scan.stamp_ns)
        out.motion_kinds.append("none" if motion is None else motion.kind)
        self.source.add_estimate(scan.stamp_ns, result.T_map_lidar,
                                 result.state == FilterState.CONVERGED)
        self._check_overlap(result)
        if self.view is not None:
            self.view.update(scan.stamp_ns, scan.points, result, self.loc.last_cloud,
                             out.warnings, self.cfg.result_particles)
        ms = sum(result.timings_ms.values())
        report(self.on_progress, Progress(
            PROGRESS_STAGE, len(out.results), self.total,
            status=f"{result.state.value:<12} match {result.match_ratio:.2f}",
            rate=f"{ms:.0f} ms/update"))
        if self.checkpoint is not None:
            self.checkpoint.tick()
        return self.cfg.max_scans is not None and len(out.results) >= self.cfg.max_scans

    def _sweep_twist(self, scan, prev_ns: int, T_prev_curr: np.ndarray) -> np.ndarray:
        """The lidar's twist during this sweep, for deskewing: the odometry's or the IMU's over
        the sweep itself where they cover it (in a turn that speeds up, the motion since the
        last scan is too slow and leaves the scan smeared), else that motion since the last
        scan."""
        start_ns, end_ns = _sweep_ns(scan)
        if self.source.kind in MEASURED_KINDS and end_ns > start_ns and self.source.covers(end_ns):
            T = self.source.motion(start_ns, end_ns).T_prev_curr
            return geometry.se3_log(T) / ((end_ns - start_ns) * 1e-9)
        return geometry.se3_log(T_prev_curr) / max((scan.stamp_ns - prev_ns) * 1e-9, 1e-6)

    def _check_overlap(self, result: LocalizationResult) -> None:
        """A global search that matched nothing after a while is in the wrong map."""
        self.best_match = max(self.best_match, result.best_match_ratio)
        n = len(self.out.results)
        if (self.cfg.localizer.init.mode == "global" and n >= NO_OVERLAP_SCANS
                and self.best_match < NO_OVERLAP_MATCH):
            raise InputError(
                f"after {n} scans no particle's scan matches the map (best match ratio "
                f"{self.best_match:.2f}): the map and the log are from different places or "
                f"frames; check the map", setting="map")


def _sweep_ns(scan) -> tuple[int, int]:
    """(first, last) stamps (ns) of a scan's points: its stamp plus their times, if finite."""
    times = scan.times_s
    if times is None or len(times) == 0 or not np.isfinite(times).all():
        return scan.stamp_ns, scan.stamp_ns
    return (scan.stamp_ns + round(float(times.min()) * 1e9),
            scan.stamp_ns + round(float(times.max()) * 1e9))


def _summary(out: LocalizeResult, cfg: LocalizeConfig, info) -> LocalizeSummary:
    res = out.results
    conv, after_s, fraction = convergence(res)
    if conv is None and cfg.localizer.init.mode == "global":
        out.warnings.append(
            f"global localization did not converge in {len(res)} scans: the log may be from "
            f"a place the map does not hold (check the map), or the map is ambiguous for this "
            f"stretch of log (try more particles or a longer log)")
    summary = LocalizeSummary(
        scans=len(res), skipped_scans=out.skipped_scans, interrupted=out.interrupted,
        backend=info.backend, device=info.device, motion_source=out.motion_source,
        particles=cfg.localizer.particles, points=cfg.localizer.sensor.points,
        init=cfg.localizer.init.mode, height_band_m=out.height_band_m,
        converged_at_scan=conv, converged_after_s=after_s, converged_fraction=fraction,
        final_state=res[-1].state.value, ms_per_update=stage_means(res), warnings=out.warnings,
        faults=out.faults, claim_checks=out.claim_checks)
    summarize(res, summary, out.gt)
    return summary
