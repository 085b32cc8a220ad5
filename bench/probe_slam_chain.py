"""Where SLAM's drift comes from on a log with ground truth: the likelihood's mode against
the truth, and keyframe-to-keyframe errors of a SLAM run against its front-end's.

1. Mode probe: `MonteCarloSlam` with one particle held at the true pose (so its keyframes
   are true too; no loops, no refinement). After each weighing a few Gauss-Newton steps on
   the same cost (the scan's points against the particle's three neighbour keyframes) from
   the truth find the cost's minimum; its offset from the truth is what selection by this
   likelihood rewards. Compared with the front-end's pose relative to the newest keyframe.
2. Chain check (`--run FOLDER` of a finished `mcl3d slam`): the error of each relative pose
   between consecutive keyframes, for SLAM's keyframe-placed trajectory and for the
   odometry's, and where those errors sum to at the last keyframe: scan-to-model odometry's
   errors cancel along the path, a chain of scan-to-keyframe matches adds them up.

    python bench/probe_slam_chain.py LOG --gt GT.tum [--scans 1100] [--run OUT_FOLDER]
        [--set KEY=VALUE ...] [--json FILE]

Axes: rotation (deg) about the lidar's x, y, z, then translation (cm) along them.
"""

from __future__ import annotations

import argparse
import csv
import json
from itertools import pairwise
from pathlib import Path

import numpy as np

from mcl3d.core import runtime
from mcl3d.core.geometry import rot_to_quat, se3_exp, se3_inverse, se3_log
from mcl3d.io.logs.reader import LogReader
from mcl3d.io.trajectory import Trajectory, read_tum
from mcl3d.odometry.scan_feed import LidarImuFeed
from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
from mcl3d.slam.slam_config import SlamConfig

MODE_STEPS = 6  # Gauss-Newton steps from the truth to the cost's minimum
PROBE = {"particles": 1, "front_end": {"fov_deg": 180.0}, "odometry": {"use_imu": False},
         "keyframes": {"capacity": 512}, "loop_closure": {"min_travel_m": 1e9},
         "correction": {"refine_without_loop": False, "spread_after_step": False}}


def nested(settings: list[str]) -> dict:
    """KEY=VALUE (dotted keys) over the probe's settings."""
    out = json.loads(json.dumps(PROBE))
    for item in settings:
        key, value = item.split("=", 1)
        node = out
        *path, leaf = key.split(".")
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = json.loads(value) if value[:1] in "0123456789-tf[{" else value
    return out


def truth_at(gt: Trajectory, stamp_ns: int) -> np.ndarray:
    i = int(np.argmin(np.abs(gt.stamps_s - stamp_ns * 1e-9)))
    return gt.poses[i]


def describe(errors: np.ndarray) -> dict:
    """Mean and standard deviation per axis (deg, cm)."""
    scaled = np.c_[np.rad2deg(errors[:, :3]), 100.0 * errors[:, 3:]]
    return {"mean": scaled.mean(0).round(3).tolist(), "std": scaled.std(0).round(3).tolist()}


def probe_modes(log: Path, gt: Trajectory, scans: int, cfg: SlamConfig) -> dict:
    slam = MonteCarloSlam(cfg, scans=scans)
    p = slam.particles
    held = {"T": np.eye(4)}
    offsets, steps = [], []

    def place(T: np.ndarray) -> None:
        p.q_cur.from_numpy(rot_to_quat(T[:3, :3])[None].astype(np.float32))
        p.t_cur.from_numpy(T[:3, 3][None].astype(np.float32))

    weigh, predict = p.weigh, slam._predict

    def weigh_then_find_mode(num_src, *args, **kwargs):
        weigh(num_src, *args, **kwargs)
        T = held["T"].copy()
        best = p.gicp.poses.best
        for it in range(MODE_STEPS):
            if it:
                p._linearize(num_src, loop_only=False)
            rows = [j for j in range(3) if p.nb[0, j] >= 0]
            H = sum(best.H.to_numpy()[j].astype(np.float64) for j in rows)
            b = sum(best.b.to_numpy()[j].astype(np.float64) for j in rows)
            T = T @ se3_exp(-np.linalg.solve(H + 1e-9 * np.eye(6), b))
            place(T)
        offsets.append(se3_log(se3_inverse(held["T"]) @ T))
        steps.append(len(slam.frames))
        place(held["T"])  # the keyframe made from this scan stays true

    def predict_then_hold(*args):
        cov = predict(*args)
        place(held["T"])
        return cov

    p.weigh, slam._predict = weigh_then_find_mode, predict_then_hold
    T_world0 = None
    with LogReader(log) as reader:
        for cloud, imu_rows, T_lidar_imu in LidarImuFeed(reader, cfg.odometry.use_imu):
            T_true = truth_at(gt, cloud.stamp_ns)
            T_world0 = se3_inverse(T_true) if T_world0 is None else T_world0
            held["T"] = T_world0 @ T_true
            slam.odometry.T_lidar_imu = T_lidar_imu
            slam.step(cloud.points, cloud.times_s, cloud.stamp_ns, imu_rows)
            if len(slam.frames) >= scans:
                break
    odometry = slam.frames.poses("T_odom_lidar")
    truth = np.array([T_world0 @ truth_at(gt, s) for s in slam.frames.stamp_ns])
    keyframes = np.array(slam.keyframe_frames)
    front_end = []
    for s in steps:
        k = keyframes[keyframes < s].max()
        front_end.append(se3_log(se3_inverse(se3_inverse(truth[k]) @ truth[s])
                                 @ se3_inverse(odometry[k]) @ odometry[s]))
    offsets, front_end = np.array(offsets), np.array(front_end)
    return {"scans": len(slam.frames), "scored": len(steps), "keyframes": len(keyframes),
            "mode_minus_truth": describe(offsets),
            "front_end_relative_to_keyframe_minus_truth": describe(front_end),
            "correlation": [round(float(np.corrcoef(offsets[:, a], front_end[:, a])[0, 1]), 3)
                            for a in range(6)]}


def chain_errors(run: Path, gt: Trajectory) -> dict:
    with open(run / "frames.csv") as f:
        keyframes = np.flatnonzero([int(row["keyframe"]) for row in csv.DictReader(f)])
    out = {}
    for name in ("slam", "odometry"):
        est = read_tum(run / f"{name}.tum")
        truth = np.array([truth_at(gt, round(s * 1e9)) for s in est.stamps_s])
        links = np.array([se3_log(se3_inverse(se3_inverse(truth[a]) @ truth[b])
                                  @ se3_inverse(est.poses[a]) @ est.poses[b])
                          for a, b in pairwise(keyframes)])
        a, b = keyframes[0], keyframes[-1]
        end = se3_log(se3_inverse(se3_inverse(truth[a]) @ truth[b])
                      @ se3_inverse(est.poses[a]) @ est.poses[b])
        out[name] = {"links": len(links), **describe(links),
                     "end_to_end": describe(end[None])["mean"]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--gt", type=Path, required=True, help="ground truth (TUM)")
    ap.add_argument("--scans", type=int, default=1100)
    ap.add_argument("--run", type=Path, help="a finished `mcl3d slam` output folder")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    runtime.init("cpu")
    gt = read_tum(args.gt)
    result = {"mode_probe": probe_modes(args.log, gt, args.scans,
                                        SlamConfig.model_validate(nested(args.set)))}
    if args.run:
        result["chain"] = chain_errors(args.run, gt)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
