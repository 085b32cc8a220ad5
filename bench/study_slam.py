"""Monte Carlo SLAM accuracy study: ATE of SLAM versus its odometry front-end alone and the
peers (kiss-icp, kiss-slam, rko-lio; bench/slam_peers.py) on the same scans.

Two experiments after the paper's §IV, on simulated logs (several seeds each):
- forest: a MID-360 driving a loop through rows of trees, points behind the sensor cropped
  (`front_end.fov_deg` 180, as the paper did) so the odometry drifts and the loop is ambiguous;
- elevator: a VLP-16 drives into an elevator on the top floor of a building of identical
  floors, rides one floor down and drives out; scored by the final height error of the
  lower floor, with and without the IMU.

- paper-forest: the paper's ~10 min walk through look-alike rows (MID-360 cropped to 180°,
  no IMU), where LiDAR-only odometry drifts metres and loops compete.
- paper-elevator: the paper's elevator route (hand-held MID-360, building of three
  identical floors: stairs 1F -> 3F, the elevator down to 2F, stairs down to 1F), with and
  without the IMU; right floor when the final height error is under 1 m.

Each run goes through `mcl3d.slam.pipeline.run`, the code behind `mcl3d slam`. ATEs are
SE(3)-aligned RMSE (`evo_ape -a`, mcl3d.evaluation.metrics) for every method. Per SLAM run
also: the cloud's consistency (scans with the truth inside its 95% region) and the
representative's loop corrections, with how many were wrong (> 2 m off the true relative
pose); for kiss-slam its accepted closures and the wrong ones. Logs are cached under
bench/results/study_slam/.

    python bench/study_slam.py [--particles 2000] [--seeds 1 2 3] [--cases forest] \
        [--preset paper] [--set KEY=VALUE ...] [--peers kiss-icp kiss-slam rko-lio] \
        [--backend cpu] [--out bench/results/study_slam.json] [--runs FOLDER]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

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


CASES["forest, no IMU"] = dict(CASES["forest"], slam={"front_end.fov_deg": 180.0,
                                                     "odometry.use_imu": False})
CASES["paper-forest"] = dict(world="forest", sensor="mid360", trajectory="paper-forest",
                             duration_s=None, overrides={},
                             slam={"front_end.fov_deg": 180.0, "odometry.use_imu": False,
                                   "keyframes.capacity": 512})
CASES["paper-elevator"] = dict(world="building", sensor="mid360", trajectory="paper-elevator",
                               duration_s=None, overrides={}, slam={})
CASES["paper-elevator, no IMU"] = dict(CASES["paper-elevator"],
                                       slam={"odometry.use_imu": False})
RIGHT_FLOOR_M = 1.0  # a final height error under this is the right floor (3.5 m apart)
PEERS = ("kiss-icp", "kiss-slam", "rko-lio")
WRONG_CLOSURE_M = 2.0  # as mcl3d.slam.slam_summary.WRONG_LOOP_M


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


def peer_rows(names: list[str], log: Path, fov_deg: float, max_range_m: float) -> dict:
    """ATE of each peer on the log's scans (cropped as the SLAM run), its time, and for
    kiss-slam the closures it kept and how many were wrong."""
    import slam_peers

    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.logs.reader import LogReader
    from mcl3d.io.trajectory import Trajectory

    runners = {"kiss-icp": slam_peers.run_kiss_icp, "kiss-slam": slam_peers.run_kiss_slam,
               "rko-lio": slam_peers.run_rko_lio}
    with LogReader(log) as reader:
        gt = Trajectory.from_ns(*reader.ground_truth())
    out = {}
    for name in names:
        try:
            peer = runners[name](log, fov_deg, max_range_m)
        except Exception as exc:  # a peer failing is a result too, not the end of the study
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        est = Trajectory.from_ns(peer.stamps_ns, peer.poses)
        ev = evaluate(gt, est, alignment="se3")
        row = {"ate_m": ev.ate.translation_m.rmse, "seconds": peer.seconds,
               "scans": len(peer.stamps_ns)}
        if name == "kiss-slam":
            errors = slam_peers.closure_errors_m(peer, gt.interpolate_poses(
                peer.stamps_ns * 1e-9))
            row.update(closures=len(errors),
                       wrong_closures=int(sum(e > WRONG_CLOSURE_M for e in errors)),
                       worst_closure_error_m=max(errors, default=0.0))
        out[name] = row
        print(f"  {name}: {json.dumps(row)}", flush=True)
    return out


def slam_row(name: str, case: dict, seed: int, log: Path, out: Path, s, seconds: float
             ) -> dict:
    ev = s.accuracy
    row = {"case": name, "seed": seed, "scans": s.scans, "path_m": s.path_length_m,
           "keyframes": s.keyframes, "ate_odometry_m": ev.odometry.ate_m,
           "ate_slam_m": ev.slam.ate_m, "ate_online_m": ev.online.ate_m,
           "ms_per_frame": s.ms_per_frame.median, "seconds": seconds,
           "loop_frames": s.loop_frames,
           "consistency_95": None if s.consistency is None else s.consistency.fraction,
           "loops_accepted": None if s.loop_check is None else s.loop_check.accepted,
           "loops_wrong": None if s.loop_check is None else s.loop_check.wrong}
    if case["trajectory"] in ("elevator", "paper-elevator"):
        row["floor_error_m"] = floor_error_m(out, log)
        row["right_floor"] = row["floor_error_m"] < RIGHT_FLOOR_M
    return row


def parse_sets(items: list[str]) -> dict:
    """KEY=VALUE pairs (dotted keys, YAML values) for the SLAM config."""
    return {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in items)}


def main() -> None:
    from mcl3d.core import config as config_io
    from mcl3d.core import runtime
    from mcl3d.slam.pipeline import SlamRequest, run
    from mcl3d.slam.presets import preset
    from mcl3d.slam.slam_config import SlamConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=2000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--cases", nargs="+", default=[c for c in CASES if not c.startswith("paper-")],
                    choices=list(CASES))
    ap.add_argument("--preset", default=None, help="SLAM preset (mcl3d.slam.presets)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="SLAM config overrides, e.g. prediction_noise.odometry_scale=1")
    ap.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS)
    ap.add_argument("--peer-threads", type=int, default=0, help="threads per peer (0: all)")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--out", type=Path, default=RESULTS / "study_slam.json")
    ap.add_argument("--runs", type=Path, default=RESULTS / "study_slam",
                    help="folder for each run's outputs (the logs stay cached in "
                         "bench/results/study_slam/)")
    args = ap.parse_args()
    info = runtime.init(args.backend)
    import slam_peers

    slam_peers.THREADS = args.peer_threads
    rows = []
    for name in args.cases:
        case = CASES[name]
        for seed in args.seeds:
            log = simulate(case, seed)
            out = args.runs / f"{name.replace(', ', '_').replace(' ', '_')}_{seed}"
            cfg = config_io.load(SlamConfig, None, {"particles": args.particles, "seed": seed,
                                                    **case["slam"], **parse_sets(args.set)},
                                 preset=preset(args.preset))
            t0 = time.perf_counter()
            s = run(SlamRequest(log=log, output_dir=out, config=cfg, force=True)).summary
            row = slam_row(name, case, seed, log, out, s, time.perf_counter() - t0)
            print(json.dumps(row), flush=True)
            if args.peers and case["trajectory"] != "elevator":
                row["peers"] = peer_rows(args.peers, log, cfg.front_end.fov_deg,
                                         cfg.odometry.max_range_m)
            rows.append(row)
            args.out.write_text(json.dumps(
                {"backend": info.backend, "device": info.device, "particles": args.particles,
                 "preset": args.preset, "set": args.set, "rows": rows}, indent=2))
    print_table(rows)


def print_table(rows: list[dict]) -> None:
    def ate(r: dict, peer: str) -> str:
        p = r.get("peers", {}).get(peer)
        return "" if p is None else ("failed" if "error" in p else f"{p['ate_m']:.3f}")

    print("\n| case | seed | path (m) | ATE odometry (m) | ATE SLAM (m) | ATE online (m) | "
          "kiss-icp | kiss-slam | rko-lio (IMU) | consistency | loops (wrong) | "
          "kiss-slam closures (wrong) | floor error (m) | ms/frame |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        floor = f"{r['floor_error_m']:.2f}" if "floor_error_m" in r else ""
        ks = r.get("peers", {}).get("kiss-slam", {})
        closures = f"{ks['closures']} ({ks['wrong_closures']})" if "closures" in ks else ""
        cons = "" if r["consistency_95"] is None else f"{100 * r['consistency_95']:.0f}%"
        loops = "" if r["loops_accepted"] is None else (f"{r['loops_accepted']} "
                                                        f"({r['loops_wrong']})")
        print(f"| {r['case']} | {r['seed']} | {r['path_m']:.0f} | {r['ate_odometry_m']:.3f} | "
              f"{r['ate_slam_m']:.3f} | {r['ate_online_m']:.3f} | {ate(r, 'kiss-icp')} | "
              f"{ate(r, 'kiss-slam')} | {ate(r, 'rko-lio')} | {cons} | {loops} | {closures} | "
              f"{floor} | {r['ms_per_frame']:.0f} |")


if __name__ == "__main__":
    main()
