"""The odometry bench's scoring and tables, and the SLAM bench's Taichi memory count."""

from __future__ import annotations

import numpy as np
import pytest


def _straight(n: int, step_m: float = 0.1) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = step_m * np.arange(n)
    return poses


def test_score_is_zero_for_the_truth_and_sees_a_scale_error(bench):
    from mcl3d.io.trajectory import Trajectory

    odo = bench("bench_odometry")
    stamps_ns = 1_700_000_000_000_000_000 + np.arange(40, dtype=np.int64) * 100_000_000
    gt = Trajectory.from_ns(stamps_ns, _straight(40))
    exact = odo.score(stamps_ns, _straight(40), gt)
    assert exact["ate_cm"] < 1e-6 and exact["rpe_cm_per_m"] < 1e-6
    short = odo.score(stamps_ns, _straight(40, 0.09), gt)  # 10 % short: 39 cm at the end
    assert short["drift_percent"] == pytest.approx(10.0, rel=1e-3)
    assert 10.0 <= short["rpe_cm_per_m"] <= 12.5  # pairs >= 1 m apart: 10 % of 1.0-1.2 m


def test_tables_report_every_seed_the_mean_and_failures(bench):
    odo = bench("bench_odometry")
    frames = np.array([[10.0, 8.0], [20.0, 16.0], [30.0, 24.0]])
    rows = [{"log": "office", "seed": s, "method": m, "frames": 3, "ate_cm": ate,
             "rpe_cm_per_m": 1.0, "rpe_deg_per_m": 0.1, "drift_percent": 0.5,
             "wall_ms": 20.0, "cpu_ms": 16.0, "frame_ms": frames * k, "x_kiss": k}
            for s, m, ate, k in ((1, "A", 1.0, 1.0), (2, "A", 3.0, 1.0), (1, "B", 5.0, 2.0))]
    rows.append({"log": "office", "seed": 2, "method": "B", "frames": 3, "error": "boom"})
    means, per_seed = odo.tables(rows, {"A": "LiDAR"}).values()
    a, b = means
    assert (a["method"], a["seeds"], a["ATE cm"], a["ATE cm per seed"]) == ("A", "2/2", 2.0,
                                                                            "1.0 / 3.0")
    assert (a["wall ms/frame"], a["cpu ms/frame"], a["input"]) == (20.0, 16.0, "LiDAR")
    assert (b["seeds"], b["ATE cm"], b["wall ms/frame"], b["x KISS-ICP wall"]) == ("1/2", 5.0,
                                                                                  40.0, 2.0)
    assert list(a) == list(b) and len(per_seed) == 4 and per_seed[3]["ATE cm"] is None


def test_taichi_bytes_counts_each_field_and_ndarray_once(bench, ti_runtime):
    import taichi as ti

    slam = bench("bench_slam")

    class Part:  # counted like mcl3d's own objects
        pass

    Part.__module__ = "mcl3d.test"
    inner, outer = Part(), Part()
    inner.q = ti.Vector.field(4, ti.f32, 10)  # 160 B
    inner.k = ti.ndarray(ti.i32, (5, 6))  # 120 B
    inner.v = ti.Vector.ndarray(3, ti.f32, 7)  # 84 B
    inner.s = ti.types.struct(a=ti.f32, b=ti.types.vector(2, ti.f64)).field(
        shape=4, layout=ti.Layout.SOA)  # 4 * (4 + 16) = 80 B
    outer.parts = [inner, {"again": inner.q}]
    outer.inner = inner
    assert slam.taichi_bytes(outer) == 160 + 120 + 84 + 80
    seen: set = set()
    assert slam.taichi_bytes(inner.q, seen) == 160
    assert slam.taichi_bytes(outer, seen) == 120 + 84 + 80
