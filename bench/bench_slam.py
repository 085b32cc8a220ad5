"""Monte Carlo SLAM: ms per frame of the whole step and measured memory versus particles N
and keyframes K.

Each (N, K) runs in a fresh child process (so peak RSS is its own) that drives the real
per-frame step, `MonteCarloSlam.step` (what `mcl3d slam` calls per scan: odometry, deskew
and downsampling, prediction, neighbour selection (on a loop also the correction and the
second selection), likelihood, refinement, keyframe test and insertion, pruning,
estimate), over a simulated MID-360 forest log with its IMU (cached under bench/results/).
Warm-up: once the robot has moved 1 m (it starts at rest), the scans run with
`keyframes.overlap` 1, so every scan becomes a keyframe, until the map holds K keyframes;
then the default overlap is restored and the next `--frames` scans are timed, each scan's
own cloud at its own place. The path goes forward, so these are tracking frames: the loop
correction's Gauss-Newton iterations do not run (a neighbour is a loop only if it is not
among the 3 newest keyframes, and none of the simulated routes comes back within a minute
of log); every other stage does.

Measured per frame: wall and process-cpu ms of `step` (device synchronized), with the
stages `step` itself times; the odometry stage is the same-run baseline (ratio). Memory:
the child's peak RSS (getrusage), its growth from just before the SLAM object was built,
and the bytes of every Taichi field and ndarray reachable from the SLAM object (shapes x
dtypes as allocated, GICP scratch included).

    python bench/bench_slam.py [--backend cpu|cuda|vulkan] [--particles 1000 10000 100000]
        [--keyframes 10 100] [--frames 8] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
START_TRAVEL_M = 1.0  # keyframes at every scan from here (the log starts at rest)
CPU_SKIP = {(100_000, 100)}  # over 15 min on 2 cores: only with --particles/--keyframes


def forest_log() -> Path:
    from mcl3d.sim.pipeline import SimulateRequest, run

    log = Path(__file__).resolve().parent / "results" / "bench_slam_forest.mcap"
    if not log.exists():
        log.parent.mkdir(parents=True, exist_ok=True)
        run(SimulateRequest(world="forest", sensor="mid360", trajectory="ground",
                            duration_s=20.0, seed=1, output=log,
                            overrides={"world.forest_rows": 6,
                                       "world.forest_trees_per_row": 10}, force=True))
    return log


def rss_bytes() -> int:
    import psutil

    return psutil.Process().memory_info().rss


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux


def taichi_bytes(root, seen: set | None = None, max_depth: int = 4) -> int:
    """Bytes of every Taichi field and ndarray reachable from `root` through mcl3d objects'
    attributes, lists, tuples and dicts (each counted once; not those already in `seen`)."""
    import taichi as ti
    from taichi.lang.struct import StructField
    from taichi.lang.util import to_numpy_type

    def nbytes(x) -> int:
        if isinstance(x, StructField):
            return sum(nbytes(getattr(x, k)) for k in x.keys)
        per = (getattr(x, "n", None) or 1) * (getattr(x, "m", None) or 1)
        return int(np.prod(x.shape)) * per * np.dtype(to_numpy_type(x.dtype)).itemsize

    seen = set() if seen is None else seen
    total, stack = 0, [(root, 0)]
    while stack:
        obj, depth = stack.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, (ti.Field, ti.Ndarray)):
            total += nbytes(obj)
        elif depth < max_depth and isinstance(obj, (list, tuple)):
            stack += [(v, depth + 1) for v in obj]
        elif depth < max_depth and isinstance(obj, dict):
            stack += [(v, depth + 1) for v in obj.values()]
        elif depth < max_depth and type(obj).__module__.startswith("mcl3d") \
                and hasattr(obj, "__dict__"):
            stack += [(v, depth + 1) for v in vars(obj).values()]
    return total


def taichi_by_owner(slam) -> dict[str, int]:
    """Taichi bytes of the SLAM object's parts, each counted once (the GICP scratch under
    `gicp`, the keyframe voxel maps under `maps`, the odometry front-end's own under
    `odometry`), and their total."""
    seen: set = set()
    out = {name: taichi_bytes(getattr(slam, name), seen)
           for name in ("maps", "gicp", "particles", "odometry", "grid", "_scan_pool")}
    out["other"] = taichi_bytes(slam, seen)
    out["total"] = sum(out.values())
    return out


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def measure(n: int, K: int, frames: int, backend: str) -> dict:
    """One child: warm up to K keyframes, time `frames` real steps, measure memory."""
    import slam_peers
    import taichi as ti

    from mcl3d.core import runtime
    from mcl3d.slam.monte_carlo_slam import MonteCarloSlam
    from mcl3d.slam.slam_config import KeyframeConfig, SlamConfig

    info = runtime.init(backend)
    log = forest_log()
    scans = list(slam_peers.scans(log, 360.0))
    cfg = SlamConfig(particles=n, seed=1)
    rss_before = rss_bytes()
    slam = MonteCarloSlam(cfg, scans[0][4])
    feed = iter(scans)
    warmup = 0
    slam.cfg.keyframes.overlap = KeyframeConfig().overlap  # the robot starts at rest
    while slam.particles.num_keyframes < K:
        stamp_ns, points, times, imu, _ = next(feed)  # StopIteration: log too short for K
        slam.step(points, times, stamp_ns, imu)
        warmup += 1
        if slam.travel_m >= START_TRAVEL_M:
            slam.cfg.keyframes.overlap = 1.0  # then every scan becomes a keyframe
    slam.cfg.keyframes.overlap = KeyframeConfig().overlap
    timed = []
    for stamp_ns, points, times, imu, _ in list(feed)[:frames]:
        t0, c0 = time.perf_counter(), cpu_s()
        frame = slam.step(points, times, stamp_ns, imu)
        ti.sync()
        timed.append({"wall_ms": (time.perf_counter() - t0) * 1e3,
                      "cpu_ms": (cpu_s() - c0) * 1e3, "stages_ms": frame.timings_ms,
                      "looping": frame.looping, "corrected": frame.corrected,
                      "keyframe": frame.keyframe, "keyframes": frame.num_keyframes})
    if len(timed) < frames:
        raise SystemExit(f"the log has too few scans for K={K} and {frames} timed frames")
    return {"particles": n, "keyframes": K, "backend": info.backend,
            "device": info.device, "warmup_frames": warmup, "frames": timed,
            "peak_rss_bytes": peak_rss_bytes(), "rss_before_slam_bytes": rss_before,
            "taichi_bytes": taichi_by_owner(slam),
            "particle_state_formula_bytes": slam.particles.state_bytes()}


def summarize(r: dict) -> dict:
    frames = r["frames"]
    wall = np.array([f["wall_ms"] for f in frames])
    odo = np.array([f["stages_ms"].get("odometry", np.nan) for f in frames])
    stages = {k: float(np.median([f["stages_ms"].get(k, 0.0) for f in frames]))
              for k in frames[0]["stages_ms"]}
    mib = 2.0 ** 20
    return {"particles": r["particles"], "keyframes": r["keyframes"],
            "wall ms/frame (median)": round(float(np.median(wall)), 1),
            "wall ms (min-max)": f"{wall.min():.0f}-{wall.max():.0f}",
            "cpu ms/frame": round(float(np.median([f["cpu_ms"] for f in frames])), 1),
            "x odometry": round(float(np.median(wall / odo)), 1),
            "stages ms": ", ".join(f"{k} {v:.0f}" for k, v in stages.items()),
            "keyframe inserts": sum(f["keyframe"] for f in frames),
            "peak RSS MiB": round(r["peak_rss_bytes"] / mib),
            "RSS growth MiB": round((r["peak_rss_bytes"] - r["rss_before_slam_bytes"]) / mib),
            "Taichi MiB": round(r["taichi_bytes"]["total"] / mib, 1),
            "of which particles / GICP / keyframe maps MiB": " / ".join(
                f"{r['taichi_bytes'][k] / mib:.0f}" for k in ("particles", "gicp", "maps"))}


def child(args) -> None:
    out = measure(args.particles[0], args.keyframes[0], args.frames, args.backend)
    print("RESULT " + json.dumps(out), flush=True)


def run_child(n: int, K: int, args) -> dict:
    cmd = [sys.executable, __file__, "--child", "--particles", str(n), "--keyframes", str(K),
           "--frames", str(args.frames), "--backend", args.backend]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"over the {args.timeout:.0f} s cap"}
    lines = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
    if proc.returncode or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        return {"error": f"exit {proc.returncode}: {tail[0][:200]}"}
    return json.loads(lines[0][len("RESULT "):])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--particles", type=int, nargs="+", default=None,
                    help="default 1000 10000 100000 (100000 x 100 keyframes skipped on cpu)")
    ap.add_argument("--keyframes", type=int, nargs="+", default=[10, 100])
    ap.add_argument("--frames", type=int, default=8, help="timed frames per configuration")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per configuration")
    ap.add_argument("--quick", action="store_true", help="1000 particles, 10 keyframes, "
                    "3 frames")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    explicit = args.particles is not None
    if args.quick:
        args.particles, args.keyframes, args.frames = [1000], [10], 3
    args.particles = args.particles or [1000, 10000, 100000]
    from results_io import Run

    run = Run("bench_slam")
    forest_log()  # simulated once, before the children read it
    rows, raw = [], []
    for K in args.keyframes:
        for n in args.particles:
            if args.backend == "cpu" and (n, K) in CPU_SKIP and not explicit:
                continue
            t0 = time.time()
            r = run_child(n, K, args)
            raw.append({"particles": n, "keyframes": K, **r})
            if "error" in r:
                print(f"N={n:,} K={K}: FAILED {r['error']}", flush=True)
                continue
            rows.append(summarize(r))
            print(json.dumps(rows[-1]), f"({time.time() - t0:.0f} s)", flush=True)
    done = next((r for r in raw if "error" not in r), {})
    figures = {"tables": {"SLAM, whole step per frame and memory": rows},
               "notes": notes(args, done, raw), "runs": raw}
    print(f"wrote {run.write(figures, args.out)}")


def notes(args, done: dict, raw: list[dict]) -> list[str]:
    out = [f"{done.get('backend', args.backend)} backend ({done.get('device', '')}), "
           f"{os.environ.get('TI_CPU_MAX_NUM_THREADS', 'all')} cpu threads; simulated MID-360 "
           f"forest log with IMU; {args.frames} timed frames per row after a warm-up to K "
           "keyframes, each configuration in a fresh process.",
           "Whole step: MonteCarloSlam.step (odometry, preprocessing, prediction, neighbour "
           "selection, likelihood, refinement, keyframe test and insertion, pruning, "
           "estimate); "
           "x odometry: median over frames of the step's wall time over its own odometry "
           "stage. Tracking frames on a forward path: no loop correction ran.",
           "Memory: peak RSS of the child process (getrusage), its growth from just before "
           "the SLAM object was built (scans already loaded), and the bytes of every Taichi "
           "field and ndarray the SLAM object owns (keyframe capacity 256, the default)."]
    if args.backend == "cpu" and args.particles and 100000 in args.particles:
        out.append("100,000 particles x 100 keyframes not run on cpu (past the 15 min budget).")
    out += [f"N={r['particles']:,} K={r['keyframes']}: {r['error']}"
            for r in raw if "error" in r]
    return out


if __name__ == "__main__":
    main()
