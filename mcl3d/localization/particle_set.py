"""The particle set on the device: SoA f32 fields allocated once at capacity.

Positions (vec3, m) and unit quaternions (vec4, x y z w) are `T_map_lidar` hypotheses; each
has a log-weight. A second pos/quat buffer receives the resampled set (a gather by parent
index), then the two are swapped, so nothing is allocated per update. Scratch fields for
weights, the CDF and parents serve mcl3d.kernels.resample.
"""

from __future__ import annotations

import os

import numpy as np
import taichi as ti

from mcl3d.core.errors import ConfigError
from mcl3d.kernels.resample import SCAN_BLOCK

MAX_PARTICLES = 8_000_000  # one parallel loop must stay under Vulkan's 8M-iteration limit
# two pose buffers + log_w, w, cdf, parent, match, ll, factor, label + locality key and order
# + the place evidence's sort buffers, place fields and log-likelihoods (88 bytes)
BYTES_PER_PARTICLE = 2 * (12 + 16) + 8 * 4 + 2 * 4 + 88


def available_memory_bytes() -> int | None:
    """Physical memory the host can still give us (Linux), or None when unknown."""
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_capacity(capacity: int) -> None:
    """ConfigError before any allocation when `capacity` particles cannot work."""
    if capacity < 1:
        raise ConfigError(f"the number of particles must be >= 1, got {capacity}",
                          setting="particles")
    if capacity > MAX_PARTICLES:
        raise ConfigError(
            f"{capacity:,} particles is more than the supported {MAX_PARTICLES:,} (one kernel "
            f"launch must stay under 8M iterations on Vulkan); use fewer particles",
            setting="particles")
    need = capacity * BYTES_PER_PARTICLE
    avail = available_memory_bytes()
    if avail is not None and need > 0.8 * avail:
        raise ConfigError(
            f"{capacity:,} particles need {need / 2**20:.0f} MiB but only "
            f"{avail / 2**20:.0f} MiB of memory is free; use fewer particles",
            setting="particles")


class ParticleSet:
    """Particle fields sized `capacity`; `n` of them are in use."""

    def __init__(self, capacity: int):
        check_capacity(capacity)
        self.capacity = int(capacity)
        self.n = int(capacity)
        c = self.capacity
        self.pos = ti.Vector.field(3, ti.f32, shape=c)
        self.quat = ti.Vector.field(4, ti.f32, shape=c)
        self.pos_back = ti.Vector.field(3, ti.f32, shape=c)
        self.quat_back = ti.Vector.field(4, ti.f32, shape=c)
        self.log_w = ti.field(ti.f32, shape=c)
        self.match = ti.field(ti.f32, shape=c)  # fraction of scan points on a surface
        self.ll_mean = ti.field(ti.f32, shape=c)  # mean per-point log-likelihood, last scan
        self.w = ti.field(ti.f32, shape=c)
        self.cdf = ti.field(ti.f32, shape=c)
        self.parent = ti.field(ti.i32, shape=c)
        self.factor = ti.field(ti.f32, shape=c)  # mode-preserving resampling factor
        self.label = ti.field(ti.i32, shape=c)  # cluster of a global search's mode floor
        self.block_sums = ti.field(ti.f32, shape=(c + SCAN_BLOCK - 1) // SCAN_BLOCK)
        self.partial_sums = ti.Vector.field(2, ti.f32, shape=(c + SCAN_BLOCK - 1) // SCAN_BLOCK)
        self.sums = ti.field(ti.f32, shape=2)

    def swap(self) -> None:
        """The back buffers (just gathered into) become the current particles."""
        self.pos, self.pos_back = self.pos_back, self.pos
        self.quat, self.quat_back = self.quat_back, self.quat

    def host(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions (n, 3), quaternions xyzw (n, 4), log-weights (n,)) as numpy copies."""
        n = self.n
        return (self.pos.to_numpy()[:n], self.quat.to_numpy()[:n], self.log_w.to_numpy()[:n])

    def set_host(self, positions: np.ndarray, quats_xyzw: np.ndarray,
                 log_w: np.ndarray | None = None) -> None:
        """Upload a particle set (tests, restarts); `n` becomes its length."""
        n = len(positions)
        if n > self.capacity:
            raise ConfigError(f"{n} particles do not fit the capacity {self.capacity}")
        pos = np.zeros((self.capacity, 3), np.float32)
        quat = np.zeros((self.capacity, 4), np.float32)
        quat[:, 3] = 1.0
        lw = np.zeros(self.capacity, np.float32)
        pos[:n], quat[:n] = positions, quats_xyzw
        if log_w is not None:
            lw[:n] = log_w
        self.pos.from_numpy(pos)
        self.quat.from_numpy(quat)
        self.log_w.from_numpy(lw)
        self.n = n
