"""Fuzzing the TUM and KITTI trajectory readers: damaged or random files are read or refused
with a TrajectoryError, never a traceback; what is read is a valid trajectory."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.fuzz import damaged, fuzz_settings, reads_or_refuses

from mcl3d.core.geometry import se3_exp
from mcl3d.io.trajectory import Trajectory, read_kitti, read_trajectory, write_kitti, write_tum


def _trajectory() -> Trajectory:
    rng = np.random.default_rng(0)
    poses = np.stack([se3_exp(rng.normal(size=6)) for _ in range(6)])
    return Trajectory.from_ns(1_317_000_015_000_000_000 + np.arange(6) * 100_000_000, poses)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_trajectory")
    write_tum(folder / "valid.tum", _trajectory())
    write_kitti(folder / "valid.kitti", _trajectory())
    return folder


def _check(traj) -> None:
    if traj is not None:
        assert np.isfinite(traj.poses).all() and (np.diff(traj.stamps_s) > 0).all()


@pytest.mark.parametrize("fmt", ["tum", "kitti"])
@fuzz_settings(examples=60)
@given(data=st.data())
def test_damaged_trajectory_files(files, fmt, data):
    blob = data.draw(damaged((files / f"valid.{fmt}").read_bytes()))
    path = files / f"damaged.{fmt}"
    path.write_bytes(blob)
    _check(reads_or_refuses(lambda: read_trajectory(path)))
    _check(reads_or_refuses(lambda: read_trajectory(path, fmt)))


_TOKENS = st.sampled_from(["0", "1", "-1", "1e308", "-1e400", "nan", "inf", "0.5", "x", "#",
                           "1317000015.300000000", "", "0x10", "1_000", "\t", "\u00a0"])


@fuzz_settings(examples=60)
@given(rows=st.lists(st.lists(_TOKENS, max_size=13), max_size=5))
def test_random_trajectory_text(files, rows):
    path = files / "random.txt"
    path.write_text("\n".join(" ".join(row) for row in rows))
    _check(reads_or_refuses(lambda: read_trajectory(path)))
    _check(reads_or_refuses(lambda: read_kitti(path, stamps_s=np.arange(len(rows)))))
