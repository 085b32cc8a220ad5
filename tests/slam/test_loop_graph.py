"""The representative's keyframes as a pose graph with registered loops
(mcl3d.slam.loop_graph)."""

import numpy as np

from mcl3d.core.geometry import rotation_angle, se3, se3_inverse, se3_log, so3_exp, transform_points
from mcl3d.slam.loop_bridge import step_covariances
from mcl3d.slam.loop_graph import LoopEdge, register_again, register_loop, solve_pose_graph


def _lanes(n: int) -> np.ndarray:
    """Out 1 m a keyframe along x, a U-turn, back 4 m aside: keyframe k and n - 1 - k face
    opposite ways across the lanes."""
    poses = []
    for k in range(n):
        half = k < n // 2
        x = float(k if half else n - 1 - k)
        poses.append(se3(so3_exp(np.array([0.0, 0.0, 0.0 if half else np.pi])),
                         np.array([x, 0.0 if half else 4.0, 0.0])))
    return np.stack(poses)


def _drifted(truth: np.ndarray, yaw_rad: float | np.ndarray) -> np.ndarray:
    """The odometry: the true steps, step k turned `yaw_rad` (or `yaw_rad[k]`) more."""
    yaw = np.broadcast_to(yaw_rad, (len(truth) - 1,))
    odom = [truth[0]]
    for k in range(len(truth) - 1):
        step = se3_inverse(truth[k]) @ truth[k + 1]
        odom.append(odom[-1] @ se3(so3_exp(np.array([0.0, 0.0, yaw[k]])), [0, 0, 0]) @ step)
    return np.stack(odom)


def _variance(n: int) -> np.ndarray:
    travel = np.arange(n, dtype=float)
    return np.c_[1e-5 * travel, 1e-4 * travel, np.zeros(n)]


def _edge(truth: np.ndarray, source: int, target: int) -> LoopEdge:
    return LoopEdge(source, target, se3_inverse(truth[target]) @ truth[source], np.eye(6) * 1e8)


def test_exact_odometry_and_loops_are_a_fixed_point():
    truth = _lanes(20)
    out = solve_pose_graph(truth, truth, step_covariances(truth, _variance(20)),
                           [_edge(truth, 15, 4), _edge(truth, 18, 1)])
    assert np.abs(out - truth).max() < 1e-9


