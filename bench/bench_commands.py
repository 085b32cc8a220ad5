"""Whole commands at real time on 2 cpu cores (issue #21, item 3): what a user waits for.

On simulated 10 Hz logs (`mcl3d simulate`, office and warehouse worlds, seed 1) the commands
run as a user runs them, each a child process `python -m mcl3d ...` with 2 cpu threads, timed
whole (start to exit: imports, Taichi start, kernel compilation, log decoding, outputs):

  - `build-map LOG` (the log's scans placed by its ground truth): target >= 2x real time;
  - `localize` with 100,000 particles x 256 points, global (`--init global`) and tracking
    (`--init gt`): target <= 100 ms per update (mean over the warm updates, scans.csv);
  - `odometry`: target <= KISS-ICP's time per frame with a lower ATE. KISS-ICP runs on the
    same decoded scans in this process, interleaved frame by frame with mcl3d's odometry,
    through bench/bench_odometry.py's drivers (same thread count);
  - `slam` with 10,000 particles: target <= 150 ms per frame, the whole step (frames.csv).

Stage breakdowns come from what the commands write per scan (localize: scans.csv, slam:
frames.csv); build-map and odometry write no per-scan stages, so they are also run in this
process through their pipeline / algorithm object with timers around their stages. What the
command spends outside its per-scan steps (start, decoding, outputs) is the whole wall time
less the sum of the steps. The start alone (imports and `runtime.init`) is measured once.

    python bench/bench_commands.py [--quick] [--backend cpu] [--worlds office warehouse]
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from results_io import RESULTS, Run, commit

SKIP_SCANS = 2  # the first updates compile kernels: "warm" excludes them
LOC_STAGES = ("motion", "likelihood", "weights", "estimate", "resample", "recovery")
TARGETS = {"build-map": "≥ 2× real time", "localize": "≤ 100 ms per update",
           "odometry": "≤ KISS-ICP ms/frame, lower ATE", "slam": "≤ 150 ms per frame"}


def peak_rss_mib(pid: int, done: threading.Event, peak: list[float]) -> None:
    """Polls the child's VmHWM (its own peak since exec: wait4's ru_maxrss would count the
    parent's memory the child held between fork and exec)."""
    status = Path(f"/proc/{pid}/status")
    while not done.wait(0.2):
        try:
            text = status.read_text()
        except OSError:
            return
        kib = [int(line.split()[1]) for line in text.splitlines() if line.startswith("VmHWM")]
        if kib:
            peak[0] = max(peak[0], kib[0] / 1024)


def run_command(args: list[str], log: Path, env: dict) -> dict:
    """One child process, timed whole: wall s, cpu s (user + system) and peak RSS."""
    t0 = time.perf_counter()
    done, peak = threading.Event(), [0.0]
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "mcl3d", *args], stdout=out,
                                stderr=subprocess.STDOUT, env=env)
        watcher = threading.Thread(target=peak_rss_mib, args=(proc.pid, done, peak))
        watcher.start()
        _, status, usage = os.wait4(proc.pid, 0)
        done.set()
        watcher.join()
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        raise RuntimeError(f"mcl3d {args[0]} exited {proc.returncode}: "
                           f"{lines[-1].strip() if lines else 'no output'} ({log})")
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
            "peak_rss_mib": peak[0]}


def startup_s(env: dict, backend: str) -> float:
    """Imports of a command and the Taichi start: paid once by every command."""
    code = ("import time; t=time.perf_counter(); import mcl3d.cli, taichi, open3d; "
            f"from mcl3d.core import runtime; runtime.init({backend!r}); "
            "print(time.perf_counter()-t)")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)
    return time.perf_counter() - t0


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    cols = {}
    for key in rows[0]:
        try:
            cols[key] = np.array([float(r[key]) for r in rows])
        except ValueError:
            cols[key] = np.array([r[key] for r in rows])
    return cols


