"""The filter's random streams. Each random draw of an update has its own stream, keyed by
(seed, update, stream), so runs repeat bit for bit with the same seed and one draw never
shifts another. Kernels hash (seed, counter, particle), the host draws from NumPy generators.
"""

from __future__ import annotations

import numpy as np

COUNTERS_PER_UPDATE = 8  # kernel counter = update * 8 + one of the salts below
MOTION_COUNTER = 0  # the motion noise; also keys the scan subset and the resampling offset
INIT_GLOBAL_COUNTER = 1  # particles drawn over the map's free space
INIT_POSE_COUNTER = 2  # particles drawn around a pose
EVIDENCE_COUNTER = 3  # the particles of each place that judge a scan (place evidence)
CHECK_COUNTER = 4  # the poses of a convergence check and the particles it re-seeds

ESTIMATE_SAMPLE_STREAM = 3  # the weighted subsample that the estimate clusters
MODE_SAMPLE_STREAM = 4  # the uniform subsample that finds populous modes
KLD_SAMPLE_STREAM = 5  # the weighted subsample that counts KLD bins
RESAMPLE_OFFSET_STREAM = 7  # the offset of systematic resampling


def kernel_counter(update: int, salt: int) -> int:
    """The u32 counter a kernel hashes for `update` and one of the *_COUNTER salts."""
    return (update * COUNTERS_PER_UPDATE + salt) & 0xFFFFFFFF


def host_rng(seed: int, key: int, stream: int | None = None) -> np.random.Generator:
    """The NumPy generator of one stream (`stream` None: the scan subset's stream)."""
    return np.random.default_rng([seed, key] if stream is None else [seed, key, stream])
