"""SLAM's bounded keyframe store: which slot a new keyframe reuses once all are used, the
poses kept of dropped keyframes, and a run that wraps the store several times while its
front-end drifts (the 30-minute office loop's failure, in seconds)."""

import dataclasses

import numpy as np
from support.voxel_hash_numpy import numpy_voxel_hash

from mcl3d.core import geometry
from mcl3d.slam.keyframe_store import KeyframeBook, slot_to_reuse


def facing(yaw_deg: float, xyz) -> np.ndarray:
    return geometry.se3(geometry.rpy_to_rot(0.0, 0.0, np.deg2rad(yaw_deg)), xyz)


def test_a_place_seen_again_gives_up_its_newer_keyframe():
    # slots hold numbers 4, 1, 2, 3, 0: a corridor walked once (0-3), then keyframe 4 made
    # on the way back where keyframe 1 was, facing the other way
    T = np.stack([facing(180, [2.1, 0.0, 0.0]), facing(0, [2.0, 0.0, 0.0]),
                  facing(0, [4.0, 0.0, 0.0]), facing(0, [6.0, 0.0, 0.0]),
                  facing(0, [0.0, 0.0, 0.0])])
    seq = np.array([4, 1, 2, 3, 0])
    cos_90 = 0.0
    # facing the other way keyframe 4 sees another side: not redundant; the evenly spaced
    # walk (2 m) gives up its newest, keyframe 3; the first keyframe is never redundant
    assert slot_to_reuse(T, seq, set(), cos_90) == 3
    # without the facing test keyframe 4 (0.1 m from keyframe 1) is the redundant one
    assert slot_to_reuse(T, seq, set(), -1.0) == 0
    assert slot_to_reuse(T, seq, {0, 2, 3}, cos_90) == 1
    assert slot_to_reuse(T, seq, {1, 2, 3, 0}, cos_90) == 4  # only keyframe 0 left: inf
    assert slot_to_reuse(T, seq, set(range(5)), cos_90) == 3  # all kept: as if none


def test_slot_to_reuse_matches_a_brute_force_search():
    rng = np.random.default_rng(3)
    for _ in range(20):
        K = 9
        T = np.stack([facing(rng.uniform(-180, 180), rng.uniform(-5, 5, 3)) for _ in range(K)])
        seq = rng.permutation(K) + 10
        protected = {int(k) for k in rng.choice(K, 3, replace=False)}
        best = None
        for k in sorted(set(range(K)) - protected):
            d = [np.linalg.norm(T[k, :3, 3] - U[:3, 3]) for U, s in zip(T, seq, strict=True)
                 if s < seq[k] and U[:3, 0] @ T[k, :3, 0] >= 0.5]
            key = (min(d, default=np.inf), -seq[k])
            best = (key, k) if best is None or key < best[0] else best
        assert slot_to_reuse(T, seq, protected, 0.5) == best[1]


def test_keyframe_book_keeps_slots_numbers_and_dropped_poses():
    book = KeyframeBook()
    clouds = [np.full((2, 3), k, np.float32) for k in range(4)]
    for k in range(3):
        book.add(k, 10 * k, clouds[k])
    book.retire(1, facing(90, [1.0, 2.0, 3.0]))
    book.add(1, 35, clouds[3])  # number 3 takes slot 1
    assert book.frames == [0, 10, 20, 35] and len(book) == 4
    assert [c[0, 0] for c in book.clouds] == [0, 3, 2]
    live = np.stack([facing(0, [k, 0, 0]) for k in range(3)])  # by slot
    poses = book.poses_by_number(live, np.array([0, 3, 2, -1]))
    np.testing.assert_allclose(poses[[0, 3, 2]], live[[0, 1, 2]])
    np.testing.assert_allclose(poses[1], facing(90, [1.0, 2.0, 3.0]))


def drifting(step, yaw_per_scan_rad: float):
    """The odometry's `step`, its motion turned by a yaw bias each scan (a front-end that
    drifts); its poses are the biased motions chained."""
    state = {}

    def step_with_drift(*args, **kwargs):
        frame = step(*args, **kwargs)
        if "T" not in state:
            state["T"] = frame.T_world_lidar
            return frame
        T_prev_curr = frame.T_prev_curr @ geometry.se3_exp(
            np.array([0.0, 0.0, yaw_per_scan_rad, 0.0, 0.0, 0.0]))
        state["T"] = state["T"] @ T_prev_curr
        return dataclasses.replace(frame, T_prev_curr=T_prev_curr, T_world_lidar=state["T"])

    return step_with_drift