def stage_rows(command: str, per_scan: dict[str, np.ndarray], whole: dict, n_scans: int,
               start_s: float, warm: np.ndarray | None = None) -> list[dict]:
    """Mean warm ms per scan of each stage (`warm`: a mask of the scans to average, default
    all but the first SKIP_SCANS), the step's total, and what the command spent outside its
    steps (start, decoding, outputs), amortized per scan."""
    warm = np.arange(n_scans) >= SKIP_SCANS if warm is None else warm
    rows = [{"command": command, "stage": name, "ms per scan": round(float(v[warm].mean()), 1)}
            for name, v in per_scan.items()]
    total_ms = sum(v for v in per_scan.values())
    rows.append({"command": command, "stage": "= the step (warm mean)",
                 "ms per scan": round(float(total_ms[warm].mean()), 1)})
    outside = (whole["wall_s"] - total_ms.sum() / 1e3) / n_scans * 1e3
    rows.append({"command": command, "stage": f"outside the steps (of it start {start_s:.1f} s)",
                 "ms per scan": round(outside, 1)})
    return rows


# ---------------------------------------------------------------- the log and the map
def simulate(folder: Path, world: str, label: str, sensor: str, duration_s: float,
             env: dict) -> Path:
    log = folder / f"{label}.mcap"
    run_command(["simulate", world, "-o", str(log), "--sensor", sensor, "--duration",
                 f"{duration_s:g}", "--seed", "1", "--force"], folder / f"{label}_simulate.txt",
                env)
    return log


NORMALS = "normals (on the device: range image, or voxel neighbours without rings)"
PASS_1 = "pass 1: poses, decoding, bounds"


def build_map_stages(log: Path, out: Path) -> tuple[dict[str, float], int, float]:
    """`build-map` in this process with timers around its stages: ms per scan of each, the
    scans, and the build's seconds (without imports and start)."""
    import taichi as ti

    from mcl3d.mapping import pipeline
    from mcl3d.maps import build

    spent = {PASS_1: 0.0, NORMALS: 0.0,
             "host preparation": 0.0, "allocate kernel": 0.0, "band + carving kernel": 0.0,
             "write the map": 0.0}

    def timed(fn, key, sync=False):
        @functools.wraps(fn)
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            value = fn(*a, **k)
            if sync:
                ti.sync()
            spent[key] += time.perf_counter() - t0
            return value
        return wrapper

    patches = [(pipeline, "_poses_and_scans", PASS_1, False),
               (pipeline, "_write", "write the map", False),
               (build.ScanFuser, "normals", NORMALS, True),
               (build.ScanFuser, "prepare", "host preparation", False),
               (build.ScanFuser, "allocate", "allocate kernel", True),
               (build.ScanFuser, "update", "band + carving kernel", True)]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _, _ in patches]
    for owner, name, key, sync in patches:
        setattr(owner, name, timed(getattr(owner, name), key, sync))
    try:
        t0 = time.perf_counter()
        result = pipeline.run(pipeline.BuildMapRequest(source=log, output=out, force=True))
        seconds = time.perf_counter() - t0
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)
    spent["host preparation"] -= spent[NORMALS]  # normals run inside prepare
    fuse = spent["host preparation"] + spent[NORMALS] + spent["allocate kernel"] \
        + spent["band + carving kernel"]
    spent["the rest: poses, new map, kernel preparation, finalize"] = (
        seconds - fuse - spent["write the map"] - spent[PASS_1])
    n = result.n_scans
    return {k: v / n * 1e3 for k, v in spent.items()}, n, seconds


