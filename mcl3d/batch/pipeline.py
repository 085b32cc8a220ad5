"""`mcl3d batch MANIFEST -o OUT/`: every run of a manifest on Ray, then one table of results.

Steps: read and check the manifest and expand its runs (paths, configs) -> check the outputs
-> start (or reach) Ray -> run each run in its own worker process through its command's
pipeline, into OUT/<job>/<run>/, trying failed ones again -> report each finished run ->
write results.csv, results.json and the pictures. Nothing runs when the manifest or an output
is wrong; Ctrl-C cancels the runs not finished and still writes the results of those that
did. The contract: `run(request, on_progress=None) -> BatchResult`.
"""

from __future__ import annotations

import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

from mcl3d import __version__
from mcl3d.batch.commands import execute
from mcl3d.batch.manifest import Manifest, RunSpec, expand, load_manifest
from mcl3d.batch.results import BatchOutputs, write_results
from mcl3d.batch.scheduler import import_ray, ray_session, remote_task, run_all
from mcl3d.core.errors import ConfigError, OutputExistsError, RunInterrupted
from mcl3d.core.outputs import check_writable, output_folder
from mcl3d.core.progress import Progress, ProgressCallback, report

PROGRESS_STAGE = "batch"


@dataclass(frozen=True)
class BatchRequest:
    manifest: Path
    output_dir: Path
    workers: int | None = None  # local Ray: runs at once (default: one per CPU)
    address: str | None = None  # a Ray cluster ("auto", "ray://head:10001"); None: local
    retries: int = 1  # times a run that crashed is tried again
    backend: str = "cpu"  # every run's compute backend
    force: bool = False  # overwrite existing results and run folders


@dataclass
class BatchResult:
    rows: list[dict]  # one per run, in manifest order
    outputs: BatchOutputs
    pictures: list[Path] = field(default_factory=list)  # the pictures the rows had data for
    wall_s: float = 0.0

    @property
    def failed(self) -> int:
        return sum(r["status"] != "ok" for r in self.rows)


def run(request: BatchRequest, on_progress: ProgressCallback | None = None) -> BatchResult:
    """Run the manifest's runs on Ray and write the results (see the module docstring)."""
    _check_request(request)
    manifest = load_manifest(request.manifest)
    specs = expand(manifest, request.manifest, Path(request.output_dir).resolve())
    import_ray()  # a clear error before any output when Ray is not installed
    with output_folder(request.output_dir):
        return _run(request, manifest, specs, on_progress)


def _run(request: BatchRequest, manifest: Manifest, specs: list[RunSpec],
         on_progress: ProgressCallback | None) -> BatchResult:
    outputs = _check_outputs(request, specs)
    start = time.perf_counter()
    rows: list[dict] = []

    def finished(row: dict) -> None:
        rows.append(row)
        report(on_progress, Progress(PROGRESS_STAGE, len(rows), len(specs),
                                     status=f"{row['job']}/{row['run']} {row['status']}",
                                     rate="" if row["wall_s"] is None
                                     else f"{row['wall_s']:.0f} s/run"))

    with ray_session(request.address, request.workers) as ray:
        task = remote_task(ray, execute, manifest.gpus_per_run)
        about = _about(request, manifest, ray)

        def submit(spec: RunSpec, attempt: int):
            return task.remote(spec, request.backend, request.force or attempt > 1,
                               manifest.success)

        try:
            rows = run_all(ray, submit, specs, request.retries, finished)
        except KeyboardInterrupt:
            order = {(s.job, s.run): i for i, s in enumerate(specs)}
            rows.sort(key=lambda r: order[(r["job"], r["run"])])
            _write(outputs, rows, about, start)
            raise RunInterrupted(f"interrupted after {len(rows)} of {len(specs)} runs; their "
                                 f"results are in {outputs.csv}") from None
    return _write(outputs, rows, about, start)


def _write(outputs: BatchOutputs, rows: list[dict], about: dict, start: float) -> BatchResult:
    wall_s = time.perf_counter() - start
    pictures = write_results(outputs, rows, {**about, "wall_s": round(wall_s, 1)})
    return BatchResult(rows, outputs, pictures, wall_s)


def _check_request(request: BatchRequest) -> None:
    if request.workers is not None and request.workers < 1:
        raise ConfigError(f"workers must be at least 1, not {request.workers}",
                          setting="workers")
    if request.retries < 0:
        raise ConfigError(f"retries must be 0 or more, not {request.retries}",
                          setting="retries")


def _check_outputs(request: BatchRequest, specs: list[RunSpec]) -> BatchOutputs:
    """The results files and every run folder, before any work."""
    outputs = BatchOutputs.in_folder(Path(request.output_dir))
    for path in (outputs.csv, outputs.json):
        check_writable(path, request.force)
    for spec in specs:
        folder = Path(spec.output_dir)
        if folder.is_dir() and any(folder.iterdir()) and not request.force:
            raise OutputExistsError(f"{folder} already holds the outputs of a run; allow "
                                    f"overwriting them", setting="force")
    return outputs


def _about(request: BatchRequest, manifest: Manifest, ray) -> dict:
    """How the batch ran, for results.json."""
    return {"manifest": str(Path(request.manifest).resolve()), "mcl3d": __version__,
            "ray": ray.__version__, "address": request.address, "workers": request.workers,
            "cluster_cpus": ray.cluster_resources().get("CPU"), "backend": request.backend,
            "gpus_per_run": manifest.gpus_per_run, "retries": request.retries,
            "success": manifest.success.model_dump(), "driver": platform.node()}


def summary_rows(result: BatchResult) -> list[tuple[str, str]]:
    """The CLI's end-of-batch table: runs, time, where the results are."""
    runs = len(result.rows)
    retried = sum(r["attempts"] > 1 for r in result.rows)
    return [("runs", f"{runs - result.failed} ok, {result.failed} failed of {runs}"
                     + (f" ({retried} tried again)" if retried else "")),
            ("wall time", f"{result.wall_s:.1f} s"),
            ("results", f"{result.outputs.csv}, {result.outputs.json.name}"),
            ("pictures", ", ".join(p.name for p in result.pictures) or "none (no figures "
                                                                         "to plot)")]
