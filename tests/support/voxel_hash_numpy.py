"""kernels/voxel_hash's home bucket in NumPy, for tests that need voxels in known slots."""

import numpy as np


def numpy_voxel_hash(keys, buckets):
    """kernels/voxel_hash.voxel_hash in NumPy (wrapping u32), masked to a home bucket."""
    k = keys.astype(np.int64).astype(np.uint32)
    with np.errstate(over="ignore"):
        h = k[:, 0] * np.uint32(73856093) + k[:, 1] * np.uint32(19349669) \
            + k[:, 2] * np.uint32(83492791)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return (h & np.uint32(buckets - 1)).astype(np.int64)