def bench_build_map(folder, world, log, duration_s, env, backend, start_s):
    tsdf = folder / f"{world}.tsdf"
    # in process first: its kernels fill Taichi's offline cache, so the command is timed as
    # a user's second run is (a first run after a kernel changed compiles for tens of s)
    stages, n_scans, seconds = build_map_stages(log, folder / f"{world}_inproc.tsdf")
    whole = run_command(["build-map", str(log), "-o", str(tsdf), "--backend", backend,
                         "--force"], folder / f"{world}_build_map.txt", env)
    # and with an empty kernel cache: what a new machine's first run pays (a map of another
    # size or origin reuses the compiled fusion kernels; another voxel size compiles them)
    cold = run_command(["build-map", str(log), "-o", str(tsdf), "--backend", backend,
                        "--force"], folder / f"{world}_build_map_cold.txt",
                       {**env, "TI_OFFLINE_CACHE_FILE_PATH": str(
                           Path(tempfile.mkdtemp(prefix="kernels_", dir=folder)))})
    factor = duration_s / whole["wall_s"]
    row = {"command": "build-map", "world": world, "scans": n_scans,
           "whole command s": round(whole["wall_s"], 1),
           "empty kernel cache s": round(cold["wall_s"], 1),
           "per scan ms": round(whole["wall_s"] / n_scans * 1e3, 1),
           "measured": f"{factor:.2f}× real time", "target": TARGETS["build-map"],
           "pass": "pass" if factor >= 2 else "FAIL"}
    rows = [{"command": f"build-map ({world})", "stage": k, "ms per scan": round(v, 1)}
            for k, v in stages.items()]
    rows.append({"command": f"build-map ({world})", "stage": "= the build in process",
                 "ms per scan": round(seconds / n_scans * 1e3, 1)})
    rows.append({"command": f"build-map ({world})", "stage": "= the whole command (start "
                 f"{start_s:.1f} s; kernels compiled by the run in process)",
                 "ms per scan": round(whole["wall_s"] / n_scans * 1e3, 1)})
    rows.append({"command": f"build-map ({world})", "stage": "= the whole command, empty "
                 "kernel cache (a new machine, or another voxel size)",
                 "ms per scan": round(cold["wall_s"] / n_scans * 1e3, 1)})
    return tsdf, row, rows, {"whole": whole, "cold": cold, "in_process_s": seconds}


def bench_localize(folder, world, log, tsdf, init, args, env, start_s):
    out = folder / f"{world}_localize_{init}"
    whole = run_command(["localize", str(log), "--map", str(tsdf), "-o", str(out), "--init",
                         init, "--particles", str(args.particles), "--points",
                         str(args.points), "--seed", str(args.seed), "--backend", args.backend,
                         "--force"], folder / f"{world}_localize_{init}.txt", env)
    scans = read_csv(out / "scans.csv")
    per_scan = {s: scans[f"ms_{s}"] for s in LOC_STAGES}
    total = scans["ms_total"]
    n = len(total)
    warm = localize_warm(n, init)
    searching = warm & (scans["state"] != "converged")
    mean = float(total[warm].mean())
    judged = float(total[searching].mean()) if init == "global" and searching.any() else mean
    name = f"localize {'global' if init == 'global' else 'tracking'}"
    measured = f"{mean:.0f} ms per update" + (
        f"; {judged:.0f} while searching ({int(searching.sum())} updates)"
        if init == "global" else "")
    row = {"command": name, "world": world, "scans": n,
           "whole command s": round(whole["wall_s"], 1),
           "per scan ms": round(whole["wall_s"] / n * 1e3, 1),
           "measured": measured, "target": TARGETS["localize"],
           "pass": "pass" if max(mean, judged) <= 100 else "FAIL"}
    summary = json.loads((out / "summary.json").read_text())
    extra = {"whole": whole, "ms_update_mean": mean, "ms_update_searching_mean": judged,
             "ms_update_p50": float(np.median(total[warm])),
             "ms_update_p90": float(np.percentile(total[warm], 90)),
             "converged_fraction": summary.get("converged_fraction"),
             "ate_all": summary.get("ate_all")}
    return row, stage_rows(f"{name} ({world})", per_scan, whole, n, start_s, warm), extra


