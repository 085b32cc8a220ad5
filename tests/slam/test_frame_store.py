"""The columnar per-scan store of a SLAM run: what goes in comes back (rows, columns, loops,
warnings, across the doublings), frames.csv holds the same numbers, and a scan adds a fixed
number of bytes and no Python object."""

from __future__ import annotations

import csv
import tracemalloc

import numpy as np

from mcl3d.core.geometry import rot_to_quat, se3_exp
from mcl3d.slam.frame_store import COLUMNS, STAGES, SlamFrame, SlamFrames

SCANS = 300


def random_frame(rng: np.random.Generator, i: int) -> SlamFrame:
    """Scan i's record with random numbers; every 7th scan took a loop correction toward 1-3
    keyframes, every 50th has odometry warnings."""
    def pose() -> np.ndarray:
        return se3_exp(rng.normal(0.0, 1.0, 6))

    loops = tuple(int(k) for k in rng.choice(40, 1 + i % 3, replace=False)) if i % 7 == 3 else ()
    A = rng.normal(size=(6, 6))
    return SlamFrame(
        1_700_000_000_000_000_000 + 100_000_000 * i, pose(), pose(), pose(),
        int(rng.integers(1000)), float(rng.uniform(1, 1000)), float(rng.uniform()),
        int(rng.integers(1, 5)), int(rng.integers(0, 50)), int(rng.integers(0, 5)),
        int(rng.integers(0, 300)), bool(i % 11 == 0), i // 11, bool(i % 13 == 0), 0.1 * i,
        [f"scan {i} is odd", "twice"] if i % 50 == 49 else [],
        {stage: float(rng.uniform(0, 20)) for stage in STAGES}, pose(), A @ A.T, loops,
        tuple(pose() for _ in loops))


def assert_same(a: SlamFrame, b: SlamFrame) -> None:
    for name in SlamFrame.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if name == "loop_relative":
            assert len(x) == len(y) and all(np.array_equal(u, v) for u, v in zip(x, y, strict=True))
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            assert x == y, name


def test_rows_columns_loops_and_warnings_come_back_exactly():
    rng = np.random.default_rng(0)
    frames = [random_frame(rng, i) for i in range(SCANS)]
    store = SlamFrames(initial_rows=4)  # doubles six times on the way
    for f in frames:
        store.append(f)
    assert len(store) == SCANS
    for i in (0, 3, 10, 49, 143, SCANS - 1, -1):
        assert_same(store[i], frames[i])
    np.testing.assert_array_equal(store.stamp_ns, [f.stamp_ns for f in frames])
    np.testing.assert_array_equal(store.pruned, [f.pruned for f in frames])
    np.testing.assert_array_equal(store.poses("T_odom_lidar"), [f.T_odom_lidar for f in frames])
    np.testing.assert_array_equal(store.covariance, [f.covariance for f in frames])
    np.testing.assert_array_equal(store.timings_ms,
                                  [[f.timings_ms[s] for s in STAGES] for f in frames])
    loops = list(store.loops())
    assert [i for i, *_ in loops] == [i for i, f in enumerate(frames) if f.loop_keyframes]
    for i, keyframes, relative in loops:
        assert keyframes == frames[i].loop_keyframes
        np.testing.assert_array_equal(relative, frames[i].loop_relative)
    assert store.warnings == [(i, w) for i, f in enumerate(frames) for w in f.odometry_warnings]


def test_frames_csv_holds_the_stored_numbers(tmp_path):
    from mcl3d.slam.pipeline import COV_COLUMNS, _write_frames

    rng = np.random.default_rng(1)
    frames = [random_frame(rng, i) for i in range(40)]
    store = SlamFrames(initial_rows=8)
    for f in frames:
        store.append(f)
    _write_frames(tmp_path / "frames.csv", store)
    with open(tmp_path / "frames.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(frames)
    for row, f in zip(rows, frames, strict=True):
        assert round(float(row["stamp_s"]) * 1e3) == f.stamp_ns // 1_000_000
        np.testing.assert_allclose([float(row[a]) for a in "xyz"], f.T_world_lidar[:3, 3],
                                   atol=5e-5)
        assert int(row["pruned"]) == f.pruned and int(row["keyframe"]) == f.keyframe
        assert int(row["elevator"]) == f.elevator and int(row["keyframes"]) == f.num_keyframes
        np.testing.assert_allclose([float(row[f"{s}_ms"]) for s in STAGES],
                                   [f.timings_ms[s] for s in STAGES], atol=5e-3)
        q = rot_to_quat(f.T_mean[:3, :3])
        np.testing.assert_allclose([float(row[f"mean_q{a}"]) for a in "xyzw"], q, atol=5e-9)
        upper = f.covariance[np.triu_indices(6)]
        np.testing.assert_allclose([float(row[c]) for c in COV_COLUMNS], upper, rtol=1e-5)
        assert row["loop_keyframes"] == " ".join(str(k) for k in f.loop_keyframes)


def test_a_scan_adds_fixed_bytes_and_no_python_objects():
    """Hundreds of scans into a store reserved for them: the traced memory (NumPy's data
    included) does not move (no per-scan object, no reallocation), and a scan takes the
    columns' row bytes (814, against ~3.5 kB as one SlamFrame object per scan)."""
    rng = np.random.default_rng(2)
    frames = [random_frame(rng, i) for i in range(600)]
    for f in frames:  # no loops, no warnings: the steady state of a long run
        f.loop_keyframes, f.loop_relative, f.odometry_warnings = (), (), []
    store = SlamFrames(initial_rows=len(frames))  # reserved for the log's scans
    for f in frames[:100]:
        store.append(f)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for f in frames[100:]:
            store.append(f)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert len(store) == 600 and grown < 2048, grown
    row_bytes = sum(np.dtype(dtype).itemsize * int(np.prod(shape))
                    for dtype, shape in COLUMNS.values())
    assert row_bytes < 900


def test_scans_hang_off_the_keyframe_before_them():
    rng = np.random.default_rng(3)
    frames = [random_frame(rng, i) for i in range(40)]
    store = SlamFrames()
    for f in frames:
        store.append(f)
    keyframe_scans = [5, 6, 20, 39]
    T_keyframes = np.stack([se3_exp(rng.normal(0.0, 1.0, 6)) for _ in keyframe_scans])
    poses = store.hung_off(T_keyframes, keyframe_scans)
    for i, f in enumerate(frames):
        if i < 5:
            np.testing.assert_array_equal(poses[i], f.T_world_lidar)
            continue
        k = max(j for j, scan in enumerate(keyframe_scans) if scan <= i)
        T_motion_keyframe = frames[keyframe_scans[k]].T_motion_lidar
        expected = T_keyframes[k] @ np.linalg.inv(T_motion_keyframe) @ f.T_motion_lidar
        np.testing.assert_allclose(poses[i], expected, atol=1e-9)
    np.testing.assert_allclose(poses[keyframe_scans], T_keyframes, atol=1e-9)
    np.testing.assert_array_equal(store.hung_off(np.zeros((0, 4, 4)), []),
                                  store.poses("T_world_lidar"))
