"""Fuzzing the KITTI sequence folder reader: a damaged times.txt, calib.txt, poses file or scan
is read or refused with an mcl3d error, never a traceback; what is read is sound (finite
points, increasing stamps, finite ground truth)."""

from __future__ import annotations

import shutil
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.io.logs.info import log_info
from mcl3d.io.logs.reader import LogReader

SCANS = 3
TR = "0 -1 0 0 0 0 -1 0 1 0 0 -0.3"  # velodyne -> camera 0, as KITTI's axes turn


def _write_sequence(folder) -> None:
    rng = np.random.default_rng(0)
    (folder / "velodyne").mkdir(parents=True)
    for k in range(SCANS):
        points = np.hstack([rng.normal(size=(8, 3)) * 5, rng.uniform(size=(8, 1))])
        points.astype("<f4").tofile(folder / "velodyne" / f"{k:06d}.bin")
    (folder / "times.txt").write_text("".join(f"{0.1 * k:.6e}\n" for k in range(SCANS)))
    (folder / "calib.txt").write_text(f"P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: {TR}\n")
    (folder / "poses.txt").write_text("".join(f"1 0 0 {k} 0 1 0 0 0 0 1 0\n"
                                              for k in range(SCANS)))


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_kitti") / "00"
    _write_sequence(folder)
    return folder


def _read(folder) -> tuple:
    with LogReader(folder) as reader:
        scans = list(reader.scans())
        truth = reader.ground_truth() if reader.topics.gt else None
    log_info(folder)
    return scans, truth


def _check(read) -> None:
    if read is None:
        return
    scans, truth = read
    assert all(np.isfinite(s.points).all() for s in scans)
    assert all(a.stamp_ns < b.stamp_ns for a, b in pairwise(scans))
    if truth is not None:
        assert np.isfinite(truth[1]).all() and (np.diff(truth[0]) > 0).all()


@pytest.mark.parametrize("name", ["times.txt", "calib.txt", "poses.txt", "velodyne/000001.bin"])
@fuzz_settings(examples=40)
@example(blob=b"0\n0.1\nnan\n")  # was read: a NaN time became a garbage stamp
@example(blob=b"Tr: 0 0 0 0 0 0 0 0 0 0 0 0\n")  # crashed (a singular Tr)
@example(blob=b"\xff\xfe\n")  # crashed (calib.txt not text)
@given(blob=st.data())
def test_damaged_kitti_sequence(sequence, tmp_path_factory, name, blob):
    folder = tmp_path_factory.mktemp("damaged") / "00"
    shutil.copytree(sequence, folder)
    original = (sequence / name).read_bytes()
    (folder / name).write_bytes(blob if isinstance(blob, bytes) else blob.draw(damaged(original)))
    _check(reads_or_refuses(lambda: _read(folder)))