def localize_warm(n_scans: int, init: str) -> np.ndarray:
    """The updates that compile no kernel: not the first SKIP_SCANS, and in a global search
    not the first SKIP_SCANS of the accurate model after the coarse phase either (each
    compiles that model's kernels for one of the two particle buffers)."""
    from mcl3d.localization.localization_config import LocalizerConfig

    warm = np.arange(n_scans) >= SKIP_SCANS
    if init == "global":
        coarse = LocalizerConfig().sensor.coarse_scans
        warm[coarse:coarse + SKIP_SCANS] = False
    return warm


# ------------------------------------------------------------------------- odometry
def ate_m(stamps_ns: np.ndarray, poses: np.ndarray, gt) -> float:
    """ATE RMSE after aligning the first pose, as bench_odometry scores (no RPE: a quick log
    may travel under a metre)."""
    from mcl3d.evaluation.metrics import evaluate
    from mcl3d.io.trajectory import Trajectory

    stamps = stamps_ns * 1e-9
    inside = (stamps >= gt.stamps_s[0]) & (stamps <= gt.stamps_s[-1])
    ref = Trajectory(stamps[inside], gt.interpolate_poses(stamps[inside]))
    est = Trajectory(stamps[inside], poses[inside])
    return float(evaluate(ref, est, alignment="origin", rpe_delta=1,
                          rpe_unit="frames").ate.translation_m.rmse)


def frame_times(ms: np.ndarray) -> dict:
    """(passes, frames, wall/cpu) ms: the median over frames of each frame's median over the
    passes, the first frames (kernel compilation) left out."""
    per_frame = np.median(ms[:, SKIP_SCANS:], axis=0)
    return {"ms_per_frame": float(np.median(per_frame[:, 0])),
            "ms_p90": float(np.percentile(per_frame[:, 0], 90)),
            "cpu_ms_per_frame": float(np.median(per_frame[:, 1]))}


class StageTimer:
    """Wraps methods of one object and sums their wall ms per call of `step`."""

    def __init__(self, obj, names: tuple[str, ...]):
        self.ms = {name: [] for name in names}
        for name in names:
            setattr(obj, name, self._timed(getattr(obj, name), name))

    def _timed(self, fn, name):
        @functools.wraps(fn)
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            value = fn(*a, **k)
            self.ms[name].append((time.perf_counter() - t0) * 1e3)
            return value
        return wrapper


