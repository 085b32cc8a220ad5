"""NumPy twin of kernels/random.py (counter-based normals), for reference tests of kernels
that draw from it."""

import numpy as np

TWO_PI = 6.283185307179586


def hash_u32(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.uint32).copy()
    x ^= x >> np.uint32(16)
    x *= np.uint32(0x7FEB352D)
    x ^= x >> np.uint32(15)
    x *= np.uint32(0x846CA68B)
    x ^= x >> np.uint32(16)
    return x


def counter_hash(seed: int, step: int, index: np.ndarray, stream: int) -> np.ndarray:
    with np.errstate(over="ignore"):
        h = hash_u32(np.uint32(seed) ^ np.uint32(0x9E3779B9))
        h = hash_u32(h ^ np.uint32(step))
        h = hash_u32(h ^ np.asarray(index, np.uint32))
        return hash_u32(h ^ (np.uint32(stream) * np.uint32(0x85EBCA6B)))


def uniform(seed: int, step: int, index: np.ndarray, stream: int) -> np.ndarray:
    bits = counter_hash(seed, step, index, stream) >> np.uint32(8)
    return bits.astype(np.float32) * np.float32(1.0 / 16777216.0)


def normal2(seed: int, step: int, index: np.ndarray, stream: int) -> np.ndarray:
    """(n, 2) standard normals, as kernels.random.normal2 (float64 arithmetic)."""
    u1 = uniform(seed, step, index, stream).astype(np.float64) + 0.5 / 16777216.0
    u2 = uniform(seed, step, index, stream + 1).astype(np.float64)
    r = np.sqrt(-2.0 * np.log(u1))
    return np.stack([r * np.cos(TWO_PI * u2), r * np.sin(TWO_PI * u2)], axis=-1)
