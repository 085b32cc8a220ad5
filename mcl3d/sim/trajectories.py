"""Smooth sensor-rig trajectories through a world, with analytic velocity and acceleration.

The rig's `base_link` follows a C2 quintic Hermite curve in (x, y, z, roll, pitch, yaw)
(`spline.QuinticHermite`), so position, velocity, acceleration, body angular velocity and
angular acceleration are all analytic and the simulated IMU is consistent with the poses.

Two effects are kept apart from the smooth motion M(t):
- a kidnap: ground truth is `T_kidnap @ M(t)` after the kidnap time, while the IMU and the
  odometry keep following M(t) (they never see the teleport);
- an elevator ride: the cab carries the rig vertically; the IMU feels it (it is part of M),
  wheel odometry does not (the carrier's motion is removed from what odometry sees).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.ndimage import gaussian_filter1d

from mcl3d.core.errors import ConfigError
from mcl3d.core.geometry import se3, se3_inverse
from mcl3d.sim.spline import QuinticHermite, catmull_rom_rates, knot_accelerations
from mcl3d.sim.worlds import PAPER_OFFICE_TOURS, World

PAPER_OFFICE = tuple(f"paper-office-{k}" for k in range(1, PAPER_OFFICE_TOURS + 1))
TRAJECTORIES = ("ground", "loop", "handheld", "drone", "elevator", "kidnap", "survey",
                "paper-forest", "paper-elevator", *PAPER_OFFICE)
VALID = {
    "office": ("ground", "loop", "handheld", "kidnap", "survey", *PAPER_OFFICE),
    "building": ("ground", "loop", "handheld", "elevator", "kidnap", "paper-elevator"),
    "forest": ("ground", "loop", "handheld", "drone", "kidnap", "paper-forest"),
    "arena": ("ground", "loop", "handheld", "drone", "kidnap"),
    "warehouse": ("ground", "loop", "handheld", "kidnap"),
}
GRAVITY_MPS2 = 9.80665
REST_S = 1.5  # the rig stands still this long at the start and end of each path


def listed(kinds: tuple[str, ...]) -> str:
    """Trajectory names for a message, the paper's office tours as one range."""
    short = [k for k in kinds if k not in PAPER_OFFICE[1:]]
    return ", ".join(f"{k}..{len(PAPER_OFFICE)}" if k == PAPER_OFFICE[0] else k for k in short)


@dataclass
class Kinematics:
    """Smooth rig motion at N times: base_link pose, world-frame velocity and acceleration,
    body-frame angular velocity and angular acceleration."""

    R_map_base: np.ndarray  # (N, 3, 3)
    p_map_base: np.ndarray  # (N, 3) m
    v_map: np.ndarray  # (N, 3) m/s
    a_map: np.ndarray  # (N, 3) m/s^2
    w_base: np.ndarray  # (N, 3) rad/s
    dw_base: np.ndarray  # (N, 3) rad/s^2