def bench_odometry(folder, world, log, args, env, start_s):
    import bench_odometry as peers
    import odometry_peers

    out = folder / f"{world}_odometry"
    whole = run_command(["odometry", str(log), "-o", str(out), "--backend", args.backend,
                         "--force"], folder / f"{world}_odometry.txt", env)
    summary = json.loads((out / "odometry_summary.json").read_text())
    scans, T_lidar_imu, gt = peers.read_log(log, 360.0)
    ours_method = odometry_peers.Mcl3dOdometry(True)
    timer = StageTimer(ours_method.odo, ("_predict", "_preprocess", "_register",
                                         "_insert_if_due", "_update_velocity"))
    methods = {"mcl3d": ours_method, "KISS-ICP": odometry_peers.KissIcp(args.threads)}
    passes = [peers.run_interleaved(methods, scans, T_lidar_imu) for _ in range(args.repeats)]
    for name, res in passes[0].items():
        if "error" in res:
            raise RuntimeError(f"{name} failed on {log}: {res['error']}")
    times = {name: frame_times(np.stack([p[name]["ms"] for p in passes]))
             for name in methods}
    ate = {name: ate_m(res["stamps_ns"], res["poses"], gt) for name, res in passes[0].items()}
    ours, kiss = times["mcl3d"]["ms_per_frame"], times["KISS-ICP"]["ms_per_frame"]
    n = summary["scans"]
    ok = ours <= kiss and ate["mcl3d"] < ate["KISS-ICP"]
    row = {"command": "odometry", "world": world, "scans": n,
           "whole command s": round(whole["wall_s"], 1),
           "per scan ms": round(whole["wall_s"] / n * 1e3, 1),
           "measured": f"{ours:.1f} vs KISS-ICP {kiss:.1f} ms/frame; ATE "
                       f"{100 * ate['mcl3d']:.1f} vs {100 * ate['KISS-ICP']:.1f} cm",
           "target": TARGETS["odometry"], "pass": "pass" if ok else "FAIL"}
    label = f"odometry ({world}, in process)"
    rows = [{"command": label, "stage": name.strip("_"),
             "ms per scan": round(float(np.median(v)), 2)} for name, v in timer.ms.items()]
    rows += [{"command": label, "stage": f"= the step, median (cpu {t['cpu_ms_per_frame']:.1f})"
              if name == "mcl3d" else f"KISS-ICP register_frame, median "
              f"(cpu {t['cpu_ms_per_frame']:.1f})", "ms per scan": round(t["ms_per_frame"], 2)}
             for name, t in times.items()]
    step_ms = summary["ms_per_frame"]["mean"]
    rows.append({"command": f"odometry ({world}, command)",
                 "stage": f"step mean incl. compile; outside the steps (start {start_s:.1f} s)",
                 "ms per scan": f"{step_ms:.1f}; "
                                f"{(whole['wall_s'] * 1e3 - step_ms * n) / n:.1f}"})
    extra = {"whole": whole, "timing": times, "ate_rmse_m": ate,
             "command_ms_per_frame": summary["ms_per_frame"]}
    return row, rows, extra


def bench_slam(folder, world, log, args, env, start_s):
    out = folder / f"{world}_slam"
    whole = run_command(["slam", str(log), "-o", str(out), "--particles",
                         str(args.slam_particles), "--seed", str(args.seed), "--backend",
                         args.backend, "--force"], folder / f"{world}_slam.txt", env)
    frames = read_csv(out / "frames.csv")
    per_scan = {k[:-3]: v for k, v in frames.items() if k.endswith("_ms")}
    total = sum(per_scan.values())
    n = len(total)
    warm = float(total[SKIP_SCANS:].mean())
    row = {"command": f"slam {args.slam_particles:,} particles", "world": world, "scans": n,
           "whole command s": round(whole["wall_s"], 1),
           "per scan ms": round(whole["wall_s"] / n * 1e3, 1),
           "measured": f"{warm:.0f} ms per frame", "target": TARGETS["slam"],
           "pass": "pass" if warm <= 150 else "FAIL"}
    summary = json.loads((out / "slam_summary.json").read_text())
    extra = {"whole": whole, "ms_frame_mean": warm, "particles": args.slam_particles,
             "ms_frame_p50": float(np.median(total[SKIP_SCANS:])),
             "ms_frame_p90": float(np.percentile(total[SKIP_SCANS:], 90)),
             "particle_state_bytes": summary.get("particle_state_bytes")}
    return row, stage_rows(f"slam ({world})", per_scan, whole, n, start_s), extra


