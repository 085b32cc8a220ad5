"""Terminal output: one progress-bar helper and one summary-table helper, both Rich.

Progress bars show on a terminal and stay silent in pipes and CI, so logs stay clean.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Sequence
from typing import TypeVar

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

console = Console(highlight=False)
err_console = Console(stderr=True, highlight=False)

T = TypeVar("T")


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


def track(items: Iterable[T], total: int | None, description: str,
          unit: str = "frames") -> Iterator[T]:
    """Iterate with a progress bar showing `unit`/s and ETA; no output outside a terminal."""
    with make_progress() as progress:
        task = progress.add_task(description, total=total, status="", rate="")
        for item in items:
            yield item
            progress.advance(task)
            speed = progress.tasks[task].speed
            if speed:
                progress.update(task, rate=f"{speed:.1f} {unit}/s")


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
