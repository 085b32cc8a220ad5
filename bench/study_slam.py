"""Monte Carlo SLAM accuracy study: SLAM against its own front-end and the peers.

ATE of `mcl3d slam` versus its odometry front-end alone and the peers (kiss-icp, kiss-slam,
rko-lio; bench/slam_peers.py) on the same scans.

Two experiments after the paper's §IV, on simulated logs (several seeds each):
- forest: a MID-360 driving a loop through rows of trees, points behind the sensor cropped
  (`front_end.fov_deg` 180, as the paper did) so the odometry drifts and the loop is ambiguous;
- elevator: a VLP-16 drives into an elevator on the top floor of a building of identical
  floors, rides one floor down and drives out; scored by the final height error of the
  lower floor, with and without the IMU.

- paper-forest: the paper's ~10 min hand-held walk through look-alike rows on a hillside,
  crowns a pulse goes into, the step's nod and quick turns at the rows' ends (MID-360
  cropped to 180°, no IMU), where LiDAR-only odometry drifts metres and loops compete.
- paper-elevator: the paper's elevator route (hand-held MID-360, building of three
  identical floors: stairs 1F -> 3F, the elevator down to 2F, stairs down to 1F), with and
  without the IMU; right floor when the final height error is under 1 m.

Each run goes through `mcl3d.slam.pipeline.run`, the code behind `mcl3d slam`. ATEs are
SE(3)-aligned RMSE (`evo_ape -a`, mcl3d.evaluation.metrics) for every method. Per SLAM run
also: the cloud's consistency (scans with the truth inside its 95% region) and the
representative's loop corrections, with how many were wrong (> 2 m off the true relative
pose); for kiss-slam its accepted closures and the wrong ones. Logs are cached under
bench/results/study_slam/, and the peers' rows beside each log (`*_peers_*.json`: they do
not change with mcl3d's code, so a rerun after a SLAM change only reruns SLAM).

#20's acceptance in one command (its defaults: paper-forest and paper-elevator with and
without the IMU, seeds 1-5, 10,000 particles, presets default and paper, every peer; hours on
a 2-core cpu): `python bench/study_slam.py`. Results: bench/results/study_slam.json
(bench/results_io.py header, tables for docs/results.md, the acceptance counts as notes).

    python bench/study_slam.py [--particles 10000] [--seeds 1 2 3 4 5] [--cases paper-forest]
        [--presets default paper] [--set KEY=VALUE ...] [--peers kiss-icp kiss-slam rko-lio]
        [--duration S] [--backend cpu] [--quick] [--out FILE] [--runs FOLDER]
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
# revision: part of the cached log's name, raised whenever the scenario changes (r2: the
# hillside, porous foliage, the step's nod and the walker's quick turns).
CASES["paper-forest"] = dict(world="forest", sensor="mid360", trajectory="paper-forest",
                             duration_s=None, overrides={}, revision="r2",
                             slam={"front_end.fov_deg": 180.0, "odometry.use_imu": False,
                                   "keyframes.capacity": 512})
CASES["paper-elevator"] = dict(world="building", sensor="mid360", trajectory="paper-elevator",
                               duration_s=None, overrides={}, slam={})
CASES["paper-elevator, no IMU"] = dict(CASES["paper-elevator"],
                                       slam={"odometry.use_imu": False})
ACCEPTANCE = ("paper-forest", "paper-elevator, no IMU", "paper-elevator")
RIGHT_FLOOR_M = 1.0  # a final height error under this is the right floor (3.5 m apart)
PEERS = ("kiss-icp", "kiss-slam", "rko-lio")
WRONG_CLOSURE_M = 2.0  # as mcl3d.slam.slam_summary.WRONG_LOOP_M


def simulate(case: dict, seed: int, duration_s: float | None = None) -> Path:
    """The case's log for `seed` (cached), cut to `duration_s` when given."""
    from mcl3d.sim.pipeline import SimulateRequest, run

    folder = RESULTS / "study_slam"
    folder.mkdir(parents=True, exist_ok=True)
    revision = f"-{case['revision']}" if "revision" in case else ""
    cut = "" if duration_s is None else f"_{duration_s:g}s"
    log = folder / f"{case['world']}_{case['trajectory']}{revision}{cut}_{seed}.mcap"
    if not log.exists():
        run(SimulateRequest(world=case["world"], sensor=case["sensor"],
                            trajectory=case["trajectory"],
                            duration_s=duration_s or case["duration_s"],
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
    kiss-slam the closures it kept and how many were wrong. Rows are cached beside the log
    (they do not depend on mcl3d's code): a rerun of the study after a SLAM change reuses them."""
    cache = log.with_name(f"{log.stem}_peers_fov{fov_deg:g}_range{max_range_m:g}.json")
    done = json.loads(cache.read_text()) if cache.exists() else {}
    todo = [name for name in names if name not in done]
    if todo:
        done.update(_run_peers(todo, log, fov_deg, max_range_m))
        cache.write_text(json.dumps({k: v for k, v in done.items() if "error" not in v},
                                    indent=2))  # a failure is retried next time
    return {name: done[name] for name in names}


def _run_peers(names: list[str], log: Path, fov_deg: float, max_range_m: float) -> dict:
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
    row = {"case": name, "seed": seed, "preset": None, "scans": s.scans, "path_m": s.path_length_m,
           "keyframes": s.keyframes, "ate_odometry_m": ev.odometry.ate_m,
           "ate_slam_m": ev.slam.ate_m, "ate_online_m": ev.online.ate_m,
           "ms_per_frame": s.ms_per_frame.median, "seconds": seconds,
           "loop_frames": s.loop_frames,
           "consistency_95": None if s.consistency is None else s.consistency.fraction,
           "loops_accepted": None if s.loop_check is None else s.loop_check.accepted,
           "loops_wrong": None if s.loop_check is None else s.loop_check.wrong,
           "loops_misplaced": None if s.loop_check is None else s.loop_check.misplaced}
    if case["trajectory"] in ("elevator", "paper-elevator"):
        row["floor_error_m"] = floor_error_m(out, log)
        row["right_floor"] = row["floor_error_m"] < RIGHT_FLOOR_M
    return row


def parse_sets(items: list[str]) -> dict:
    """KEY=VALUE pairs (dotted keys, YAML values) for the SLAM config."""
    return {k: yaml.safe_load(v) for k, v in (item.split("=", 1) for item in items)}


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=10_000)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--cases", nargs="+", default=list(ACCEPTANCE), choices=list(CASES))
    ap.add_argument("--presets", nargs="+", default=["default", "paper"],
                    help="SLAM presets (mcl3d.slam.presets), each run on every case and seed")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="SLAM config overrides, e.g. prediction_noise.odometry_scale=1")
    ap.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS)
    ap.add_argument("--peer-threads", type=int, default=0, help="threads per peer (0: all)")
    ap.add_argument("--duration", type=float, default=None,
                    help="cut every route to this many seconds (default: each case's own)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: paper-forest seed 1 cut to 20 s, 500 particles, default "
                         "preset, kiss-icp only")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--out", type=Path, default=None,
                    help="results JSON (default bench/results/study_slam[_quick].json)")
    ap.add_argument("--runs", type=Path, default=RESULTS / "study_slam",
                    help="folder for each run's outputs (the logs stay cached in "
                         "bench/results/study_slam/)")
    args = ap.parse_args()
    if args.quick:
        args.seeds, args.cases, args.presets = [1], ["paper-forest"], ["default"]
        args.particles, args.peers, args.duration = 500, ["kiss-icp"], args.duration or 20.0
    return args


