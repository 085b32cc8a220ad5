"""Ouster .pcap + metadata JSON read as a log: the real OS1-128 capture in ../shared/data
(ouster-sdk test set, BSD-3-Clause) against the Ouster SDK's decode (recorded in
support/ouster_sdk_reference.json; compared whole when `ouster.sdk` imports) and an
independent struct decode of its IMU packets; `mcl3d info` and `mcl3d odometry` on it; the
metadata found beside it; a cut capture read up to the cut; another sensor's JSON or none:
one line, exit 1, nothing written.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mcl3d.core.errors import LogFormatError
from mcl3d.io.logs import ouster_source as ous
from mcl3d.io.logs.reader import LogReader

FOLDER = "ouster_os1_128_lb_n3"
STEM = "OS-1-128_v2.3.0_1024x10"
PCAP = f"{STEM}_lb_n3.pcap"
REFERENCE = Path(__file__).parents[1] / "support" / "ouster_sdk_reference.json"
ROWS, COLUMNS = 128, 1024


@pytest.fixture(scope="module")
def data(shared_data):
    return shared_data / FOLDER


@pytest.fixture(scope="module")
def scans(data):
    with LogReader(data / PCAP) as reader:
        organized = [msg for _t, _ns, msg in reader.source.messages([ous.POINTS_TOPIC])]
        return list(reader.scans()), organized, reader.faults


def organized_xyz(msg) -> np.ndarray:
    """(rows * columns, 3) from a PointCloud2's bytes, by its own field offsets."""
    offsets = {f.name: int(f.offset) for f in msg.fields}
    dtype = np.dtype({"names": list("xyz"), "formats": ["<f4"] * 3,
                      "offsets": [offsets[a] for a in "xyz"], "itemsize": int(msg.point_step)})
    raw = np.frombuffer(bytes(msg.data), dtype)
    return np.stack([raw[a] for a in "xyz"], axis=1)


