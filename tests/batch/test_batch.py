"""`mcl3d batch`: manifest checks, a two-job manifest on a local Ray with two workers against
the same runs one after the other, retries of crashed runs, and the missing-Ray error.

One Ray session serves the module (started once, shut down after): the batch uses a session
its process already runs."""

import json
import os
import sys

import pytest

from mcl3d.batch.manifest import SuccessCriterion, expand, load_manifest
from mcl3d.core.errors import ConfigError, Mcl3dError

localize_world = pytest.importorskip("support.localize_world")

TIGHT_STD = [0.05, 0.05, 0.02, 0.573, 0.573, 1.146]  # m, deg
SCANS = 16  # 2.3 m of path: enough for RPE pairs 1 m apart
IGNORED = ("wall_s", "output", "attempts", "ms_per_scan")  # what differs between the same
# run here and there: timings and the folder


@pytest.fixture(scope="module")
def data(tmp_path_factory, backend):
    from mcl3d.core import runtime

    runtime.init(backend)
    d = tmp_path_factory.mktemp("batch")
    localize_world.write_log(d / "room.mcap", SCANS)
    localize_world.save_room_map(d / "room.tsdf", 0.1)
    localize_world.write_log(d / "empty.mcap", 3, odom=False, empty_scans=(0, 1, 2))
    return d


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def write_manifest(path, text: str):
    path.write_text(text)
    return path


TWO_JOBS = f"""
jobs:
  - name: loc
    command: localize
    log: room.mcap
    map: room.tsdf
    config:
      localizer: {{init: {{mode: gt, std: {TIGHT_STD}}}}}
    seeds: [1, 2]
    particles: [1500]
  - name: odo
    command: odometry
    log: room.mcap
    config: {{use_imu: false}}
"""


@pytest.mark.parametrize(("job", "said"), [
    ("{name: a, command: fly, log: room.mcap}", "job 'a': command: Input should be"),
    ("{name: a, command: odometry, log: nowhere.mcap}", "job 'a': log: "),
    ("{name: a, command: localize, log: room.mcap}", "job 'a': map: localize needs a map"),
    ("{name: a, command: localize, log: room.mcap, map: room.tsdf, config: {localizer.nope: 1}}",
     "job 'a': config.localizer.nope: Extra inputs are not permitted"),
    ("{name: a, command: slam, log: room.mcap, particles: [0]}",
     "job 'a': config.particles: Input should be greater than or equal to 1"),
    ("{name: o, command: odometry, log: room.mcap, seeds: [1]}", "job 'o': seeds: odometry has no"),
    ("{name: a, command: slam, log: 'room_{seed}.mcap'}", "job 'a': seeds: the log or map names"),
    ("{name: a, command: slam, log: room.mcap, preset: fast}", "job 'a': unknown SLAM preset"),
    ("{name: a, command: slam, log: room.mcap, seeds: one}", "job 'a': seeds: Input should be"),
    ("{command: slam, log: room.mcap}", "job number 1: name: Field required"),
    ("{name: 'a/b', command: slam, log: room.mcap}", "job 'a/b': name: String should match"),
])
def test_a_bad_manifest_names_the_job_and_key_before_any_work(data, tmp_path, job, said):
    manifest = write_manifest(data / "bad.yaml", f"jobs:\n  - {job}\n")
    with pytest.raises(ConfigError) as exc:
        expand(load_manifest(manifest), manifest, tmp_path / "out")
    text = str(exc.value)
    assert text.startswith(f"manifest {manifest}: ") and said in text, text
    assert "\n" not in text


@pytest.mark.parametrize(("text", "said"), [
    ("jobs: []\n", "jobs: List should have at least 1 item"),
    ("- just a list\n", "must be a mapping with a list of `jobs`"),
    ("jobs: [\n", "is not valid YAML"),
    ("jobs:\n  - {name: a, command: slam, log: room.mcap}\n"
     "  - {name: a, command: odometry, log: room.mcap}\n", "job 'a': name: used by 2 jobs"),
])
def test_a_bad_manifest_file(data, text, said):
    manifest = write_manifest(data / "bad.yaml", text)
    with pytest.raises(ConfigError) as exc:
        load_manifest(manifest)
    assert said in str(exc.value)


