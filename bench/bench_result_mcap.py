"""What a Foxglove result MCAP (`--result-mcap`) costs per scan.

1. The publisher alone, at real sizes: per scan the estimate with its ellipsoid and a scan of
   `--scan-points` points (an OS1-64 sweep is ~65,000), `--particles` particles (5,000 of
   them sent), three hypotheses, ground truth, stats and a log line; median wall and process
   cpu time per scan over `--scans` scans, and the file's bytes per scan. Baseline: what the
   ROS-typed result log before it wrote per scan (mcl3d.io.logs.writer: a PoseStamped, 2,000
   particle positions and the scan transformed into the map, as PointCloud2).
2. End to end: `localize` on the tiny ray-cast room log of the tests with and without
   `--result-mcap` (same seed), ms per scan, after a warm-up run that compiles the kernels.

    python bench/bench_result_mcap.py [--quick]   # bench/results/bench_result_mcap.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from results_io import Run

ROOT = Path(__file__).resolve().parents[1]


def timed(fn) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    fn()
    return (time.perf_counter() - wall) * 1e3, (time.process_time() - cpu) * 1e3


def ros_baseline(folder: Path, scans: list, positions: np.ndarray, n: int) -> tuple:
    """ms per scan (median wall) and bytes per scan of the old ROS-typed result log."""
    from mcl3d.core.geometry import transform_points
    from mcl3d.io.logs.messages import PointCloud, PoseStamped
    from mcl3d.io.logs.writer import LogWriter

    path, T, walls = folder / "ros.mcap", np.eye(4), []
    with LogWriter(path) as w:
        for i in range(n):
            stamp = (i + 1) * 100_000_000

            def one_scan(stamp=stamp, scan=scans[i % 4]):
                w.write_pose("/localization/pose", PoseStamped(stamp, "map", T))
                w.write_points("/localization/particles", PointCloud(
                    stamp, "map", positions[:2000].astype(np.float32), None))
                w.write_points("/localization/scan", PointCloud(
                    stamp, "map", transform_points(T, scan).astype(np.float32), None))

            walls.append(timed(one_scan)[0])
    return statistics.median(walls), path.stat().st_size / n


def publisher_cost(args, folder: Path) -> dict:
    from mcl3d.io.foxglove_results import ResultPublisher

    rng = np.random.default_rng(0)
    scans = [rng.uniform(-30, 30, (args.scan_points, 3)) for _ in range(4)]
    positions = rng.uniform(-30, 30, (args.particles, 3))
    weights = rng.exponential(1.0, args.particles)
    cov = np.diag([1e-4, 1e-4, 4e-4, 0.04, 0.01, 0.0025])
    T = np.eye(4)
    path = folder / "publisher.mcap"
    walls, cpus = [], []
    with ResultPublisher(path, name="bench") as pub:
        pub.publish_map(0, rng.uniform(-30, 30, (300_000, 3)))
        for i in range(args.scans):
            stamp = (i + 1) * 100_000_000

            def one_scan(stamp=stamp, scan=scans[i % 4]):
                pub.publish_estimate(stamp, T, cov, scan)
                pub.publish_particles(stamp, positions, weights)
                pub.publish_hypotheses(stamp, [(T, cov, 0.2)] * 3)
                pub.publish_ground_truth(stamp, T)
                pub.publish_stats(stamp, {"ess": 100.0, "error_m": 0.1, "hypotheses": 3})
                pub.log(stamp, "info", "filter converged")

            wall, cpu = timed(one_scan)
            walls.append(wall)
            cpus.append(cpu)
    ros_ms, ros_bytes = ros_baseline(folder, scans, positions, args.scans)
    return {"scan_points": args.scan_points, "particles": args.particles, "scans": args.scans,
            "ms_per_scan_wall": statistics.median(walls),
            "ms_per_scan_cpu": statistics.median(cpus),
            "baseline_ros_ms": ros_ms, "baseline_ros_bytes_per_scan": ros_bytes,
            "ratio_to_baseline": statistics.median(walls) / ros_ms,
            "bytes_per_scan": path.stat().st_size / args.scans}


def localize_cost(folder: Path, backend: str) -> dict:
    sys.path.insert(0, str(ROOT / "tests"))
    from support import localize_world

    from mcl3d.core import runtime
    from mcl3d.localization.pipeline import LocalizeConfig, LocalizeRequest, run

    runtime.init(backend)
    n = 12
    localize_world.write_log(folder / "room.mcap", n)
    localize_world.save_room_map(folder / "room.tsdf", 0.1)
    cfg = LocalizeConfig()
    cfg.localizer.particles, cfg.localizer.init.mode = 3000, "gt"

    def once(name: str, mcap: Path | None) -> float:
        t = time.perf_counter()
        run(LocalizeRequest(folder / "room.mcap", folder / "room.tsdf", folder / name, cfg,
                            force=True, result_mcap=mcap))
        return (time.perf_counter() - t) * 1e3 / n

    once("warmup", None)
    without = min(once("a", None) for _ in range(2))
    with_mcap = min(once("b", folder / "r.mcap") for _ in range(2))
    return {"scans": n, "particles": 3000, "ms_per_scan_without": without,
            "ms_per_scan_with": with_mcap, "ratio": with_mcap / without}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan-points", type=int, default=65_536)
    parser.add_argument("--particles", type=int, default=200_000)
    parser.add_argument("--scans", type=int, default=None, help="default 50, --quick 10")
    parser.add_argument("--quick", action="store_true", help="10 scans")
    parser.add_argument("--backend", default="cpu", help="of the end-to-end localize run")
    parser.add_argument("--skip-localize", action="store_true")
    parser.add_argument("--out", type=Path, help="JSON (default bench/results/"
                                                 "bench_result_mcap.json)")
    args = parser.parse_args()
    args.scans = args.scans or (10 if args.quick else 50)
    bench_run = Run("bench_result_mcap", baselines=("mcap", "foxglove-sdk"))
    with tempfile.TemporaryDirectory() as tmp:
        result = {"publisher": publisher_cost(args, Path(tmp))}
        if not args.skip_localize:
            result["localize_room"] = localize_cost(Path(tmp), args.backend)
    print(f"{'':24}{'ms/scan':>10}{'cpu ms':>10}{'baseline':>10}{'ratio':>8}{'kB/scan':>10}")
    p = result["publisher"]
    print(f"{'foxglove publisher':24}{p['ms_per_scan_wall']:10.2f}{p['ms_per_scan_cpu']:10.2f}"
          f"{p['baseline_ros_ms']:10.2f}{p['ratio_to_baseline']:8.2f}"
          f"{p['bytes_per_scan'] / 1e3:10.0f}")
    if "localize_room" in result:
        r = result["localize_room"]
        print(f"{'localize room (with)':24}{r['ms_per_scan_with']:10.2f}{'':10}"
              f"{r['ms_per_scan_without']:10.2f}{r['ratio']:8.2f}")
    path = bench_run.write({"tables": tables(result, args), "notes": [
        "Publisher: median over the scans of the wall and process-cpu time per scan; the "
        "baseline is the ROS-typed result log written in the same run (a PoseStamped, 2,000 "
        "particle positions and the scan in the map frame as PointCloud2).",
        "End to end: `localize` on the tests' ray-cast room log (12 scans, 3,000 particles, "
        "tracking), best of two runs each, after a warm-up run."], **result}, args.out)
    print(f"wrote {path}")


def tables(result: dict, args) -> dict:
    p = result["publisher"]
    rows = {f"Foxglove result MCAP per scan ({args.scan_points:,} scan points, 5,000 of "
            f"{args.particles:,} particles, {args.scans} scans)": [
                {"writer": "Foxglove result MCAP", "ms per scan": round(p["ms_per_scan_wall"], 2),
                 "cpu ms": round(p["ms_per_scan_cpu"], 2),
                 "kB per scan": round(p["bytes_per_scan"] / 1e3)},
                {"writer": "ROS-typed result log (baseline)",
                 "ms per scan": round(p["baseline_ros_ms"], 2), "cpu ms": "",
                 "kB per scan": round(p["baseline_ros_bytes_per_scan"] / 1e3)}]}
    if "localize_room" in result:
        r = result["localize_room"]
        rows["localize end to end, ms per scan"] = [
            {"without --result-mcap": round(r["ms_per_scan_without"], 1),
             "with --result-mcap": round(r["ms_per_scan_with"], 1),
             "ratio": round(r["ratio"], 2)}]
    return rows


if __name__ == "__main__":
    main()