def main() -> None:
    from results_io import Run

    from mcl3d.core import config as config_io
    from mcl3d.core import runtime
    from mcl3d.slam.pipeline import SlamRequest, run
    from mcl3d.slam.presets import preset
    from mcl3d.slam.slam_config import SlamConfig

    args = parse_args()
    bench = Run("study_slam_quick" if args.quick else "study_slam", baselines=PEERS)
    info = runtime.init(args.backend)
    import slam_peers

    slam_peers.THREADS = args.peer_threads
    rows, peers = [], {}
    for name in args.cases:
        case = CASES[name]
        for seed in args.seeds:
            log = simulate(case, seed, args.duration)
            for preset_name in args.presets:
                out = args.runs / (f"{name.replace(', ', '_').replace(' ', '_')}_{seed}"
                                   f"_{preset_name}")
                cfg = config_io.load(SlamConfig, None, {"particles": args.particles,
                                                        "seed": seed, **case["slam"],
                                                        **parse_sets(args.set)},
                                     preset=preset(preset_name))
                t0 = time.perf_counter()
                s = run(SlamRequest(log=log, output_dir=out, config=cfg, force=True)).summary
                row = slam_row(name, case, seed, log, out, s, time.perf_counter() - t0)
                row["preset"] = preset_name
                print(json.dumps(row), flush=True)
                if args.peers and "elevator" not in case["trajectory"]:
                    if (name, seed) not in peers:  # the peers do not depend on the preset
                        peers[name, seed] = peer_rows(args.peers, log, cfg.front_end.fov_deg,
                                                      cfg.odometry.max_range_m)
                    row["peers"] = peers[name, seed]
                rows.append(row)
                figures = {"backend": info.backend, "device": info.device,
                           "particles": args.particles, "presets": args.presets,
                           "set": args.set, "duration_s": args.duration, "rows": rows,
                           "tables": tables(rows, args.particles),
                           "notes": acceptance_notes(rows)}
                path = bench.write(figures, args.out)
    print_tables(figures["tables"], figures["notes"])
    print(f"\nwrote {path}")


