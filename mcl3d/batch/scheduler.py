"""The batch's runs on Ray: a local Ray by default, a cluster at `address`.

Each run is one Ray task in a fresh worker process (`max_calls=1`): a process has one Taichi
runtime (CONVENTIONS §5), and nothing a run allocated is left for the next. A run whose task
raised something other than a typed `Mcl3dError`, or whose worker died, is submitted again up
to `retries` times; a typed error is the run's result (the same input fails the same way).
Ray is imported here only, inside the functions, so mcl3d installs and imports without it.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

from mcl3d.batch.commands import base_row
from mcl3d.batch.manifest import RunSpec
from mcl3d.core.errors import ConfigError, Mcl3dError

RAY_MISSING = "mcl3d batch needs Ray: pip install 'mcl3d[batch]'"

Submit = Callable[[RunSpec, int], Any]  # (run, attempt number from 1) -> a Ray object ref


def import_ray():
    """The `ray` module, or an Mcl3dError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise Mcl3dError(RAY_MISSING) from None
    return ray


@contextlib.contextmanager
def ray_session(address: str | None, workers: int | None) -> Iterator[Any]:
    """Ray, started for the batch (local with `workers` CPUs, or connected to the cluster at
    `address`) and shut down after it; a session this process already runs is used as it is."""
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        try:
            ray.init(address=address, num_cpus=None if address else workers,
                     include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"the Ray cluster at {address}" if address else "a local Ray"
            raise Mcl3dError(f"cannot start or reach {where}: {exc}", setting="address") from None
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def remote_task(ray, function: Callable, gpus_per_run: float):
    """`function` as a Ray task: one CPU (and `gpus_per_run` GPUs) per run, a fresh process
    per run, no retries by Ray (the scheduler resubmits)."""
    if gpus_per_run > 0 and ray.cluster_resources().get("GPU", 0) <= 0:
        raise ConfigError(f"the manifest asks {gpus_per_run} GPU per run but the Ray cluster "
                          f"has no GPU; set gpus_per_run to 0 or connect to one with GPUs")
    return ray.remote(num_cpus=1, num_gpus=gpus_per_run, max_calls=1, max_retries=0)(function)


def run_all(ray, submit: Submit, specs: list[RunSpec], retries: int,
            on_row: Callable[[dict], None]) -> list[dict]:
    """Submit every run, hand each finished run's row to `on_row` as it comes, and return the
    rows in the order of `specs`. Ctrl-C cancels the runs not finished and re-raises."""
    pending = {submit(spec, 1): (index, 1) for index, spec in enumerate(specs)}
    rows: dict[int, dict] = {}
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            index, attempt = pending.pop(ready[0])
            try:
                row = ray.get(ready[0])
            except ray.exceptions.RayError as exc:  # the task raised, or its worker died
                if attempt <= retries:
                    pending[submit(specs[index], attempt + 1)] = (index, attempt + 1)
                    continue
                row = {**base_row(specs[index]), "status": "failed", "error": _reason(exc)}
            row["attempts"] = attempt
            rows[index] = row
            on_row(row)
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    return [rows[i] for i in sorted(rows)]


def _reason(exc: Exception) -> str:
    """One line: the exception the task raised (its first line), else Ray's last line on
    what happened to the worker."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        return f"{type(cause).__name__}: {cause}".splitlines()[0]
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[-1] if lines else type(exc).__name__
