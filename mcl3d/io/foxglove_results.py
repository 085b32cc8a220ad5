"""A run's results for Foxglove: written to a result MCAP and/or served live over the Foxglove
SDK's WebSocket server, every channel with a `foxglove.*` schema (docs/foxglove.md).

`ResultPublisher` owns one private SDK context, so its channels reach only its own sinks: the
MCAP file (written to a temporary name and renamed when the run ends cleanly, never
half-written) and the live server. Channels are created when first published, so a command
advertises only what it has. A live client that subscribes to the map after it was published
gets it again on the next update (the server does not latch messages); the MCAP then holds
that map message twice.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from pathlib import Path

import foxglove
import numpy as np
from foxglove.channels import (
    FrameTransformsChannel,
    JointStatesChannel,
    LogChannel,
    PointCloudChannel,
    PoseInFrameChannel,
    PosesInFrameChannel,
    SceneUpdateChannel,
)
from foxglove.messages import Log, LogLevel

from mcl3d import __version__
from mcl3d.core.errors import Mcl3dError, RunInterrupted
from mcl3d.core.geometry import se3_inverse
from mcl3d.core.outputs import atomic_path, check_writable
from mcl3d.io import foxglove_messages as fm

MAP_FRAME = "map"
LIDAR_FRAME = "lidar"
MAX_PARTICLES = 5000  # particles per message at most (evenly picked, weights kept)
MAX_SCAN_POINTS = 100_000  # scan points per message at most (evenly picked)
LIVE_HOST = "127.0.0.1"

# topic -> the SDK channel that carries its foxglove schema
CHANNELS = {
    "/map": PointCloudChannel,
    "/scan": PointCloudChannel,
    "/tf": FrameTransformsChannel,
    "/estimate": PoseInFrameChannel,
    "/estimate/covariance": SceneUpdateChannel,
    "/particles": PointCloudChannel,
    "/hypotheses": SceneUpdateChannel,
    "/ground_truth": PoseInFrameChannel,
    "/stats": JointStatesChannel,
    "/log": LogChannel,
    "/keyframes": PosesInFrameChannel,
    "/loops": SceneUpdateChannel,
    "/trajectories": SceneUpdateChannel,
}
LEVELS = {"info": LogLevel.Info, "warning": LogLevel.Warning, "error": LogLevel.Error}
ESTIMATE_RGBA = (0.1, 0.8, 0.2, 0.35)
HYPOTHESIS_RGBA = (1.0, 0.6, 0.1, 0.35)
LOOP_RGBA = (0.9, 0.1, 0.9, 1.0)
TRAJECTORY_RGBA = ((0.2, 0.5, 1.0, 1.0), (1.0, 0.6, 0.1, 1.0), (0.9, 0.2, 0.2, 1.0),
                   (0.6, 0.3, 0.9, 1.0), (0.2, 0.8, 0.8, 1.0))


def evenly(count: int, keep: int) -> np.ndarray:
    """Indices of at most `keep` of `count` items, evenly spread (deterministic)."""
    if count <= keep:
        return np.arange(count)
    return np.linspace(0, count - 1, keep).astype(np.int64)


class _MapRequests:
    """WebSocket listener noting that a client subscribed to the map (it missed it)."""

    def __init__(self) -> None:
        self.pending = threading.Event()

    def on_subscribe(self, client, channel) -> None:
        if channel.topic == "/map":
            self.pending.set()


class ResultPublisher:
    """Context manager; `publish_*` per scan (numpy in, map frame), `publish_map` once."""

    def __init__(self, mcap_path: Path | None = None, live_port: int | None = None, *,
                 force: bool = False, name: str = "mcl3d") -> None:
        if mcap_path is not None:
            check_writable(Path(mcap_path), force)
        self.mcap_path = None if mcap_path is None else Path(mcap_path)
        self.live_port, self.name = live_port, name
        self.context = foxglove.Context()
        self.server = None
        self._stack: contextlib.ExitStack | None = None
        self._channels: dict[str, object] = {}
        self._map_message = None
        self._requests = _MapRequests()

    def __enter__(self) -> ResultPublisher:
        self._stack = contextlib.ExitStack()
        try:
            if self.mcap_path is not None:
                tmp = self._stack.enter_context(atomic_path(self.mcap_path))
                writer = foxglove.open_mcap(tmp, allow_overwrite=True, context=self.context)
                self._stack.callback(writer.close)
                writer.write_metadata("mcl3d", {"version": __version__, "command": self.name})
            if self.live_port is not None:
                self.server = self._serve(self.live_port)
                self._stack.callback(self.server.stop)
        except BaseException:
            self._stack.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        """Closes the writer, then keeps the file (a clean or interrupted run: what it
        finished) or removes it (a failed run)."""
        assert self._stack is not None
        for channel in self._channels.values():
            channel.close()
        if exc_type is not None and issubclass(exc_type, RunInterrupted | KeyboardInterrupt):
            exc_type = exc = tb = None
        self._stack.__exit__(exc_type, exc, tb)
        self._stack = None

    def _serve(self, port: int):
        try:
            return foxglove.start_server(name=f"mcl3d {self.name}", host=LIVE_HOST, port=port,
                                         context=self.context, server_listener=self._requests)
        except RuntimeError as e:
            raise Mcl3dError(f"cannot serve the live view on {LIVE_HOST}:{port} ({e}); choose "
                             f"a free port", setting="live_port") from None

    def _log(self, topic: str, build: Callable[[], object], stamp_ns: int) -> None:
        """Advertise the topic's channel (once) and log `build()` on it, built only when a
        sink takes it: the file, or a live client subscribed to the topic."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = CHANNELS[topic](topic, context=self.context)
        if channel.has_sinks():
            channel.log(build(), log_time=int(stamp_ns))

    def _resend_map(self, stamp_ns: int) -> None:
        if self._map_message is not None and self._requests.pending.is_set():
            self._requests.pending.clear()
            self._log("/map", lambda: self._map_message, stamp_ns)

    # ---- what a run publishes ----

    def publish_map(self, stamp_ns: int, points: np.ndarray) -> None:
        """The map's points (map frame), once: TSDF surface, SLAM or odometry keyframe map."""
        self._map_message = fm.point_cloud(stamp_ns, MAP_FRAME, points)
        self._log("/map", lambda: self._map_message, stamp_ns)

    def publish_estimate(self, stamp_ns: int, T_map_lidar: np.ndarray,
                         covariance: np.ndarray | None = None,
                         scan_lidar: np.ndarray | None = None) -> None:
        """The pose (transform map→lidar and pose), its covariance ellipsoid when given (6x6,
        rotation first, tangent at the pose) and the scan in the map frame: its lidar-frame
        points under the cloud's pose T_map_lidar, exact and with no transform to pay."""
        self._resend_map(stamp_ns)
        self._log("/tf", lambda: fm.transform(stamp_ns, MAP_FRAME, LIDAR_FRAME, T_map_lidar),
                  stamp_ns)
        self._log("/estimate", lambda: fm.pose_in_frame(stamp_ns, MAP_FRAME, T_map_lidar),
                  stamp_ns)
        if covariance is not None:
            self.publish_covariance(stamp_ns, T_map_lidar, covariance)
        if scan_lidar is not None:
            self._log("/scan", lambda: self._scan(stamp_ns, T_map_lidar, scan_lidar), stamp_ns)

    @staticmethod
    def _scan(stamp_ns: int, T_map_lidar: np.ndarray, scan_lidar: np.ndarray):
        pts = np.asarray(scan_lidar).reshape(-1, 3)
        return fm.point_cloud(stamp_ns, MAP_FRAME, pts[evenly(len(pts), MAX_SCAN_POINTS)],
                              T_frame_cloud=T_map_lidar)

    def publish_covariance(self, stamp_ns: int, T_mean: np.ndarray, covariance: np.ndarray
                           ) -> None:
        """The positional ellipsoid of a 6x6 covariance (rotation first) in the tangent at
        `T_mean`."""
        self._log("/estimate/covariance", lambda: fm.scene(stamp_ns, MAP_FRAME, {"estimate": {
            "spheres": [fm.ellipsoid(T_mean, covariance[3:, 3:], ESTIMATE_RGBA)]}}), stamp_ns)

    def publish_particles(self, stamp_ns: int, positions: np.ndarray, weights: np.ndarray,
                          limit: int = MAX_PARTICLES) -> None:
        """At most `limit` (<= `MAX_PARTICLES`) particles, evenly picked, with a `weight`
        field relative to the heaviest (0..1), for colouring by weight."""

        def cloud():
            pick = evenly(len(positions), min(limit, MAX_PARTICLES))
            w = np.asarray(weights, np.float64)[pick]
            top = float(w.max()) if len(w) else 0.0
            return fm.point_cloud(stamp_ns, MAP_FRAME, positions[pick],
                                  {"weight": w / top if top > 0 else w})

        self._log("/particles", cloud, stamp_ns)

    def publish_hypotheses(self, stamp_ns: int, hypotheses: list[tuple[np.ndarray, np.ndarray,
                                                                       float]]) -> None:
        """Other hypotheses (T_map_lidar, 6x6 covariance, weight share): each an ellipsoid, an
        arrow and its share of the weight; an empty list clears them."""

        def scene():
            return fm.scene(stamp_ns, MAP_FRAME, {f"hypothesis {i + 1}": {
                "spheres": [fm.ellipsoid(T, cov[3:, 3:], HYPOTHESIS_RGBA)],
                "arrows": [fm.arrow(T, 1.0, (*HYPOTHESIS_RGBA[:3], 1.0))],
                "texts": [fm.text(T, f"{100 * weight:.0f}%", (1.0, 1.0, 1.0, 1.0))]}
                for i, (T, cov, weight) in enumerate(hypotheses)})

        self._log("/hypotheses", scene, stamp_ns)

    def publish_ground_truth(self, stamp_ns: int, T_map_lidar: np.ndarray) -> None:
        self._log("/ground_truth", lambda: fm.pose_in_frame(stamp_ns, MAP_FRAME, T_map_lidar),
                  stamp_ns)

    def publish_stats(self, stamp_ns: int, values: dict[str, float | None]) -> None:
        """Numbers to plot over time (ESS, error, hypotheses, ms); None values are left out."""
        self._log("/stats", lambda: fm.named_values(stamp_ns, values), stamp_ns)

    def log(self, stamp_ns: int, level: str, text: str) -> None:
        """A warning or a change of state (`level`: info, warning or error)."""
        self._log("/log", lambda: Log(timestamp=fm.stamp(stamp_ns), level=LEVELS[level],
                                      message=text, name=f"mcl3d {self.name}"), stamp_ns)

    def publish_keyframes(self, stamp_ns: int, poses: np.ndarray) -> None:
        self._log("/keyframes", lambda: fm.poses_in_frame(stamp_ns, MAP_FRAME, poses), stamp_ns)

    def publish_loops(self, stamp_ns: int, segments: np.ndarray, name: str | None = None
                      ) -> None:
        """Accepted loop corrections (K, 2, 3): a line from the pose to the loop keyframe.
        They replace the lines drawn before, or with `name` are added to them as that entity
        (a long run then publishes each loop once)."""
        pairs = np.asarray(segments, np.float64).reshape(-1, 3)
        lines = {name or "loops": {"lines": [fm.lines(pairs, LOOP_RGBA, "list", 0.08)]}}
        self._log("/loops", lambda: fm.scene(stamp_ns, MAP_FRAME, lines if len(pairs) else {},
                                             replace=name is None), stamp_ns)

    def publish_trajectories(self, stamp_ns: int, paths: list[np.ndarray]) -> None:
        """One line strip per hypothesis (positions (N, 3), heaviest first)."""
        self._log("/trajectories", lambda: fm.scene(stamp_ns, MAP_FRAME, {
            f"hypothesis {i + 1}": {"lines": [fm.lines(p, TRAJECTORY_RGBA[i % len(
                TRAJECTORY_RGBA)])]} for i, p in enumerate(paths) if len(p) >= 2}), stamp_ns)


