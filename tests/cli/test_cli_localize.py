"""`mcl3d localize` end to end on a tiny ray-cast room log, plus the bad-input cases."""

import json

import numpy as np
import pytest
from support.pictures import assert_picture
from typer.testing import CliRunner

localize_world = pytest.importorskip("support.localize_world")

TIGHT = "0.05 0.05 0.02 0.573 0.573 1.146"  # m, deg
EMPTY_STAMP = localize_world.START_NS + 2 * 100_000_000  # bare.mcap's empty scan


@pytest.fixture(scope="module")
def data(tmp_path_factory, backend):
    from mcl3d.core import runtime

    runtime.init(backend)
    d = tmp_path_factory.mktemp("localize")
    localize_world.write_log(d / "room.mcap", 12)
    localize_world.write_log(d / "bare.mcap", 6, odom=False, gt=False, empty_scans=(2,))
    localize_world.write_log(d / "empty.mcap", 3, odom=False, empty_scans=(0, 1, 2))
    localize_world.save_room_map(d / "room.tsdf", 0.1)
    localize_world.save_room_map(d / "far.tsdf", 0.1, offset_m=(200.0, 0.0, 0.0))
    save_corridor_map(d / "corridor.tsdf")
    return d


def save_corridor_map(path) -> None:
    """A map of another place: a long bare corridor, nothing like the room."""
    from mcl3d.maps.build import BuildConfig, build_from_mesh
    from mcl3d.maps.map_file import save_map
    from mcl3d.sim.mesh import MeshBuilder

    b = MeshBuilder()
    length, width, height, t = 30.0, 2.5, 3.0, 0.2
    b.box((-t, -t, -t), (length + t, width + t, 0.0), 0.5)
    b.box((-t, -t, height), (length + t, width + t, height + t), 0.5)
    b.box((-t, -t, 0.0), (0.0, width + t, height), 0.5)
    b.box((length, -t, 0.0), (length + t, width + t, height), 0.5)
    b.box((0.0, -t, 0.0), (length, 0.0, height), 0.5)
    b.box((0.0, width, 0.0), (length, width + t, height), 0.5)
    mesh = b.build()
    tsdf = build_from_mesh(mesh.vertices, mesh.triangles,
                           BuildConfig(voxel_size_m=0.1))
    save_map(path, tsdf, source={"kind": "test corridor"}, build={})


def invoke(*args):
    from mcl3d.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def said(result) -> str:
    """What the user sees: the output, or the typed error the app prints as one line (with
    the flag of the setting that fixes it)."""
    from mcl3d.cli import _with_flag
    from mcl3d.core.errors import Mcl3dError

    exc = result.exception
    if exc is None:
        return result.output
    return result.output + (_with_flag(exc) if isinstance(exc, Mcl3dError) else str(exc))


def test_tracking_end_to_end(data, tmp_path):
    out = tmp_path / "out"
    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o", out,
               "--init", "gt", "--init-std", TIGHT, "--particles", 3000, "--seed", 3,
               "--backend", "cpu", "--result-mcap", tmp_path / "result.mcap")
    assert r.exit_code == 0, r.output
    assert "Localization" in r.output and "ATE" in r.output
    tum = np.loadtxt(out / "trajectory.tum")
    assert tum.shape == (12, 8)
    assert np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-6)
    assert np.loadtxt(out / "trajectory.kitti").shape == (12, 12)
    rows = (out / "scans.csv").read_text().splitlines()
    assert rows[0].startswith("stamp_s,x,y,z,qx,qy,qz,qw,var_rx") and len(rows) == 13
    assert all(",odom," in row for row in rows[2:])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["motion_source"] == "odom"
    assert summary["ate_all"]["translation_rmse_m"] < 0.08
    assert summary["final_state"] == "converged"
    assert "localizer" in (out / "config.yaml").read_text()
    assert_picture(out / "localize.png")
    assert "picture" in r.output
    from support.foxglove_check import read_result

    assert len(read_result(tmp_path / "result.mcap")["/scan"]) == 12  # foxglove.PointCloud
    # the same command again: outputs exist, refused before any work
    again = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o", out,
                   "--init", "gt", "--backend", "cpu")
    assert again.exit_code == 1 and "--force" in said(again)


def test_global_init_and_reproducible(data, tmp_path):
    args = ("localize", data / "room.mcap", "--map", data / "room.tsdf", "--particles", 4000,
            "--seed", 9, "--backend", "cpu", "--max-scans", 4)
    r1 = invoke(*args, "-o", tmp_path / "a")
    r2 = invoke(*args, "-o", tmp_path / "b")
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    a = np.loadtxt(tmp_path / "a" / "trajectory.tum")
    b = np.loadtxt(tmp_path / "b" / "trajectory.tum")
    assert a.shape == (4, 8)
    np.testing.assert_array_equal(a, b)


def test_no_motion_source_and_empty_scan(data, tmp_path):
    out = tmp_path / "out"
    r = invoke("localize", data / "bare.mcap", "--map", data / "room.tsdf", "-o", out,
               "--init", "6.1 2.8 0.8 0 0 90", "--init-std", TIGHT, "--particles", 2000,
               "--backend", "cpu")
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["motion_source"] == "constant_velocity"
    assert summary["skipped_scans"] == 0 and summary["scans"] == 5  # the empty scan: a fault
    assert summary["faults"] == {"scan_empty": {"count": 1, "first_stamps_ns": [EMPTY_STAMP]}}
    assert "1 scan dropped with no valid point" in r.output
    assert any("constant-velocity" in w for w in summary["warnings"])
    assert "ate_all" not in summary  # no ground truth in this log


