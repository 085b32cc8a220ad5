"""The representative's keyframes between loop anchors (mcl3d.slam.loop_bridge)."""

import numpy as np

from mcl3d.core.geometry import rotation_angle, se3, so3_exp
from mcl3d.slam.loop_bridge import anchored_keyframes, bridge_between_anchors


def _path(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A walk 1 m a keyframe with a gentle turn: (poses, travel)."""
    poses, T = [], np.eye(4)
    for _ in range(n):
        poses.append(T.copy())
        T = T @ se3(so3_exp(np.radians([0.0, 0.5, 3.0])), np.array([1.0, 0.0, 0.0]))
    return np.stack(poses), np.arange(n, dtype=float)


def test_a_keyframe_is_anchored_by_a_loop_scan_while_it_is_the_newest():
    keyframe_scans = np.array([0, 10, 20, 30])
    anchored = anchored_keyframes(np.array([3, 10, 25]), keyframe_scans)
    assert anchored.tolist() == [True, True, True, False]
    assert not anchored_keyframes(np.zeros(0, int), keyframe_scans).any()


def test_between_anchors_the_random_walk_gives_way_to_the_odometry_chain():
    """Odometry exact, the particle's keyframes a random walk around it, the loop anchors on
    the truth: bridged, every keyframe is on the truth again."""
    truth, travel = _path(30)
    rng = np.random.default_rng(4)
    walk = truth.copy()
    offset = np.eye(4)
    for k in range(1, 30):
        offset = se3(so3_exp(np.radians(0.3) * rng.normal(size=3)), 0.05 * rng.normal(size=3)) \
            @ offset
        walk[k] = offset @ truth[k]
    anchored = np.zeros(30, bool)
    anchored[[12, 29]] = True
    walk[[12, 29]] = truth[[12, 29]]
    variance = np.c_[1e-5 * travel, 1e-3 * travel, np.zeros(30)]
    out = bridge_between_anchors(walk, truth, variance, anchored)
    assert np.abs(out - truth).max() < 1e-9
    assert np.abs(walk - truth).max() > 0.05


def test_the_anchors_offset_goes_where_the_drift_variance_grew():
    """Straight odometry, the particle 0.4 m aside from keyframe 4 on (an anchor), the
    rotation's variance negligible: the offset is spread in proportion to the translational
    variance summed along the way (the first step holds a quarter of it); after the anchor
    the keyframes follow the odometry from it; anchors keep their poses."""
    odom = np.stack([se3(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(7)])
    variance = np.c_[np.zeros(7), [0.0, 1.0, 3.0, 3.5, 4.0, 5.0, 6.0], np.zeros(7)]
    particle = odom.copy()
    particle[4:, 1, 3] = 0.4
    anchored = np.zeros(7, bool)
    anchored[4] = True
    out = bridge_between_anchors(particle, odom, variance, anchored)
    assert np.allclose(out[[0, 4]], particle[[0, 4]])
    assert np.allclose(out[1, :3, 3] - odom[1, :3, 3], [0.0, 0.1, 0.0], atol=1e-9)
    assert np.allclose(out[3, :3, 3] - odom[3, :3, 3], [0.0, 0.35, 0.0], atol=1e-9)
    assert rotation_angle(out[1, :3, :3]) < 1e-6
    for k in (5, 6):  # the odometry hung from the anchor (keyframe 6, the newest, on it)
        assert np.allclose(out[k], particle[4] @ np.linalg.inv(odom[4]) @ odom[k])


def test_a_turned_anchor_bends_the_chain_with_its_lever_arm():
    """The odometry misses a steady turn of 1° a metre; the anchor 10 m on is where the
    turning path really ends. The bridged chain lies on the turning path within 1 cm; the
    anchor's offset spread as a translation alone would cut the arc's corner by 0.2 m."""
    odom = np.stack([se3(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(11)])
    truth = [np.eye(4)]
    for _ in range(10):
        truth.append(truth[-1] @ se3(so3_exp(np.radians([0.0, 0.0, 1.0])),
                                     np.array([1.0, 0.0, 0.0])))
    truth = np.stack(truth)
    particle = odom.copy()
    particle[10] = truth[10]
    anchored = np.zeros(11, bool)
    anchored[10] = True
    variance = np.c_[np.arange(11) * 1e-4, np.arange(11) * 1e-4, np.zeros(11)]
    out = bridge_between_anchors(particle, odom, variance, anchored)
    assert np.abs(out[:, :3, 3] - truth[:, :3, 3]).max() < 0.01
    linear = odom[5, :3, 3] + 0.5 * (truth[10, :3, 3] - odom[10, :3, 3])
    assert np.linalg.norm(linear - truth[5, :3, 3]) > 0.1


def test_an_elevator_ride_takes_the_height_between_anchors():
    """The odometry saw no ride (a closed cab); the particle came out 3.5 m lower, and an
    anchor later confirms it: the drop goes to the ride's steps (their vertical random walk),
    not along the walk before and after."""
    odom = np.stack([se3(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(9)])
    particle = odom.copy()
    particle[5:, 2, 3] = -3.5
    anchored = np.zeros(9, bool)
    anchored[[1, 8]] = True
    ride = np.array([0, 0, 0, 0, 1, 2, 2, 2, 2], float) * 0.5  # steps 3 -> 4 -> 5 ride
    variance = np.c_[np.arange(9) * 1e-6, np.arange(9) * 1e-4, ride]
    out = bridge_between_anchors(particle, odom, variance, anchored)
    assert np.allclose(out[[2, 3], 2, 3], 0.0, atol=0.01)
    assert np.isclose(out[4, 2, 3], -1.75, atol=0.01)
    assert np.allclose(out[5:, 2, 3], -3.5, atol=0.01)
    assert np.abs(out[:, :2, 3] - odom[:, :2, 3]).max() < 1e-3  # not moved aside
