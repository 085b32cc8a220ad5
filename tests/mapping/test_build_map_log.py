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
