"""How well a SLAM run's loop pairs register, and how much the sweep's deskewing costs.

The loop graph (mcl3d/slam/loop_graph.py) registers a scan onto an old keyframe's cloud; its
edges are only as good as those registrations. This study takes the keyframe pairs a run's
representative closed loops between (`frames.csv` of `mcl3d slam`), registers the two
keyframe scans from the log as the graph does (`mcl3d.registration.align`, the graph's
resolutions, the front-end's field-of-view crop and voxel size) from the true relative pose
perturbed by 0.4 m / 2° (seeded), and compares the result with the truth for four versions
of each sweep:
- raw: not deskewed;
- truth: deskewed with the true motion (the ground truth interpolated at each point's time);
- odometry over the sweep: with the run's odometry poses interpolated over the sweep itself
  (from the scan's stamp to the next: known once the next scan is registered);
- odometry before the stamp: with the odometry's motion over the scan period before the
  stamp, laid over the sweep (what a scan can be deskewed with when it arrives).
Errors are medians over the pairs: position per world axis, rotation per world axis (roll,
pitch, yaw for a level sensor), and the position error's norm (median and 90th percentile).

    python bench/study_loop_registration.py LOG.mcap TRUTH.tum SLAM_OUT [--pairs 30]
        [--fov-deg 180] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
INIT_SIGMA_M = 0.4  # the filter's loop estimate can be this far off ...
INIT_SIGMA_DEG = 2.0
MIN_RANGE_M = 0.5
VARIANTS = ("raw", "truth", "odometry over the sweep", "odometry before the stamp")


def loop_pairs(frames_csv: Path, count: int) -> tuple[list[tuple[int, int]], np.ndarray]:
    """(source keyframe, loop keyframe) numbers the representative closed, evenly sampled
    down to `count`, and the scan index of each keyframe number."""
    with open(frames_csv) as f:
        rows = list(csv.DictReader(f))
    keyframe_scans = np.flatnonzero([int(r["keyframe"]) for r in rows])
    newest = np.searchsorted(keyframe_scans, np.arange(len(rows)), side="right") - 1
    pairs = sorted({(int(newest[i]), int(k)) for i, r in enumerate(rows)
                    for k in r["loop_keyframes"].split() if int(k) != newest[i]})
    return pairs[::max(1, len(pairs) // count)], keyframe_scans


def deskewed(points: np.ndarray, times_s: np.ndarray, trajectory, stamp_s: float,
             shift_s: float = 0.0) -> np.ndarray:
    """Points moved into the sensor frame at the stamp along `trajectory` between
    stamp + shift_s and stamp + shift_s + each point's time (held at the trajectory's ends:
    the first and last scans)."""
    from mcl3d.core.geometry import se3_inverse

    def at(t_s):
        return trajectory.interpolate_poses(np.clip(t_s, trajectory.stamps_s[0],
                                                    trajectory.stamps_s[-1]))

    T_at = at(stamp_s + shift_s + times_s)
    T_ref = at(np.array([stamp_s + shift_s]))[0]
    T_rel = np.einsum("ij,njk->nik", se3_inverse(T_ref), T_at)
    return np.einsum("nij,nj->ni", T_rel[:, :3, :3], points) + T_rel[:, :3, 3]


def keyframe_clouds(log: Path, scans: set[int], truth, odometry, fov_deg: float, voxel_m: float
                    ) -> tuple[dict[str, dict[int, np.ndarray]], dict[int, np.ndarray]]:
    """Each variant's downsampled cloud of the log's scans `scans`, and their true poses."""
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.registration.preprocess import voxel_downsample
    from mcl3d.slam.monte_carlo_slam import crop_fov

    clouds: dict[str, dict[int, np.ndarray]] = {v: {} for v in VARIANTS}
    T_true: dict[int, np.ndarray] = {}
    with LogReader(log) as reader:
        for i, scan in enumerate(reader.scans()):
            if i > max(scans):
                break
            if i not in scans:
                continue
            if scan.times_s is None:
                raise SystemExit(f"{log} has no per-point times: nothing to deskew")
            points, times = crop_fov(scan.points.astype(np.float64),
                                     scan.times_s.astype(np.float64), fov_deg)
            keep = np.linalg.norm(points, axis=1) > MIN_RANGE_M
            points, times = points[keep], times[keep]
            stamp_s = scan.stamp_ns * 1e-9
            period_s = float(times.max() - times.min())
            T_true[i] = truth.interpolate_poses(np.array([stamp_s]))[0]
            for variant, cloud in zip(VARIANTS, (
                    points, deskewed(points, times, truth, stamp_s),
                    deskewed(points, times, odometry, stamp_s),
                    deskewed(points, times, odometry, stamp_s, -period_s)), strict=True):
                clouds[variant][i] = voxel_downsample(cloud, voxel_m)
    return clouds, T_true


def registration_errors(pairs: list[tuple[int, int]], keyframe_scans: np.ndarray,
                        clouds: dict[int, np.ndarray], T_true: dict[int, np.ndarray],
                        offsets: list[np.ndarray]) -> dict:
    """Median errors of registering each pair's source scan onto its target, as the loop
    graph does, from the truth moved by `offsets`."""
    from mcl3d.core.geometry import se3_inverse, se3_log
    from mcl3d.registration.align import align
    from mcl3d.slam.loop_graph import LOOP_RESOLUTIONS_M

    errors = []
    for (source, target), offset in zip(pairs, offsets, strict=True):
        i, j = int(keyframe_scans[source]), int(keyframe_scans[target])
        T_target_source = se3_inverse(T_true[j]) @ T_true[i]
        result = align(clouds[j], clouds[i], T_target_source @ offset,
                       voxel_resolution_m=LOOP_RESOLUTIONS_M)
        position_m = T_true[j][:3, :3] @ (result.T_target_source[:3, 3]
                                          - T_target_source[:3, 3])
        rotation_deg = np.degrees(T_true[i][:3, :3] @ se3_log(
            se3_inverse(T_target_source) @ result.T_target_source)[:3])
        errors.append(np.r_[np.abs(position_m), np.abs(rotation_deg),
                            np.linalg.norm(position_m)])
    e = np.array(errors)
    return {"median_abs_xyz_m": np.median(e[:, :3], axis=0).round(3),
            "median_abs_roll_pitch_yaw_deg": np.median(e[:, 3:6], axis=0).round(2),
            "median_m": round(float(np.median(e[:, 6])), 3),
            "p90_m": round(float(np.percentile(e[:, 6], 90)), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("truth", type=Path, help="TUM ground truth of the log")
    parser.add_argument("slam_out", type=Path, help="a `mcl3d slam` output folder")
    parser.add_argument("--pairs", type=int, default=30)
    parser.add_argument("--fov-deg", type=float, default=180.0)
    parser.add_argument("--voxel-m", type=float, default=0.25)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS / "study_loop_registration.json")
    args = parser.parse_args()
    frames, odometry_tum = args.slam_out / "frames.csv", args.slam_out / "odometry.tum"
    for path in (args.log, args.truth, frames, odometry_tum):
        if not path.is_file():
            raise SystemExit(f"{path} does not exist (give a log, its TUM ground truth and a "
                             "`mcl3d slam` output folder)")
    if args.pairs < 1 or args.voxel_m <= 0:
        raise SystemExit("--pairs must be >= 1 and --voxel-m > 0")

    from results_io import Run

    from mcl3d.core import runtime
    from mcl3d.core.geometry import se3, so3_exp
    from mcl3d.io.trajectory import read_tum

    run = Run("study_loop_registration")
    runtime.init("cpu")
    pairs, keyframe_scans = loop_pairs(frames, args.pairs)
    if not pairs:
        raise SystemExit(f"{frames} has no loop: nothing to register")
    truth, odometry = read_tum(args.truth), read_tum(odometry_tum)
    clouds, T_true = keyframe_clouds(args.log, {int(keyframe_scans[k]) for p in pairs for k in p},
                                     truth, odometry, args.fov_deg, args.voxel_m)
    rng = np.random.default_rng(args.seed)
    offsets = [se3(so3_exp(np.radians(rng.normal(0, INIT_SIGMA_DEG, 3))),
                   rng.normal(0, INIT_SIGMA_M, 3)) for _ in pairs]
    figures = {"pairs": len(pairs), "log": str(args.log), "slam_out": str(args.slam_out)}
    print(f"{len(pairs)} loop pairs of {args.slam_out}")
    for variant in VARIANTS:
        f = figures[variant] = registration_errors(pairs, keyframe_scans, clouds[variant],
                                                   T_true, offsets)
        print(f"{variant:26s} |x y z| {f['median_abs_xyz_m']} m  |roll pitch yaw| "
              f"{f['median_abs_roll_pitch_yaw_deg']} deg  median {f['median_m']} m  "
              f"p90 {f['p90_m']} m")
    print(f"written to {run.write(figures, args.out)}")


if __name__ == "__main__":
    main()