def _euler_rotations(rpy: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), batched."""
    cr, sr = np.cos(rpy[:, 0]), np.sin(rpy[:, 0])
    cp, sp = np.cos(rpy[:, 1]), np.sin(rpy[:, 1])
    cy, sy = np.cos(rpy[:, 2]), np.sin(rpy[:, 2])
    R = np.empty((len(rpy), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
    return R


def _body_rates(rpy, d_rpy, dd_rpy) -> tuple[np.ndarray, np.ndarray]:
    """Body angular velocity and its derivative from ZYX Euler angles and their derivatives."""
    r, p = rpy[:, 0], rpy[:, 1]
    dr, dp, dy = d_rpy.T
    ddr, ddp, ddy = dd_rpy.T
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    w = np.stack([dr - dy * sp, dp * cr + dy * sr * cp, -dp * sr + dy * cr * cp], axis=1)
    dw = np.stack([
        ddr - ddy * sp - dy * dp * cp,
        ddp * cr - dp * dr * sr + ddy * sr * cp + dy * dr * cr * cp - dy * dp * sr * sp,
        -ddp * sr - dp * dr * cr + ddy * cr * cp - dy * dr * sr * cp - dy * dp * cr * sp,
    ], axis=1)
    return w, dw


class SimTrajectory:
    """The rig's motion over [0, duration_s]: smooth M(t), optional kidnap and elevator."""

    def __init__(self, kind: str, world: World, t_knots: np.ndarray, values: np.ndarray,
                 stops: np.ndarray, duration_s: float, kidnap_t_s: float | None = None,
                 carrier: QuinticHermite | None = None,
                 door_closed_s: tuple[float, float] | None = None,
                 cab_z0_m: float | None = None) -> None:
        self.kind = kind
        self.world = world
        self.duration_s = duration_s
        values = values.copy()
        values[:, 5] = np.unwrap(values[:, 5])
        rates = catmull_rom_rates(t_knots, values, stops)
        self.motion = QuinticHermite(t_knots, values, rates,
                                     knot_accelerations(t_knots, rates, stops))
        self.kidnap_t_s = kidnap_t_s
        self.carrier = carrier
        self.door_closed_s = door_closed_s
        elevator = world.elevator
        self.cab_z0_m = cab_z0_m if cab_z0_m is not None else (
            elevator.floor_z_m[0] if elevator is not None else 0.0)

    def kinematics(self, t_s: np.ndarray) -> Kinematics:
        """The smooth motion M(t) (what the IMU feels; no kidnap jump)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        x, dx, ddx = (self.motion(t, k) for k in range(3))
        w, dw = _body_rates(x[:, 3:], dx[:, 3:], ddx[:, 3:])
        return Kinematics(_euler_rotations(x[:, 3:]), x[:, :3], dx[:, :3], ddx[:, :3], w, dw)

    def _smooth_poses(self, t: np.ndarray) -> np.ndarray:
        x = self.motion(t)
        return se3(_euler_rotations(x[:, 3:]), x[:, :3])

    def T_map_base(self, t_s: np.ndarray) -> np.ndarray:
        """Ground-truth base_link poses (N, 4, 4), including the kidnap jump."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        T = self._smooth_poses(t)
        if self.kidnap_t_s is not None:
            jumped = t >= self.kidnap_t_s
            T[jumped] = self.world.T_kidnap @ T[jumped]
        return T

    def T_odom_base(self, t_s: np.ndarray) -> np.ndarray:
        """What perfect wheel odometry measures: M(t) without the carrier (cab) motion,
        relative to the start pose."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        T = self._smooth_poses(t)
        T0 = self._smooth_poses(np.array([0.0]))[0]
        if self.carrier is not None:
            T[:, 2, 3] -= self.carrier(t)[:, 0]
        return se3_inverse(T0) @ T

    def cab_z_m(self, t_s: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if self.carrier is None:
            return np.full(len(t), self.cab_z0_m)
        return self.cab_z0_m + self.carrier(t)[:, 0]

    def door_closed(self, t_s: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if self.door_closed_s is None:
            return np.zeros(len(t), dtype=bool)
        return (t >= self.door_closed_s[0]) & (t <= self.door_closed_s[1])

    def path_length_m(self, step_s: float = 0.05) -> float:
        t = np.arange(0.0, self.duration_s + step_s, step_s)
        p = self.T_map_base(t)[:, :3, 3]
        d = np.linalg.norm(np.diff(p, axis=0), axis=1)
        if self.kidnap_t_s is not None:  # the teleport is not travelled
            d[np.searchsorted(t, self.kidnap_t_s) - 1] = 0.0
        return float(d.sum())


# ---------------------------------------------------------------------------------- paths
@dataclass
class _Style:
    speed_mps: float
    yaw_rate_max: float
    accel_mps2: float
    knot_dt_s: float


STYLES = {
    "ground": _Style(0.8, 0.6, 0.5, 0.1),
    "handheld": _Style(1.1, 0.9, 0.8, 0.04),
    "drone": _Style(1.5, 0.8, 1.0, 0.1),
}


def _densify(points: np.ndarray, max_step_m: float) -> np.ndarray:
    """Split polyline segments longer than `max_step_m` (bounds how far corners get cut)."""
    out = [points[:1]]
    for a, b in itertools.pairwise(points):
        n = max(int(np.ceil(np.linalg.norm(b - a) / max_step_m)), 1)
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.vstack(out)


def _chaikin(points: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Corner cutting of an open polyline (endpoints kept): converges to a quadratic B-spline."""
    for _ in range(iterations):
        a, b = points[:-1], points[1:]
        mids = np.empty((2 * len(a), points.shape[1]))
        mids[0::2] = 0.75 * a + 0.25 * b
        mids[1::2] = 0.25 * a + 0.75 * b
        points = np.vstack([points[:1], mids, points[-1:]])
    return points


