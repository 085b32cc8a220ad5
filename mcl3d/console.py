"""The CLI's terminal output, all Rich: progress bars drawn from the pipelines' progress
reports, summary tables, the tables (and JSON) of `mcl3d info` and `mcl3d map-info`, and
library errors with their flags.

Progress bars show on a terminal and stay silent in pipes and CI, so logs stay clean. Tables
fit a terminal's width; in pipes and CI they print at their natural width, so that scripts
and logs see every topic name and path whole.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.cells import cell_len
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from mcl3d.core import progress as pipeline_progress
from mcl3d.evaluation.metrics import Evaluation
from mcl3d.io.logs.info import CloudInfo, LogInfo
from mcl3d.io.logs.info import iso_utc as _iso_utc
from mcl3d.io.logs.ros_types import short_type

if TYPE_CHECKING:
    from mcl3d.mapping.map_info import MapInfo

console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False)

# settings whose flag is not named like them
FLAG_OF_SETTING = {"max_capacity_blocks": "--capacity-blocks"}
WIDEST_TABLE = 10_000  # columns a table may take when printed to a pipe


def show_progress() -> bool:
    return console.is_terminal and not os.environ.get("CI")


def make_progress() -> Progress:
    """A progress bar with rate and ETA; disabled when output is not a terminal."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TextColumn("[cyan]{task.fields[rate]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        disable=not show_progress(),
        transient=False,
    )


def flag_of(setting: str | None) -> str | None:
    """The CLI flag of a library setting (the library names settings, never flags)."""
    if setting is None:
        return None
    return FLAG_OF_SETTING.get(setting, "--" + setting.replace("_", "-"))


def with_flag(message: str, setting: str | None) -> str:
    """A library message plus the CLI flag of the setting that fixes it."""
    if setting is None:
        return message
    return f"{message} ({flag_of(setting)})"


def print_tables(tables: Sequence[Table]) -> None:
    """Print tables to stdout: fitted to a terminal, at their natural width elsewhere (a
    pipe has no width to fit, and a name folded mid-word breaks scripts that grep it)."""
    if console.is_terminal:
        for table in tables:
            console.print(table)
        return
    wide = console.options.update_width(WIDEST_TABLE)
    natural = [console.measure(table, options=wide).maximum for table in tables]
    titles = [cell_len(t.title) if isinstance(t.title, str) else 0 for t in tables]
    out = Console(highlight=False, width=max([console.width, *natural, *titles]))
    for table, width, title in zip(tables, natural, titles, strict=True):
        if title > width:
            out.print(table.title, markup=False)  # on its own line, not wrapped to the table
            table = copy.copy(table)
            table.title = None
        out.print(table)


def print_json(document: dict) -> None:
    """One JSON document on stdout, nothing else (plain write: no Rich markup or wrapping)."""
    console.file.write(json.dumps(document, indent=2, allow_nan=False) + "\n")


def summary_table(title: str, rows: Sequence[tuple[str, str]]) -> Table:
    """A two-column summary table (what, value) printed at the end of a run."""
    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    for key, value in rows:
        table.add_row(key, value)
    return table


class ProgressBars:
    """The CLI's end of the pipeline contract: `on_progress` draws one bar per stage (rate
    and ETA), silent outside a terminal. Use as a context manager around `run(...)`."""

    def __init__(self) -> None:
        self._progress = make_progress()
        self._tasks: dict[str, int] = {}

    def __enter__(self) -> ProgressBars:
        self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._progress.__exit__(*exc)

    def on_progress(self, report: pipeline_progress.Progress) -> None:
        task = self._tasks.get(report.stage)
        if task is None:
            task = self._progress.add_task(report.stage, total=report.total, status="", rate="")
            self._tasks[report.stage] = task
        rate = report.rate
        if not rate:
            speed = self._progress.tasks[task].speed
            rate = f"{speed:.1f}/s" if speed else ""
        self._progress.update(task, completed=report.done, total=report.total,
                              status=report.status, rate=rate)


def _iso(stamp_ns: int | None) -> str:
    if stamp_ns is None:
        return "-"
    return f"{_iso_utc(stamp_ns)[:23]}Z ({stamp_ns * 1e-9:.3f} s)"


def _cloud_table(topic: str, cloud: CloudInfo) -> Table:
    layout = (f"organized {cloud.height} x {cloud.width}" if cloud.organized
              else f"unorganized, {cloud.width} points")
    fields = " ".join(f"{n}:{t}" + (f"[{c}]" if c > 1 else "") for n, t, c in cloud.fields)
    time_text = "none"
    if cloud.time_field:
        time_text = f"field {cloud.time_field!r}"
        if cloud.time_span_s is not None:
            time_text += f", spans {cloud.time_span_s * 1e3:.1f} ms"
    plural = "s" if cloud.scans_decoded != 1 else ""
    title = f"Point cloud {topic} (first {cloud.scans_decoded} scan{plural} decoded)"
    return summary_table(title, [
        ("layout", layout),
        ("fields", fields),
        ("valid points", f"min {cloud.valid_min}, mean {cloud.valid_mean:.0f}, "
                         f"max {cloud.valid_max} (NaN/inf/zero points dropped)"),
        ("per-point time", time_text),
    ])


