"""How well each place explains every scan since the last (re-)initialization: the rival
test that keeps the filter from claiming `converged` at one of several look-alike places,
and the floor that keeps such places alive until the scans rule them out.

A cluster's weight is a Monte Carlo sum whose noise compounds scan by scan: between two
look-alike places (identical rack aisles, identical rooms) the weight ratio random-walks
until one place holds 80% of the weight and looks converged, although no scan ever told the
places apart, and a place whose particles died by chance gives no evidence at all.

Instead each particle carries the evidence of the best path through the places it came
from: before a scan's tempered log-likelihood is added, every particle takes the best
evidence of its place (a cell of position and yaw), and children inherit their parent's at
resampling. A single lineage would pay for every scan in which it, by chance, sat a few
centimetres off the optimum (a sparse place loses several nats a scan that way, the
true place among them); the best of the place does not. The best increment is taken over
a fixed number of the place's particles, else the place with the most particles would win
every scan's maximum by their number alone. A place away from the dominant cluster within
a margin of the dominant's best still explains the scans: the filter is ambiguous,
whatever the weights say.

Which particles a place happens to hold still makes each place's evidence a random walk,
and the best of hundreds of look-alike places outruns any one of them (the true one among
them) by a few nats per hundred scans. So a place is ruled out only when it falls behind by
more than that noise can explain: `noise_margin`, from the spread between two disjoint
draws of the same place's particles, grows with the square root of the scans and with the
number of places compared.

All of it runs on the device (kernels/place_evidence.py): per update only the number of
places, the noise statistic, the live places and the rival test's two maxima come back
(a few dozen bytes, whatever the particle count).
"""

from __future__ import annotations

import math

import numpy as np
import taichi as ti

from mcl3d.core import geometry
from mcl3d.core.errors import ConfigError
from mcl3d.kernels import place_evidence as kpe
from mcl3d.kernels.particle_stats import gather_values
from mcl3d.localization.particle_set import ParticleSet

MAX_PLACE_KEYS = 1 << 64  # cells x yaw bins of the particles' bounding box (u64 keys)