def test_all_scans_empty_is_an_error(data, tmp_path):
    r = invoke("localize", data / "empty.mcap", "--map", data / "room.tsdf", "-o",
               tmp_path / "o", "--init", "gt", "--particles", 1000, "--backend", "cpu")
    assert r.exit_code == 1
    assert "no scan on /lidar/points has 10 points or more" in said(r)


def test_map_and_log_far_apart(data, tmp_path):
    r = invoke("localize", data / "room.mcap", "--map", data / "far.tsdf", "-o",
               tmp_path / "o", "--init", "gt", "--particles", 1000, "--backend", "cpu")
    assert r.exit_code == 1
    assert "outside the map" in said(r) and "different frames" in said(r)


def test_global_init_in_a_map_of_another_place_says_so(data, tmp_path):
    """No overlap that global init can notice at once (walls match walls): the run finishes,
    never converges, and says why in a warning and in summary.json."""
    out = tmp_path / "out"
    r = invoke("localize", data / "room.mcap", "--map", data / "corridor.tsdf", "-o", out,
               "--particles", 2000, "--seed", 1, "--backend", "cpu")
    assert r.exit_code == 0, r.output
    assert "converged" in r.output and "never" in r.output
    assert "did not converge" in r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged_at_scan"] is None and summary["final_state"] != "converged"
    assert any("check the map" in w for w in summary["warnings"])


def test_motion_source_asked_for_but_missing(data, tmp_path):
    r = invoke("localize", data / "bare.mcap", "--map", data / "room.tsdf", "-o",
               tmp_path / "o", "--init", "gt", "--motion", "odom", "--backend", "cpu")
    assert r.exit_code == 1
    assert "--motion" in said(r) and "no odometry" in said(r)
    assert not (tmp_path / "o").exists()


def test_more_particles_than_memory_is_refused_before_work(data, tmp_path, monkeypatch):
    import mcl3d.localization.particle_set

    monkeypatch.setattr(mcl3d.localization.particle_set, "available_memory_bytes",
                        lambda: 64 * 2**20)
    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o",
               tmp_path / "o", "--init", "gt", "--particles", 1_000_000, "--backend", "cpu")
    assert r.exit_code == 1
    assert "1,000,000 particles need" in said(r) and "of memory is free" in said(r)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("args", "message"), [
    (("--particles", 9_000_000), "9,000,000 particles"),
    (("--particles", 0), "particles"),
    (("--init", "1 2 3"), "--init"),
    (("--init", "gt", "--init-std", "a b c d e f"), "--init-std"),
    (("--height-band", "2 1"), "height band"),
])
def test_bad_parameters(data, tmp_path, args, message):
    r = invoke("localize", data / "room.mcap", "--map", data / "room.tsdf", "-o",
               tmp_path / "o", "--backend", "cpu", *args)
    assert r.exit_code in (1, 2)
    assert message in said(r)
    assert not (tmp_path / "o" / "trajectory.tum").exists()


def test_interrupt_keeps_the_trajectory(data, tmp_path):
    from mcl3d.core.errors import RunInterrupted
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    cfg = LocalizeConfig.model_validate({"localizer": {"particles": 1000, "init": {
        "mode": "gt", "std": [0.05, 0.05, 0.02, 0.573, 0.573, 1.146]}}})

    def stop_after_three(progress):
        if progress.done == 3:
            raise KeyboardInterrupt

    with pytest.raises(RunInterrupted, match="after 3 scans"):
        run(LocalizeRequest(data / "room.mcap", data / "room.tsdf", tmp_path / "o", cfg,
                            backend="cpu"), on_progress=stop_after_three)
    assert np.loadtxt(tmp_path / "o" / "trajectory.tum").shape == (3, 8)


def test_a_crash_keeps_the_checkpointed_trajectory(data, tmp_path, monkeypatch):
    from mcl3d.core.checkpoint import CHECKPOINT_ENV
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    monkeypatch.setenv(CHECKPOINT_ENV, "0")  # a checkpoint after every scan
    cfg = LocalizeConfig.model_validate({"localizer": {"particles": 1000, "init": {
        "mode": "gt", "std": [0.05, 0.05, 0.02, 0.573, 0.573, 1.146]}}})

    def crash_at_five(progress):
        if progress.done == 5:
            raise RuntimeError("crash")

    with pytest.raises(RuntimeError, match="crash"):
        run(LocalizeRequest(data / "room.mcap", data / "room.tsdf", tmp_path / "o", cfg,
                            backend="cpu"), on_progress=crash_at_five)
    assert np.loadtxt(tmp_path / "o" / "trajectory.tum").shape == (4, 8)
    assert np.loadtxt(tmp_path / "o" / "trajectory.kitti").shape == (4, 12)
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["checkpoint"] is True and summary["scans"] == 4


def test_missing_inputs_leave_no_output_folder(data, tmp_path):
    out = tmp_path / "out"
    r = invoke("localize", tmp_path / "nope.mcap", "--map", data / "room.tsdf", "-o", out,
               "--backend", "cpu")
    assert r.exit_code == 1 and "no such file" in said(r)
    r = invoke("localize", data / "room.mcap", "--map", tmp_path / "nope.tsdf", "-o", out,
               "--backend", "cpu")
    assert r.exit_code == 1 and "does not exist" in said(r)
    assert not out.exists()
