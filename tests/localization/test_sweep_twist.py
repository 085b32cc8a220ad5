"""Deskewing in localize: the twist of a sweep comes from the motion source over the sweep
itself when it covers it (a turn that speeds up), else from the motion since the last scan."""

from types import SimpleNamespace

import numpy as np

from mcl3d.core import geometry
from mcl3d.localization.motion_source import Motion
from mcl3d.localization.pipeline import _ScanLoop, _sweep_ns

START_NS = 1_000_000_000_000


class AcceleratingTurn:
    """Odometry of a turn whose yaw rate grows with time: rate = 10 * t rad/s (t from START)."""

    kind = "odom"

    def __init__(self, covered_until_ns: int):
        self.covered_until_ns = covered_until_ns

    def covers(self, stamp_ns: int) -> bool:
        return stamp_ns <= self.covered_until_ns

    def motion(self, t0_ns: int, t1_ns: int) -> Motion:
        t0, t1 = (t0_ns - START_NS) * 1e-9, (t1_ns - START_NS) * 1e-9
        yaw = 5.0 * (t1 * t1 - t0 * t0)
        return Motion(geometry.se3(geometry.rpy_to_rot(0.0, 0.0, yaw), [0, 0, 0]), "odom",
                      (0.0, 0.0))


def _scan(stamp_ns):
    return SimpleNamespace(stamp_ns=stamp_ns, times_s=np.linspace(0.0, 0.125, 50,
                                                                  dtype=np.float32))


def test_the_sweep_spans_its_points_times():
    scan = _scan(START_NS + 300_000_000)
    assert _sweep_ns(scan) == (scan.stamp_ns, scan.stamp_ns + 125_000_000)
    scan.times_s = None
    assert _sweep_ns(scan) == (scan.stamp_ns, scan.stamp_ns)


def test_a_covered_sweep_is_deskewed_with_its_own_motion():
    prev, stamp = START_NS + 200_000_000, START_NS + 300_000_000
    source = AcceleratingTurn(covered_until_ns=START_NS + 10**9)
    since_last = source.motion(prev, stamp).T_prev_curr  # 0.25 rad over 0.1 s
    loop = SimpleNamespace(source=source)
    twist = _ScanLoop._sweep_twist(loop, _scan(stamp), prev, since_last)
    assert np.isclose(twist[2], 3.625, rtol=1e-4)  # (0.425^2 - 0.3^2) * 5 / 0.125 s


def test_a_sweep_past_the_motion_data_uses_the_motion_since_the_last_scan():
    prev, stamp = START_NS + 200_000_000, START_NS + 300_000_000
    source = AcceleratingTurn(covered_until_ns=stamp)
    since_last = source.motion(prev, stamp).T_prev_curr
    loop = SimpleNamespace(source=source)
    twist = _ScanLoop._sweep_twist(loop, _scan(stamp), prev, since_last)
    assert np.isclose(twist[2], 2.5, rtol=1e-4)  # (0.3^2 - 0.2^2) * 5 / 0.1 s
