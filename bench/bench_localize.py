"""Benchmark of one MCL update: per-stage times and sensor-model throughput vs N and M.

For N particles (spread 0.3 m / 0.1 rad around the true pose, as while tracking) and M scan
points, runs full Localizer updates (resampling forced every update so every stage counts)
and reports the median ms of each stage (and the process cpu time of an update: 2 threads
give up to 2x the wall time) plus the likelihood kernel's best time, warm, repeated on one
scan, and its throughput in particle*points/s. Warm means the map blocks that the scan touches
are already in the cpu's L3 cache; inside an update (a new scan) the kernel runs cold, ~1.5x
slower on 2 cpu cores, which the likelihood stage shows.
A second table times global search (`--init global` on the same log: the coarse phase, then
the accurate model with annealing, place evidence and mode-preserving resampling, all on the
device): median stage ms, wall and process cpu of the accurate-model updates, the first of
them (it compiles that model's kernels) untimed, at each N with the first M.
The baseline, measured in the same run, is the NumPy-vectorised implementation of the same
sensor model (mcl3d.localization.sensor_model.scan_log_likelihood_numpy) on a subset of the
particles (its cost is linear in N); the table shows the Taichi/NumPy ratio. Also compares the
kernel with and without the coarse-block cache and with an f16 map.

Data: a simulated office log and its 5 cm map, made with `mcl3d simulate` and
`mcl3d build-map` into --cache-dir unless --log/--map are given.

    python bench/bench_localize.py [--quick] [--backend cpu]   # bench/results/bench_localize.json
    python bench/bench_localize.py --n 1000000 --m 256 1024 --no-f16   # a part of the grid
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from results_io import RESULTS, Run


def ensure_data(cache: Path, log: Path | None, map_path: Path | None) -> tuple[Path, Path]:
    cache.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-m", "mcl3d"]
    log = log or cache / "office.mcap"
    map_path = map_path or cache / "office.tsdf"
    if not log.exists():
        subprocess.run([*exe, "simulate", "office", "-o", str(log), "--duration", "5",
                        "--seed", "1", "--export-mesh", str(cache / "office.ply")], check=True)
    if not map_path.exists():
        subprocess.run([*exe, "build-map", str(cache / "office.ply"), "-o", str(map_path),
                        "--backend", "cpu"], check=True)
    return log, map_path


def first_scan(log: Path):
    from mcl3d.io.logs.reader import LogReader

    with LogReader(log) as reader:
        scan = next(iter(reader.scans()))
        stamps, poses = reader.ground_truth()
    k = int(np.argmin(np.abs(stamps - scan.stamp_ns)))
    return scan.points, poses[k]


def scans_with_motion(log: Path, count: int):
    """The first `count` scans with the ground-truth pose and stamp (s)."""
    from mcl3d.io.logs.reader import LogReader

    with LogReader(log) as reader:
        stamps, poses = reader.ground_truth()
        out = []
        for scan in reader.scans():
            out.append((scan.points, poses[int(np.argmin(np.abs(stamps - scan.stamp_ns)))],
                        scan.stamp_ns * 1e-9))
            if len(out) == count:
                break
    return out


def global_case(tsdf, log: Path, n: int, m: int, updates: int) -> dict:
    """Median stage ms, wall and process-cpu ms of global-search updates with the accurate
    model (the defaults of `mcl3d localize --init global`, ground-truth motion); the coarse
    phase and the first accurate update are not timed. Updates after convergence (tracking)
    are left out and counted."""
    import taichi as ti

    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer
    from mcl3d.localization.state import STAGES

    cfg = LocalizerConfig.model_validate({"particles": n, "seed": 1, "sensor": {"points": m}})
    loc = Localizer(tsdf, cfg)
    loc.init_global()
    untimed = cfg.sensor.coarse_scans + 1
    rows, T_prev, converged = [], None, 0
    for k, (points, T, stamp_s) in enumerate(scans_with_motion(log, untimed + updates)):
        motion = None if T_prev is None else np.linalg.inv(T_prev) @ T
        T_prev = T
        ti.sync()
        t0, c0 = time.perf_counter(), time.process_time()
        r = loc.step(points, motion, stamp_s)
        ti.sync()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if k >= untimed and r.state.value == "converged":
            converged += 1
        elif k >= untimed:
            rows.append((1e3 * wall, 1e3 * cpu, r.timings_ms))
    def median(values) -> float:  # nan when the search converged before a timed update
        values = list(values)
        return statistics.median(values) if values else float("nan")

    return {"N": n, "M": m, "searching_updates": len(rows), "converged_updates": converged,
            "stage_ms": {s: median(r[2][s] for r in rows) for s in STAGES},
            "update_ms": median(r[0] for r in rows), "update_cpu_ms": median(r[1] for r in rows)}


def kernel_seconds(loc, pts, cache_block: bool, repeats: int) -> tuple[float, float]:
    """(best wall s, cpu s of that call) of the likelihood kernel alone."""
    import taichi as ti

    loc.weigher.upload_scan(pts)
    times = []
    for _ in range(repeats + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        loc.weigher.scan_likelihood(loc.particles, len(pts), cache_block)
        ti.sync()
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    return min(times[1:])


def numpy_seconds_per_particle(host, loc, pts, n_sub: int) -> float:
    from mcl3d.localization.sensor_model import scan_log_likelihood_numpy

    pos, quat, _ = loc.particles.host()
    n_sub = min(n_sub, len(pos))
    t0 = time.perf_counter()
    scan_log_likelihood_numpy(host, pos[:n_sub].astype(np.float64),
                              quat[:n_sub].astype(np.float64), pts, loc.cfg.sensor)
    return (time.perf_counter() - t0) / n_sub


def bench_case(tsdf, host, scan, T, n: int, m: int, repeats: int, numpy_sub: int) -> dict:
    from mcl3d.localization.localization_config import LocalizerConfig
    from mcl3d.localization.localizer import Localizer
    from mcl3d.localization.sensor_model import reduce_scan
    from mcl3d.localization.state import STAGES

    cfg = LocalizerConfig.model_validate({
        "particles": n, "seed": 1,
        "sensor": {"points": m, "voxel_m": 0.05},
        "resample": {"ess_threshold": 1.0, "anneal_min_ess": 0.0},
        "recovery": {"enabled": False}})
    loc = Localizer(tsdf, cfg)
    loc.ever_converged = True  # measure steady tracking (no annealing)
    spread = [0.3, 0.3, 0.05, 0.02, 0.02, 0.1]
    loc.init_pose(T, spread)
    dT = np.eye(4)
    dT[0, 3] = 0.05
    stage_ms = {s: [] for s in STAGES}
    update_cpu_ms = []
    import taichi as ti

    for k in range(repeats + 2):  # two warm-ups: both particle buffers compile their kernels
        loc.init_pose(T, spread)  # the same spread every update, not a converged cloud
        ti.sync()  # keep the re-initialization out of the motion stage's time
        c0 = time.process_time()
        r = loc.step(scan, dT, 0.1 * k)
        if k > 1:
            update_cpu_ms.append(1e3 * (time.process_time() - c0))
            for s in STAGES:
                stage_ms[s].append(r.timings_ms[s])
    med = {s: statistics.median(v) for s, v in stage_ms.items()}
    pts = reduce_scan(scan, cfg.sensor, np.random.default_rng(0))
    m_used = len(pts)
    loc.init_pose(T, spread)
    t_plain, cpu_plain = kernel_seconds(loc, pts, False, repeats)
    t_cache, cpu_cache = kernel_seconds(loc, pts, True, repeats)
    t_np = numpy_seconds_per_particle(host, loc, pts, numpy_sub) * n
    best = min(t_plain, t_cache)
    out = {"N": n, "M": m, "M_used": m_used, "stage_ms": med,
           "update_ms": sum(med.values()),
           "update_cpu_ms": statistics.median(update_cpu_ms),
           "likelihood_kernel_ms": {"plain": 1e3 * t_plain, "cached_block": 1e3 * t_cache},
           "likelihood_kernel_cpu_ms": {"plain": 1e3 * cpu_plain,
                                        "cached_block": 1e3 * cpu_cache},
           "throughput_pp_per_s": n * m_used / best,
           "numpy_ms_extrapolated": 1e3 * t_np, "numpy_subset": min(numpy_sub, n),
           "ratio_taichi_vs_numpy": t_np / best}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--log", type=Path)
    ap.add_argument("--map", type=Path)
    ap.add_argument("--cache-dir", type=Path, default=Path("/tmp/mcl3d-bench"))
    ap.add_argument("--quick", action="store_true",
                    help="N in 10k, 100k; M 256; one repeat; no f16 comparison")
    ap.add_argument("--n", type=int, nargs="+", help="particle counts (default 10k 100k 1M)")
    ap.add_argument("--m", type=int, nargs="+", help="scan points (default 256 512 1024)")
    ap.add_argument("--no-f16", action="store_true", help="skip the f16-map comparison")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--numpy-subset", type=int, default=5000)
    ap.add_argument("--global-updates", type=int, default=8,
                    help="accurate-model global-search updates timed per N")
    ap.add_argument("--json", type=Path, default=RESULTS / "bench_localize.json")
    args = ap.parse_args()
    if args.quick:
        args.repeats, args.no_f16 = 1, True
    bench_run = Run("bench_localize")
    partial = args.json.with_suffix(".partial.json")

    from rich.console import Console
    from rich.table import Table

    from mcl3d.core import runtime
    from mcl3d.localization.sensor_model import NumpyTsdf
    from mcl3d.maps.map_file import load_map

    log, map_path = ensure_data(args.cache_dir, args.log, args.map)
    info = runtime.init(args.backend)
    scan, T = first_scan(log)
    ns = args.n or ([10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000])
    ms = args.m or ([256] if args.quick else [256, 512, 1024])
    results = {"backend": info.backend, "device": info.device, "log": str(log),
               "map": str(map_path), "cases": [], "f16": [], "global": []}
    for f16 in (False,) if args.no_f16 else (False, True):
        tsdf = load_map(map_path, f16=f16)
        host = NumpyTsdf.of(tsdf)
        for n in ns:
            for m in ms:
                if f16 and (n, m) != (100_000, 256):
                    continue
                case = bench_case(tsdf, host, scan, T, n, m, args.repeats, args.numpy_subset)
                case["map_f16"] = f16
                (results["f16"] if f16 else results["cases"]).append(case)
                print(json.dumps({k: case[k] for k in ("N", "M", "update_ms",
                                                       "throughput_pp_per_s")}), flush=True)
                partial.write_text(json.dumps(results, indent=2))  # a crash keeps the rows
        tsdf.destroy()
    tsdf = load_map(map_path)
    for n in ns:
        results["global"].append(global_case(tsdf, log, n, ms[0], args.global_updates))
        print(json.dumps({k: results["global"][-1][k] for k in ("N", "update_ms",
                                                                  "update_cpu_ms")}), flush=True)
        partial.write_text(json.dumps(results, indent=2))
    tsdf.destroy()
    table = Table(title=f"MCL update on {info.backend} ({info.device})")
    for col in ("N", "M", "map", "motion", "likelihood", "weights", "estimate", "resample",
                "update ms (cpu)", "kernel ms plain/cached", "pp/s", "NumPy ms", "x NumPy"):
        table.add_column(col, justify="right")
    for c in results["cases"] + results["f16"]:
        s = c["stage_ms"]
        table.add_row(f"{c['N']:,}", f"{c['M_used']}", "f16" if c["map_f16"] else "f32",
                      *(f"{s[k]:.1f}" for k in ("motion", "likelihood", "weights", "estimate",
                                                "resample")),
                      f"{c['update_ms']:.1f} ({c['update_cpu_ms']:.0f})",
                      f"{c['likelihood_kernel_ms']['plain']:.1f} / "
                      f"{c['likelihood_kernel_ms']['cached_block']:.1f}",
                      f"{c['throughput_pp_per_s']:.2e}", f"{c['numpy_ms_extrapolated']:.0f}",
                      f"{c['ratio_taichi_vs_numpy']:.1f}")
    Console(width=max(Console().width, 160)).print(table)
    for row in tables(results)["tables"][global_caption(results)]:
        print(row)
    path = bench_run.write({**results, **tables(results)}, args.json)
    partial.unlink(missing_ok=True)
    print(f"wrote {path}")


def tables(results: dict) -> dict:
    """The rendered part of the JSON: one row per case, stage medians in ms."""
    rows = []
    for c in results["cases"] + results["f16"]:
        s = c["stage_ms"]
        rows.append({"N": f"{c['N']:,}", "M": c["M_used"], "map": "f16" if c["map_f16"] else "f32",
                     **{k: round(s.get(k, 0.0), 1) for k in ("motion", "likelihood", "weights",
                                                             "estimate", "resample")},
                     "update ms": round(c["update_ms"], 1),
                     "update cpu ms": round(c["update_cpu_ms"]),
                     "kernel ms plain / cached": f"{c['likelihood_kernel_ms']['plain']:.1f} / "
                                                 f"{c['likelihood_kernel_ms']['cached_block']:.1f}",
                     "particle·points/s": f"{c['throughput_pp_per_s']:.2e}",
                     "NumPy ms (extrapolated)": round(c["numpy_ms_extrapolated"]),
                     "× NumPy": round(c["ratio_taichi_vs_numpy"], 1)})
    search = [{"N": f"{c['N']:,}", "M": c["M"],
               "timed updates": f"{c['searching_updates']} (+{c['converged_updates']} "
                                "converged, not timed)",
               **{k: round(c["stage_ms"][k], 1) for k in ("motion", "likelihood", "weights",
                                                          "estimate", "resample")},
               "update ms": round(c["update_ms"], 1), "update cpu ms": round(c["update_cpu_ms"])}
              for c in results["global"]]
    return {"tables": {f"MCL update on {results['backend']} ({results['device']}), median "
                       "ms per stage": rows, global_caption(results): search},
            "notes": ["Particles spread 0.3 m / 0.1 rad around the true pose (tracking), "
                      "resampling forced every update; the kernel columns are the likelihood "
                      "alone, best of the repeats on one scan (warm), without and with the "
                      "coarse-block cache; NumPy: the vectorised reference of the same model "
                      "on a subset of the particles, extrapolated to N.",
                      "Global search: a global start (seed 1) on the same log with ground-truth "
                      "motion; the coarse phase and the first accurate-model update (it "
                      "compiles kernels) untimed; medians over the accurate-model updates "
                      "before convergence. `likelihood` includes the annealing, `estimate` "
                      "the place evidence, clustering and mode floor."]}


def global_caption(results: dict) -> str:
    return (f"Global search update (accurate model) on {results['backend']} "
            f"({results['device']}), median ms per stage")


if __name__ == "__main__":
    main()