def test_scans_match_the_ouster_sdk(scans):
    clouds, organized, faults = scans
    reference = json.loads(REFERENCE.read_text())["frames"]
    assert len(clouds) == len(reference) == 3 and not faults.found()
    for cloud, msg, ref in zip(clouds, organized, reference, strict=True):
        assert cloud.stamp_ns == ref["first_column_ns"] and cloud.frame_id == ous.SENSOR_FRAME
        assert len(cloud.points) == ref["returns"]
        assert cloud.n_dropped == ROWS * COLUMNS - ref["returns"]
        assert (cloud.height, cloud.width) == (ROWS, COLUMNS)
        assert cloud.times_s.min() >= 0 and cloud.times_s.max() < 0.1
        xyz = organized_xyz(msg)
        pixel = np.asarray(ref["row"]) * COLUMNS + np.asarray(ref["column"])
        np.testing.assert_allclose(xyz[pixel], np.asarray(ref["xyz"]), rtol=0, atol=2e-5)
        returns = (xyz != 0).any(axis=1)
        assert np.array_equal(cloud.points, xyz[returns])
        assert np.array_equal(cloud.fields["ring"], np.flatnonzero(returns) // COLUMNS)


def test_scans_match_the_installed_ouster_sdk_whole(data, scans):
    sdk = pytest.importorskip("ouster.sdk", reason="ouster-sdk is not installed (it pins "
                              "rosbags 0.9.23, so it is no test dependency; the recorded "
                              "reference above covers it)")
    from ouster.sdk import core

    source = sdk.open_source(str(data / PCAP), meta=[str(data / f"{STEM}.json")])
    lut = core.XYZLut(source.sensor_info[0], use_extrinsics=False)
    clouds, _organized, _faults = scans
    for frames, cloud in zip(source, clouds, strict=True):
        rng = frames[0].field("RANGE")
        returns = rng.ravel() > 0
        ref = lut(rng).reshape(-1, 3)[returns]
        assert np.abs(ref - cloud.points).max() < 2e-5
        column = np.flatnonzero(returns) % COLUMNS
        stamps = frames[0].timestamp.astype(np.int64)
        np.testing.assert_allclose(cloud.times_s, (stamps[column] - stamps.min()) * 1e-9,
                                   rtol=0, atol=1e-8)


def imu_packets(pcap: Path, port: int) -> list[tuple]:
    """(gyro ns, ax ay az g, wx wy wz deg/s) of each IMU datagram, by struct alone."""
    data = pcap.read_bytes()
    out, pos = [], 24
    while pos + 16 <= len(data):
        length = struct.unpack_from("<I", data, pos + 8)[0]
        frame = data[pos + 16:pos + 16 + length]
        pos += 16 + length
        ip = 14
        udp = ip + (frame[ip] & 0x0F) * 4
        if struct.unpack_from(">H", frame, udp + 2)[0] == port:
            payload = frame[udp + 8:]
            out.append(struct.unpack_from("<QQQ6f", payload))
    return [(p[2], *p[3:]) for p in out]


def test_imu_and_its_extrinsic(data):
    meta = json.loads((data / f"{STEM}.json").read_text())
    expected = imu_packets(data / PCAP, meta["udp_port_imu"])
    with LogReader(data / PCAP) as reader:
        assert reader.topics.imu == ous.IMU_TOPIC and reader.count("imu") == len(expected) == 30
        imus = [m for _k, m in reader.messages(("imu",))]
        T = reader.static_transform(ous.SENSOR_FRAME, ous.IMU_FRAME)
    for imu, ref in zip(imus, expected, strict=True):
        assert imu.stamp_ns == ref[0] and imu.frame_id == ous.IMU_FRAME
        np.testing.assert_allclose(imu.linear_acceleration, np.array(ref[1:4]) * 9.80665,
                                   rtol=1e-6)
        np.testing.assert_allclose(imu.angular_velocity, np.deg2rad(ref[4:7]), rtol=1e-6)
    T_mm = np.asarray(meta["imu_to_sensor_transform"], float).reshape(4, 4)
    np.testing.assert_allclose(T[:3, 3], T_mm[:3, 3] / 1000)
    np.testing.assert_allclose(T[:3, :3], T_mm[:3, :3])


def mcl3d(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mcl3d", *map(str, args)], capture_output=True,
                          text=True, env={"COLUMNS": "200", "PATH": ""}, timeout=300)


def test_info_and_odometry_end_to_end(data, tmp_path):
    info = mcl3d("info", data / PCAP, "--json")
    assert info.returncode == 0, info.stderr
    doc = json.loads(info.stdout)
    assert doc["format"].startswith("Ouster pcap (OS-1-128 1024x10, RNG15_RFL8_NIR8")
    topics = {t["name"]: t for t in doc["topics"]}
    assert topics[ous.POINTS_TOPIC]["count"] == 3 and topics[ous.IMU_TOPIC]["count"] == 30
    assert topics[ous.POINTS_TOPIC]["rate_hz"] == pytest.approx(10.0, rel=0.01)  # 1024x10
    assert topics[ous.IMU_TOPIC]["rate_hz"] == pytest.approx(100.0, rel=0.01)
    cloud = topics[ous.POINTS_TOPIC]["cloud"]
    assert (cloud["height"], cloud["width"], cloud["time_field"]) == (ROWS, COLUMNS, "t")
    assert doc["selection"]["points"]["topic"] == ous.POINTS_TOPIC
    run = mcl3d("odometry", data / PCAP, "-o", tmp_path / "odo", "--max-scans", "2",
                "--backend", "cpu")
    assert run.returncode == 0, run.stderr
    rows = [r for r in (tmp_path / "odo" / "odometry.tum").read_text().splitlines()
            if r and not r.startswith("#")]
    assert len(rows) == 2
    assert float(rows[1].split()[1]) == pytest.approx(0.245, abs=0.05)  # the SDK's pose 1


def test_metadata_beside_the_pcap(data, tmp_path):
    pcap = tmp_path / "drive.pcap"
    shutil.copy(data / PCAP, pcap)
    with pytest.raises(LogFormatError, match=r"there is no \.json beside it"):
        LogReader(pcap)
    (tmp_path / "other.json").write_text("{}")
    (tmp_path / "more.json").write_text("{}")
    with pytest.raises(LogFormatError, match=r"2 \.json files \(more.json, other.json\)"):
        LogReader(pcap)
    shutil.copy(data / f"{STEM}.json", tmp_path / "drive.json")  # the same stem wins
    with LogReader(pcap) as reader:
        assert reader.source.meta.path.name == "drive.json"
    (tmp_path / "drive.json").rename(tmp_path / "dri.json")  # the pcap's name starts with it
    with LogReader(pcap) as reader:
        assert reader.source.meta.path.name == "dri.json"


def test_cut_capture_keeps_the_whole_frames(data, tmp_path):
    raw = (data / PCAP).read_bytes()
    cut = tmp_path / "cut.pcap"
    size = int(len(raw) * 0.8)
    cut.write_bytes(raw[:size])  # inside the third frame
    shutil.copy(data / f"{STEM}.json", tmp_path / "cut.json")
    with LogReader(cut) as reader:
        clouds = list(reader.scans())
        truncation = reader.faults.truncation
    assert len(clouds) == 2 and truncation is not None and truncation.scans_read == 2
    assert truncation.total_bytes == size
    info = mcl3d("info", cut, "--json")
    assert info.returncode == 0 and "cut at byte" in json.loads(info.stdout)["format"]


def _other_sensor(meta: dict) -> None:  # an OS1-64: 64 beams
    meta["data_format"]["pixels_per_column"] = 64
    meta["beam_altitude_angles"] = meta["beam_altitude_angles"][::2]
    meta["beam_azimuth_angles"] = meta["beam_azimuth_angles"][::2]


def _other_mode(meta: dict) -> None:  # 512x20: measurement ids beyond 511
    meta["data_format"]["columns_per_frame"] = 512
    meta["lidar_mode"] = "512x20"


def _wider_mode(meta: dict) -> None:  # 2048x10: no frame ever fills 2048 columns
    meta["data_format"]["columns_per_frame"] = 2048
    meta["lidar_mode"] = "2048x10"


@pytest.mark.parametrize(("change", "words"), [
    (_other_sensor, "another sensor or mode"), (_other_mode, "another mode"),
    (_wider_mode, "no complete Ouster frame")])
def test_metadata_of_another_sensor_fails_with_one_line(data, tmp_path, change, words):
    pcap = tmp_path / "run.pcap"
    shutil.copy(data / PCAP, pcap)
    meta = json.loads((data / f"{STEM}.json").read_text())
    change(meta)
    (tmp_path / "run.json").write_text(json.dumps(meta))
    with pytest.raises(LogFormatError, match=words):
        LogReader(pcap)
    if change is _other_sensor:  # the CLI: one line, exit 1, nothing written
        result = mcl3d("odometry", pcap, "-o", tmp_path / "out")
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 1 and len(lines) == 1, result.stderr
        assert lines[0].startswith("error:") and "run.json" in lines[0]
        assert not (tmp_path / "out").exists()


def test_missing_metadata_fails_with_one_line(data, tmp_path):
    pcap = tmp_path / "alone.pcap"
    shutil.copy(data / PCAP, pcap)
    result = mcl3d("info", pcap)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert "metadata JSON" in lines[0] and "alone.json" in lines[0]