def test_a_job_expands_to_seeds_times_particles(data, tmp_path):
    manifest = write_manifest(data / "grid.yaml", """
jobs:
  - {name: g, command: localize, log: room.mcap, map: room.tsdf, seeds: [1, 2, 3],
     particles: [1000, 2000], max_scans: 5, topics: {gt: /ground_truth}}
  - {name: m, command: build-map, log: room.mcap, config: {voxel_size_m: 0.2}}
""")
    runs = expand(load_manifest(manifest), manifest, tmp_path / "out")
    assert [r.run for r in runs[:6]] == ["seed1_n1000", "seed1_n2000", "seed2_n1000",
                                         "seed2_n2000", "seed3_n1000", "seed3_n2000"]
    assert runs[1].log == data / "room.mcap" and runs[1].map == data / "room.tsdf"
    assert runs[1].output_dir == tmp_path / "out" / "g" / "seed1_n2000"
    assert runs[6].run == "run" and runs[6].overrides == {"voxel_size_m": 0.2}


def test_two_jobs_on_ray_equal_the_same_runs_one_after_the_other(data, tmp_path, ray_session):
    """`mcl3d batch` end to end on two workers, then each run again here, one after the
    other: the same rows and, byte for byte, the same trajectories."""
    from typer.testing import CliRunner

    from mcl3d.batch.commands import execute
    from mcl3d.cli import app

    manifest = write_manifest(data / "two.yaml", TWO_JOBS)
    out = tmp_path / "ray"
    said = CliRunner().invoke(app, ["batch", str(manifest), "-o", str(out), "--workers", "2",
                                    "--backend", "cpu"])
    assert said.exit_code == 0, said.output
    assert "3 ok, 0 failed of 3" in said.output and "Jobs" in said.output
    saved = json.loads((out / "results.json").read_text())
    rows = saved["runs"]
    assert [(r["job"], r["run"], r["status"]) for r in rows] == [
        ("loc", "seed1_n1500", "ok"), ("loc", "seed2_n1500", "ok"),
        ("odo", "run", "ok")], rows

    specs = expand(load_manifest(manifest), manifest, tmp_path / "one_by_one")
    sequential = [execute(spec, "cpu", False, SuccessCriterion()) for spec in specs]
    for batch_row, row in zip(rows, sequential, strict=True):
        assert {k: v for k, v in batch_row.items() if k not in IGNORED} == \
               {k: v for k, v in row.items() if k not in IGNORED}
    for folder, name in (("loc/seed1_n1500", "trajectory.tum"),
                         ("loc/seed2_n1500", "trajectory.tum"),
                         ("odo/run", "odometry.tum")):
        assert (out / folder / name).read_bytes() == \
               (tmp_path / "one_by_one" / folder / name).read_bytes()

    loc, odo = rows[0], rows[2]
    assert loc["success"] is True and loc["converged"] and loc["ate_m"] < 0.1
    assert loc["seed"] == 1 and loc["particles"] == 1500 and loc["scans"] == SCANS
    assert odo["ate_m"] < 0.1 and odo["rpe_m"] is not None and odo["rpe_m"] < 0.1
    assert odo["drift_percent"] is not None
    assert rows[0]["ate_m"] != rows[1]["ate_m"]  # the seeds differ, so do the runs

    csv_lines = (out / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 4 and csv_lines[0].startswith("job,run,command,log,map,preset")
    assert saved["jobs"][0]["runs"] == 2 and saved["jobs"][0]["success_rate"] == 1.0
    assert saved["cluster_cpus"] == 2
    for name in ("success_vs_particles.png", "ate_per_log.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_run_that_stops_on_bad_input_is_a_failed_row_not_retried(data, tmp_path,
                                                                   ray_session):
    from mcl3d.batch.pipeline import BatchRequest, run

    manifest = write_manifest(data / "mixed.yaml", """
jobs:
  - {name: empty, command: odometry, log: empty.mcap}
  - {name: map, command: build-map, log: room.mcap, config: {voxel_size_m: 0.2}}
""")
    progress = []
    result = run(BatchRequest(manifest, tmp_path / "out", backend="cpu", retries=2),
                 progress.append)
    empty, built = result.rows
    assert empty["status"] == "failed" and empty["attempts"] == 1
    assert "empty.mcap" in empty["error"] and "\n" not in empty["error"]
    assert not (tmp_path / "out" / "empty" / "run").exists()  # nothing half-written
    assert built["status"] == "ok" and built["scans"] == SCANS and built["map_bytes"] > 0
    assert (tmp_path / "out" / "map" / "run" / "map.tsdf").is_file()
    assert sorted(p.status for p in progress) == ["empty/run failed", "map/run ok"]
    assert [p.done for p in progress] == [1, 2] and progress[0].total == 2
    assert result.failed == 1
    assert result.pictures == []  # no success and no ATE to plot
    lines = result.outputs.csv.read_text().splitlines()
    assert lines[1].startswith("empty,run,odometry,") and ",failed," in lines[1]


def test_runs_that_raise_or_whose_worker_dies_are_tried_again(tmp_path, ray_session):
    from mcl3d.batch.manifest import RunSpec
    from mcl3d.batch.scheduler import run_all

    def flaky(spec):  # defined here: Ray ships it by value to its workers
        from mcl3d.batch.commands import base_row

        tried = spec.output_dir / "tried"
        first = not tried.exists()
        spec.output_dir.mkdir(parents=True, exist_ok=True)
        tried.touch()
        if spec.job == "dies":
            os._exit(3)
        if spec.job == "raises" or first:
            raise RuntimeError(f"{spec.job} failed")
        return {**base_row(spec), "status": "ok"}

    task = ray_session.remote(num_cpus=1, max_calls=1, max_retries=0)(flaky)
    specs = [RunSpec(job, "run", "odometry", tmp_path / "log", None, "default", {},
                     tmp_path / job) for job in ("recovers", "raises", "dies")]
    seen = []
    rows = run_all(ray_session, lambda spec, attempt: task.remote(spec), specs, 1, seen.append)
    assert len(seen) == 3
    recovers, raises, dies = rows
    assert recovers["status"] == "ok" and recovers["attempts"] == 2
    assert raises["status"] == "failed" and raises["attempts"] == 2
    assert raises["error"] == "RuntimeError: raises failed"
    assert dies["status"] == "failed" and dies["attempts"] == 2 and dies["error"]


def test_without_ray_the_batch_says_how_to_install_it(data, tmp_path, monkeypatch):
    from mcl3d.batch.pipeline import BatchRequest, run

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    manifest = write_manifest(data / "two.yaml", TWO_JOBS)
    with pytest.raises(Mcl3dError) as exc:
        run(BatchRequest(manifest, tmp_path / "out", backend="cpu"))
    assert str(exc.value) == "mcl3d batch needs Ray: pip install 'mcl3d[batch]'"
    assert not (tmp_path / "out").exists()


def test_existing_results_are_kept_without_force(data, tmp_path, ray_session):
    from mcl3d.batch.pipeline import BatchRequest, run
    from mcl3d.core.errors import OutputExistsError

    manifest = write_manifest(data / "two.yaml", TWO_JOBS)
    (tmp_path / "out" / "loc" / "seed2_n1500").mkdir(parents=True)
    (tmp_path / "out" / "loc" / "seed2_n1500" / "trajectory.tum").write_text("kept\n")
    with pytest.raises(OutputExistsError, match="seed2_n1500 already holds"):
        run(BatchRequest(manifest, tmp_path / "out", backend="cpu"))
    assert (tmp_path / "out" / "loc" / "seed2_n1500" / "trajectory.tum").read_text() == "kept\n"
    assert not (tmp_path / "out" / "results.csv").exists()


@pytest.mark.parametrize("name", ["study_global.yaml", "study_slam.yaml"])
def test_the_studies_manifests_are_valid(tmp_path, name):
    """bench/manifests/: every job's settings are valid for its command (the logs they name
    stand in as empty files: only their existence is checked before a batch runs)."""
    from pathlib import Path

    source = Path(__file__).resolve().parents[2] / "bench" / "manifests" / name
    manifest = tmp_path / "manifests" / name
    manifest.parent.mkdir()
    manifest.write_text(source.read_text())
    for job in load_manifest(manifest).jobs:
        for seed in job.seeds:
            for text in (job.log, job.map or job.log):
                path = manifest.parent / text.replace("{seed}", str(seed))
                path.parent.mkdir(parents=True, exist_ok=True)
                path.touch()
    runs = expand(load_manifest(manifest), manifest, tmp_path / "out")
    assert len(runs) == {"study_global.yaml": 80, "study_slam.yaml": 12}[name]


def test_the_command_stops_on_a_bad_manifest_or_option(data, tmp_path):
    from typer.testing import CliRunner

    from mcl3d.cli import app

    manifest = write_manifest(data / "bad.yaml", "jobs:\n  - {name: a, command: fly, log: x}\n")
    said = CliRunner().invoke(app, ["batch", str(manifest), "-o", str(tmp_path / "out")])
    assert said.exit_code == 1 and isinstance(said.exception, ConfigError)
    assert "job 'a': command:" in str(said.exception)
    said = CliRunner().invoke(app, ["batch", str(manifest), "-o", str(tmp_path / "out"),
                                    "--workers", "0"])
    assert said.exit_code == 2  # a usage error
    assert not (tmp_path / "out").exists()