def open_results(mcap_path: Path | None, live_port: int | None, force: bool, name: str
                 ) -> contextlib.AbstractContextManager[ResultPublisher | None]:
    """A `ResultPublisher` when a result MCAP or the live view is asked for, else nothing
    (no SDK object is made)."""
    if mcap_path is None and live_port is None:
        return contextlib.nullcontext(None)
    return ResultPublisher(mcap_path, live_port, force=force, name=name)


class StartAligned:
    """Ground truth in a run's own frame (odometry and SLAM start at their first scan): the
    first scan with ground truth ties the two frames together."""

    def __init__(self) -> None:
        self.T_run_gt: np.ndarray | None = None

    def __call__(self, T_run_lidar: np.ndarray, T_gt_lidar: np.ndarray) -> np.ndarray:
        if self.T_run_gt is None:
            self.T_run_gt = T_run_lidar @ se3_inverse(T_gt_lidar)
        return self.T_run_gt @ T_gt_lidar


def nearest_pose(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int,
                 tolerance_ns: int = 100_000_000) -> np.ndarray | None:
    """The pose stamped nearest `stamp_ns` (sorted stamps), None when none is within
    `tolerance_ns`."""
    if len(stamps_ns) == 0:
        return None
    i = int(np.clip(np.searchsorted(stamps_ns, stamp_ns), 1, max(len(stamps_ns) - 1, 1)))
    best = min({i - 1, min(i, len(stamps_ns) - 1)}, key=lambda j: abs(stamps_ns[j] - stamp_ns))
    return poses[best] if abs(int(stamps_ns[best]) - stamp_ns) <= tolerance_ns else None
