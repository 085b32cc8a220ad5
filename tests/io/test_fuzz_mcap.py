"""Fuzzing the MCAP log reader: a small log (several chunks, every message kind mcl3d reads)
damaged by bit flips, cuts and spliced or overwritten bytes, or random bytes behind the MCAP
magic, is read (past its damage) or refused with an mcl3d error, never a traceback; what is
read is sound and in order."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs.info import log_info
from mcl3d.io.logs.messages import Imu, PointCloud, PoseStamped, Transform
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.sources import MCAP_MAGIC
from mcl3d.io.logs.writer import LogWriter

T0 = 1_317_000_015_000_000_000
SCANS = 6


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    """Six scans of 20 points with IMU, ground truth and a static transform, about one scan per
    chunk: a few kB, so damage often hits the structure (heads, indexes, summary)."""
    path = tmp_path_factory.mktemp("fuzz_mcap") / "log.mcap"
    rng = np.random.default_rng(0)
    with LogWriter(path, chunk_size=400) as w:
        w.write_tf("/tf_static", [Transform(T0, "base", "lidar", np.eye(4))])
        for k in range(SCANS):
            stamp = T0 + k * 100_000_000
            points = (rng.normal(size=(20, 3)) * 5).astype(np.float32)
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", points, None))
            w.write_imu("/imu/data", Imu(stamp, "imu", rng.normal(size=3), rng.normal(size=3)))
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", np.eye(4)))
    return path


def _read(path) -> tuple:
    """Everything a run reads from a log: scans, IMU, ground truth, transforms, info."""
    with LogReader(path) as reader:
        counts = {kind: reader.count(kind) for kind in ("points", "imu", "gt")
                  if kind not in reader.problems}
        scans = list(reader.scans()) if reader.topics.points else []
        imu = [m for _k, m in reader.messages(("imu",))] if reader.topics.imu else []
        truth = reader.ground_truth() if reader.topics.gt else None
        reader.static_transforms()
        faults = reader.faults.as_dict()
        reader.faults.warnings()
    log_info(path)
    return scans, imu, truth, counts, faults


def _check(read) -> None:
    if read is None:
        return
    scans, imu, truth, _counts, _faults = read
    for messages in (scans, imu):
        assert all(a.stamp_ns < b.stamp_ns for a, b in pairwise(messages))
    assert all(np.isfinite(s.points).all() for s in scans)
    if truth is not None:
        assert np.isfinite(truth[1]).all() and (np.diff(truth[0]) > 0).all()


def test_the_small_log_reads_whole(small_log):
    scans, imu, truth, counts, faults = _read(small_log)
    assert len(scans) == len(imu) == len(truth[0]) == SCANS and faults == {}
    assert counts == {"points": SCANS, "imu": SCANS, "gt": SCANS}


@fuzz_settings(examples=60)
@given(data=st.data())
def test_damaged_mcap(small_log, tmp_path_factory, data):
    blob = data.draw(damaged(small_log.read_bytes()))
    if data.draw(st.booleans()):  # keep the magic so the reader goes past its first check
        blob = MCAP_MAGIC + blob[len(MCAP_MAGIC):]
    path = tmp_path_factory.getbasetemp() / "damaged.mcap"
    path.write_bytes(blob)
    _check(reads_or_refuses(lambda: _read(path)))


def test_a_damaged_type_definition_is_named(small_log, tmp_path):
    """Found by fuzzing: a flipped byte in the summary's copy of a message definition (a field
    renamed) made converting the messages fail with an AttributeError."""
    data = small_log.read_bytes()
    summary = data.index(b"geometry_msgs/Quaternion orientation")  # only the summary is plain
    bad = tmp_path / "renamed.mcap"
    bad.write_bytes(data[:summary] + data[summary:].replace(b"Quaternion orientation",
                                                            b"Quaternion orientatinn"))
    with LogReader(bad) as reader, pytest.raises(LogFormatError, match="/ground_truth does not "
                                                 "hold the fields of geometry_msgs/PoseStamped"):
        reader.ground_truth()
