"""Counter-based random numbers: a pure function of (seed, step, index, stream).

`ti.random` is not reproducible across runs in parallel loops; hashing the counters gives
the same particles for the same `--seed` on every backend and thread count.
"""

import taichi as ti

_TWO_PI = 6.283185307179586


@ti.func
def hash_u32(x: ti.u32) -> ti.u32:
    """lowbias32 (C. Wellons): a well-mixed 32-bit integer hash."""
    x ^= x >> ti.u32(16)
    x *= ti.u32(0x7FEB352D)
    x ^= x >> ti.u32(15)
    x *= ti.u32(0x846CA68B)
    x ^= x >> ti.u32(16)
    return x


@ti.func
def counter_hash(seed: ti.u32, step: ti.u32, index: ti.u32, stream: ti.u32) -> ti.u32:
    h = hash_u32(seed ^ ti.u32(0x9E3779B9))
    h = hash_u32(h ^ step)
    h = hash_u32(h ^ index)
    return hash_u32(h ^ (stream * ti.u32(0x85EBCA6B)))


@ti.func
def uniform(seed: ti.u32, step: ti.u32, index: ti.u32, stream: ti.u32) -> ti.f32:
    """Uniform in [0, 1) from the top 24 bits (exactly representable in f32)."""
    bits = counter_hash(seed, step, index, stream) >> ti.u32(8)
    return ti.cast(bits, ti.f32) * (1.0 / 16777216.0)


@ti.func
def normal2(seed: ti.u32, step: ti.u32, index: ti.u32, stream: ti.u32) -> ti.math.vec2:
    """Two independent standard normals (Box-Muller) from streams `stream` and `stream + 1`."""
    u1 = uniform(seed, step, index, stream) + (0.5 / 16777216.0)
    u2 = uniform(seed, step, index, stream + ti.u32(1))
    r = ti.sqrt(-2.0 * ti.log(u1))
    return ti.math.vec2(r * ti.cos(_TWO_PI * u2), r * ti.sin(_TWO_PI * u2))
