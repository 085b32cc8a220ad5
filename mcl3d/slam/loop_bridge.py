"""The representative's keyframes between loops, as their expectation rather than one draw.

Between two loop corrections a particle's keyframe poses are the odometry chain plus the
prediction noise it drew: a random walk that no scan tested (only loops weigh the particles).
Its most likely path given both ends is the odometry chain with the smallest steps, in the
odometry's drift covariance, that reach the far end: a two-ended chain solved by
Gauss-Newton. A keyframe is an anchor when the representative took a loop correction while
it was the newest keyframe: there the scan matched an old keyframe, so its pose is evidence,
not noise; so is the newest keyframe's, the filter's present estimate (after an elevator
ride without an IMU, the floor it chose).
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np

from mcl3d.core.geometry import se3_adjoint, se3_exp, se3_inverse, se3_log

BRIDGE_ITERATIONS = 3  # Gauss-Newton steps per chain: 10° and 2.6 m over 40 steps miss by < 1e-6
MIN_STEP_VARIANCE = 1e-12  # added to a step's variances (rad², m²): a step without drift


def anchored_keyframes(loop_scans: np.ndarray, keyframe_scans: np.ndarray) -> np.ndarray:
    """(K,) bool: keyframe k is an anchor when one of `loop_scans` (scans on which the
    representative took a loop correction) falls between its scan and the next keyframe's."""
    anchored = np.zeros(len(keyframe_scans), bool)
    newest = np.searchsorted(keyframe_scans, loop_scans, side="right") - 1
    anchored[newest[newest >= 0]] = True
    return anchored


def bridge_between_anchors(T_world_keyframe: np.ndarray, T_motion_keyframe: np.ndarray,
                           drift_variance: np.ndarray, anchored: np.ndarray,
                           up: np.ndarray | None = None) -> np.ndarray:
    """(K, 4, 4) keyframe poses: anchors, the first and the newest keyframe keep theirs;
    between anchors a and b, keyframe k+1 = keyframe k × the odometry's motion × exp(δ_k), the
    δ the smallest (in each step's drift covariance) that land exactly on b.
    `T_motion_keyframe`: the odometry's poses at the keyframes' scans; `drift_variance`
    (K, 3): summed along the path up to each keyframe, the prediction's rotational variance
    (rad², the trace), its translational one (m², the trace) and the elevator's vertical
    random walk (m², along `up`, default +z)."""
    T_out = np.array(T_world_keyframe, dtype=np.float64)
    K = len(T_out)
    ends = (np.arange(K) == 0) | (np.arange(K) == K - 1)
    anchors = np.flatnonzero(anchored | ends)
    motion = [se3_inverse(T_motion_keyframe[k]) @ T_motion_keyframe[k + 1] for k in range(K - 1)]
    step_cov = step_covariances(T_motion_keyframe, drift_variance, up)
    for a, b in pairwise(anchors):
        if b - a > 1:
            T_out[a + 1:b] = _two_ended_chain(T_out[a], T_out[b], motion[a:b],
                                              step_cov[a:b])[1:-1]
    return T_out


def step_covariances(T_motion_keyframe: np.ndarray, drift_variance: np.ndarray,
                     up: np.ndarray | None = None) -> np.ndarray:
    """(K - 1, 6, 6) covariance of the odometry's step from each keyframe to the next (rotation
    first, in the later keyframe's frame): the growth of `drift_variance` (see
    `bridge_between_anchors`) spread evenly over the axes, the elevator's along `up`."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, np.float64)
    grown = np.diff(np.asarray(drift_variance, np.float64), axis=0)
    step_cov = np.zeros((len(grown), 6, 6))
    step_cov[:, :3, :3] = np.eye(3) * grown[:, 0, None, None] / 3.0
    step_cov[:, 3:, 3:] = np.eye(3) * grown[:, 1, None, None] / 3.0
    up_local = np.einsum("kji,j->ki", T_motion_keyframe[1:, :3, :3], up)  # in each step's frame
    step_cov[:, 3:, 3:] += grown[:, 2, None, None] * np.einsum("ki,kj->kij", up_local, up_local)
    return step_cov + np.eye(6) * MIN_STEP_VARIANCE


def _two_ended_chain(T_start: np.ndarray, T_end: np.ndarray, motion: list[np.ndarray],
                     step_cov: np.ndarray) -> np.ndarray:
    """Poses from T_start by `motion[j] exp(δ_j)`, the δ of least Σ δᵀ W_j⁻¹ δ ending on
    T_end (W_j = step_cov[j], rotation first)."""
    def walk(delta: np.ndarray) -> list[np.ndarray]:
        poses = [T_start]
        for step, d in zip(motion, delta, strict=True):
            poses.append(poses[-1] @ step @ se3_exp(d))
        return poses

    n = len(motion)
    delta = np.zeros((n, 6))
    for _ in range(BRIDGE_ITERATIONS):
        poses = walk(delta)
        residual = se3_log(se3_inverse(poses[-1]) @ T_end)
        # a step's δ_j moves the end by Ad((T_{j+1}⁻¹ T_end)⁻¹) δ_j, in the end's frame
        J = np.stack([se3_adjoint(se3_inverse(se3_inverse(poses[j + 1]) @ poses[-1]))
                      for j in range(n)])
        S = np.einsum("jab,jbc,jdc->ad", J, step_cov, J)
        lam = np.linalg.solve(S, residual)
        delta += np.einsum("jab,jcb,c->ja", step_cov, J, lam)
    return np.stack(walk(delta))