def test_loops_pull_a_drifted_chain_onto_the_truth_and_anchors_stay():
    """The odometry's heading slips 4° in the U-turn (its drift variance grows evenly); the
    first keyframe and the newest (the filter's present estimate) are on the truth, loops
    across the lanes tie the way back to the way out: the keyframes come back within
    a centimetre where the chain alone (the bridge, anchored at both ends, spreading the
    slip along the way) was decimetres off."""
    n = 30
    truth = _lanes(n)
    slip = np.zeros(n - 1)
    slip[n // 2 - 1] = np.radians(4.0)
    odom = _drifted(truth, slip)
    start = odom.copy()
    start[-1] = truth[-1]
    cov = step_covariances(odom, _variance(n))
    loops = [_edge(truth, n - 1 - k, k) for k in range(2, n // 2, 2)]
    chain = solve_pose_graph(start, odom, cov, [])
    out = solve_pose_graph(start, odom, cov, loops)
    assert np.allclose(out[[0, -1]], start[[0, -1]])
    error = np.linalg.norm(out[:, :3, 3] - truth[:, :3, 3], axis=1)
    chain_error = np.linalg.norm(chain[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert chain_error.max() > 0.1
    assert error.max() < 0.01
    for e in loops:
        r = se3_log(se3_inverse(e.T_target_source) @ se3_inverse(out[e.target]) @ out[e.source])
        assert np.linalg.norm(r[3:]) < 0.01


def test_without_loops_the_graph_is_the_odometry_chain_between_the_ends():
    """No loop: the keyframes follow the odometry, bent onto the newest keyframe in the drift
    covariance (as the bridge between two anchors)."""
    from mcl3d.slam.loop_bridge import bridge_between_anchors

    n = 12
    truth = _lanes(n)
    odom = _drifted(truth, np.radians(0.5))
    start = odom.copy()
    start[-1] = truth[-1]
    variance = _variance(n)
    out = solve_pose_graph(start, odom, step_covariances(odom, variance), [])
    bridged = bridge_between_anchors(start, odom, variance, np.zeros(n, bool))
    assert np.abs(out - bridged).max() < 1e-3  # both linearize; within a millimetre


def _pillars(rng: np.random.Generator) -> np.ndarray:
    """A ground plane and trunks, as a forest scan sees them (world frame)."""
    ground = np.c_[rng.uniform(-15, 15, (3000, 2)), rng.normal(0.0, 0.01, 3000)]
    trunks = []
    for cx, cy in rng.uniform(-12, 12, (25, 2)):
        a = rng.uniform(0, 2 * np.pi, 200)
        trunks.append(np.c_[cx + 0.3 * np.cos(a), cy + 0.3 * np.sin(a), rng.uniform(0, 4, 200)])
    return np.concatenate([ground, *trunks])


def test_a_loop_registered_from_the_filters_estimate(ti_runtime):
    """Keyframes 3 m apart see the same trunks; from an estimate 0.6 m and 3° off the
    registration lands within 2 cm and 0.2°, with a Hessian that weighs every axis."""
    rng = np.random.default_rng(7)
    world = _pillars(rng)
    T_target = se3(so3_exp(np.radians([0.0, 0.0, 10.0])), [0.0, 0.0, 1.0])
    T_source = se3(so3_exp(np.radians([0.0, 0.0, 25.0])), [3.0, 1.0, 1.0])
    cloud_target = transform_points(se3_inverse(T_target), world)
    cloud_source = transform_points(se3_inverse(T_source), world[rng.permutation(len(world))])
    truth = se3_inverse(T_target) @ T_source
    guess = truth @ se3(so3_exp(np.radians([0.0, 0.0, 3.0])), [0.5, -0.3, 0.1])
    edge = register_loop(4, 1, cloud_source, cloud_target, guess)
    assert edge is not None and (edge.source, edge.target) == (4, 1)
    off = se3_inverse(truth) @ edge.T_target_source
    assert np.linalg.norm(off[:3, 3]) < 0.02 and np.degrees(rotation_angle(off[:3, :3])) < 0.2
    assert np.linalg.eigvalsh(edge.information).min() > 0


def test_a_scan_registered_for_its_keyframe(ti_runtime):
    """The scan is 1.5 m and 20° past the source keyframe (the odometry says where): the edge
    is the source keyframe's pose in the target's frame, and a perturbation of the scan's
    pose weighs as the same perturbation of the keyframe's, carried by the adjoint."""
    from mcl3d.core.geometry import se3_adjoint

    rng = np.random.default_rng(9)
    world = _pillars(rng)
    T_target = se3(so3_exp(np.radians([0.0, 0.0, 10.0])), [0.0, 0.0, 1.0])
    T_source = se3(so3_exp(np.radians([0.0, 0.0, 25.0])), [3.0, 1.0, 1.0])
    T_source_scan = se3(so3_exp(np.radians([0.0, 0.0, 20.0])), [1.5, 0.0, 0.0])
    scan = transform_points(se3_inverse(T_source @ T_source_scan), world)
    T_target_scan = se3_inverse(T_target) @ T_source @ T_source_scan
    edge = register_loop(4, 1, scan, transform_points(se3_inverse(T_target), world),
                         T_target_scan @ se3(np.eye(3), [0.3, 0.2, 0.0]), T_source_scan)
    assert edge is not None
    off = se3_inverse(se3_inverse(T_target) @ T_source) @ edge.T_target_source
    assert np.linalg.norm(off[:3, 3]) < 0.02 and np.degrees(rotation_angle(off[:3, :3])) < 0.2
    same = register_loop(4, 1, scan, transform_points(se3_inverse(T_target), world),
                         T_target_scan @ se3(np.eye(3), [0.3, 0.2, 0.0]))
    Ad = se3_adjoint(T_source_scan)  # a scan perturbation δ is Ad δ of the keyframe
    np.testing.assert_allclose(Ad.T @ edge.information @ Ad, same.information, rtol=1e-6,
                               atol=1e-6 * np.abs(same.information).max())


def test_a_pair_is_registered_again_only_from_much_nearer():
    assert register_again(None, 9.0)
    assert register_again(4.0, 2.0) and not register_again(4.0, 2.5)
    assert not register_again(0.8, 0.1)  # already from within a metre


def test_a_loop_that_matches_nothing_is_no_edge(ti_runtime):
    """A keyframe registered onto a place it never saw (clouds 100 m apart): no edge."""
    rng = np.random.default_rng(8)
    cloud = _pillars(rng)
    far = cloud + np.array([100.0, 0.0, 0.0])
    assert register_loop(2, 0, cloud, far, np.eye(4)) is None


def test_an_edge_another_hypothesis_took_is_not_in_the_map():
    """Two loops onto keyframe 1: one the keyframes agree with within a few centimetres, one
    3.5 m up (a look-alike floor the representative of that scan held)."""
    from mcl3d.slam.loop_graph import agreeing_edges

    truth = _lanes(12)
    held = _edge(truth, 9, 1)
    held = LoopEdge(9, 1, held.T_target_source @ se3(np.eye(3), [0.03, 0.0, 0.0]),
                    held.information)
    floor = LoopEdge(10, 1, se3(np.eye(3), [0.0, 0.0, 3.5]) @ _edge(truth, 10, 1).T_target_source,
                     np.eye(6))
    assert agreeing_edges(truth, [held, floor]) == [held]


def test_measured_ups_take_the_odometry_pitch_drift_out():
    """The odometry pitches 0.2° more each step (a half view's drift) and no loop closes:
    each keyframe's up, measured from its plumb surfaces, holds its tilt; the heights come
    back within 7 cm where the chain alone was 35 cm off (the steps' 0.1° against the ups'
    0.5°)."""
    from mcl3d.slam.structure_up import UpMeasurement, horizontal_axes

    n = 30
    truth = _lanes(n)
    odom = [truth[0]]
    for k in range(n - 1):
        step = se3_inverse(truth[k]) @ truth[k + 1]
        odom.append(odom[-1] @ se3(so3_exp(np.array([0.0, np.radians(0.2), 0.0])), [0, 0, 0])
                    @ step)
    odom = np.stack(odom)
    start = odom.copy()
    start[-1] = truth[-1]
    cov = step_covariances(odom, _variance(n))
    up_world = np.array([0.0, 0.0, 1.0])
    ups = {}
    for k in range(n):
        up = truth[k][:3, :3].T @ up_world
        ups[k] = UpMeasurement(up, horizontal_axes(up), np.full(2, 1.0 / np.radians(0.5) ** 2))
    chain = solve_pose_graph(start, odom, cov, [])
    out = solve_pose_graph(start, odom, cov, [], ups, up_world)

    def worst(T):  # height (m) and tilt (°) furthest off the truth
        tilt = [rotation_angle(T[k][:3, :3].T @ truth[k][:3, :3]) for k in range(n)]
        return np.abs(T[:, 2, 3] - truth[:, 2, 3]).max(), np.degrees(max(tilt))

    (chain_dz, chain_tilt), (dz, tilt) = worst(chain), worst(out)
    assert chain_dz > 0.3 and chain_tilt > 2.5
    assert dz < 0.25 * chain_dz and tilt < 0.4 * chain_tilt
    assert np.allclose(solve_pose_graph(start, odom, cov, [], ups, None), chain)
