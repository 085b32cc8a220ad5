"""What `mcl3d slam` reports against the ground truth besides ATE: the cloud's consistency
(aligned at the first scan) and which of the representative's loop corrections were wrong.
Built from hand-made frames, so each number is known."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mcl3d.core.geometry import se3, se3_exp, so3_exp
from mcl3d.io.trajectory import Trajectory
from mcl3d.slam.frame_store import SlamFrame, SlamFrames
from mcl3d.slam.loop_graph import LoopEdge
from mcl3d.slam.slam_summary import WRONG_LOOP_M, _check_against_truth

SIGMA = np.array([0.01, 0.01, 0.02, 0.1, 0.1, 0.05])


def frame(stamp_ns: int, T_mean: np.ndarray, cov: np.ndarray, loop_kfs=(), loop_rel=()):
    return SlamFrame(stamp_ns, T_mean, T_mean, T_mean, 0, 1.0, 1.0, 1, 0, 0, 0, False, 1,
                     False, 0.0, [], {}, T_mean, cov, tuple(loop_kfs), tuple(loop_rel))


def stored(frames: list[SlamFrame]) -> SlamFrames:
    store = SlamFrames(initial_rows=16)  # grows while the frames go in
    for f in frames:
        store.append(f)
    return store


def test_consistency_and_loops_against_the_truth():
    rng = np.random.default_rng(0)
    n = 400
    stamps = 1_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    truth = np.stack([se3(so3_exp([0, 0, 0.01 * k]), [0.5 * k, 0, 0]) for k in range(n)])
    # SLAM's world is the first pose's frame: the truth starts elsewhere
    offset = se3(so3_exp([0.0, 0.0, 1.0]), [10.0, -3.0, 0.5])
    gt = Trajectory.from_ns(stamps, offset @ truth)
    cov = np.diag(SIGMA**2)
    means = [truth[0]] + [truth[k] @ se3_exp(rng.normal(0, SIGMA)) for k in range(1, n)]
    kf = 5  # scan 5 is keyframe 0
    right = np.linalg.inv(truth[kf]) @ truth[300]
    wrong = se3_exp([0, 0, 0, 0, 4.0, 0]) @ right  # matched to the next row, 4 m over
    frames = [frame(int(s), m, cov) for s, m in zip(stamps, means, strict=True)]
    frames[300] = frame(int(stamps[300]), means[300], cov, [0], [right])
    frames[301] = frame(int(stamps[301]), means[301], cov, [0], [wrong])
    # right against keyframe 0, off against keyframe 1, which the particle holds 2.5 m low
    held_low = se3_exp([0, 0, 0, 0, 0, 2.5]) @ np.linalg.inv(truth[300]) @ truth[302]
    frames[302] = frame(int(stamps[302]), means[302], cov, [0, 1],
                        [np.linalg.inv(truth[kf]) @ truth[302], held_low])
    # the loop graph's edges: keyframes 1 and 2 (scans 300, 301) registered onto keyframe 0,
    # 2 onto the next row; one registration rejected
    edges = {(1, 0): LoopEdge(1, 0, right, np.eye(6)),
             (2, 0): LoopEdge(2, 0, se3_exp([0, 0, 0, 0, 4.0, 0]) @ np.linalg.inv(truth[kf])
                              @ truth[301], np.eye(6)),
             (2, 1): None}
    slam = SimpleNamespace(frames=stored(frames), keyframe_frames=[kf, 300, 301],
                           map_loop_edges=lambda: [e for e in edges.values() if e is not None])
    cloud, loops = _check_against_truth(slam, gt)
    assert cloud.scans == n and 0.9 <= cloud.fraction <= 0.99
    assert loops.accepted == 3 and loops.wrong == 2 and loops.misplaced == 1
    assert loops.worst_m > WRONG_LOOP_M and abs(loops.farthest_m - 0.5 * 296) < 1.0
    assert loops.edges_wrong == 1 and abs(loops.edges_worst_m - 4.0) < 1e-6
    narrow = [frame(f.stamp_ns, f.T_mean, cov / 25) for f in frames]
    cloud, _ = _check_against_truth(SimpleNamespace(frames=stored(narrow), keyframe_frames=[],
                                                    map_loop_edges=list), gt)
    assert cloud.fraction < 0.1
    assert _check_against_truth(slam, None) == (None, None)
