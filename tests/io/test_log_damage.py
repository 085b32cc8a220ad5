"""A log cut part way (a recorder killed mid-chunk) is read up to the cut, the cut chunk's whole
records included, and the truncation is named in the run's faults; a file damaged before its
first message, or not an MCAP at all, stops with one error."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs.messages import Imu, PointCloud
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import CHUNK_SIZE, LogWriter

T0 = 1_317_000_015_000_000_000
PERIOD = 100_000_000
SCANS = 40


def write_scans(path, seed: int, chunk_size: int = CHUNK_SIZE):
    """SCANS scans of 2000 random points with IMU between them."""
    rng = np.random.default_rng(seed)
    with LogWriter(path, chunk_size=chunk_size) as w:
        for k in range(SCANS):
            stamp = T0 + k * PERIOD
            pts = (rng.normal(size=(2000, 3)) * 10).astype(np.float32)
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", pts, None))
            for j in range(5):
                w.write_imu("/imu/data", Imu(stamp + j * 20_000_000, "imu", rng.normal(size=3),
                                             rng.normal(size=3)))
    return path


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    """The scans in one chunk, so any cut is mid-chunk."""
    return write_scans(tmp_path_factory.mktemp("damage") / "log.mcap", seed=0)


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


# ---- damage in the middle: skipped, reading on at the next intact chunk ----

CHUNK_BYTES = 40_000  # about one scan per chunk, as a recorder's small chunks hold


@pytest.fixture(scope="module")
def chunked_log(tmp_path_factory):
    """The same kind of scans in chunks of about one scan each."""
    return write_scans(tmp_path_factory.mktemp("chunked") / "log.mcap", seed=1,
                       chunk_size=CHUNK_BYTES)


def _chunk_starts(path) -> list[tuple[int, int]]:
    """(start byte, length) of each chunk record, from the log's summary."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(ci.chunk_start_offset, ci.chunk_length)
                for ci in make_reader(f).get_summary().chunk_indexes]


def _summary_start(data: bytearray) -> int:
    """Where the summary starts, from the footer (29 bytes before the closing 8-byte magic)."""
    return int.from_bytes(data[-28:-20], "little")


def _garbage_in_records(data: bytearray, chunks) -> None:
    start, length = chunks[len(chunks) // 2]
    data[start + length // 2:start + length // 2 + 300] = np.random.default_rng(5).bytes(300)


def _zeros_over_a_head(data: bytearray, chunks) -> None:
    start, _length = chunks[len(chunks) // 3]
    data[start - 40:start + 2000] = bytes(2040)


def _one_bit_flipped(data: bytearray, chunks) -> None:
    start, length = chunks[len(chunks) // 2]
    data[start + length - 100] ^= 0x10


def _summary_garbage_too(data: bytearray, chunks) -> None:
    _garbage_in_records(data, chunks)
    summary_start = _summary_start(data)
    data[summary_start:summary_start + 500] = np.random.default_rng(6).bytes(500)


DAMAGES = {"garbage in a chunk's records": _garbage_in_records,
           "zeros over a chunk head": _zeros_over_a_head,
           "one bit flipped": _one_bit_flipped,
           "a damaged summary as well": _summary_garbage_too}


@pytest.mark.parametrize("damage", DAMAGES)
def test_damage_in_the_middle_is_skipped(chunked_log, tmp_path, damage):
    data = bytearray(chunked_log.read_bytes())
    DAMAGES[damage](data, _chunk_starts(chunked_log))
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data))
    with LogReader(bad) as reader:
        stamps = [cloud.stamp_ns for cloud in reader.scans()]
        imu = sum(1 for _ in reader.messages(("imu",)))
        faults = reader.faults.as_dict()
        warnings = reader.faults.warnings()
        assert "damaged stretch skipped" in reader.source.format
    expected = [T0 + k * PERIOD for k in range(SCANS)]
    assert len(stamps) >= 0.9 * SCANS and set(stamps) < set(expected)
    assert stamps == sorted(stamps) and stamps[0] == expected[0] and stamps[-1] == expected[-1]
    assert imu >= 5 * (len(stamps) - 2)
    assert list(faults) == ["log_damaged"], faults  # nothing truncated: the tail is intact
    lost = faults["log_damaged"]
    assert lost["scans_lost"] == SCANS - len(stamps)
    assert lost["messages_lost"] == lost["scans_lost"] + 5 * SCANS - imu
    assert 0 < lost["bytes_lost"] < 0.2 * len(data) and lost["total_bytes"] == len(data)
    assert len(warnings) == 1 and "damaged in 1 place" in warnings[0]
    assert f"{SCANS - len(stamps)} scan" in warnings[0]


def test_damage_in_the_middle_and_a_cut_tail(chunked_log, tmp_path):
    data = bytearray(chunked_log.read_bytes())
    _garbage_in_records(data, _chunk_starts(chunked_log))
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data[:int(len(data) * 0.8)]))
    with LogReader(bad) as reader:
        stamps = [cloud.stamp_ns for cloud in reader.scans()]
        faults = reader.faults.as_dict()
        assert len(reader.faults.warnings()) == 2
    assert 0.6 * SCANS < len(stamps) < 0.8 * SCANS
    assert faults["log_truncated"]["scans_read"] == len(stamps)
    assert faults["log_damaged"]["stretches"][0][1] < faults["log_truncated"]["damaged_at_byte"]


def test_every_chunk_damaged_stops(chunked_log, tmp_path):
    data = bytearray(chunked_log.read_bytes())
    for start, length in _chunk_starts(chunked_log):
        data[start + length // 2] ^= 0xFF
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(LogFormatError, match=r"corrupt \(all \d+ chunks holding these "
                                             r"topics are damaged"), LogReader(bad) as reader:
        list(reader.scans())


def test_a_stretch_whose_indexes_are_lost_too_counts_no_scans(chunked_log, tmp_path):
    """Zeros over a chunk and the message indexes after it, and garbage over the summary: the
    stretch is skipped, but how many scans it held cannot be told."""
    data = bytearray(chunked_log.read_bytes())
    start, length = _chunk_starts(chunked_log)[5]
    data[start - 40:start + length + 200] = bytes(length + 240)
    summary_start = _summary_start(data)
    data[summary_start:-37] = np.random.default_rng(8).bytes(len(data) - 37 - summary_start)
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data))
    with LogReader(bad) as reader:
        stamps = [cloud.stamp_ns for cloud in reader.scans()]
        lost = reader.faults.as_dict()["log_damaged"]
        warnings = reader.faults.warnings()
    assert SCANS - 4 <= len(stamps) < SCANS
    assert lost["scans_lost"] is None and lost["messages_lost"] is None
    assert warnings == [w for w in warnings if "an unknown number of scans lost" in w]
