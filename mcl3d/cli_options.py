"""Options, checks and helpers shared by the `mcl3d` commands (the CLI layer)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

BACKEND_HELP = (
    "Compute backend: auto (cuda, then a hardware Vulkan GPU, then cpu), cuda, vulkan or cpu."
)


class Globals:
    """Settings of the `mcl3d` callback that every command reads."""

    backend: str = "auto"


def check_backend(value: str | None) -> str | None:
    from mcl3d.core.runtime import BACKENDS

    if value is not None and value not in BACKENDS:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(BACKENDS)}")
    return value


BackendOption = Annotated[
    str | None,
    typer.Option("--backend", help=BACKEND_HELP + " Overrides the global --backend.",
                 callback=check_backend, show_default=False),
]


def init_backend(backend: str | None):
    """Start the compute runtime on the command's --backend, else the global one."""
    from mcl3d.core import runtime

    return runtime.init(backend or Globals.backend)


def one_of(allowed: tuple[str, ...]):
    """A Typer callback that accepts only `allowed` values (usage error, exit 2, otherwise)."""

    def check(value: str) -> str:
        if value not in allowed:
            raise typer.BadParameter(f"{value!r} is not one of {', '.join(allowed)}")
        return value

    return check


# Topic overrides shared by every command that reads a log (CONVENTIONS §3).
PointsTopicOption = Annotated[str | None, typer.Option(
    "--points-topic", help="PointCloud2 topic (default: the only one in the log).")]
ImuTopicOption = Annotated[str | None, typer.Option(
    "--imu-topic", help="Imu topic (default: the only one in the log).")]
OdomTopicOption = Annotated[str | None, typer.Option(
    "--odom-topic", help="Odometry topic (default: the only one not named like ground truth).")]
GtTopicOption = Annotated[str | None, typer.Option(
    "--gt-topic", help="Ground-truth pose topic (default: the one named ground_truth, "
                       "groundtruth or gt).")]
JsonOption = Annotated[bool, typer.Option("--json", help="Print the facts as one JSON document "
                                          "instead (keys: docs/json-output.md).")]

# Foxglove results of the commands that estimate poses (docs/foxglove.md).
ResultMcapOption = Annotated[Path | None, typer.Option(
    "--result-mcap", dir_okay=False, help="Also write the run's results for Foxglove (scans, "
    "estimate, particles, hypotheses, map) to this MCAP (docs/foxglove.md).")]
LiveOption = Annotated[bool, typer.Option(
    "--live", help="Serve the same results live to Foxglove (WebSocket) while the run goes.")]
LivePortOption = Annotated[int, typer.Option("--live-port", min=1, max=65535,
                                             help="Port of the --live server (127.0.0.1).")]


def live_port(live: bool, port: int) -> int | None:
    """The --live port, None when off (then nothing of the live view is made)."""
    if not live:
        return None
    from mcl3d.console import console

    console.print(f"live view: ws://127.0.0.1:{port} (in Foxglove: Open connection)")
    return port


def print_notes(notes: list[str], warnings: list[str], num_warnings: int,
                faults: list[str]) -> None:
    """A run's notes, its messages dropped for faults (a line per kind) and first warnings."""
    from mcl3d.console import console

    for note in notes:
        console.print(f"[yellow]note:[/] {note}")
    for w in [*faults, *warnings[:5]]:
        console.print(f"[yellow]warning:[/] {w}")
    if num_warnings > 5:
        console.print(f"[yellow]... {num_warnings - 5} more warnings in the summary[/]")
