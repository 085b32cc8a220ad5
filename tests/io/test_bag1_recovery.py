"""A damaged ROS 1 bag (a recorder killed mid-write: no index, a cut chunk; garbage over a
chunk) is read up to and past its damage, like a damaged MCAP; fuzzed bags are read or refused
with an mcl3d error, never a traceback."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.typesys import Stores, get_typestore
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs.bag1_source import RecoveredBagSource
from mcl3d.io.logs.messages import Imu, PointCloud, PoseStamped
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.logs.writer import LogWriter

T0 = 1_317_000_015_000_000_000
SCANS = 8
COMPRESSIONS = {"none": None, "bz2": Bag1Writer.CompressionFormat.BZ2,
                "lz4": Bag1Writer.CompressionFormat.LZ4}


def write_bag(tmp_path, compression: str):
    """Eight scans of 200 points with IMU and ground truth, one scan per chunk: written as an
    MCAP by mcl3d, then re-recorded as a ROS 1 bag the way `rosbag record` stores it."""
    mcap = tmp_path / "log.mcap"
    rng = np.random.default_rng(0)
    with LogWriter(mcap) as w:
        for k in range(SCANS):
            stamp = T0 + k * 100_000_000
            points = (rng.normal(size=(200, 3)) * 5).astype(np.float32)
            w.write_points("/lidar/points", PointCloud(stamp, "lidar", points, None))
            w.write_imu("/imu/data", Imu(stamp, "imu", rng.normal(size=3), rng.normal(size=3)))
            w.write_pose("/ground_truth", PoseStamped(stamp, "map", np.eye(4)))
    bag = tmp_path / f"log_{compression}.bag"
    ros1 = get_typestore(Stores.ROS1_NOETIC)
    writer = Bag1Writer(bag)
    writer.chunk_threshold = 2_000
    if COMPRESSIONS[compression] is not None:
        writer.set_compression(COMPRESSIONS[compression])
    with AnyReader([mcap]) as reader, writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=ros1)
                 for c in reader.connections}
        for c, stamp, raw in reader.messages():
            writer.write(conns[c.id], stamp, reader.typestore.cdr_to_ros1(raw, c.msgtype))
    return bag


def read_scans(path):
    with LogReader(path) as reader:
        return [cloud.stamp_ns for cloud in reader.scans()], reader.faults


@pytest.fixture(scope="module", params=list(COMPRESSIONS))
def bag(request, tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bag1"), request.param)


def chunk_starts(data: bytes) -> list[int]:
    """Byte offsets of the chunk records (their op field, less the header fields before it)."""
    starts, at = [], data.find(b"op=\x05")
    while at >= 0:
        starts.append(at)
        at = data.find(b"op=\x05", at + 1)
    return starts


def test_cut_bag_is_read_up_to_the_cut(bag, tmp_path):
    full, _ = read_scans(bag)
    assert len(full) == SCANS
    data = bag.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    with pytest.raises(Exception, match=r"index|Header"), AnyReader([cut]):
        pass  # rosbags alone refuses it
    stamps, faults = read_scans(cut)
    assert 2 <= len(stamps) < SCANS
    assert stamps == full[:len(stamps)]
    assert faults.truncation is not None and faults.truncation.scans_read == len(stamps)
    assert "truncated or damaged" in faults.warnings()[0]


def test_garbage_over_a_chunk_is_skipped(bag, tmp_path):
    full, _ = read_scans(bag)
    data = bytearray(bag.read_bytes())
    third = chunk_starts(bytes(data))[2]
    data[third - 30:third + 200] = b"\xff" * 230
    damaged_bag = tmp_path / "damaged.bag"
    damaged_bag.write_bytes(bytes(data))
    stamps, faults = read_scans(damaged_bag)
    assert set(stamps) < set(full) and len(stamps) >= SCANS - 2
    assert stamps[-1] == full[-1]  # read on past the damage
    assert len(faults.damage.stretches) == 1
    assert "damaged in 1 place" in " ".join(faults.warnings())


@pytest.mark.parametrize("compression", ["bz2", "lz4"])
def test_an_indexed_bag_with_a_chunk_that_does_not_decompress(compression, tmp_path):
    """rosbags opens it (the index is whole) and fails at the chunk: reading goes on past it,
    and the index says what was lost."""
    bag = write_bag(tmp_path, compression)
    full, _ = read_scans(bag)
    data = bytearray(bag.read_bytes())
    fourth = chunk_starts(bytes(data))[3]
    data[fourth + 80:fourth + 120] = bytes(40)
    damaged_bag = tmp_path / "damaged.bag"
    damaged_bag.write_bytes(bytes(data))
    stamps, faults = read_scans(damaged_bag)
    assert stamps == full[:3] + full[4:]
    assert faults.damage.as_dict()["scans_lost"] == 1
    assert "1 scan lost" in " ".join(faults.warnings())


def test_a_bag_cut_before_its_first_message_keeps_rosbags_reason(bag, tmp_path):
    cut = tmp_path / "head.bag"
    cut.write_bytes(bag.read_bytes()[:300])
    with pytest.raises(LogFormatError, match="truncated or corrupt"):
        read_scans(cut)
    with pytest.raises(LogFormatError, match="no message before the damage"):
        RecoveredBagSource(cut)


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    return write_bag(tmp_path_factory.mktemp("bag1_fuzz"), "none").read_bytes()


def test_fuzzed_bags_never_raise_a_traceback(small_bag, tmp_path):
    @fuzz_settings(examples=40)
    @given(damaged(small_bag))
    def check(data):
        path = tmp_path / "fuzz.bag"
        path.write_bytes(data)
        stamps = reads_or_refuses(lambda: read_scans(path)[0])
        if stamps:
            assert all(isinstance(s, int) for s in stamps)

    check()
