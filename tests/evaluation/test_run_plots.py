"""The pictures `localize` and `slam` write: which panels and lines they draw, on tiny runs
with and without ground truth, and that they come out as PNGs."""

import numpy as np
import pytest
from support.pictures import assert_picture

from mcl3d.core.geometry import se3
from mcl3d.evaluation.run_plots import localize_figure, slam_figure, write_png
from mcl3d.io.trajectory import Trajectory
from mcl3d.localization.state import FilterState, LocalizationResult
from mcl3d.slam.frame_store import SlamFrame, SlamFrames

STAMPS_NS = 1_700_000_000_000_000_000 + np.arange(6) * 100_000_000
MAP_POINTS = np.random.default_rng(0).uniform(-5.0, 5.0, (2000, 3))


def poses(offset_m: float = 0.0) -> np.ndarray:
    """A curve in the x-y plane, shifted by `offset_m` in y."""
    return np.stack([se3(np.eye(3), [0.5 * i, offset_m + 0.1 * i * i, 0.0])
                     for i in range(len(STAMPS_NS))])


def ground_truth() -> Trajectory:
    return Trajectory.from_ns(STAMPS_NS, poses())


def localization_results() -> list[LocalizationResult]:
    states = [FilterState.INITIALIZING] * 2 + [FilterState.CONVERGED] * 4
    return [LocalizationResult(
        stamp_s=ns * 1e-9, T_map_lidar=T, T_best=T, covariance=np.eye(6) * 1e-4, state=state,
        hypotheses=[None] * (3 if i < 2 else 1), ess=100.0 * (i + 1), n_particles=1000,
        match_ratio=0.5 + 0.05 * i, mean_log_likelihood=-1.0, n_points=256, resampled=True,
        reseeded="")
        for i, (ns, T, state) in enumerate(zip(STAMPS_NS, poses(0.1), states, strict=True))]


def slam_run() -> tuple[SlamFrames, dict[str, Trajectory]]:
    slam, odom = poses(0.05), poses(0.2)
    frames = [SlamFrame(stamp_ns=int(ns), T_world_lidar=T, T_odom_lidar=To, T_motion_lidar=To,
                        representative=0, ess=50.0, max_weight=0.1, hypotheses=2,
                        looping=i % 2, corrected=0, pruned=i, keyframe=i == 0, num_keyframes=1,
                        elevator=False, travel_m=0.5 * i, odometry_warnings=[])
              for i, (ns, T, To) in enumerate(zip(STAMPS_NS, slam, odom, strict=True))]
    store = SlamFrames()
    for frame in frames:
        store.append(frame)
    return store, {"slam": Trajectory.from_ns(STAMPS_NS, slam),
                    "odometry": Trajectory.from_ns(STAMPS_NS, odom)}


@pytest.mark.parametrize("with_gt", [True, False])
def test_localize_figure_panels(with_gt, tmp_path):
    fig = localize_figure(localization_results(), MAP_POINTS,
                          ground_truth() if with_gt else None, 0.1)
    # top view, [error + its rotation twin], ESS, match ratio + its hypotheses twin
    assert len(fig.axes) == (6 if with_gt else 4)
    top = fig.axes[0]
    labels = [line.get_label() for line in top.get_lines()]
    assert labels == (["ground truth"] if with_gt else []) + ["estimate", "initializing",
                                                               "converged"]
    assert len(top.get_images()) == 1  # the map
    write_png(tmp_path / "localize.png", fig)
    assert_picture(tmp_path / "localize.png")


@pytest.mark.parametrize("with_gt", [True, False])
def test_slam_figure_panels(with_gt, tmp_path):
    frames, trajectories = slam_run()
    fig = slam_figure(frames, trajectories, MAP_POINTS, ground_truth() if with_gt else None,
                      particles=100, map_cell_m=0.1)
    # top view, [error + its rotation twin], ESS and hypotheses, loops and pruning
    assert len(fig.axes) == (5 if with_gt else 3)
    labels = [line.get_label() for line in fig.axes[0].get_lines()]
    assert labels == (["ground truth (SE(3)-aligned)"] if with_gt else []) + [
        "odometry only", "SLAM"]
    if with_gt:  # SLAM and odometry: translation on the left, rotation on the twin axis
        assert len(fig.axes[1].get_lines()) == 2 == len(fig.axes[-1].get_lines())
    write_png(tmp_path / "slam.png", fig)
    assert_picture(tmp_path / "slam.png")


def test_an_empty_map_still_draws_the_trajectory():
    fig = localize_figure(localization_results(), np.zeros((0, 3)), None, 0.1)
    assert not fig.axes[0].get_images() and fig.axes[0].get_lines()
