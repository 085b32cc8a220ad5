"""Where the LiDAR-only front-end's drift comes from: its rotation error per sensor axis.

SLAM without an IMU inherits its front-end's drift between loops. This study runs the
front-end (`mcl3d.odometry.LidarOdometry`, no IMU) over a simulated log with ground truth
once per variant (the field of view cropped as `mcl3d slam`'s `front_end.fov_deg` does;
the sweep deskewed by the front-end itself, with the true motion before the front-end sees
it, or not at all) and reports per sensor axis (x, y, z: roll, pitch, yaw for a level
sensor) how fast its orientation error grows (deg/s: the mean relative rotation error over
windows of `--window-s`, divided by the window), how much a pose jitters (the spread of the
one-scan relative rotation error), the keyframes it made and its ATE (SE(3)-aligned).

    python bench/study_front_end_drift.py LOG.mcap TRUTH.tum [--fov-deg 180 360]
        [--deskew front-end truth none] [--max-scans N] [--window-s 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
DESKEW_MODES = ("front-end", "truth", "none")


def relative_rotation_errors(T_est: np.ndarray, T_true: np.ndarray, starts: np.ndarray,
                             lag: int) -> np.ndarray:
    """Rotation vectors (rad, in the sensor frame at the window's end) of the estimate's
    motion from each start to start + lag against the true motion."""
    from mcl3d.core.geometry import so3_log

    def turn(T: np.ndarray) -> np.ndarray:
        return np.einsum("nji,njk->nik", T[starts, :3, :3], T[starts + lag, :3, :3])

    return so3_log(np.einsum("nji,njk->nik", turn(T_true), turn(T_est)))


def rotation_drift(stamps_s: np.ndarray, T_est: np.ndarray, T_true: np.ndarray,
                   window_s: float) -> dict:
    """Mean rotation error rate per sensor axis (deg/s) over back-to-back windows of
    `window_s`, and the spread (deg) of the one-scan rotation error per axis."""
    period_s = float(np.median(np.diff(stamps_s)))
    lag = max(1, round(window_s / period_s))
    if len(stamps_s) <= lag:
        raise ValueError(f"{len(stamps_s)} scans are shorter than one {window_s} s window")
    starts = np.arange(0, len(stamps_s) - lag, lag)
    rates = relative_rotation_errors(T_est, T_true, starts, lag) / (
        stamps_s[starts + lag] - stamps_s[starts])[:, None]
    one_scan = relative_rotation_errors(T_est, T_true, np.arange(len(stamps_s) - 1), 1)
    return {"rate_deg_per_s": np.degrees(rates.mean(axis=0)).round(4).tolist(),
            "jitter_deg": np.degrees(one_scan.std(axis=0)).round(3).tolist()}


def run_front_end(log: Path, truth, fov_deg: float, deskew: str, max_scans: int | None
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """Stamps (s), poses and the keyframe count of the front-end over the log."""
    from study_loop_registration import deskewed

    from mcl3d.io.logs.reader import LogReader
    from mcl3d.odometry.lidar_odometry import LidarOdometry
    from mcl3d.odometry.odometry_config import OdometryConfig
    from mcl3d.slam.monte_carlo_slam import crop_fov

    odometry = LidarOdometry(OdometryConfig(use_imu=False, deskew=deskew == "front-end"))
    stamps_s, poses, keyframes = [], [], 0
    with LogReader(log) as reader:
        for scan in itertools.islice(reader.scans(), max_scans):
            times = None if scan.times_s is None else scan.times_s.astype(np.float64)
            points, times = crop_fov(scan.points.astype(np.float64), times, fov_deg)
            if deskew == "truth":
                if times is None:
                    raise SystemExit(f"{log} has no per-point times: nothing to deskew")
                points, times = deskewed(points, times, truth, scan.stamp_ns * 1e-9), None
            frame = odometry.step(points, times, scan.stamp_ns)
            stamps_s.append(scan.stamp_ns * 1e-9)
            poses.append(frame.T_world_lidar)
            keyframes += frame.keyframe
    return np.array(stamps_s), np.array(poses), keyframes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("truth", type=Path, help="TUM ground truth of the log")
    parser.add_argument("--fov-deg", type=float, nargs="+", default=[180.0, 360.0])
    parser.add_argument("--deskew", nargs="+", default=["front-end", "truth"],
                        choices=DESKEW_MODES)
    parser.add_argument("--max-scans", type=int, default=None)
    parser.add_argument("--window-s", type=float, default=5.0)
    parser.add_argument("--out", type=Path, default=RESULTS / "study_front_end_drift.json")
    args = parser.parse_args()
    for path in (args.log, args.truth):
        if not path.is_file():
            raise SystemExit(f"{path} does not exist (give a log and its TUM ground truth)")
    if any(not 0 < f <= 360 for f in args.fov_deg) or args.window_s <= 0 or (
            args.max_scans is not None and args.max_scans < 2):
        raise SystemExit("--fov-deg must be in (0, 360], --window-s > 0, --max-scans >= 2")

    from results_io import Run

    from mcl3d.core import runtime
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.trajectory import Trajectory, read_tum

    run = Run("study_front_end_drift")
    runtime.init("cpu")
    truth = read_tum(args.truth)
    figures = {"log": str(args.log), "window_s": args.window_s, "variants": []}
    for fov_deg, deskew in itertools.product(args.fov_deg, args.deskew):
        stamps_s, poses, keyframes = run_front_end(args.log, truth, fov_deg, deskew,
                                                   args.max_scans)
        T_true = truth.interpolate_poses(np.clip(stamps_s, truth.stamps_s[0],
                                                 truth.stamps_s[-1]))
        ate_m = evaluate(truth, Trajectory(stamps_s, poses),
                         alignment="se3").ate.translation_m.rmse
        f = {"fov_deg": fov_deg, "deskew": deskew, "scans": len(stamps_s),
             "keyframes": keyframes, "ate_m": round(float(ate_m), 3),
             **rotation_drift(stamps_s, poses, T_true, args.window_s)}
        figures["variants"].append(f)
        print(f"fov {fov_deg:5.1f}, deskew {deskew:9s} | rotation error rate x y z "
              f"{f['rate_deg_per_s']} deg/s  one-scan jitter {f['jitter_deg']} deg | "
              f"{keyframes} keyframes, ATE {f['ate_m']} m", flush=True)
    print(f"written to {run.write(figures, args.out)}")


if __name__ == "__main__":
    main()