def _resample(points: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    points = points[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    s_new = np.arange(0.0, s[-1], step_m)
    if s_new[-1] < s[-1]:
        s_new = np.append(s_new, s[-1])
    columns = [np.interp(s_new, s, points[:, i]) for i in range(points.shape[1])]
    return np.column_stack(columns), s_new


def _timed_path(waypoints: np.ndarray, style: _Style, t0: float, min_end_s: float | None,
                closed: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Knot times, xy (xyz for waypoints with a height) and heading along the smoothed
    route, speed limited by turn rate and acceleration, starting and ending at rest. A
    closed route is repeated until the motion lasts past `min_end_s`."""
    loop_m = float(np.linalg.norm(np.diff(np.vstack([waypoints, waypoints[:1]]), axis=0),
                                  axis=1).sum())
    repeats = 1 if min_end_s is None else max(1, int((min_end_s - t0) * style.speed_mps / loop_m))
    while True:
        route = np.vstack([waypoints] * repeats + [waypoints[:1]]) if closed else waypoints
        curve, s = _resample(_chaikin(_densify(route, 1.0)), 0.05)
        d = np.gradient(curve, s, axis=0)
        heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        kernel = np.ones(9) / 9
        curvature = np.abs(np.convolve(np.gradient(heading, s), kernel, mode="same"))
        v = np.minimum(style.speed_mps, style.yaw_rate_max / np.maximum(curvature, 1e-6))
        v[0] = v[-1] = 0.0
        ds = np.diff(s)
        for i in range(1, len(v)):  # acceleration limit forwards, then braking backwards
            v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * style.accel_mps2 * ds[i - 1]))
        for i in range(len(v) - 2, -1, -1):
            v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * style.accel_mps2 * ds[i]))
        t = t0 + np.concatenate([[0.0], np.cumsum(2 * ds / np.maximum(v[1:] + v[:-1], 1e-6))])
        if min_end_s is None or t[-1] >= min_end_s or not closed:
            break
        repeats += 1
    # Knots at even times, with the rig at rest for REST_S before and after the path; a
    # low-pass over ~0.25 s then bounds the angular acceleration where turns begin and end.
    dt = style.knot_dt_s
    pad = int(np.ceil(REST_S / dt))
    n = max(int(np.ceil((t[-1] - t0) / dt)), 1)
    t_path = np.linspace(t0, t[-1], n + 1)
    xy = np.column_stack([np.interp(t_path, t, curve[:, i]) for i in range(curve.shape[1])])
    heading = np.interp(t_path, t, heading)
    xy = np.vstack([np.repeat(xy[:1], pad, axis=0), xy, np.repeat(xy[-1:], pad, axis=0)])
    heading = np.concatenate([np.full(pad, heading[0]), heading, np.full(pad, heading[-1])])
    t_k = t0 + np.concatenate([np.arange(pad) * dt, pad * dt + (t_path - t0),
                               pad * dt + (t_path[-1] - t0) + (np.arange(pad) + 1) * dt])
    sigma = 0.25 / dt
    ends = xy[[0, -1]], heading[[0, -1]]
    xy = gaussian_filter1d(xy, sigma, axis=0, mode="nearest")
    heading = gaussian_filter1d(heading, sigma, mode="nearest")
    xy[[0, -1]], heading[[0, -1]] = ends
    return t_k, xy, heading


def _ground_height(world: World, xy: np.ndarray, z_ref: float) -> np.ndarray:
    """Height of the walkable surface below each xy point, ray cast down from z_ref + 2 m (a
    storey's floor, not the one above), or in a one-level world from above its highest
    ground (a hillside climbs more than 2 m)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(world.ground.vertices.astype(np.float32)),
                        o3d.core.Tensor(world.ground.triangles.astype(np.uint32)))
    start = z_ref + 2.0
    if len(world.floor_z_m) == 1 and len(world.ground.vertices):
        start = max(start, float(world.ground.vertices[:, 2].max()) + 1.0)
    rays = np.zeros((len(xy), 6), dtype=np.float32)
    rays[:, :2], rays[:, 2], rays[:, 5] = xy, start, -1.0
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(t_hit), start - t_hit, z_ref)


def _pose_values(world: World, kind: str, t: np.ndarray, xy: np.ndarray, heading: np.ndarray,
                 z_ref: float, flat: bool, rng: np.random.Generator) -> np.ndarray:
    """(K, 6) knot values x y z roll pitch yaw of base_link for a rig `kind`."""
    n = len(t)
    values = np.zeros((n, 6))
    values[:, :2], values[:, 5] = xy, heading
    ground = (lambda p: np.full(len(p), z_ref)) if flat else (
        lambda p: _ground_height(world, p, z_ref))
    fwd = np.column_stack([np.cos(heading), np.sin(heading)])
    left = np.column_stack([-fwd[:, 1], fwd[:, 0]])
    if kind == "ground":  # wheels on the ground: 0.6 m wheelbase, 0.5 m track
        zf, zb = ground(xy + 0.3 * fwd), ground(xy - 0.3 * fwd)
        zl, zr = ground(xy + 0.25 * left), ground(xy - 0.25 * left)
        values[:, 2] = 0.5 * (zf + zb)
        values[:, 4] = -np.arctan2(zf - zb, 0.6)
        values[:, 3] = np.arctan2(zl - zr, 0.5)
        return values
    phase = rng.uniform(0, 2 * np.pi, 4)
    # oscillations fade in and out over 2 s so the rig starts and ends at rest
    env = np.clip(np.minimum(t - t[0], t[-1] - t) / 2.0, 0.0, 1.0)
    env = env * env * (3 - 2 * env)
    if kind == "handheld":  # walking: bob at step frequency, sway at stride frequency
        values[:, 2] = ground(xy) + 1.25 + env * 0.025 * np.sin(2 * np.pi * 1.8 * t + phase[0])
        values[:, 3] = env * 0.04 * np.sin(2 * np.pi * 0.9 * t + phase[1])
        values[:, 4] = -0.03 + env * 0.04 * np.sin(2 * np.pi * 0.9 * t + phase[2])
        values[:, 5] = heading + env * 0.2 * np.sin(2 * np.pi * 0.15 * t + phase[3])
        return values
    # drone: altitude changes, tilt follows horizontal acceleration, slow yaw oscillation
    ceiling = 2.0 if world.name == "forest" else 3.0
    values[:, 2] = ground(xy) + ceiling + env * 0.5 * np.sin(2 * np.pi * t / 13.0 + phase[0])
    acc = np.gradient(np.gradient(xy, t, axis=0), t, axis=0)
    acc = gaussian_filter1d(acc, 0.3 / (t[1] - t[0]), axis=0, mode="nearest")
    yaw = heading + env * 0.4 * np.sin(2 * np.pi * t / 9.0 + phase[1])
    a_fwd = acc[:, 0] * np.cos(yaw) + acc[:, 1] * np.sin(yaw)
    a_left = -acc[:, 0] * np.sin(yaw) + acc[:, 1] * np.cos(yaw)
    values[:, 3] = -np.arctan2(a_left, GRAVITY_MPS2)
    values[:, 4] = np.arctan2(a_fwd, GRAVITY_MPS2)
    values[:, 5] = yaw
    return values


def _elevator(world: World, duration_s: float, rng: np.random.Generator) -> SimTrajectory:
    """Drive into the cab on the top floor, turn around, ride one floor down, drive out."""
    elev = world.elevator
    style = STYLES["ground"]
    z_top, z_low = elev.floor_z_m[-1], elev.floor_z_m[-2]
    cab, door = elev.center_xy, elev.door_approach_xy
    approach = np.array([[door[0] - 8.0, door[1]], [door[0] - 1.2, door[1]],
                         [cab[0], door[1] + 0.5], cab])
    t1, xy1, h1 = _timed_path(approach, style, 0.0, None, closed=False)
    t_in = t1[-1]
    turn_end = t_in + 5.0
    ride_start = turn_end + 1.5
    ride_s = max(4.0, 1.6 * abs(z_top - z_low))
    ride_end = ride_start + ride_s
    exit_start = ride_end + 1.5
    exit_path = np.array([cab, [cab[0], door[1] + 0.5], [door[0] - 1.2, door[1]],
                          *world.routes["loop"][::-1]])
    t3, xy3, h3 = _timed_path(exit_path, style, exit_start, duration_s + 1.0, closed=False)
    if ride_end + 2.0 > duration_s:
        raise ConfigError(f"trajectory 'elevator' needs a duration >= {ride_end + 2.0:.0f} s "
                          f"to finish the ride (got {duration_s:g} s)", setting="duration")
    yaw_in = h1[-1]
    yaw_out = yaw_in + np.pi
    h3 = h3 + np.round((yaw_out - h3[0]) / (2 * np.pi)) * 2 * np.pi
    hold = [(turn_end, yaw_out, z_top), (ride_start, yaw_out, z_top), (ride_end, yaw_out, z_low)]
    t = np.concatenate([t1, [h[0] for h in hold], t3])
    values = np.zeros((len(t), 6))
    values[: len(t1), :2], values[: len(t1), 2], values[: len(t1), 5] = xy1, z_top, h1
    for i, (_, yaw, z) in enumerate(hold):
        values[len(t1) + i, :2], values[len(t1) + i, 2], values[len(t1) + i, 5] = cab, z, yaw
    values[len(t1) + 3:, :2], values[len(t1) + 3:, 2], values[len(t1) + 3:, 5] = xy3, z_low, h3
    stops = np.zeros(len(t), dtype=bool)
    stops[len(t1) - 1: len(t1) + 4] = True
    carrier = QuinticHermite(np.array([0.0, ride_start, ride_end, max(duration_s, ride_end) + 1]),
                             np.array([[0.0], [0.0], [z_low - z_top], [z_low - z_top]]),
                             np.zeros((4, 1)))
    return SimTrajectory("elevator", world, t, values, stops, duration_s, carrier=carrier,
                         door_closed_s=(ride_start - 1.0, ride_end + 1.0), cab_z0_m=z_top)


# The SLAM paper's forest recording: a MID-360 carried at a walk over uneven ground, with the
# irregular turns of a hand-held sensor on top of the gait's regular sway. A walker turns
# round at a row's end in a couple of seconds (up to 1.5 rad/s), not in a wheeled robot's
# wide arc, and each step jolts the hand: pitch nods at the step rate with a harmonic from
# the heel strike, fast enough that one 100 ms sweep holds a curved, not a constant, motion.
PAPER_FOREST_STYLE = _Style(1.0, 1.5, 0.8, 0.04)
PAPER_FOREST_JITTER_DEG = (1.0, 1.0, 2.0)  # roll, pitch, yaw sigma of the irregular part
PAPER_FOREST_JITTER_S = 0.3  # its correlation time
PAPER_FOREST_STEP_HZ = 1.8  # steps per second (the 'handheld' gait's bob)
PAPER_FOREST_STEP_NOD_DEG = (1.5, 0.6)  # pitch amplitude at the step rate and twice it
# World settings (SimConfig.world keys) a named scenario uses wherever the config leaves the
# default: paper-forest walks a plantation on a hillside (rows running down the slope) inside
# a wild wood (something to see when facing out of the rows, as in a real wood), with shrubs,
# a bumpy floor and crowns a laser pulse goes into before a leaf returns it, as real foliage
# does (no solid shells for the registration to lock onto).
SCENARIO_WORLD = {"paper-forest": {"forest_border_m": 20.0, "forest_undergrowth": 0.4,
                                   "forest_roughness_m": 0.04, "forest_slope_percent": 6.0,
                                   "forest_foliage_depth_m": 0.5}}
SCENARIO_SENSOR = {"paper-forest": "mid360"}  # the LiDAR a scenario uses unless told


def _paper_forest_path(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    route = world.routes.get("paper-forest")
    if route is None:
        raise ConfigError("trajectory 'paper-forest' needs a forest of at least 8 rows "
                          "(world.forest_rows)")
    return _timed_path(route, PAPER_FOREST_STYLE, 0.0, None, closed=False)


def _paper_forest(world: World, duration_s: float, rng: np.random.Generator) -> SimTrajectory:
    """The forest walk of `worlds._paper_forest_route`, hand-held: the gait of the
    'handheld' rig plus smooth random roll, pitch and yaw. A duration past the walk's end
    leaves the walker standing at the end; a shorter one cuts the walk."""
    t, xy, heading = _paper_forest_path(world)
    values = _pose_values(world, "handheld", t, xy, heading, 0.0, False, rng)
    env = np.clip(np.minimum(t - t[0], t[-1] - t) / 2.0, 0.0, 1.0)
    sigma_knots = PAPER_FOREST_JITTER_S / PAPER_FOREST_STYLE.knot_dt_s
    for axis, sigma_deg in enumerate(PAPER_FOREST_JITTER_DEG):
        noise = gaussian_filter1d(rng.standard_normal(len(t)), sigma_knots, mode="nearest")
        noise *= np.radians(sigma_deg) / max(float(np.std(noise)), 1e-12)
        values[:, 3 + axis] += env * noise
    step = 2 * np.pi * PAPER_FOREST_STEP_HZ * t + rng.uniform(0, 2 * np.pi)
    nod, strike = np.radians(PAPER_FOREST_STEP_NOD_DEG)
    values[:, 4] += env * (nod * np.sin(step) + strike * np.sin(2 * step))
    stops = np.zeros(len(t), dtype=bool)
    stops[[0, -1]] = True
    return SimTrajectory("paper-forest", world, t, values, stops, duration_s)


# The SLAM paper's elevator recording (its Fig. 6), hand-held through `worlds.building`: up
# the stairwell from the ground floor, along every floor below the top to the elevator's
# landing and back, to the top floor and into the cab, one floor down, and back down the
# stairs to the ground floor's furnished room where the walk began. The stairwell has no
# landing slabs, so the walk crosses the well at floor height; it never passes through a solid.
PAPER_ELEVATOR_STYLE = STYLES["handheld"]
PAPER_ELEVATOR_CARRY_M = -0.3  # held at the chest: headroom under the flight above
STAIR_DOOR_XY = (4.0, 7.25)  # in the corridor, in front of the stairwell's door
GROUND_ROOM_XY = ((11.6, 7.25), (11.6, 4.4), (13.0, 2.8), (14.4, 3.4), (13.2, 4.8),
                  (11.7, 5.3), (11.6, 7.25))  # room 2, as the building's 'loop' route


def _stairs(z_from: float, z_to: float, rise: float) -> list[tuple[float, float, float]]:
    """(x, y, feet height) from the stairwell door on the floor at `z_from` to the one on
    the adjacent floor at `z_to`: along the south flight eastwards, round the turn, along
    the north flight westwards (each climbs half a storey over x 3.2 -> 0.2 m)."""
    z, half = min(z_from, z_to), rise / 2
    x, y = STAIR_DOOR_XY
    up = [(x, y, z), (x, 9.7, z), (4.0, 11.2, z), (1.2, 11.2, z), (0.5, 10.3, z),
          (0.5, 9.2, z + 0.1 * half), (3.2, 9.2, z + half), (4.0, 9.7, z + half),
          (4.0, 12.7, z + half), (3.2, 13.2, z + half), (0.5, 13.2, z + 1.9 * half),
          (0.7, 12.0, z + rise), (4.0, 11.2, z + rise), (x, 9.7, z + rise), (x, y, z + rise)]
    return up if z_to > z_from else up[::-1]


def _to_the_landing_and_back(door_xy: np.ndarray, z: float) -> list[tuple[float, float, float]]:
    """Along the corridor from the stairwell to the elevator's landing doors, round, and back."""
    x, y = STAIR_DOOR_XY
    return [(x + 2.0, 6.75, z), (door_xy[0] - 0.5, 6.75, z), (door_xy[0] + 0.8, y, z),
            (door_xy[0] - 0.5, 7.8, z), (x + 2.0, 7.8, z), (x, y, z)]


def _paper_elevator_paths(world: World):
    """The two walks (knot times, xyz of the feet, heading) around the ride and its times:
    up to the top floor into the cab, and from the cab one floor lower back down."""
    elev = world.elevator
    floors = elev.floor_z_m
    if len(floors) < 3:
        raise ConfigError("trajectory 'paper-elevator' needs a building of at least 3 floors "
                          "(world.building_floors)")
    rise = floors[1] - floors[0]
    cab, door = elev.center_xy, elev.door_approach_xy
    room = [(x, y, floors[0]) for x, y in GROUND_ROOM_XY]
    walk_up = [(16.0, 7.25, floors[0]), *room]
    for k in range(1, len(floors)):
        walk_up += _stairs(floors[k - 1], floors[k], rise)
        if k < len(floors) - 1:
            walk_up += _to_the_landing_and_back(door, floors[k])
    walk_up += [(door[0] - 1.2, door[1], floors[-1]), (cab[0], door[1] + 0.5, floors[-1]),
                (cab[0], cab[1], floors[-1])]
    t1, p1, h1 = _timed_path(np.array(walk_up), PAPER_ELEVATOR_STYLE, 0.0, None, closed=False)
    ride_start = t1[-1] + 5.0 + 1.5  # turn round in the cab, doors close
    ride_end = ride_start + max(4.0, 1.6 * rise)
    walk_down = [(cab[0], cab[1], floors[-2]), (cab[0], door[1] + 0.5, floors[-2]),
                 (door[0] - 1.2, door[1], floors[-2])]
    for k in range(len(floors) - 2, 0, -1):
        walk_down += _stairs(floors[k], floors[k - 1], rise)
    walk_down += [*room[::-1], (16.0, 7.25, floors[0])]
    t3, p3, h3 = _timed_path(np.array(walk_down), PAPER_ELEVATOR_STYLE, ride_end + 1.5, None,
                             closed=False)
    return (t1, p1, h1), (t3, p3, h3), (ride_start, ride_end)


def _paper_elevator(world: World, duration_s: float, rng: np.random.Generator) -> SimTrajectory:
    """The walk of `_paper_elevator_paths`, hand-held (the 'handheld' rig's gait); in the cab
    the walker turns round and stands still while it rides one floor down. A duration past
    the walk's end leaves the walker standing at the end; a shorter one cuts the walk."""
    elev = world.elevator
    (t1, p1, h1), (t3, p3, h3), (ride_start, ride_end) = _paper_elevator_paths(world)
    z_top, z_low = elev.floor_z_m[-1], elev.floor_z_m[-2]
    v1 = _pose_values(world, "handheld", t1, p1[:, :2], h1, 0.0, True, rng)
    v3 = _pose_values(world, "handheld", t3, p3[:, :2], h3, 0.0, True, rng)
    v1[:, 2] += p1[:, 2] + PAPER_ELEVATOR_CARRY_M
    v3[:, 2] += p3[:, 2] + PAPER_ELEVATOR_CARRY_M
    yaw_out = h1[-1] + np.pi
    v3[:, 5] += np.round((yaw_out - v3[0, 5]) / (2 * np.pi)) * 2 * np.pi
    hold = np.repeat(v1[-1:], 3, axis=0)  # turned round, then the ride
    hold[:, 5] = yaw_out
    hold[2, 2] += z_low - z_top
    t = np.concatenate([t1, [t1[-1] + 5.0, ride_start, ride_end], t3])
    values = np.vstack([v1, hold, v3])
    stops = np.zeros(len(t), dtype=bool)
    stops[[0, len(t1) - 1, len(t1), len(t1) + 1, len(t1) + 2, len(t1) + 3, -1]] = True
    end = max(duration_s, t3[-1]) + 1.0
    carrier = QuinticHermite(np.array([0.0, ride_start, ride_end, end]),
                             np.array([[0.0], [0.0], [z_low - z_top], [z_low - z_top]]),
                             np.zeros((4, 1)))
    return SimTrajectory("paper-elevator", world, t, values, stops, duration_s, carrier=carrier,
                         door_closed_s=(ride_start - 1.0, ride_end + 1.0), cab_z0_m=z_top)


def default_duration_s(world: World, kind: str) -> float:
    """Seconds to simulate when none are asked for: a named route's own length (to the
    scan after its end), else 10 s."""
    if kind == "paper-forest":
        return float(np.ceil(_paper_forest_path(world)[0][-1]))
    if kind == "paper-elevator":
        return float(np.ceil(_paper_elevator_paths(world)[1][0][-1]))
    if kind in PAPER_OFFICE:
        return float(np.ceil(_timed_path(world.routes[kind], STYLES["ground"], 0.0, None,
                                         closed=True)[0][-1]))
    return 10.0


def build_trajectory(world: World, kind: str, duration_s: float, seed: int = 0) -> SimTrajectory:
    """The trajectory `kind` through `world`, lasting `duration_s` seconds."""
    if not duration_s > 0:
        raise ConfigError(f"the duration must be > 0 seconds, got {duration_s:g}",
                          setting="duration")
    valid = VALID[world.name]
    if kind not in valid:
        raise ConfigError(f"trajectory {kind!r} does not fit world {world.name!r}; "
                          f"choose one of {listed(valid)}")
    rng = np.random.default_rng([seed, 7])
    if kind == "elevator":
        return _elevator(world, duration_s, rng)
    if kind == "paper-forest":
        return _paper_forest(world, duration_s, rng)
    if kind == "paper-elevator":
        return _paper_elevator(world, duration_s, rng)
    rig = "ground" if kind in ("loop", "kidnap", "survey", *PAPER_OFFICE) else kind
    route = world.routes[world.kidnap_route if kind == "kidnap" else kind]
    level = len(world.floor_z_m) - 1 if kind == "kidnap" else 0
    z_ref = world.floor_z_m[level]
    once = kind in PAPER_OFFICE  # a tour: once round, then at rest (other routes repeat)
    t, xy, heading = _timed_path(route, STYLES[rig], 0.0, None if once else duration_s + 1.0,
                                 closed=True)
    values = _pose_values(world, rig, t, xy, heading, z_ref, world.name == "building", rng)
    stops = np.zeros(len(t), dtype=bool)
    stops[[0, -1]] = True
    kidnap_t = 0.5 * duration_s if kind == "kidnap" else None
    return SimTrajectory(kind, world, t, values, stops, duration_s, kidnap_t_s=kidnap_t)