class PlaceEvidence:
    """Accumulated tempered log-likelihood per particle (device, f32) and the places of the
    last update; see the module."""

    def __init__(self, capacity: int) -> None:
        self.fields = kpe.PlaceFields(capacity)
        self.log_l = ti.field(ti.f32, shape=capacity)
        self._log_l_back = ti.field(ti.f32, shape=capacity)
        self.n = 0  # particles the evidence is for
        self.scans = 0  # scans accumulated since the last reset
        self.variance = 0.0  # summed per-scan variance of a place's increment, nats^2
        self.places = 0  # places of the last update
        self._sorted = 0  # the sort buffer holding the last update's places

    def reset(self, n: int) -> None:
        self.n = int(n)
        self.scans = 0
        self.variance = 0.0
        self.places = 0
        self.log_l.fill(0.0)

    def noise_margin(self, places: int, false_alarm: float = 0.01) -> float:
        """Nats by which one of `places` equally good places may trail the best by chance:
        a Bonferroni z over the places times the std of two places' evidence difference."""
        z = np.sqrt(2.0 * np.log(max(places, 2) / false_alarm))
        return float(z * np.sqrt(2.0 * self.variance))

    def add(self, p: ParticleSet, scale: float, cell_m: float, yaw_bins: int, sample: int,
            seed: int, counter: int, leaders_nats: float = 10.0) -> None:
        """One scan, increments scale * p.ll_mean: each place (a cell of `cell_m` and
        360/`yaw_bins` degrees) continues from the best evidence among its particles, plus
        the best increment among `sample` of its particles drawn at random (so a place
        with many particles does not win the maximum by their number alone). The places
        within `leaders_nats` of the best measure this scan's noise. The draw is keyed by
        (seed, counter)."""
        if self.n != p.n:
            self.reset(p.n)
        f, n = self.fields, p.n
        kpe.place_cells(p.pos, p.quat, n, cell_m, yaw_bins, f)
        lo, hi = f.bounds.to_numpy().astype(np.int64)
        dims = hi - lo + 1
        keys = math.prod(int(d) for d in dims)
        if keys > MAX_PLACE_KEYS:
            raise ConfigError(
                f"the particles spread over {keys:,} place cells (more than 2^64); raise "
                f"resample.place_cell_m ({cell_m} m) or place_yaw_deg", setting="resample")
        kpe.place_keys(f, n, ti.math.ivec4(*dims.tolist()), seed, counter)
        src = 0
        for word, bits in ((0, kpe.RAND_BITS), (1, (keys - 1).bit_length())):
            for shift in range(0, bits, 8):
                kpe.radix_pass(f, n, src, word, shift)
                src = 1 - src
        kpe.place_runs(f, n, src)
        kpe.place_scores(f, n, src, self.log_l, p.ll_mean, scale, sample)
        kpe.noise_mad(f, leaders_nats)
        out = f.out.to_numpy()
        self.places = int(out[kpe.OUT_PLACES])
        if out[kpe.OUT_LEADERS] > 0:  # robust: the MAD over the leading places
            self.variance += float((1.4826 * float(out[kpe.OUT_MAD])) ** 2 / 2.0)
        self.scans += 1
        self._sorted = src

    def floor(self, p: ParticleSet, margin_nats: float, min_particles: int) -> int:
        """The live places of the last `add` (evidence within `margin_nats` of the best
        one, and weight); when there are two or more, p.factor = resampling factors that
        give each at least `min_particles` expected copies (at most half the particles go
        to such floors). Returns the number of live places.

        Resampling by weight alone lets a look-alike place whose cluster weight drifted low
        die by chance, and a dead place can never win again; with these factors (applied
        as weight * factor, each copy carrying -log(factor), see `resampling`) a place dies
        only when the scans rule it out.
        """
        f = self.fields
        kpe.place_weights(f, self._sorted, p.w, margin_nats)
        live = int(f.out[kpe.OUT_LIVE])
        if live >= 2:
            kpe.place_floor(f, p.n, min(min_particles / p.n, 0.5 / live), p.factor)
        return live

    def rival_gap(self, p: ParticleSet, T_dominant: np.ndarray, radius_m: float,
                  angle_rad: float) -> float:
        """Best evidence among particles away from the dominant pose (farther than
        `radius_m` or turned more than `angle_rad`) minus the best within `radius_m / 2`
        and `angle_rad / 2` of it: > -margin means another place still explains the scans.
        -inf when every particle is near the dominant pose, +inf when none is close to it."""
        if self.n != p.n or not p.n:
            return -np.inf
        t, q = geometry.tq_from_se3(np.asarray(T_dominant, np.float64))
        kpe.rival_bests(p.pos, p.quat, self.log_l, p.n, ti.math.vec3(*t), ti.math.vec4(*q),
                        radius_m, math.cos(0.5 * min(0.5 * angle_rad, math.pi)),
                        math.cos(0.5 * min(angle_rad, math.pi)), self.fields)
        out = self.fields.out.to_numpy()
        if out[kpe.OUT_N_AWAY] == 0:
            return -np.inf
        if out[kpe.OUT_N_INSIDE] == 0:  # no particle (with evidence) at the mean: no verdict
            return np.inf
        return float(out[kpe.OUT_AWAY]) - float(out[kpe.OUT_INSIDE])

    def best_near(self, p: ParticleSet, T: np.ndarray, radius_m: float, angle_rad: float
                  ) -> float:
        """The best evidence within `radius_m` / 2 and `angle_rad` / 2 of pose T (0.0 when no
        particle is there): what a place re-seeded beside it starts from."""
        if self.n != p.n or not p.n:
            return 0.0
        t, q = geometry.tq_from_se3(np.asarray(T, np.float64))
        kpe.rival_bests(p.pos, p.quat, self.log_l, p.n, ti.math.vec3(*t), ti.math.vec4(*q),
                        radius_m, math.cos(0.5 * min(0.5 * angle_rad, math.pi)),
                        math.cos(0.5 * min(angle_rad, math.pi)), self.fields)
        out = self.fields.out.to_numpy()
        return float(out[kpe.OUT_INSIDE]) if out[kpe.OUT_N_INSIDE] > 0 else 0.0

    def inherit(self, parent, n_out: int) -> None:
        """After resampling: child k continues the evidence of particle `parent[k]` (a
        device field)."""
        if self.n:
            gather_values(self.log_l, parent, n_out, self._log_l_back)
            self.log_l, self._log_l_back = self._log_l_back, self.log_l
            self.n = int(n_out)
