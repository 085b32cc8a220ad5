"""The representative's keyframes as a pose graph: held together by the odometry between
consecutive keyframes (in the drift covariance of the prediction noise, as the bridge) and by
every loop the representative took, registered to convergence.

The filter decides which loops hold: its particles keep the look-alike hypotheses until the
scans rule them out. It does not measure them to the centimetre: a loop step is one
Gauss-Newton step per scan inside a trust region, with the prediction noise drawn on top, and
the representative of a later scan descends from another particle. So when the
representative takes a loop from its newest keyframe a to an old keyframe b, the scan is
registered onto b's cloud, coarse to fine, from the filter's relative pose; the edge a -> b is
that registration and the odometry from a to the scan, its information the registration's
GICP Hessian. A pair is registered once, and again from a scan at most half as far from b
(nearer, the scan overlaps b's cloud more). The representative of a scan may hold a
hypothesis that later dies (another floor, the next row): the graph takes only the edges the
final representative's own keyframes agree with, within the registration's reach. Where a
keyframe measured up from the plumb surfaces it saw (mcl3d/slam/structure_up.py), its tilt
is held to that too. Solved by Gauss-Newton on SE(3) (right perturbations, rotation first),
the first and the newest keyframe fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import spsolve

from mcl3d.core.geometry import hat, rotation_angle, se3_adjoint, se3_exp, se3_inverse, se3_log
from mcl3d.registration.align import align
from mcl3d.slam.structure_up import UpMeasurement

GRAPH_ITERATIONS = 5  # Gauss-Newton steps from the filter's poses (converged in 2-3)
LOOP_RESOLUTIONS_M = (2.0, 1.0, 0.5)  # coarse to fine: the filter's estimate can be 1 m off
MAX_CORRECTION_M = 1.5  # a registration moving the filter's loop further did not find it
MAX_CORRECTION_DEG = 10.0
MIN_INLIER_FRACTION = 0.3  # of the source cloud's points, at the finest resolution
MIN_EDGE_INFORMATION = 1e-9  # added to an edge's information diagonal (a degenerate cloud)
NEARER_FRACTION = 0.5  # a pair is registered again from a scan this much nearer ...
NEARER_ABOVE_M = 1.0  # ... while the last registration was from further than this


@dataclass(frozen=True)
class LoopEdge:
    """Keyframe `source`'s pose in keyframe `target`'s frame, as registered."""

    source: int  # keyframe number (the one newest when the loop was taken)
    target: int  # the old keyframe it closed to
    T_target_source: np.ndarray
    information: np.ndarray  # 6x6, rotation first, in the source's frame


def register_again(known_m: float | None, distance_m: float) -> bool:
    """Whether a pair last registered from `known_m` away (None: never) is registered again
    from a scan `distance_m` from the loop keyframe."""
    return known_m is None or (known_m > NEARER_ABOVE_M and distance_m <= NEARER_FRACTION * known_m)


def register_loop(source: int, target: int, cloud: np.ndarray, cloud_target: np.ndarray,
                  T_target_cloud: np.ndarray, T_source_cloud: np.ndarray | None = None
                  ) -> LoopEdge | None:
    """The loop edge from keyframe `source` to keyframe `target`: `cloud` (a scan, in its
    lidar frame, at `T_source_cloud` in the source keyframe's frame; default: the source
    keyframe's own cloud) registered onto `cloud_target` from the estimate `T_target_cloud`.
    None when the registration did not converge, matched too little, or moved the filter's
    estimate further than it can be off."""
    result = align(cloud_target.astype(np.float64), cloud.astype(np.float64), T_target_cloud,
                   voxel_resolution_m=LOOP_RESOLUTIONS_M)
    if (not result.converged or result.num_inliers < MIN_INLIER_FRACTION * len(cloud)
            or not _within_reach(se3_inverse(T_target_cloud) @ result.T_target_source)):
        return None
    T_source_cloud = np.eye(4) if T_source_cloud is None else T_source_cloud
    # a perturbation δ of the cloud's pose is Ad(T_source_cloud) δ of the source keyframe's
    to_source = np.linalg.inv(se3_adjoint(T_source_cloud))
    H = 0.5 * (result.H + result.H.T)
    return LoopEdge(source, target, result.T_target_source @ se3_inverse(T_source_cloud),
                    to_source.T @ H @ to_source + np.eye(6) * MIN_EDGE_INFORMATION)


def _within_reach(T_offset: np.ndarray) -> bool:
    """Whether an offset from the filter's loop is one a registration can mean."""
    return bool(np.linalg.norm(T_offset[:3, 3]) <= MAX_CORRECTION_M
                and np.degrees(rotation_angle(T_offset[:3, :3])) <= MAX_CORRECTION_DEG)


class LoopEdges:
    """The loop edges of a run, by (source, target) keyframe numbers: a pair is registered
    when the representative first takes it and again from a much nearer scan
    (`register_again`); a failed registration keeps an earlier success."""

    def __init__(self) -> None:
        self._edges: dict[tuple[int, int], LoopEdge | None] = {}  # None: every try failed
        self._range_m: dict[tuple[int, int], float] = {}  # of the scan last registered

    def take(self, source: int, target: int, scan: np.ndarray, cloud_target: np.ndarray,
             T_target_scan: np.ndarray, T_source_scan: np.ndarray) -> None:
        """The representative took the loop source -> target on `scan` (see
        `register_loop`)."""
        pair = (source, target)
        distance_m = float(np.linalg.norm(T_target_scan[:3, 3]))
        if source == target or not register_again(self._range_m.get(pair), distance_m):
            return
        edge = register_loop(source, target, scan, cloud_target, T_target_scan, T_source_scan)
        if edge is not None or pair not in self._edges:
            self._edges[pair] = edge
        self._range_m[pair] = distance_m

    def registered(self) -> list[LoopEdge]:
        return [e for e in self._edges.values() if e is not None]

    @property
    def rejected(self) -> int:
        """Pairs whose every registration failed its checks."""
        return sum(e is None for e in self._edges.values())


def agreeing_edges(T_world_keyframe: np.ndarray, edges: list[LoopEdge]) -> list[LoopEdge]:
    """The edges the keyframes `T_world_keyframe` (the representative's own, by number) hold
    within the registration's reach: a loop another hypothesis took (a look-alike floor,
    the next row) is metres off in this representative's map, and not part of it."""
    return [e for e in edges if _within_reach(se3_inverse(e.T_target_source) @ se3_inverse(
        T_world_keyframe[e.target]) @ T_world_keyframe[e.source])]


def solve_pose_graph(T_world_keyframe: np.ndarray, T_motion_keyframe: np.ndarray,
                     step_cov: np.ndarray, loops: list[LoopEdge],
                     ups: dict[int, UpMeasurement] | None = None,
                     up_world: np.ndarray | None = None) -> np.ndarray:
    """(K, 4, 4) keyframe poses minimizing Σ rᵀ W r over the odometry edges (keyframe k to
    k + 1: its measured motion `T_motion_keyframe[k]⁻¹ T_motion_keyframe[k + 1]`, covariance
    `step_cov[k]`), the loop edges (information `LoopEdge.information`) and, with `ups` and
    `up_world`, each measured keyframe's tilt (its up in its own frame against `up_world`),
    from `T_world_keyframe`. The first and the newest keyframe keep their poses, as the bridge's
    anchors: the first fixes the map's frame, the newest is the filter's present estimate
    (after an elevator ride without an IMU, the floor it chose)."""
    T = np.array(T_world_keyframe, dtype=np.float64)
    K = len(T)
    if K < 3:
        return T
    motion = [se3_inverse(T_motion_keyframe[k]) @ T_motion_keyframe[k + 1] for k in range(K - 1)]
    edges = [(k, k + 1, motion[k], np.linalg.inv(step_cov[k])) for k in range(K - 1)]
    edges += [(e.target, e.source, e.T_target_source, e.information) for e in loops]
    tilts = ups if ups and up_world is not None else {}
    free = slice(6, 6 * (K - 1))  # keyframes 1 .. K - 2
    for _ in range(GRAPH_ITERATIONS):
        rows, cols, vals = [], [], []
        b = np.zeros(6 * K)
        for i, j, Z, W in edges:  # r = log(Z⁻¹ T_i⁻¹ T_j); ∂r/∂δ_j = I, ∂r/∂δ_i = -Ad(T_j⁻¹ T_i)
            r = se3_log(se3_inverse(Z) @ se3_inverse(T[i]) @ T[j])
            J = {i: -se3_adjoint(se3_inverse(T[j]) @ T[i]), j: np.eye(6)}
            for a, Ja in J.items():
                b[6 * a:6 * a + 6] += Ja.T @ W @ r
                for c, Jc in J.items():
                    rows.append(np.repeat(np.arange(6 * a, 6 * a + 6), 6))
                    cols.append(np.tile(np.arange(6 * c, 6 * c + 6), 6))
                    vals.append((Ja.T @ W @ Jc).ravel())
        for k, up in tilts.items():
            v = T[k][:3, :3].T @ up_world  # r = axes · R_kᵀ up_world; ∂r/∂δθ_k = axes [v]x
            J = np.zeros((2, 6))
            J[:, :3] = up.axes @ hat(v)
            W = np.diag(up.information)
            b[6 * k:6 * k + 6] += J.T @ W @ (up.axes @ v)
            rows.append(np.repeat(np.arange(6 * k, 6 * k + 6), 6))
            cols.append(np.tile(np.arange(6 * k, 6 * k + 6), 6))
            vals.append((J.T @ W @ J).ravel())
        H = sparse.csc_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                      np.concatenate(cols))), shape=(6 * K,) * 2)
        delta = spsolve(H[free, free], -b[free]).reshape(K - 2, 6)
        for k in range(1, K - 1):
            T[k] = T[k] @ se3_exp(delta[k - 1])
    return T