# ---------------------------------------------------------------------------- main
def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one 5 s office log, one pass")
    ap.add_argument("--backend", default="cpu", choices=("cpu", "cuda", "vulkan"))
    ap.add_argument("--worlds", nargs="+", default=None, help="default office warehouse")
    ap.add_argument("--duration", type=float, default=None, help="log seconds (default 60)")
    ap.add_argument("--sensor", default="vlp16", help="simulated lidar (mcl3d simulate "
                    "--sensor); other than vlp16 it names the world's rows, e.g. office-os1-64")
    ap.add_argument("--threads", type=int, default=2, help="cpu threads of every command")
    ap.add_argument("--particles", type=int, default=100_000, help="localize particles")
    ap.add_argument("--points", type=int, default=256, help="localize points per update")
    ap.add_argument("--slam-particles", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=None, help="odometry passes (default 3)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--commands", nargs="+", default=["build-map", "localize", "odometry",
                                                      "slam"])
    ap.add_argument("--keep", type=Path, help="keep the logs and outputs in this folder")
    ap.add_argument("--out", type=Path, help="JSON (default bench/results/bench_commands.json)")
    ap.add_argument("--update", action="store_true",
                    help="keep the rows of commands and worlds not rerun from the existing "
                         "JSON (their run is named in a note) and replace the rest")
    args = ap.parse_args()
    args.worlds = args.worlds or (["office"] if args.quick else ["office", "warehouse"])
    args.duration = args.duration or (5.0 if args.quick else 60.0)
    args.repeats = args.repeats or (1 if args.quick else 3)
    return args


def main() -> None:
    args = parse_args()
    run = Run("bench_commands", baselines=("kiss-icp",))
    os.environ["TI_CPU_MAX_NUM_THREADS"] = str(args.threads)
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    from mcl3d.core import runtime

    info = runtime.init(args.backend)
    start_s = startup_s(env, args.backend)
    rows, stages, raw = [], [], {}

    def add(key: str, measure, *arguments) -> None:
        """Measure one command; a failure becomes its row and the others still run."""
        try:
            row, stage_list, raw[key] = measure(*arguments)
        except Exception as exc:
            world, command = key.split("/", 1)
            rows.append({"command": command, "world": world, "measured": "failed: "
                         + (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200],
                         "pass": "error"})
            raw[key] = {"error": str(exc)[-3000:]}
            print(f"{key} failed: {exc}", flush=True)
            return
        rows.append(with_usage(row, raw[key]["whole"]))
        stages.extend(stage_list)

    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for world_name in args.worlds:
            world = world_name if args.sensor == "vlp16" else f"{world_name}-{args.sensor}"
            log = simulate(folder, world_name, world, args.sensor, args.duration, env)
            tsdf = None
            if {"build-map", "localize"} & set(args.commands):
                built = {}

                def build_map(world=world, log=log, built=built):
                    built["tsdf"], *result = bench_build_map(folder, world, log, args.duration,
                                                             env, args.backend, start_s)
                    return result
                add(f"{world}/build-map", build_map)
                tsdf = built.get("tsdf")
            if "localize" in args.commands and tsdf is not None:
                for init in ("global", "gt"):
                    add(f"{world}/localize-{init}", bench_localize, folder, world, log, tsdf,
                        init, args, env, start_s)
            if "odometry" in args.commands:
                add(f"{world}/odometry", bench_odometry, folder, world, log, args, env, start_s)
            if "slam" in args.commands:
                add(f"{world}/slam", bench_slam, folder, world, log, args, env, start_s)
    print_tables(rows, stages)
    notes = [f"{info.backend} backend ({info.device}), {args.threads} threads per command; "
             f"{args.duration:g} s simulated 10 Hz logs (seed 1; a VLP-16 unless the world "
             f"names another lidar), filter seed {args.seed}; "
             f"localize {args.particles:,} particles × {args.points} points, slam "
             f"{args.slam_particles:,} particles.",
             f"Whole command: wall time of `python -m mcl3d ...` from start to exit, {start_s:.1f}"
             " s of it the start (imports, Taichi start). Per-update and per-frame figures are "
             f"means over the warm scans (the first {SKIP_SCANS} compile kernels, and in a "
             f"global search the first {SKIP_SCANS} of the accurate model); localize global "
             "passes when its updates while searching (not yet converged) do too.",
             "Odometry: the step timed in this process, interleaved frame by frame with "
             f"KISS-ICP on the same decoded scans, median over frames of {args.repeats} "
             "pass(es); the command's own per-scan time is in its stage rows."]
    measured = (f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime(run.started))} UTC (commit "
                f"{commit()}, load {run.load_before:.2f} at its start)")
    for figures in raw.values():
        figures["measured"] = measured
    if args.update:
        rows, stages, raw, notes = kept_from_earlier(args.out or RESULTS, raw, rows, stages,
                                                     notes)
    notes += largest_stages(stages)
    path = run.write({"tables": {"Whole commands against the targets": rows,
                                 "Where the time goes, per scan": stages},
                      "notes": notes, "raw": raw, "backend": info.backend,
                      "device": info.device}, args.out)
    print(f"wrote {path}")


