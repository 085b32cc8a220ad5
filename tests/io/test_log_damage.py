"""A log cut part way (a recorder killed mid-chunk) is read up to the cut, the cut chunk's whole
records included, and the truncation is named in the run's faults; a file damaged before its
first message, or not an MCAP at all, stops with one error."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs.messages import Imu, PointCloud
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import LogWriter

T0 = 1_317_000_015_000_000_000
PERIOD = 100_000_000
SCANS = 40


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    """40 scans of 2000 random points with IMU between them: one chunk, so any cut is mid-chunk."""
    path = tmp_path_factory.mktemp("damage") / "log.mcap"
    rng = np.random.default_rng(0)
    with LogWriter(path) as w:
        for k in range(SCANS):
            stamp = T0 + k * PERIOD
            pts = (rng.normal(size=(2000, 3)) * 10).astype(np.float32)
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, None))
            for j in range(5):
                w.write_imu("/imu/data", Imu(stamp + j * 20_000_000, "imu", rng.normal(size=3),
                                             rng.normal(size=3)))
    return path


def test_a_cut_log_is_read_up_to_the_cut(small_log, tmp_path):
    data = small_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    with LogReader(cut) as reader:
        stamps = [cloud.stamp_ns for cloud in reader.scans()]
        imu = sum(1 for _ in reader.messages(("imu",)))
        truncation = reader.faults.truncation
        assert reader.count("points") == len(stamps)
        faults = reader.faults.as_dict()
        warnings = reader.faults.warnings()
    assert SCANS // 2 <= len(stamps) < SCANS
    assert stamps == [T0 + k * PERIOD for k in range(len(stamps))]
    assert imu >= 5 * (len(stamps) - 1)
    assert truncation.scans_read == len(stamps) and truncation.total_bytes == len(cut.read_bytes())
    assert faults == {"log_truncated": truncation.as_dict()}
    assert len(warnings) == 1 and f"read the {len(stamps)} scans up to the damage" in warnings[0]


def test_a_clean_log_is_not_truncated(small_log):
    with LogReader(small_log) as reader:
        assert sum(1 for _ in reader.scans()) == SCANS
        assert reader.faults.truncation is None and not reader.faults.found()


@pytest.mark.parametrize("keep", [100, 2000])
def test_a_log_damaged_before_its_first_message_stops(small_log, tmp_path, keep):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(small_log.read_bytes()[:keep])
    with pytest.raises(LogFormatError, match="damaged before its first message"):
        LogReader(cut)


def test_a_file_that_is_not_an_mcap_stops(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a log" * 100)
    with pytest.raises(LogFormatError, match="not an MCAP file"):
        LogReader(junk)
