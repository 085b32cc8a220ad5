"""The check of a global search's convergence claim against the whole map.

The filter's own protections against look-alike places (mode floors, place evidence, the
rival test: see `evidence`) only protect places that still hold particles. With too few
particles for the map (10,000 in the office: 0.15 per candidate cell) the true room's
particles can all die while the robot drives down a corridor whose doors repeat every 6 m;
the filter then follows the look-alike place one room along and claims `converged` there.

So before the first `converged` of a search the claim is checked against places the filter
may no longer hold: test poses on a grid over the map's global candidates (a position per
`grid_m` cell times yaws `yaw_deg` apart, the claim's roll and pitch) are scored on a scan
with a wide coarse model; the best pose of each place (a `place_m` cell and `place_yaw_deg`
bin) away from the claim is a candidate. The grid is placed at each of the newest
`anchor_scans` scans of the window and its candidates moved to the newest scan by the motion
input: a robot in a doorway stands where the map saw no floor (no global candidate, no test
pose within a metre of it), but a few metres back it did not. The claim and the best
`candidates` are then refined alike (two rounds of `refine_poses` poses around each, the
accurate model) and compared on a window of scans spread over the search so far, placed by
the motion input. A place within `margin_nats` of the claim's window score (or better) that
the filter holds no particles at explains the scans about as well: the claim is withheld
(the update reports `ambiguous`) and the localizer re-seeds a share of its particles there,
so that the filter's own evidence decides between the places from then on. A place
re-seeded once in a search and ruled out since does not stop a later claim.

All scoring runs in the ordinary likelihood kernels on the device (kernels/claim_check.py
places, moves and reduces the test poses); per check only each place's best score and pose
index come back (8 bytes a place and anchor scan), then a few dozen poses.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import taichi as ti

from mcl3d.core import geometry
from mcl3d.core.field_tree import FieldTree
from mcl3d.kernels import claim_check as kcc
from mcl3d.localization.initialization import FreeCells
from mcl3d.localization.localization_config import LocalizerConfig
from mcl3d.localization.particle_set import ParticleSet

MAX_TEST_POSES = 1 << 15  # test poses scored per launch (and the test set's capacity)
MAX_CENTRES = 64  # the claim and its candidates
# (translation std x y z [m], rotation std [rad]) of the refinement rounds
ROUNDS = (((0.15, 0.15, 0.05), (0.01, 0.01, 0.06)),
          ((0.05, 0.05, 0.02), (0.004, 0.004, 0.015)))
INJECT_STD = ((0.08, 0.08, 0.03), (0.01, 0.01, 0.03))  # particles re-seeded at a place


@dataclass(frozen=True)
class Rival:
    """A place that explains the window of scans about as well as the claim."""

    T_map_lidar: np.ndarray  # (4, 4) its refined pose now
    gap_nats: float  # its window score minus the claim's (> -margin)


class ScanWindow:
    """The reduced scans of the search so far (the newest `history`) with their poses
    chained from the motion input (the filter's own motion model)."""

    def __init__(self, history: int):
        self.scans: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=history)
        self._T_now = np.eye(4)

    def clear(self) -> None:
        self.scans.clear()
        self._T_now = np.eye(4)

    def add(self, points: np.ndarray, T_prev_curr: np.ndarray | None) -> None:
        if T_prev_curr is not None:
            self._T_now = self._T_now @ np.asarray(T_prev_curr, np.float64)
        self.scans.append((np.array(points, np.float32), self._T_now.copy()))

    def pick(self, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """`k` scans spread evenly over the window, newest first, each with T_curr_scan
        (its pose in the newest scan's frame)."""
        n = len(self.scans)
        idx = np.unique(np.round(np.linspace(0, n - 1, min(k, n))).astype(int))[::-1]
        T_inv = geometry.se3_inverse(self._T_now)
        return [(self.scans[i][0], T_inv @ self.scans[i][1]) for i in idx]


class _Grid:
    """Test positions (one per `grid_m` cell holding a global candidate) and their places."""

    def __init__(self, free: FreeCells, grid_m: float, place_m: float, bins: int):
        centres = free.corners_m.astype(np.float64) + 0.5 * free.cell_m
        _, first = np.unique(np.floor(centres / grid_m).astype(np.int64), axis=0,
                             return_index=True)
        self.positions = centres[np.sort(first)]
        _, group = np.unique(np.floor(self.positions / place_m).astype(np.int64), axis=0,
                             return_inverse=True)
        n = len(self.positions)
        self.groups = (int(group.max()) + 1 if n else 0) * bins
        by_map = FieldTree()  # sized by the map (field_tree)
        self.pos = by_map.field(ti.f32, max(n, 1), n=3)
        self.group = by_map.field(ti.i32, max(n, 1))
        self.best = by_map.field(ti.f32, max(self.groups, 1))
        self.arg = by_map.field(ti.i32, max(self.groups, 1))
        by_map.finalize()
        if n:
            self.pos.from_numpy(self.positions.astype(np.float32))
            self.group.from_numpy(group.ravel().astype(np.int32))


class ClaimCheck:
    """See the module docstring; `rivals` runs one check."""

    def __init__(self, cfg: LocalizerConfig):
        self.cfg = cfg
        self.window = ScanWindow(cfg.check.history_scans)
        self.runs = 0
        self.ms = 0.0
        self.withheld = 0
        self.reseeded_particles = 0
        self._tried: list[np.ndarray] = []  # places re-seeded in this search, moved along
        self._grid: _Grid | None = None
        self._test: ParticleSet | None = None

    def reset(self) -> None:
        """A new search: an empty window, no place re-seeded yet."""
        self.window.clear()
        self._tried.clear()

    def add_scan(self, points: np.ndarray, T_prev_curr: np.ndarray | None) -> None:
        self.window.add(points, T_prev_curr)
        if T_prev_curr is not None:
            self._tried = [T @ T_prev_curr for T in self._tried]

    def tried(self, T_map_lidar: np.ndarray) -> None:
        self._tried.append(np.asarray(T_map_lidar, np.float64))

    def stats(self) -> dict:
        return {"runs": self.runs, "ms_total": round(self.ms, 1),
                "ms_per_run": round(self.ms / self.runs, 1) if self.runs else 0.0,
                "withheld": self.withheld, "reseeded_particles": self.reseeded_particles}

    def rivals(self, weigher, p: ParticleSet, T_claim: np.ndarray, free: FreeCells,
               seed: int, counter: int) -> list[Rival]:
        """The places without particles that explain the scans about as well as the claim."""
        t0 = time.perf_counter()
        c = self.cfg.check
        self._allocate(p, free)
        window = self.window.pick(c.window_scans)
        found = self._anchored_candidates(weigher, window, T_claim)
        rivals: list[Rival] = []
        if found:
            poses, scores = self._refine(weigher, window, [T_claim, *found], seed, counter)
            rivals = [Rival(T, float(s - scores[0])) for T, s in zip(poses[1:], scores[1:],
                                                                     strict=True)
                      if s - scores[0] > -c.margin_nats and self._away(T, poses[0], 2.0)]
            rivals = self._unheld(p, self._distinct(rivals))
        self.runs += 1
        self.ms += 1e3 * (time.perf_counter() - t0)
        return rivals

    def _allocate(self, p: ParticleSet, free: FreeCells) -> None:
        c = self.cfg.check
        if self._grid is None:
            self._grid = _Grid(free, c.grid_m, c.place_m, round(360.0 / c.place_yaw_deg))
            self._test = ParticleSet(min(p.capacity, MAX_TEST_POSES))
            self._centre_pos = ti.Vector.field(3, ti.f32, shape=MAX_CENTRES)
            self._centre_quat = ti.Vector.field(4, ti.f32, shape=MAX_CENTRES)
            self._centre_best = ti.field(ti.f32, shape=MAX_CENTRES)
            self._centre_arg = ti.field(ti.i32, shape=MAX_CENTRES)
            self._centre_count = ti.field(ti.i32, shape=MAX_CENTRES)
            self._ident = ti.field(ti.i32, shape=MAX_CENTRES)
            self._ident.from_numpy(np.arange(MAX_CENTRES, dtype=np.int32))

    def _away(self, T: np.ndarray, T_ref: np.ndarray, factor: float) -> bool:
        """Whether T is another place than T_ref: farther than `factor` cluster radii or
        turned more than `factor` cluster angles."""
        e = self.cfg.estimate
        d = float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3]))
        a = float(geometry.rotation_angle(T_ref[:3, :3].T @ T[:3, :3]))
        return d > factor * e.cluster_radius_m or a > factor * e.cluster_angle_rad

    def _score(self, weigher, scans, count: int, coarse_sigma: float | None) -> None:
        """test.log_w[k] = the summed tempered log-likelihood of `scans` at test pose k
        (the base fields) moved to each scan."""
        test = self._test
        test.n = count
        test.log_w.fill(0.0)
        for points, T_curr_scan in scans:
            t, q = geometry.tq_from_se3(T_curr_scan)
            kcc.moved_poses(test.pos_back, test.quat_back, count, ti.math.vec3(*t),
                            ti.math.vec4(*q), test.pos, test.quat)
            weigher.upload_scan(points)
            if coarse_sigma is None:
                weigher.scan_likelihood(test, len(points), weigher.cache_block)
            else:
                weigher.coarse_likelihood(test, len(points), coarse_sigma)

    def _anchored_candidates(self, weigher, window, T_claim: np.ndarray) -> list[np.ndarray]:
        """The candidates of test poses placed at each of the newest `anchor_scans` scans of
        the window, moved to the newest scan by the motion input. The robot may stand where
        the map has no global candidate (a doorway, beside furniture: the map saw no floor
        there), where no test pose can be near it, but not at every scan of the window. Not
        merged across anchors: a poor pose of a place from one must not hide a good one of
        the same place from another (the refined rivals are, see `_distinct`)."""
        c = self.cfg.check
        found: list[np.ndarray] = []
        for a in range(min(c.anchor_scans, len(window))):
            T_anchor_curr = geometry.se3_inverse(window[a][1])
            scans = [(pts, T_anchor_curr @ T) for pts, T in window[a:a + c.coarse_scans]]
            T_claim_anchor = T_claim @ window[a][1]
            roll, pitch, _ = geometry.rot_to_rpy(T_claim_anchor[:3, :3])
            found += [T @ T_anchor_curr for T in self._candidates(
                weigher, scans, T_claim_anchor, float(roll), float(pitch))]
        return found[:MAX_CENTRES - 1]

    def _distinct(self, rivals: list[Rival]) -> list[Rival]:
        """The best of rivals at one place (anchors may find a place twice, refined alike)."""
        kept: list[Rival] = []
        for r in sorted(rivals, key=lambda r: -r.gap_nats):
            if all(self._away(r.T_map_lidar, k.T_map_lidar, 2.0) for k in kept):
                kept.append(r)
        return kept

    def _candidates(self, weigher, scans, T_claim: np.ndarray, roll: float, pitch: float
                    ) -> list[np.ndarray]:
        """The best test pose of each place, best first, away from the claim and from each
        other: at most `candidates`."""
        c, g, test = self.cfg.check, self._grid, self._test
        if not g.groups:
            return []
        n_yaw = round(360.0 / c.yaw_deg)
        bins = round(360.0 / c.place_yaw_deg)
        coarse = c.coarse_sigma_m if weigher.coarse_summary is not None else None
        total = len(g.positions) * n_yaw
        kcc.reset_best(g.best, g.arg, g.groups)
        for start in range(0, total, test.capacity):
            count = min(test.capacity, total - start)
            kcc.grid_poses(g.pos, n_yaw, start, count, roll, pitch, test.pos_back,
                           test.quat_back)
            self._score(weigher, scans, count, coarse)
            kcc.group_best(test.log_w, g.group, n_yaw, bins, start, count, g.best)
            kcc.group_arg(test.log_w, g.group, n_yaw, bins, start, count, g.best, g.arg)
        best, arg = g.best.to_numpy()[:g.groups], g.arg.to_numpy()[:g.groups]
        chosen: list[np.ndarray] = []
        for k in np.argsort(-best, kind="stable"):
            if arg[k] < 0 or len(chosen) >= c.candidates:
                break
            j = int(arg[k])
            R = geometry.rpy_to_rot(roll, pitch, 2.0 * math.pi * (j % n_yaw) / n_yaw)
            T = geometry.se3(R, g.positions[j // n_yaw])
            if self._away(T, T_claim, 2.0) and all(self._away(T, C, 2.0) for C in chosen):
                chosen.append(T)
        return chosen

    def _refine(self, weigher, scans, centres: list[np.ndarray], seed: int, counter: int
                ) -> tuple[list[np.ndarray], np.ndarray]:
        """Each centre's best pose and window score after the refinement rounds (every
        centre alike: the same number of poses, the same draws)."""
        test = self._test
        n = len(centres)
        per = min(self.cfg.check.refine_poses, test.capacity // n)
        tq = [geometry.tq_from_se3(T) for T in centres]
        pos = np.zeros((MAX_CENTRES, 3), np.float32)
        quat = np.tile(np.float32([0, 0, 0, 1]), (MAX_CENTRES, 1))
        pos[:n] = [t for t, _ in tq]
        quat[:n] = [q for _, q in tq]
        self._centre_pos.from_numpy(pos)
        self._centre_quat.from_numpy(quat)
        for r, (std_t, std_r) in enumerate(ROUNDS):
            kcc.around_centres(self._centre_pos, self._centre_quat, per, n * per,
                               ti.math.vec3(*std_t), ti.math.vec3(*std_r),
                               (seed + 7919 * (r + 1)) & 0xFFFFFFFF, counter, test.pos_back,
                               test.quat_back)
            self._score(weigher, scans, n * per, None)
            kcc.reset_best(self._centre_best, self._centre_arg, n)
            kcc.group_best(test.log_w, self._ident, per, 1, 0, n * per, self._centre_best)
            kcc.group_arg(test.log_w, self._ident, per, 1, 0, n * per, self._centre_best,
                          self._centre_arg)
            kcc.take(test.pos_back, test.quat_back, self._centre_arg, n, self._centre_pos,
                     self._centre_quat)
        pos = self._centre_pos.to_numpy()[:n].astype(np.float64)
        quat = self._centre_quat.to_numpy()[:n].astype(np.float64)
        poses = [geometry.se3_from_tq(t, q / np.linalg.norm(q)) for t, q in zip(pos, quat,
                                                                                strict=True)]
        return poses, self._centre_best.to_numpy()[:n].astype(np.float64)

    def _unheld(self, p: ParticleSet, rivals: list[Rival]) -> list[Rival]:
        """The rivals where the filter holds fewer than place_min_particles particles (where
        it holds them, its place evidence decides) and that were not re-seeded before."""
        if not rivals:
            return []
        e = self.cfg.estimate
        pos = np.zeros((MAX_CENTRES, 3), np.float32)
        quat = np.tile(np.float32([0, 0, 0, 1]), (MAX_CENTRES, 1))
        for k, r in enumerate(rivals):
            pos[k], quat[k] = geometry.tq_from_se3(r.T_map_lidar)
        self._centre_pos.from_numpy(pos)
        self._centre_quat.from_numpy(quat)
        kcc.count_near(p.pos, p.quat, p.n, self._centre_pos, self._centre_quat, len(rivals),
                       e.cluster_radius_m, math.cos(0.5 * min(e.cluster_angle_rad, math.pi)),
                       self._centre_count)
        counts = self._centre_count.to_numpy()[:len(rivals)]
        held = max(self.cfg.resample.place_min_particles, 1)
        return [r for r, k in zip(rivals, counts, strict=True) if k < held
                and all(self._away(r.T_map_lidar, T, 1.0) for T in self._tried)]