def test_slam_keeps_closing_loops_after_the_keyframe_store_wraps(ti_runtime):
    """One and a half laps of the room with a front-end that turns 0.4 deg a scan too far and
    a store of 6 keyframes, which wraps four times: new keyframes keep coming (in reused
    slots), the first ones stay and loops to them keep pulling the pose back, and the
    trajectory (every scan hung off its keyframe) stays near the truth (0.16 m at worst, where
    only loops correct). Before, a full store took no keyframe and every later scan hung off
    the last one by the front-end's motion: the trajectory drifted with the front-end (0.75 m
    here)."""
    from support.localize_world import Scanner, path

    from mcl3d.slam.loop_bridge import anchored_keyframes
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    capacity = 6
    cfg = SlamConfig.model_validate({
        "particles": 64, "seed": 1,
        "keyframes": {"capacity": capacity, "overlap": 0.9, "overlap_voxel_m": 0.5},
        "loop_closure": {"min_travel_m": 4.0}})
    slam = MonteCarloSlam(cfg)
    slam.odometry.step = drifting(slam.odometry.step, np.deg2rad(0.4))
    scanner = Scanner(n_azimuth=120, noise_m=0.005, seed=1)
    truth = path(60, step_m=0.3)
    for k, T in enumerate(truth):
        slam.step(scanner.scan(T), None, 1_700_000_000_000_000_000 + k * 100_000_000)
    truth = geometry.se3_inverse(truth[0]) @ truth  # SLAM's world is its first pose
    _, poses = slam.trajectory()
    err = np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)
    odo = slam.frames.poses("T_odom_lidar")
    odo_err = np.linalg.norm(odo[:, :3, 3] - truth[:, :3, 3], axis=1)
    made = len(slam.keyframe_frames)
    assert slam.particles.num_keyframes == capacity and made >= 4 * capacity
    kept = set(slam.particles.seq[:capacity].tolist())
    assert 0 in kept and {made - 1, made - 2, made - 3} <= kept
    late = slice(40, None)  # the second lap
    assert odo_err[late].max() > 0.5  # the front-end is off by half a metre and more
    assert err[late].max() < 0.25, err[late].max()
    assert (slam.frames.corrected[late] > 0).mean() > 0.5  # loops kept closing
    travel = slam.frames.travel_m  # a loop keyframe is named by number, slots reused or not
    for i, keyframes, _ in slam.frames.loops():
        assert all(travel[i] - travel[slam.keyframe_frames[k]] > 4.0 for k in keyframes)
    # the written trajectory is the loop graph, its loops registered while both keyframes were
    # kept; bridged instead, the keyframes the loops anchor, dropped from the store or not,
    # stay where the particle has them
    assert slam.loop_edges.registered()
    slam.cfg.trajectory.loop_graph = False
    _, bridged = slam.trajectory()
    slam.cfg.trajectory.bridge_between_loops = False
    _, own = slam.trajectory()
    anchors = np.asarray(slam.keyframe_frames)[anchored_keyframes(
        np.array([i for i, _, _ in slam.frames.loops()]), np.asarray(slam.keyframe_frames))]
    assert len(anchors) > 3 and np.allclose(bridged[anchors], own[anchors])
    assert not np.allclose(bridged, own) and not np.allclose(poses, own)


def test_a_keyframe_map_takes_a_long_run_of_colliding_voxels(ti_runtime):
    """~64 voxels with one home slot (every cell of a 64³ cube that hashes to slot 0 of the
    keyframe table): a probe run past 32 slots, which ended a SLAM run once (0.25 m keyframe
    voxels, the 45th keyframe); a SLAM keyframe map (gaussian_voxels.MAX_PROBES) holds them,
    a 32-probe table does not."""
    import pytest

    from mcl3d.core.errors import MapError
    from mcl3d.registration.gaussian_voxels import GaussianVoxelMaps
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import SlamConfig

    slam = MonteCarloSlam(SlamConfig.model_validate({"particles": 4, "seed": 1,
                                                     "keyframes": {"capacity": 2}}))
    maps, voxel_m = slam.maps, 0.25
    cells = np.stack(np.meshgrid(*[np.arange(64)] * 3, indexing="ij"), -1).reshape(-1, 3)
    crowd = cells[numpy_voxel_hash(cells, maps.buckets) == 0]
    assert len(crowd) > 40
    points = (crowd + 0.5) * voxel_m
    covs = np.repeat(np.eye(3)[None] * 0.01, len(points), axis=0)
    maps.clear(0, voxel_m)
    assert maps.insert(0, points, covs) == len(crowd)
    short = GaussianVoxelMaps(max_maps=1, buckets_per_map=maps.buckets,
                              max_points=maps.max_points, max_probes=32)
    short.clear(0, voxel_m)
    with pytest.raises(MapError, match="no free slot within 32 probes"):
        short.insert(0, points, covs)
