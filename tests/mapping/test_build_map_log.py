"""build-map from a log: pass 1 keeps the decoded scans (what fusion reads of them) for the
fusion pass, so the log is decoded once; a spinning lidar's scans take their normals from the
range image on the device."""

import numpy as np
import pytest
from typer.testing import CliRunner

from mcl3d.cli import app


@pytest.fixture(scope="module")
def vlp16_log(tmp_path_factory):
    log = tmp_path_factory.mktemp("log") / "office.mcap"
    result = CliRunner().invoke(app, ["simulate", "office", "--duration", "0.3", "--seed",
                                      "1", "-o", str(log)])
    assert result.exit_code == 0, result.output
    return log


def _bounds(log, **config):
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.mapping import pipeline
    from mcl3d.maps.build import BuildConfig

    request = pipeline.BuildMapRequest(source=log, output=log.with_suffix(".tsdf"),
                                       config=BuildConfig(**config))
    with LogReader(log) as reader:
        traj, _ = pipeline._poses(request, reader)
        return pipeline._scan_bounds(request, reader, traj), list(reader.scans())


def test_pass_one_keeps_the_scans_while_they_fit(vlp16_log):
    scans, decoded = _bounds(vlp16_log)
    assert scans.n_scans == len(scans.cached) == len(decoded) == 3
    for kept, cloud in zip(scans.cached, decoded, strict=True):
        assert set(kept.fields) == {"ring"}  # only what fusion reads
        np.testing.assert_array_equal(kept.points, cloud.points)
        np.testing.assert_array_equal(kept.times_s, cloud.times_s)
        np.testing.assert_array_equal(kept.fields["ring"], cloud.fields["ring"])
    assert _bounds(vlp16_log, scan_cache_mb=0)[0].cached is None  # read again in pass 2


def test_ground_truth_and_scans_come_from_one_read_while_the_scans_fit(vlp16_log,
                                                                       monkeypatch):
    """With the log's ground truth as poses, one read of the log gives the poses and pass 1
    (the same as the poses first, then pass 1); scans that would overflow the cache take
    the two reads."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.mapping import pipeline
    from mcl3d.maps.build import BuildConfig

    reads = []
    messages = LogReader.messages

    def counted(self, kinds=("points", "gt")):
        reads.append(tuple(kinds))
        return messages(self, kinds)

    monkeypatch.setattr(LogReader, "messages", counted)
    two_reads, _ = _bounds(vlp16_log)
    for cache_mb, last_reads in ((512, [("points", "gt")]), (0, [("gt",), ("points",)])):
        request = pipeline.BuildMapRequest(source=vlp16_log, output=vlp16_log.with_suffix(
            ".tsdf"), config=BuildConfig(scan_cache_mb=cache_mb))
        with LogReader(vlp16_log) as reader:
            reads.clear()
            traj, _, scans = pipeline._poses_and_scans(request, reader)
        assert reads[-len(last_reads):] == last_reads  # before them: the first scan alone
        assert reads.count(("gt",)) == (cache_mb == 0)
        np.testing.assert_array_equal(scans.lo_m, two_reads.lo_m)
        np.testing.assert_array_equal(scans.hi_m, two_reads.hi_m)
        assert scans.n_scans == two_reads.n_scans == 3
        assert (scans.cached is None) == (cache_mb == 0)
        with LogReader(vlp16_log) as reader:
            truth, _ = pipeline._poses(request, reader)
        np.testing.assert_array_equal(traj.stamps_ns, truth.stamps_ns)
        np.testing.assert_array_equal(traj.poses, truth.poses)


def test_log_fused_from_the_cache_with_range_image_normals(ti_runtime, vlp16_log, tmp_path,
                                                           monkeypatch):
    from mcl3d.mapping import pipeline
    from mcl3d.maps import build

    fused = []
    fuse_all = pipeline._fuse_all

    def recorded(clouds, *args):
        fused.append(clouds)
        return fuse_all(clouds, *args)

    def no_host_normals(*_args, **_kwargs):
        raise AssertionError("a scan with rings took the host KNN normals")

    monkeypatch.setattr(pipeline, "_fuse_all", recorded)
    monkeypatch.setattr(build, "oriented_normals", no_host_normals)
    result = pipeline.run(pipeline.BuildMapRequest(source=vlp16_log,
                                                   output=tmp_path / "map.tsdf"))
    assert result.n_scans == 3 and result.stats.blocks > 100
    assert isinstance(fused[0], list) and len(fused[0]) == 3  # no second read of the log


def test_pass_one_bounds_are_those_of_the_points_in_range():
    """world_bounds (column by column) against the plain (n, 3) transform of the points
    within range; None when no point is in range."""
    from scipy.spatial.transform import Rotation

    from mcl3d.mapping.pipeline import world_bounds

    rng = np.random.default_rng(4)
    points = rng.normal(0.0, 20.0, (5000, 3)).astype(np.float32)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=5).as_matrix()
    T[:3, 3] = [12.0, -3.0, 1.5]
    r = np.linalg.norm(points, axis=1)
    inside = points[(r >= 2.0) & (r <= 30.0)].astype(np.float64)
    world = inside @ T[:3, :3].T + T[:3, 3]
    lo, hi = world_bounds(points, T, 2.0, 30.0)
    np.testing.assert_allclose(lo, world.min(axis=0), atol=1e-4)
    np.testing.assert_allclose(hi, world.max(axis=0), atol=1e-4)
    assert world_bounds(points * 100.0, T, 2.0, 30.0) is None
