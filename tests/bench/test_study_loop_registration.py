"""The loop-registration study's pair list and deskewing (bench/study_loop_registration.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mcl3d.core.geometry import se3_exp
from mcl3d.io.trajectory import Trajectory


@pytest.fixture
def study(bench):
    return bench("study_loop_registration")


def test_loop_pairs_are_the_newest_keyframe_and_each_loop_keyframe(study, tmp_path):
    frames = tmp_path / "frames.csv"
    rows = [(1, ""), (0, ""), (1, ""), (0, "0"), (1, "0 1"), (0, "1 0"), (0, "2")]
    frames.write_text("keyframe,loop_keyframes\n" + "".join(f"{k},{loops}\n"
                                                            for k, loops in rows))
    pairs, keyframe_scans = study.loop_pairs(frames, 10)
    assert keyframe_scans.tolist() == [0, 2, 4]
    # scan 3: newest keyframe 1 closes to 0; scan 4 (keyframe 2) to 0 and 1; scan 6 to itself
    assert pairs == [(1, 0), (2, 0), (2, 1)]
    assert len(study.loop_pairs(frames, 1)[0]) == 1


def test_deskewing_along_a_constant_twist_is_the_exponential(study):
    twist = np.array([0.0, 0.3, 0.1, 1.0, 0.2, -0.1])  # rad/s, m/s in the sensor frame
    stamps_s = 100.0 + 0.01 * np.arange(40)
    poses = np.stack([se3_exp(twist * (t - 100.0)) for t in stamps_s])
    trajectory = Trajectory(stamps_s, poses)
    rng = np.random.default_rng(0)
    points = rng.uniform(-5, 5, (50, 3))
    times_s = rng.uniform(0, 0.1, 50)
    moved = study.deskewed(points, times_s, trajectory, 100.1)
    expected = np.stack([(se3_exp(twist * t) @ np.r_[p, 1.0])[:3]
                         for p, t in zip(points, times_s, strict=True)])
    np.testing.assert_allclose(moved, expected, atol=1e-3)
    # held at the trajectory's start: before it the sensor does not move
    held = study.deskewed(points, times_s, trajectory, 100.0, shift_s=-0.2)
    np.testing.assert_allclose(held, points, atol=1e-9)
