"""The batch manifest: jobs (a command on a log, with settings) and the runs they expand to.

A manifest is YAML:

    jobs:
      - name: office                # the folder OUT/office/ holds its runs
        command: localize           # localize | odometry | slam | build-map
        log: logs/office_{seed}.mcap    # {seed}: one log per seed
        map: maps/office_{seed}.tsdf    # localize only
        preset: default             # the command's --preset
        config: {localizer.init.mode: global, max_scans: 200}   # dotted keys, as --config
        seeds: [1, 2, 3]            # localize and slam
        particles: [10000, 30000]   # localize and slam

Every job expands to the product seeds x particles, one run each, in OUT/<job>/<run>/.
Relative paths are taken from the manifest's folder. Everything is checked before any run
starts: a mistake is one `ConfigError` naming the manifest, the job and the key.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError

from mcl3d.core.config import Section
from mcl3d.core.errors import ConfigError, Mcl3dError

COMMANDS = ("localize", "odometry", "slam", "build-map")
RANDOM_COMMANDS = ("localize", "slam")  # the ones with a seed and a particle count
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"  # job names are folder names


class Topics(Section):
    """Topics of the job's log (default: detected, as the commands do)."""

    points: str | None = None
    imu: str | None = None
    odom: str | None = None
    gt: str | None = None


class Job(Section):
    """One command on one log (or one log per seed) with its settings."""

    name: str = Field(pattern=NAME_PATTERN, description="folder of its runs under OUT/")
    command: Literal["localize", "odometry", "slam", "build-map"]
    log: str = Field(description="the log (build-map: any source build-map takes); "
                                 "{seed} is replaced by each run's seed")
    map: str | None = Field(None, description="localize: the TSDF map; {seed} as in log")
    preset: str = Field("default", description="the command's named settings (--preset)")
    config: dict[str, Any] = Field(default_factory=dict,
                                   description="settings as dotted keys, as in --config files")
    seeds: list[int] | None = Field(None, min_length=1, description="one run per seed")
    particles: list[int] | None = Field(None, min_length=1,
                                        description="one run per particle count")
    max_scans: int | None = Field(None, ge=1, description="stop each run after this many scans")
    topics: Topics = Topics()


class SuccessCriterion(Section):
    """When a global localization run counts as a success, judged against ground truth (as
    bench/study_global.py): each of its last `tail_scans` estimates within the tolerances."""

    tail_scans: int = Field(10, ge=1)
    tolerance_m: float = Field(0.2, gt=0.0)
    tolerance_deg: float = Field(3.0, gt=0.0)


class Manifest(Section):
    jobs: list[Job] = Field(min_length=1)
    success: SuccessCriterion = SuccessCriterion()
    gpus_per_run: float = Field(0.0, ge=0.0, description="GPUs Ray reserves for each run "
                                "(e.g. 0.5: two runs share a GPU); 0 on cpu")


@dataclass(frozen=True)
class RunSpec:
    """One run: everything a worker process needs to execute it (plain, picklable data)."""

    job: str
    run: str  # the run's folder name under the job's
    command: str
    log: Path
    map: Path | None
    preset: str
    overrides: dict[str, Any]  # dotted keys, seed and particles included
    output_dir: Path
    seed: int | None = None
    particles: int | None = None
    max_scans: int | None = None
    topics: dict[str, str | None] = field(default_factory=dict)


def load_manifest(path: Path) -> Manifest:
    """Read and validate the manifest (structure and values; the files come in `expand`)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"manifest {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"manifest {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"manifest {path} must be a mapping with a list of `jobs`")
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"manifest {path}: {_where(exc, data)}") from None
    names = [job.name for job in manifest.jobs]
    for name in names:
        if names.count(name) > 1:
            raise ConfigError(f"manifest {path}: job {name!r}: name: used by "
                              f"{names.count(name)} jobs; give each job its own name")
    return manifest


def _where(exc: ValidationError, data: dict) -> str:
    """`job 'NAME': key: what is wrong` for the first error (the job by name when it has one)."""
    first = exc.errors()[0]
    loc = list(first["loc"])
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    if len(loc) >= 2 and loc[0] == "jobs" and isinstance(loc[1], int):
        jobs = data.get("jobs")
        job = jobs[loc[1]] if isinstance(jobs, list) else None
        label = (repr(job["name"]) if isinstance(job, dict) and isinstance(job.get("name"), str)
                 else f"number {loc[1] + 1}")
        key = ".".join(str(part) for part in loc[2:]) or "job"
        return f"job {label}: {key}: {first['msg']}{more}"
    return f"{'.'.join(str(part) for part in loc) or 'manifest'}: {first['msg']}{more}"


def expand(manifest: Manifest, manifest_path: Path, output_dir: Path) -> list[RunSpec]:
    """Every run of every job, with its paths resolved and its config checked."""
    from mcl3d.batch.commands import check_run

    root = Path(manifest_path).resolve().parent
    runs: list[RunSpec] = []
    for job in manifest.jobs:
        try:
            job_runs = _job_runs(job, root, Path(output_dir))
            for spec in job_runs:
                check_run(spec)
        except Mcl3dError as exc:
            raise ConfigError(f"manifest {manifest_path}: job {job.name!r}: {exc}") from None
        runs.extend(job_runs)
    return runs


def _job_runs(job: Job, root: Path, output_dir: Path) -> list[RunSpec]:
    random = job.command in RANDOM_COMMANDS
    for key in ("seeds", "particles"):
        if getattr(job, key) is not None and not random:
            raise ConfigError(f"{key}: {job.command} has no {key[:-1]} (only "
                              f"{' and '.join(RANDOM_COMMANDS)} do); remove the key")
    if job.command == "localize" and job.map is None:
        raise ConfigError("map: localize needs a map (a .tsdf file from build-map)")
    if job.command != "localize" and job.map is not None:
        raise ConfigError(f"map: {job.command} takes no map; remove the key")
    if "{seed}" in job.log + (job.map or "") and job.seeds is None:
        raise ConfigError("seeds: the log or map names {seed}, so the job needs seeds")
    config = _dotted(job.config)
    runs = []
    for seed, particles in itertools.product(job.seeds or [None], job.particles or [None]):
        name = "_".join([*([f"seed{seed}"] if seed is not None else []),
                         *([f"n{particles}"] if particles is not None else [])]) or "run"
        runs.append(RunSpec(
            job=job.name, run=name, command=job.command,
            log=_resolve(root, job.log, seed, "log"),
            map=None if job.map is None else _resolve(root, job.map, seed, "map"),
            preset=job.preset, overrides=config, output_dir=output_dir / job.name / name,
            seed=seed, particles=particles, max_scans=job.max_scans,
            topics=job.topics.model_dump()))
    return runs


def _dotted(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested sections flattened to dotted keys, so a preset keeps what they do not name."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict):
            flat.update(_dotted(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _resolve(root: Path, text: str, seed: int | None, key: str) -> Path:
    path = Path(text.replace("{seed}", str(seed)))
    path = path if path.is_absolute() else root / path
    if not path.exists():
        raise ConfigError(f"{key}: {path} does not exist")
    return path