def kept_from_earlier(path: Path, raw: dict, rows: list[dict], stages: list[dict],
                      notes: list[str]) -> tuple[list[dict], list[dict], dict, list[str]]:
    """--update: the earlier JSON's rows, stages and raw figures of the (world, command)
    pairs not rerun, then this run's; a note names the run of each pair (kept in its raw
    figures, so a chain of updates keeps them all)."""
    path = path / "bench_commands.json" if path.is_dir() else path
    if not path.exists():
        return rows, stages, raw, notes
    earlier = json.loads(path.read_text())
    figures = earlier["figures"]
    rerun = {_unit(*key.split("/", 1)) for key in raw}
    table_rows, table_stages = figures["tables"].values()
    kept_rows = [r for r in table_rows if _unit(r["world"], r["command"]) not in rerun]
    kept_stages = [r for r in table_stages
                   if _unit(r["command"].split("(")[1].split(",")[0].rstrip(")"),
                            r["command"]) not in rerun]
    kept_raw = {k: v for k, v in figures["raw"].items() if _unit(*k.split("/", 1)) not in rerun}
    merged = {**kept_raw, **raw}
    runs: dict[str, list[str]] = {}
    for key, figures in merged.items():
        runs.setdefault(figures.get("measured", f"{earlier['date']} (commit "
                                    f"{earlier['commit']})"), []).append(key)
    note = "Measured in several runs: " + "; ".join(
        f"{', '.join(sorted(keys))} on {when}" for when, keys in sorted(runs.items())) + "."
    return kept_rows + rows, kept_stages + stages, merged, [note, *notes]


def _unit(world: str, command: str) -> tuple[str, str]:
    """(world, command name) of a row, stage row or raw key: 'localize tracking',
    'localize-gt' and 'localize global (office)' are all localize."""
    name = command.split()[0]
    return world, name if name.startswith("build-map") else name.split("-")[0]


def with_usage(row: dict, whole: dict) -> dict:
    """The row with the command's process cpu time and peak RSS after its per-scan time."""
    out = {}
    for key, value in row.items():
        out[key] = value
        if key == "per scan ms":
            out["cpu s"] = round(whole["cpu_s"], 1)
            out["peak RSS MiB"] = round(whole["peak_rss_mib"])
    return out


def largest_stages(stages: list[dict]) -> list[str]:
    """One line per command: its three costliest stages per scan (where a gap comes from)."""
    by_command: dict[str, list[tuple[float, str]]] = {}
    for row in stages:
        value = row["ms per scan"]
        if isinstance(value, (int, float)) and not row["stage"].startswith(("=", "outside",
                                                                             "KISS")):
            by_command.setdefault(row["command"], []).append((value, row["stage"]))
    return [f"{command}: " + ", ".join(f"{stage} {ms:g} ms" for ms, stage in
                                       sorted(rows, reverse=True)[:3]) + " per scan."
            for command, rows in by_command.items()]


def print_tables(rows: list[dict], stages: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(width=max(Console().width, 150))
    for title, table_rows in (("Whole commands", rows), ("Stages", stages)):
        table = Table(title=title, title_justify="left")
        for col in table_rows[0]:
            table.add_column(col)
        for r in table_rows:
            table.add_row(*(str(v) for v in r.values()))
        console.print(table)


if __name__ == "__main__":
    main()
