"""The `mcl3d` command line: parses, calls one pipeline, prints a Rich summary.

Heavy imports (taichi, open3d, mcap) happen inside the commands so `mcl3d --help` is instant.
Library errors (`Mcl3dError`) become one red line on stderr and exit code 1; usage errors
exit 2; Ctrl-C exits 130 after the running command has kept what it finished.
"""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from mcl3d import __version__
from mcl3d.errors import Mcl3dError, RunInterrupted

BACKEND_HELP = (
    "Compute backend: auto (cuda, then a hardware Vulkan GPU, then cpu), cuda, vulkan or cpu."
)


class _App(typer.Typer):
    """Typer app that turns library errors into one line and the documented exit codes."""

    def __call__(self, *args, **kwargs):
        try:
            return super().__call__(*args, **kwargs)
        except RunInterrupted as exc:
            _error(str(exc))
            sys.exit(130)
        except Mcl3dError as exc:
            _error(str(exc))
            sys.exit(1)


def _error(message: str) -> None:
    from mcl3d.console import err_console

    err_console.print(f"[bold red]error:[/] {message}", soft_wrap=True)


app = _App(
    name="mcl3d",
    help="6-DoF Monte Carlo localization and Monte Carlo SLAM for 3D LiDAR "
    "(Taichi kernels on cuda, vulkan or cpu).",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


class _Globals:
    backend: str = "auto"


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mcl3d {__version__}")
        raise typer.Exit()


def _check_backend(value: str | None) -> str | None:
    from mcl3d.runtime import BACKENDS

    if value is not None and value not in BACKENDS:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(BACKENDS)}")
    return value


BackendOption = Annotated[
    str | None,
    typer.Option("--backend", help=BACKEND_HELP + " Overrides the global --backend.",
                 callback=_check_backend, show_default=False),
]


@app.callback()
def main(
    backend: Annotated[
        str, typer.Option("--backend", help=BACKEND_HELP, callback=_check_backend)
    ] = "auto",
    version: Annotated[
        bool, typer.Option("--version", help="Print the version and exit.", callback=_version,
                           is_eager=True)
    ] = False,
) -> None:
    _Globals.backend = backend


def _init_backend(backend: str | None):
    """Start the compute runtime on the command's --backend, else the global one."""
    from mcl3d import runtime

    return runtime.init(backend or _Globals.backend)


@app.command()
def backends(backend: BackendOption = None) -> None:
    """List the compute backends on this machine and start the selected one."""
    from mcl3d.console import console, summary_table
    from mcl3d.vulkan_probe import vulkan_devices

    devices = vulkan_devices()
    vulkan_text = ", ".join(f"{d.name} ({d.device_type})" for d in devices) or "no Vulkan driver"
    info = _init_backend(backend)
    console.print(summary_table("Compute backends", [
        ("vulkan devices", vulkan_text),
        ("requested", info.requested),
        ("running", f"{info.backend} on {info.device}"),
    ]))
