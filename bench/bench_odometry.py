"""Odometry accuracy and speed on simulated logs: mcl3d against KISS-ICP, GenZ-ICP, small_gicp
(LiDAR only) and rko-lio (LiDAR-inertial), the same scans and IMU samples for every method.

Logs are simulated in the run, one per world and seed (`--seeds`: the simulator's seeds):
an office loop (VLP-16), a warehouse drive (OS1-64) and a forest drive (MID-360) cropped to
the 180 deg in front of the sensor as `bench/study_slam.py`'s forest case crops it. Scans
come through `slam_peers.scans` (mcl3d's log reader and scan/IMU pairing, the 0.5-100 m
crop); `bench/odometry_peers.py` drives the methods and states how each deskews (every one
with per-point times and its own motion estimate) and where its poses are stamped.

Every method steps frame i before any steps frame i + 1, in an order that rotates with the
frame, each with `--threads` threads. Per frame: wall and process-cpu ms of the whole step
(preprocessing and deskew included; the first two frames of a log excluded: mcl3d compiles
its kernels there). Reported per log and seed and as the mean over seeds: ATE RMSE after
aligning the first pose, RPE per metre (translation, rotation), end-point drift, median
ms/frame (wall, cpu) and the median per-frame ratio of each method's wall time to KISS-ICP's
on the same frame. The peers are dev-only dependencies: `pip install -e '.[bench]'`.

    python bench/bench_odometry.py [--seeds 1 2 3 4] [--logs office warehouse forest-180]
        [--duration 20] [--threads 2] [--backend cpu] [--quick]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

LOGS = {
    "office": dict(world="office", sensor="vlp16", trajectory="loop", overrides={}, fov=360.0),
    "warehouse": dict(world="warehouse", sensor="os1-64", trajectory="ground", overrides={},
                      fov=360.0),
    "forest-180": dict(world="forest", sensor="mid360", trajectory="ground", fov=180.0,
                       overrides={"world.forest_rows": 6, "world.forest_trees_per_row": 10}),
}
SKIP_FRAMES = 2  # kernel compilation
BASELINE = "KISS-ICP"
PEERS = ("kiss-icp", "genz-icp", "rko-lio", "small_gicp")


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def simulate(folder: Path, name: str, seed: int, duration_s: float) -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    case = LOGS[name]
    out = folder / f"{name}_{seed}.mcap"
    run(SimulateRequest(world=case["world"], sensor=case["sensor"],
                        trajectory=case["trajectory"], duration_s=duration_s, seed=seed,
                        output=out, overrides=case["overrides"], force=True))
    return out


def read_log(log: Path, fov_deg: float):
    """Scans (stamp_ns, points, times_s, imu rows), T_lidar_imu and the ground truth."""
    import slam_peers

    from mcl3d.io.trajectory import read_tum

    scans, extrinsics = [], [np.eye(4)]
    for stamp_ns, points, times, imu, T_lidar_imu in slam_peers.scans(log, fov_deg):
        scans.append((stamp_ns, points, times, imu))
        extrinsics.append(T_lidar_imu)
    return scans, extrinsics[-1], read_tum(log.with_name(log.stem + "_gt.tum"))


def run_interleaved(methods: dict, scans, T_lidar_imu) -> dict:
    """Every method over the log, frame by frame in turn. Returns per method its trajectory
    and (frames, 2) wall/cpu ms, or the error that stopped it."""
    names = list(methods)
    ms = {name: np.full((len(scans), 2), np.nan) for name in names}
    failed: dict[str, str] = {}
    for name, method in methods.items():
        try:
            method.reset(T_lidar_imu)
        except Exception as exc:  # a peer that cannot start is reported, not fatal
            failed[name] = f"{type(exc).__name__}: {exc}"
    for i, (stamp_ns, points, times, imu) in enumerate(scans):
        shift = i % len(names)
        for name in names[shift:] + names[:shift]:
            if name in failed:
                continue
            t0, c0 = time.perf_counter(), cpu_s()
            try:
                methods[name].step(stamp_ns, points, times, imu)
            except Exception as exc:
                failed[name] = f"frame {i}: {type(exc).__name__}: {exc}"
                traceback.print_exc()
                continue
            ms[name][i] = (time.perf_counter() - t0) * 1e3, (cpu_s() - c0) * 1e3
    out = {}
    for name in names:
        if name in failed:
            out[name] = {"error": failed[name]}
            continue
        stamps, poses = methods[name].trajectory()
        out[name] = {"stamps_ns": stamps, "poses": poses, "ms": ms[name]}
    return out


def score(stamps_ns, poses, gt) -> dict:
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.trajectory import Trajectory

    inside = (stamps_ns * 1e-9 >= gt.stamps_s[0]) & (stamps_ns * 1e-9 <= gt.stamps_s[-1])
    stamps = stamps_ns[inside] * 1e-9
    ref = Trajectory(stamps, gt.interpolate_poses(stamps))
    est = Trajectory(stamps, poses[inside])
    ev = evaluate(ref, est, alignment="origin", rpe_delta=1.0, rpe_unit="m")
    length = ref.path_length_m()
    end = np.linalg.norm(ev.association.ref_poses[-1, :3, 3] - ev.est_aligned_poses[-1, :3, 3])
    return {"ate_cm": 100 * ev.ate.translation_m.rmse,
            "rpe_cm_per_m": 100 * ev.rpe.translation_m.mean,
            "rpe_deg_per_m": ev.rpe.rotation_deg.mean, "drift_percent": 100 * end / length,
            "path_m": length, "poses": int(inside.sum())}


def log_rows(log: str, seed: int, out: dict, gt, frames: int) -> list[dict]:
    """One row per method for this log and seed (its per-frame times kept for the means)."""
    base = out.get(BASELINE, {}).get("ms")
    rows = []
    for name, res in out.items():
        row = {"log": log, "seed": seed, "method": name, "frames": frames}
        if "error" in res:
            rows.append({**row, "error": res["error"]})
            continue
        ms = res["ms"][SKIP_FRAMES:]
        row.update(score(res["stamps_ns"], res["poses"], gt))
        row.update(wall_ms=float(np.nanmedian(ms[:, 0])), cpu_ms=float(np.nanmedian(ms[:, 1])),
                   wall_ms_p90=float(np.nanpercentile(ms[:, 0], 90)), frame_ms=ms)
        if base is not None:
            row["x_kiss"] = float(np.nanmedian(ms[:, 0] / base[SKIP_FRAMES:, 0]))
        rows.append(row)
    return rows


def _r(value, digits: int):
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def tables(rows: list[dict], inputs: dict) -> dict:
    """The per-seed table and the mean over seeds (times: median over every frame of every
    seed; ratio: median over frames of the per-frame ratio to KISS-ICP)."""
    per_seed = [{"log": r["log"], "seed": r["seed"], "method": r["method"],
                 "ATE cm": _r(r.get("ate_cm"), 1), "RPE cm/m": _r(r.get("rpe_cm_per_m"), 2),
                 "RPE deg/m": _r(r.get("rpe_deg_per_m"), 3),
                 "drift %": _r(r.get("drift_percent"), 2),
                 "wall ms/frame": _r(r.get("wall_ms"), 1), "cpu ms/frame": _r(r.get("cpu_ms"), 1),
                 "x KISS-ICP wall": _r(r.get("x_kiss"), 2)} for r in rows]
    means = []
    for log in dict.fromkeys(r["log"] for r in rows):
        for method in dict.fromkeys(r["method"] for r in rows if r["log"] == log):
            mine = [r for r in rows if r["log"] == log and r["method"] == method]
            ok = [r for r in mine if "error" not in r]
            row = {"log": log, "method": method, "input": inputs.get(method, ""),
                   "seeds": f"{len(ok)}/{len(mine)}"}
            if ok:
                frames = np.concatenate([r["frame_ms"] for r in ok])
                row.update({
                    "ATE cm": _r(np.mean([r["ate_cm"] for r in ok]), 1),
                    "ATE cm per seed": " / ".join(f"{r['ate_cm']:.1f}" for r in ok),
                    "RPE cm/m": _r(np.mean([r["rpe_cm_per_m"] for r in ok]), 2),
                    "RPE deg/m": _r(np.mean([r["rpe_deg_per_m"] for r in ok]), 3),
                    "wall ms/frame": _r(np.nanmedian(frames[:, 0]), 1),
                    "cpu ms/frame": _r(np.nanmedian(frames[:, 1]), 1),
                    "x KISS-ICP wall": _r(np.median([r["x_kiss"] for r in ok if "x_kiss" in r])
                                          if any("x_kiss" in r for r in ok) else None, 2)})
            means.append(row)
    keys = list(dict.fromkeys(k for row in means for k in row))
    means = [{k: row.get(k) for k in keys} for row in means]
    return {"Odometry, mean over seeds (ATE, RPE) and median over frames (times)": means,
            "Odometry, every seed": per_seed}


def print_table(caption: str, rows: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=caption)
    for key in rows[0]:
        table.add_column(key, justify="left" if key in ("log", "method", "input") else "right")
    for row in rows:
        table.add_row(*("" if v is None else str(v) for v in row.values()))
    Console(width=200).print(table)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4],
                        help="simulator seeds: one log per world and seed")
    parser.add_argument("--logs", nargs="+", default=list(LOGS), choices=list(LOGS))
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per log")
    parser.add_argument("--threads", type=int, default=2,
                        help="threads of every method (Taichi's cpu backend and the peers)")
    parser.add_argument("--quick", action="store_true",
                        help="one seed, the office log, 12 s: a smoke run")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.logs, args.duration = args.seeds[:1], ["office"], 12.0

    # same thread count everywhere; OpenMP threads sleep instead of spinning while they wait
    os.environ["TI_CPU_MAX_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from odometry_peers import INPUTS, methods
    from results_io import Run

    from mcl3d.core import runtime

    run = Run("bench_odometry", baselines=PEERS)
    info = runtime.init(args.backend)
    everyone = methods(args.threads)
    rows, loads = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.logs:
            for seed in args.seeds:
                log = simulate(Path(tmp), name, seed, args.duration)
                scans, T_lidar_imu, gt = read_log(log, LOGS[name]["fov"])
                log.unlink()
                out = run_interleaved(everyone, scans, T_lidar_imu)
                loads.append(round(os.getloadavg()[0], 2))
                for row in log_rows(name, seed, out, gt, len(scans)):
                    rows.append(row)
                    print(f"{name:10s} seed {seed} {row['method']:20s} "
                          + (f"ATE {row['ate_cm']:6.1f} cm  {row['wall_ms']:6.1f} ms/frame"
                             if "error" not in row else f"FAILED {row['error']}"), flush=True)
    figures = {"tables": tables(rows, INPUTS),
               "notes": notes(args, info, loads, rows),
               "settings": {"seeds": args.seeds, "logs": args.logs, "duration_s": args.duration,
                            "threads": args.threads, "skip_frames": SKIP_FRAMES,
                            "backend": info.backend, "device": info.device},
               "rows": [{k: v for k, v in r.items() if k != "frame_ms"} for r in rows]}
    for caption, table in figures["tables"].items():
        print_table(caption, table)
    print(f"wrote {run.write(figures, args.out)}")


def notes(args, info, loads: list[float], rows: list[dict]) -> list[str]:
    out = [f"{len(args.seeds)} seeds ({', '.join(map(str, args.seeds))}) x {len(args.logs)} "
           f"simulated logs of {args.duration:.0f} s at 10 Hz; {info.backend} backend, "
           f"{args.threads} threads per method, methods interleaved frame by frame; load "
           f"average after each log {min(loads):.1f}-{max(loads):.1f}.",
           "Same inputs: every method gets the same scans (0.5-100 m), per-point times and "
           "deskews with its own motion (mcl3d: IMU or constant velocity; KISS-ICP, GenZ-ICP: "
           "constant velocity; small_gicp: mcl3d's deskew kernel with its own last motion; "
           "rko-lio: IMU); every pose is scored at the scans' header stamps.",
           "ATE: RMSE after aligning the first pose; RPE over 1 m; times: the whole step "
           "(deskew, preprocessing, registration, map update), first 2 frames excluded; "
           "x KISS-ICP: median over frames of the wall-time ratio to KISS-ICP on the same frame."]
    out += [f"{r['method']} failed on {r['log']} seed {r['seed']}: {r['error']}"
            for r in rows if "error" in r]
    return out


if __name__ == "__main__":
    main()
