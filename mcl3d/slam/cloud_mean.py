"""The SLAM particle cloud's weighted SE(3) mean and the covariance about it, from moments the
device sums: `evaluation.consistency.weighted_pose_mean`'s fixed point without bringing every
pose to the host (that host mean took 250 of a 294 ms frame at 100,000 particles on an H100).

Each iteration sends the mean down and brings back 27 numbers: the weighted sums of
xi = se3_log(T_mean^-1 T_k) and of xi xi^T (kernels/particle_stats.py, block-ordered: the
same bits on every run and thread count). The sums are f32, so the iteration stops once its
step is below f32's rounding of the particles' poses, not at the host's 1e-10.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from mcl3d.core.geometry import rot_to_quat, se3_exp, symmetric_from_upper
from mcl3d.evaluation.consistency import MEAN_ITERATIONS
from mcl3d.kernels import particle_stats as ks
from mcl3d.kernels.resample import SCAN_BLOCK

MEAN_TOLERANCE_F32 = 1e-6  # rad, m: a smaller step is f32 rounding of the sums


class CloudMean:
    """Device fields for the moments of up to `capacity` particles."""

    def __init__(self, capacity: int):
        blocks = (int(capacity) + SCAN_BLOCK - 1) // SCAN_BLOCK
        self._w = ti.field(ti.f32, shape=int(capacity))
        self._partial = ti.Vector.field(27, ti.f32, shape=blocks)
        self._sum = ti.Vector.field(27, ti.f32, shape=1)

    def __call__(self, q_cur, t_cur, weights: np.ndarray,
                 T_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T_mean (4, 4), covariance (6, 6) rotation first) of the poses in the fields q_cur,
        t_cur with `weights` (N,) summing to 1, iterated from `T_start` (weighted_pose_mean
        starts at the heaviest pose's rotation and the weighted mean position)."""
        n = len(weights)
        w32 = np.zeros(self._w.shape, np.float32)
        w32[:n] = weights
        self._w.from_numpy(w32)
        total = float(np.sum(w32, dtype=np.float64))
        mean = np.asarray(T_start, np.float64).copy()
        for iteration in range(MEAN_ITERATIONS + 1):
            ks.tangent_moment_partials(t_cur, q_cur, self._w, n,
                                       ti.math.vec3(*mean[:3, 3]),
                                       ti.math.vec4(*rot_to_quat(mean[:3, :3])), self._partial)
            ks.sum_vector_partials(self._partial, n, self._sum)
            x = self._sum.to_numpy()[0].astype(np.float64) / total
            step = x[:6]
            if np.max(np.abs(step)) < MEAN_TOLERANCE_F32 or iteration == MEAN_ITERATIONS:
                break
            mean = mean @ se3_exp(step)
        return mean, symmetric_from_upper(x[6:], 6) - np.outer(step, step)
