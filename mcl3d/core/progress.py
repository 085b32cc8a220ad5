"""The progress half of the one pipeline contract, `run(request, on_progress=None) -> result`:
a pipeline reports each finished unit of work as a `Progress` value and never draws
anything itself; the CLI turns the reports into a Rich progress bar."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Progress:
    """How far one stage of a run has come."""

    stage: str  # what is being done, e.g. "localize", "fuse scans"
    done: int  # units finished in this stage
    total: int | None  # units in the stage, None when unknown
    status: str = ""  # a few words on the last unit, e.g. the filter state
    rate: str = ""  # throughput of the last unit, e.g. "42 ms/update"


ProgressCallback = Callable[[Progress], None]


def report(on_progress: ProgressCallback | None, progress: Progress) -> None:
    """Hand `progress` to the caller's callback, if it gave one."""
    if on_progress is not None:
        on_progress(progress)
