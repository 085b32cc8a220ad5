"""Monte Carlo SLAM accuracy study: ATE of SLAM versus its odometry front-end alone.

Two experiments after the paper's §IV, on simulated logs (several seeds each):
- forest: a MID-360 driving a loop through rows of trees, points behind the sensor cropped
  (`front_end.fov_deg` 180, as the paper did) so the odometry drifts and the loop is ambiguous;
- elevator: a VLP-16 drives into an elevator on the top floor of a building of identical
  floors, rides one floor down and drives out; scored by the final height error of the
  lower floor, with and without the IMU.

Each run goes through `mcl3d.slam.pipeline.run`, the code behind `mcl3d slam`. ATEs are
SE(3)-aligned RMSE (`evo_ape -a`). Logs are cached under bench/results/study_slam/.

    python bench/study_slam.py [--particles 2000] [--seeds 1 2 3] [--cases forest] \
        [--backend cpu] [--out bench/results/study_slam.json] [--runs FOLDER]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
CASES = {
    "forest": dict(world="forest", sensor="mid360", trajectory="ground", duration_s=130.0,
                   overrides={"world.forest_rows": 6, "world.forest_trees_per_row": 10},
                   slam={"front_end.fov_deg": 180.0}),
    "elevator": dict(world="building", sensor="vlp16", trajectory="elevator", duration_s=60.0,
                     overrides={}, slam={}),
    "elevator, no IMU": dict(world="building", sensor="vlp16", trajectory="elevator",
                             duration_s=60.0, overrides={},
                             slam={"odometry.use_imu": False}),
}


def simulate(case: dict, seed: int) -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    folder = RESULTS / "study_slam"
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / f"{case['world']}_{case['trajectory']}_{seed}.mcap"
    if not log.exists():
        run(SimulateRequest(world=case["world"], sensor=case["sensor"],
                            trajectory=case["trajectory"], duration_s=case["duration_s"],
                            seed=seed, output=log, overrides=case["overrides"]))
    return log


def floor_error_m(out: Path, log: Path) -> float:
    """Height error of the representative's last pose (the lower floor) after aligning the
    trajectory's start (before the ride) with the ground truth."""
    from mcl3d.io.trajectory import read_tum

    est = read_tum(out / "slam.tum")
    gt = read_tum(log.with_name(log.stem + "_gt.tum"))
    G = gt.interpolate_poses(est.stamps_s)
    A = G[0] @ np.linalg.inv(est.poses[0])
    return float(abs((A @ est.poses[-1])[2, 3] - G[-1][2, 3]))


def main() -> None:
    from mcl3d.core import config as config_io
    from mcl3d.core import runtime
    from mcl3d.slam.pipeline import SlamRequest, run
    from mcl3d.slam.slam_config import SlamConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--out", type=Path, default=RESULTS / "study_slam.json")
    ap.add_argument("--runs", type=Path, default=RESULTS / "study_slam",
                    help="folder for each run's outputs (the logs stay cached in "
                         "bench/results/study_slam/)")
    args = ap.parse_args()
    info = runtime.init(args.backend)
    rows = []
    for name in args.cases:
        case = CASES[name]
        for seed in args.seeds:
            log = simulate(case, seed)
            out = args.runs / f"{name.replace(', ', '_').replace(' ', '_')}_{seed}"
            cfg = config_io.load(SlamConfig, None, {"particles": args.particles, "seed": seed,
                                                    **case["slam"]})
            s = run(SlamRequest(log=log, output_dir=out, config=cfg, force=True)).summary
            ev = s.accuracy
            row = {"case": name, "seed": seed, "scans": s.scans, "path_m": s.path_length_m,
                   "keyframes": s.keyframes, "ate_odometry_m": ev.odometry.ate_m,
                   "ate_slam_m": ev.slam.ate_m, "ate_online_m": ev.online.ate_m,
                   "ms_per_frame": s.ms_per_frame.median, "loop_frames": s.loop_frames}
            if case["trajectory"] == "elevator":
                row["floor_error_m"] = floor_error_m(out, log)
            rows.append(row)
            print(json.dumps(row), flush=True)
            args.out.write_text(json.dumps(
                {"backend": info.backend, "device": info.device,
                 "particles": args.particles, "rows": rows}, indent=2))
    print("\n| case | seed | path (m) | ATE odometry (m) | ATE SLAM (m) | ATE online (m) | "
          "floor error (m) | ms/frame |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        floor = f"{r['floor_error_m']:.2f}" if "floor_error_m" in r else ""
        print(f"| {r['case']} | {r['seed']} | {r['path_m']:.0f} | {r['ate_odometry_m']:.3f} | "
              f"{r['ate_slam_m']:.3f} | {r['ate_online_m']:.3f} | {floor} | "
              f"{r['ms_per_frame']:.0f} |")


if __name__ == "__main__":
    main()
