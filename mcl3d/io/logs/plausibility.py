"""Checks that a log's scans can be what the run needs, made on its first scans before any work:
a run on scans in millimetres or from a planar scanner would end "successfully" with
meaningless output (every point out of range, a 6-DoF pose from a 2-D slice), so it stops
at once with the reason instead.

Units: no lidar has a median range beyond 1 km, while a scan in millimetres has the ranges of
one in metres times 1000 (an office's 0.5-30 m become 500 m-30 km, so not all of them pass
10 km); a scan whose farthest point is within 0.1 m is in kilometres or scaled down.
Planar: every scan lies in one plane through the sensor (a single ring, a 2-D scanner) when
its points are no farther from the best such plane than 1% of their spread.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mcl3d.core.errors import InputError
from mcl3d.io.logs.messages import PointCloud

FIRST_SCANS = 5  # scans looked at
MIN_POINTS = 10  # scans with fewer points say nothing
MILLIMETRE_MEDIAN_M = 1000.0  # a median range beyond this is not in metres
KILOMETRE_MAX_M = 0.1  # a farthest point within this is not in metres
PLANE_THICKNESS = 0.01  # RMS distance to the plane through the sensor, over the RMS range


def first_scans(reader, n: int = FIRST_SCANS) -> list[PointCloud]:
    """The first `n` scans with at least MIN_POINTS points (a short, separate pass)."""
    scans: list[PointCloud] = []
    it = reader.scans()
    try:
        for cloud in it:
            if len(cloud) >= MIN_POINTS:
                scans.append(cloud)
            if len(scans) >= n:
                break
    finally:
        it.close()
    return scans


def check_units(log: Path, scans: list[PointCloud]) -> None:
    """InputError when the scans' ranges are not those of metres."""
    if not scans:
        return
    ranges = np.concatenate([np.linalg.norm(np.asarray(s.points, np.float64), axis=1)
                             for s in scans])
    median, farthest = float(np.median(ranges)), float(ranges.max())
    if median > MILLIMETRE_MEDIAN_M:
        raise InputError(f"{log}: the first scans' median range is {median:,.0f} m (nearest "
                         f"{ranges.min():,.1f} m): coordinates look like millimetres or "
                         "centimetres; mcl3d reads points in metres, convert the log")
    if farthest < KILOMETRE_MAX_M:
        raise InputError(f"{log}: every point of the first scans lies within {farthest:.3g} m "
                         "of the sensor: coordinates look like kilometres or scaled down; "
                         "mcl3d reads points in metres, convert the log")


def _planar(scan: PointCloud) -> bool:
    rings = scan.fields.get("ring")
    if rings is not None and len(np.unique(rings)) == 1:
        return True
    pts = np.asarray(scan.points, np.float64)
    second_moment = pts.T @ pts / len(pts)  # about the sensor, not the centroid
    smallest, largest = np.linalg.eigvalsh(second_moment)[[0, 2]]
    return bool(np.sqrt(max(smallest, 0.0)) <= PLANE_THICKNESS * np.sqrt(largest))


def check_3d(log: Path, scans: list[PointCloud]) -> None:
    """InputError when every scan lies in one plane through the sensor."""
    if scans and all(_planar(s) for s in scans):
        raise InputError(f"{log}: one ring: every scan lies in one plane through the sensor "
                         "(a 2-D scanner), so 6-DoF is not observable; odometry and SLAM need "
                         "a 3-D lidar")


def check_scans(reader, log: Path, needs_3d: bool) -> None:
    """The checks above on the log's first scans; `needs_3d` for 6-DoF motion from scans."""
    scans = first_scans(reader)
    if not scans:
        raise InputError(f"{log}: no scan on {reader.topics.points} has {MIN_POINTS} points or "
                         "more (every one is empty or all NaN): nothing to work with; if the "
                         "scans are on another topic, name it with --points-topic")
    check_units(log, scans)
    if needs_3d:
        check_3d(log, scans)