def _ate(r: dict, peer: str):
    p = r.get("peers", {}).get(peer)
    return None if p is None else ("failed" if "error" in p else round(p["ate_m"], 3))


def _pct(x: float | None):
    return None if x is None else round(100 * x, 1)


def forest_table_row(r: dict) -> dict:
    ks = r.get("peers", {}).get("kiss-slam", {})
    loops = None if r["loops_accepted"] is None else f"{r['loops_accepted']} ({r['loops_wrong']})"
    return {"seed": r["seed"], "preset": r["preset"], "path (m)": round(r["path_m"]),
            "mcl3d odometry": round(r["ate_odometry_m"], 3),
            "kiss-icp": _ate(r, "kiss-icp"), "mcl3d slam": round(r["ate_slam_m"], 3),
            "slam / odometry": round(r["ate_slam_m"] / r["ate_odometry_m"], 2),
            "slam online": round(r["ate_online_m"], 3), "kiss-slam": _ate(r, "kiss-slam"),
            "rko-lio (IMU)": _ate(r, "rko-lio"),
            "consistency (%)": _pct(r["consistency_95"]), "loops (wrong)": loops,
            "kiss-slam closures (wrong)": (f"{ks['closures']} ({ks['wrong_closures']})"
                                           if "closures" in ks else None),
            "ms/frame": round(r["ms_per_frame"])}


def elevator_table_row(r: dict) -> dict:
    return {"seed": r["seed"], "preset": r["preset"],
            "final height error (m)": round(r["floor_error_m"], 2),
            "right floor": "yes" if r["right_floor"] else "no",
            "ATE slam (m)": round(r["ate_slam_m"], 3),
            "ATE odometry (m)": round(r["ate_odometry_m"], 3),
            "consistency (%)": _pct(r["consistency_95"]), "ms/frame": round(r["ms_per_frame"])}


def tables(rows: list[dict], particles: int) -> dict:
    """One table per case for docs/results.md: ATEs beside the peers, or the final floor."""
    out: dict[str, list[dict]] = {}
    for r in rows:
        if "floor_error_m" in r:
            caption = f"{r['case']}: final floor ({particles:,} particles)"
            out.setdefault(caption, []).append(elevator_table_row(r))
        else:
            caption = f"{r['case']}: ATE (m), SE(3)-aligned ({particles:,} particles)"
            out.setdefault(caption, []).append(forest_table_row(r))
    return out


def acceptance_notes(rows: list[dict]) -> list[str]:
    """#20's acceptance counted per case and preset over the seeds run."""
    notes = []
    for case, preset_name in dict.fromkeys((r["case"], r["preset"]) for r in rows):
        group = [r for r in rows if r["case"] == case and r["preset"] == preset_name]
        n, seeds = len(group), ",".join(str(r["seed"]) for r in group)
        head = f"{case}, preset {preset_name}, seeds {seeds}:"
        if "floor_error_m" in group[0]:
            right = sum(r["right_floor"] for r in group)
            notes.append(f"{head} right floor in {right} of {n}.")
            continue
        half = sum(r["ate_slam_m"] <= 0.5 * r["ate_odometry_m"] for r in group)
        ks = [(r["ate_slam_m"], _ate(r, "kiss-slam")) for r in group]
        beat = sum(isinstance(k, float) and a <= k for a, k in ks)
        wrong = sum(r["loops_wrong"] or 0 for r in group)
        accepted = sum(r["loops_accepted"] or 0 for r in group)
        cons = [r["consistency_95"] for r in group if r["consistency_95"] is not None]
        mean_cons = f"{100 * np.mean(cons):.1f}%" if cons else "n/a"
        notes.append(f"{head} SLAM ATE <= 0.5x odometry in {half} of {n}; <= kiss-slam in "
                     f"{beat} of {n}; loop corrections {accepted}, wrong {wrong}; "
                     f"consistency (truth in the cloud's 95% region) {mean_cons} on average.")
    return notes


def print_tables(tabs: dict, notes: list[str]) -> None:
    for caption, table in tabs.items():
        cols = list(table[0])
        print(f"\n{caption}\n| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
        for row in table:
            print("| " + " | ".join("" if row[c] is None else str(row[c]) for c in cols) + " |")
    for note in notes:
        print(f"- {note}")


if __name__ == "__main__":
    main()