def log_info_tables(info: LogInfo) -> tuple[Table, ...]:
    """`mcl3d info`'s tables: the log summary, its topics, and the topics mcl3d would use."""
    duration = f"{info.duration_s:.3f} s" if info.duration_s is not None else "-"
    head = summary_table(f"Log {info.path}", [
        ("format", f"{info.format}, profile {info.profile}"),
        ("library", info.library),
        ("size", f"{info.size_bytes / 1e6:.1f} MB"),
        ("duration", duration),
        ("start", _iso(info.start_ns)),
        ("end", _iso(info.end_ns)),
        ("messages", str(info.message_count)),
    ])
    topics = Table(title="Topics", title_justify="left")
    for column in ("topic", "type", "count", "rate Hz", "frame"):
        topics.add_column(column, overflow="fold",
                          justify="right" if column in ("count", "rate Hz") else "left")
    for t in info.topics:
        topics.add_row(t.topic, short_type(t.msgtype), "-" if t.count is None else str(t.count),
                       "-" if t.rate_hz is None else f"{t.rate_hz:.1f}",
                       ", ".join(t.frame_ids) or "-")
    clouds = [_cloud_table(t.topic, t.cloud) for t in info.topics if t.cloud is not None]
    chosen = summary_table("Topics mcl3d uses (--points-topic, --imu-topic, --odom-topic, "
                           "--gt-topic override)",
                           [(kind, with_flag(c.problem, c.setting) if c.problem
                             else c.topic or "-") for kind, c in info.selection.items()])
    return (head, topics, *clouds, chosen)


def log_info_json(info: LogInfo) -> dict:
    """`mcl3d info --json`: the library's facts plus, where a topic choice has a problem,
    the flag that resolves it."""
    document = info.as_dict()
    for choice in document["selection"].values():
        choice["flag"] = flag_of(choice["setting"])
    return document


def map_info_table(info: MapInfo) -> Table:
    """`mcl3d map-info`'s table: the header, blocks, voxels, memory, and the exports written."""
    from mcl3d.mapping.pipeline import map_rows

    header, exports = info.header, info.exports
    # map files record no clock since issue #22 (reproducible bytes); older ones show theirs
    created = f", {header['created_utc']}" if "created_utc" in header else ""
    seconds = header.get("build", {}).get("seconds")
    rows = [("file", str(info.path)),
            ("format", f"{header['format']} v{header['format_version']} (mcl3d "
                       f"{header.get('mcl3d_version', '?')}{created})"),
            ("frame", header["frame_id"]),
            ("precision", header["distance_dtype"]),
            *map_rows(info.geometry, info.stats),
            ("built from", json.dumps(header.get("source", {}))),
            *([("build time", f"{seconds} s")] if seconds is not None else [])]
    if info.mesh_path:
        rows.append(("mesh", f"{exports.mesh_triangles} triangles -> {info.mesh_path}"))
    if info.points_path:
        rows.append(("points", f"{exports.surface_points} points -> {info.points_path}"))
    return summary_table("Map", rows)


def evaluation_tables(result: Evaluation, ref: Path, est: Path, plot: Path | None,
                      json_path: Path | None) -> tuple[Table, Table]:
    """`mcl3d eval`'s tables: what was compared and how, and the error statistics."""
    how = result.alignment
    aligned = {"none": "none", "origin": "origin (first poses coincide)",
               "se3": "se3 (Umeyama)", "sim3": f"sim3 (Umeyama), scale {how.scale:.6f}"}
    rows = [("reference", f"{ref} ({result.num_ref} poses)"),
            ("estimate", f"{est} ({result.num_est} poses)"),
            ("associated", f"{len(result.association)} poses within "
                           f"{result.association.max_diff_s:g} s"),
            ("alignment", aligned[how.method]),
            ("RPE pairs", f"{result.rpe.pairs.shape[0]} at {result.rpe.delta:g} {result.rpe.unit}"
                          f"{' (all pairs)' if result.rpe.all_pairs else ''}")]
    rows += [(name, str(path)) for name, path in (("plot", plot), ("json", json_path)) if path]
    stats = Table(title="Trajectory error", title_justify="left")
    for column in ("metric", "unit", "rmse", "mean", "median", "std", "min", "max"):
        stats.add_column(column, justify="left" if column in ("metric", "unit") else "right")
    for name, unit, s in (("ATE translation", "m", result.ate.translation_m),
                          ("ATE rotation", "deg", result.ate.rotation_deg),
                          ("RPE translation", "m", result.rpe.translation_m),
                          ("RPE rotation", "deg", result.rpe.rotation_deg)):
        stats.add_row(name, unit, *(f"{v:.4f}" for v in
                                    (s.rmse, s.mean, s.median, s.std, s.min, s.max)))
    return summary_table("Evaluation", rows), stats
